"""Checkpoints load with ``weights_only=True``: a file carrying code is refused and nothing runs."""
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mvtn_exp.runtime import checkpoint, seeding

ROOT = Path(__file__).resolve().parents[1]


class _Payload:
    """Unpickling this runs a shell command (the attack)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _evil(tmp_path) -> tuple[Path, Path]:
    marker = tmp_path / "ran"
    path = tmp_path / "evil.pt"
    torch.save({"model": {}, "config": {"views": 1}, "epoch": 0, "x": _Payload(marker)}, path)
    # the file really is an attack: the unsafe loader runs it
    probe = tmp_path / "probe"
    torch.save({"x": _Payload(probe)}, tmp_path / "probe.pt")
    torch.load(tmp_path / "probe.pt", weights_only=False)
    assert probe.exists()
    return path, marker


def test_a_checkpoint_carrying_code_is_refused_and_nothing_runs(tmp_path):
    path, marker = _evil(tmp_path)
    with pytest.raises(checkpoint.CheckpointMismatch) as e:
        checkpoint.load(path)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg and "refused" in msg and "system" in msg
    assert not marker.exists()


def test_mvtn_eval_refuses_it_in_one_line_with_exit_2(tmp_path):
    path, marker = _evil(tmp_path)
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.eval", f"ckpt={path}", f"hydra.run.dir={tmp_path / 'e'}"],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 2, r.stderr[-2000:]
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and "refused" in err[0] and str(path) in err[0], r.stderr
    assert "Traceback" not in r.stderr and not marker.exists()


def test_rng_state_is_plain_data_and_restores_exactly(tmp_path):
    import random

    import numpy as np

    seeding.seed_everything(5)
    state = seeding.rng_state()
    torch.save({"rng": state}, tmp_path / "s.pt")
    loaded = torch.load(tmp_path / "s.pt", weights_only=True)["rng"]  # no numpy objects inside
    a = (random.random(), np.random.rand(3).tolist(), np.random.randn(), torch.rand(2).tolist())
    seeding.set_rng_state(loaded)
    assert (random.random(), np.random.rand(3).tolist(), np.random.randn(), torch.rand(2).tolist()) == a


def test_weights_only_everywhere():
    """No loader in the package unpickles arbitrary objects."""
    hits = [str(p.relative_to(ROOT)) for p in (ROOT / "mvtn_exp").rglob("*.py")
            if "weights_only=False" in p.read_text() or "pickle.load" in p.read_text()]
    assert hits == []


def test_numpy_rng_arrays_load_and_other_formats_are_refused_in_one_line(tmp_path):
    """An RNG state holding numpy's key array loads (plain number arrays are allowed) and restores;
    a file of another checkpoint format is refused naming its format and where to read it."""
    import numpy as np

    rng = {**seeding.rng_state(), "numpy": np.random.get_state()}
    torch.save({"model": {"w": torch.ones(2)}, "config": {"views": 1}, "epoch": 1, "format": checkpoint.FORMAT,
                "rng": rng}, tmp_path / "now.pt")
    state = checkpoint.load(tmp_path / "now.pt")
    assert isinstance(state["rng"]["numpy"][1], np.ndarray)
    seeding.set_rng_state(state["rng"])
    for written in (None, 2, 3):  # format 1 files carried no format key; 3: one union schema of every dataset's keys
        old = {"model": {"w": torch.ones(2)}, "config": {"views": 1}, "epoch": 0, **({"format": written} if written else {})}
        torch.save(old, tmp_path / "old.pt")
        with pytest.raises(checkpoint.CheckpointMismatch) as err:
            checkpoint.load(tmp_path / "old.pt")
        assert f"format {written or 1}" in str(err.value) and "docs/training.md#checkpoint-formats" in str(err.value)
        assert "\n" not in str(err.value)
    # an object array would smuggle other globals: still refused
    torch.save({"model": {}, "config": {}, "x": np.array([_Payload(tmp_path / "ran")], dtype=object)}, tmp_path / "obj.pt")
    with pytest.raises(checkpoint.CheckpointMismatch, match="refused"):
        checkpoint.load(tmp_path / "obj.pt")
    assert not (tmp_path / "ran").exists()


@pytest.mark.parametrize("content, what", [
    (b'{"test_acc": 0.5}', "is a JSON or other text file (starts with '{\"test_acc\": 0.5}')"),
    (b"", "is an empty file"),
    (bytes(range(150, 250)), "is binary data of 100 bytes (starts with 96 97 98"),
    (b"OFF\n3 1 0\n", "is a text file (starts with 'OFF"),
])
def test_a_file_that_is_no_checkpoint_is_named_for_what_it_is(tmp_path, content, what):
    path = tmp_path / "last.pt"
    path.write_bytes(content)
    with pytest.raises(checkpoint.CheckpointMismatch, match="not a checkpoint") as e:
        checkpoint.load(path)
    assert what in str(e.value) and "\n" not in str(e.value)


def test_an_npz_is_named_and_a_real_checkpoint_is_not(tmp_path):
    import numpy as np

    np.savez(tmp_path / "a.npz", x=np.zeros(3))
    with pytest.raises(checkpoint.CheckpointMismatch, match=r"is a NumPy \.npz archive \(1 entries, e\.g\. 'x\.npy'\)"):
        checkpoint.load(tmp_path / "a.npz")
    checkpoint.save_atomic(tmp_path / "ok.pt", {"model": {}, "config": {}})
    assert checkpoint.describe_non_checkpoint(tmp_path / "ok.pt") is None
    torch.save({"model": {}, "config": {}}, tmp_path / "legacy.pt", _use_new_zipfile_serialization=False)
    assert checkpoint.describe_non_checkpoint(tmp_path / "legacy.pt") is None


def test_a_run_folder_given_as_a_checkpoint_is_named_as_a_folder(tmp_path):
    """``ckpt=RUN`` (the folder, not its file): one line saying so and which file to pass."""
    with pytest.raises(FileNotFoundError, match="is a folder, not a checkpoint file: it holds no best.pt"):
        checkpoint.load(tmp_path)
    (tmp_path / "last.pt").write_bytes(b"")
    with pytest.raises(FileNotFoundError, match=f"is a folder, not a checkpoint file: pass {tmp_path / 'last.pt'}"):
        checkpoint.load(tmp_path)
