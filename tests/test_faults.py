"""Faults a run meets at run time: a full disk (a small tmpfs, where this machine lets us mount one)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY = ["epochs=1", "views=2", "image_size=32", "dataset.num_per_class=[4,2,2]", "batch_size=8",
        "logger.progress=false", "logger.tensorboard=false"]


@pytest.fixture()
def small_disk(tmp_path):
    """A 600 KiB tmpfs: room for a run's records, not for its checkpoints."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({(r.stderr or r.stdout).strip() or 'not permitted'})")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


def test_a_full_disk_is_one_line_with_the_run_records_written(small_disk, tmp_path):
    run = small_disk / "run"
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *TINY, f"dataset.root={tmp_path / 'cache'}",
                        f"hydra.run.dir={run}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(err) == 1, r.stderr[-3000:]
    assert err[0].startswith("mvtn-train: error: no space left on the device (writing ") and ".pt)" in err[0]
    assert json.loads((run / "status.json").read_text())["status"] == "error"
    assert "no space left" in (run / "train.log").read_text()
    assert not list(run.glob(".*.tmp"))  # the half-written checkpoint is gone
