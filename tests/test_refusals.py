"""A refused command writes nothing: an unreadable or foreign checkpoint is refused before any file
or folder is made, a resume refused later (weights of another shape) leaves the folder as it was;
a failure after an epoch was saved says how to resume."""
from __future__ import annotations

import errno
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from hydra.types import RunMode

from mvtn_exp.cli import train as train_cli
from mvtn_exp.engine import run_dir as rd

ROOT = Path(__file__).resolve().parents[1]
TINY = ["epochs=1", "views=2", "image_size=32", "dataset.num_per_class=[4,2,2]", "batch_size=8",
        "logger.progress=false", "logger.tensorboard=false"]


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): (p.read_bytes() if p.is_file() else b"<dir>")
            for p in sorted(folder.rglob("*"))}


def _resume(ckpt: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", f"ckpt_path={ckpt}", *extra], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


BAD = {
    "zero-byte": b"",
    "random": bytes(range(256)) * 40,
    "text": b"not a checkpoint\n",
}


def _bad_checkpoints(folder: Path) -> list[Path]:
    torch.save({"conv.weight": torch.zeros(2, 3)}, folder / "plain.pt")  # a bare state_dict
    whole = folder / "whole.pt"
    torch.save({"model": {"w": torch.zeros(1000)}, "config": {}, "format": 4}, whole)
    (folder / "truncated.pt").write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    whole.unlink()
    for name, data in BAD.items():
        (folder / f"{name}.pt").write_bytes(data)
    return sorted(folder.glob("*.pt"))


def test_each_unreadable_or_foreign_checkpoint_is_refused_in_one_line_before_the_run_starts(tmp_path, capsys):
    for ckpt in _bad_checkpoints(tmp_path):
        with pytest.raises(SystemExit) as exc:
            train_cli.resume_in_place([f"ckpt_path={ckpt}", "epochs=3"])  # (main: before Hydra or any lock)
        lines = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(lines) == 1, (ckpt.name, lines)
        assert lines[0].startswith(f"mvtn-train: error: ckpt_path={ckpt}: checkpoint "), lines


def test_a_refused_checkpoint_leaves_nothing_beside_it(tmp_path):
    folder = tmp_path / "bad"
    folder.mkdir()
    ckpt = next(p for p in _bad_checkpoints(folder) if p.name == "truncated.pt")
    before = _files(folder)
    r = _resume(ckpt, *TINY)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr[-2000:]
    assert "is a damaged zip archive, not a checkpoint" in r.stderr
    assert _files(folder) == before  # no .hydra, train.log or lock beside it


@pytest.mark.slow  # a training run first (make test-all)
def test_a_resume_refused_for_weights_of_another_shape_leaves_the_folder_as_it_was(tmp_path):
    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *TINY, f"dataset.root={tmp_path / 'cache'}",
                        f"hydra.run.dir={run}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    state = torch.load(run / "last.pt", weights_only=False)
    key = next(k for k, v in state["model"].items() if v.ndim == 2)
    state["model"][key] = torch.zeros(3, 3)
    for fresh in (False, True):  # in its own run folder, and alone in a new one
        folder = run if not fresh else tmp_path / "alone"
        folder.mkdir(exist_ok=True)
        torch.save(state, folder / "reshaped.pt")
        before = _files(folder)
        r = _resume(folder / "reshaped.pt", f"dataset.root={tmp_path / 'cache'}")
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr[-2000:]
        assert "weights do not fit" in r.stderr
        assert _files(folder) == before


@pytest.mark.parametrize("mode,hint", [(RunMode.RUN, "resume with: mvtn-train ckpt_path={run}/last.pt"),
                                       (RunMode.MULTIRUN, "the sweep resumes with: mvtn-train --resume-sweep {sweep}")])
def test_a_full_disk_after_an_epoch_was_saved_says_how_to_resume(tmp_path, capsys, mode, hint):
    run = tmp_path / "sweep" / "0_seed-0"
    run.mkdir(parents=True)
    (run / "last.pt").write_bytes(b"epoch 1")
    exc = OSError(errno.ENOSPC, "No space left on device", str(run / ".last.pt.tmp"))
    code = train_cli.failed(exc, SimpleNamespace(ckpt_path=None), SimpleNamespace(mode=mode, output_subdir=".hydra"), run)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1
    assert err[0].startswith("mvtn-train: error: no space left on the device (writing ")
    assert err[0].endswith("the last finished epoch is saved, " + hint.format(run=run, sweep=run.parent))
    assert json.loads((run / rd.STATUS_FILE).read_text())["status"] == "error"
