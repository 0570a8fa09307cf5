"""The prepared GPU check runs end to end as a dry run on the CPU: every stage in its own process,
each recorded (results or the error), small text records only, and a stage past its deadline is
recorded as such while the next one runs."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mvtn_exp.bench import device_check

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_dry_run_writes_every_stage_as_small_text_records(tmp_path):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "device_check.py"), str(out), "--dry-run"],
                       capture_output=True, text=True, timeout=400, cwd=ROOT)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert sorted(p.name for p in out.iterdir()) == ["device_check.json", "device_check.md"]
    assert all(p.stat().st_size < 200_000 for p in out.iterdir())
    records = json.loads((out / "device_check.json").read_text())
    assert list(records) == list(device_check.STAGES) and all(rec["ok"] for rec in records.values())
    parity = records["parity"]["result"]["rows"]
    assert [row["kind"] for row in parity] == ["hard", "soft", "points"]
    assert all(row["images_ok"] and row["grads_ok"] for row in parity)  # (dry: CPU against CPU)
    counts = records["paper_scale_fp32"]["result"]["counts"]
    assert {row["kind"] for row in counts} == {"hard", "soft", "points"} and all(row["fwd_ops"] > 0 for row in counts)
    steps = records["train_step"]["result"]["rows"]
    assert {(row["mvnet"], row["mode"]) for row in steps} == {(m, r) for m in ("mvcnn", "viewgcn") for r in ("hard", "soft")}
    assert all(row["render_ms"] > 0 and row["backbone_ms"] > 0 for row in steps)
    opt = records["options"]["result"]
    assert opt["deterministic_repeats"] and opt["default_repeats"] and opt["compile"] == "skipped in the dry run"
    assert 0.0 <= records["train_embedded"]["result"]["test_acc"] <= 1.0
    text = (out / "device_check.md").read_text()
    assert "(dry run, CPU)" in text and "## Training step" in text and "Paper-scale targets" in text


def test_a_failing_or_overrunning_stage_is_recorded_and_the_next_runs(tmp_path, monkeypatch):
    # a budget spent before a stage: skipped with the reason, the records still written
    records = device_check.run(tmp_path, dry=True, stages=("environment", "parity"), total_s=3)
    assert all(not rec["ok"] and "budget is spent" in rec["error"] for rec in records.values())
    assert json.loads((tmp_path / "device_check.json").read_text())["parity"]["ok"] is False
    # a stage past its deadline (the child is killed by subprocess.run's timeout), then one that fails
    real = subprocess.run

    def child(cmd, **kw):
        if "parity" in cmd:
            raise subprocess.TimeoutExpired(cmd, kw["timeout"])
        return real([sys.executable, "-c", "import sys; sys.exit(3)"], **kw)  # a child that dies, writing nothing

    monkeypatch.setattr(device_check.subprocess, "run", child)
    records = device_check.run(tmp_path, dry=True, stages=("parity", "environment"), total_s=60)
    assert not records["parity"]["ok"] and records["parity"]["error"].startswith("timeout: over its deadline")
    assert not records["environment"]["ok"] and records["environment"]["error"].startswith("exit 3")
    assert "FAILED: timeout" in (tmp_path / "device_check.md").read_text()
