"""Three commands that say what happened: a render too large for the machine (``mvtn-render``), a
report over a folder without runs (``mvtn-report``), a bad ``backbone.weights`` file (``mvtn-train``).
Each refusal is one line on stderr, exit code 2, nothing written."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mvtn_exp.cli import render
from mvtn_exp.models import pretrained

ROOT = Path(__file__).resolve().parents[1]
TINY = ["epochs=1", "views=2", "image_size=32", "dataset.num_per_class=[4,2,2]", "batch_size=8",
        "logger.progress=false", "logger.tensorboard=false"]
GB = 10**9


# ----------------------------------------------------------------------------- mvtn-render: size

# runs mvtn-render with its estimate and its measured peak (resident set) printed on stderr; the
# peak is VmHWM, this process's own high-water mark: ru_maxrss would keep the peak of the pytest
# worker that started it (Linux carries it over execve)
MEASURED = """
import sys
from mvtn_exp.cli import render
check = render.check_size
def noted(cfg):
    est = render.estimate(cfg)
    print("ESTIMATE", est.output_bytes, est.peak_bytes, file=sys.stderr)
    check(cfg)
render.check_size = noted
sys.argv = ["mvtn-render", *sys.argv[1:]]
render.main()
hwm = [line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:")]
print("PEAK", int(hwm[0]) * 1024, file=sys.stderr)
"""


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="the peak is read from /proc/self/status (Linux)")
def test_the_estimate_matches_a_measured_render(tmp_path):
    """images.npy's size is estimated exactly (the array's nbytes and the .npy header); the peak
    memory within a factor of 2 either way of the measured peak resident set (1.0-1.2x alone on
    this machine, up to 1.8x beside `make test`'s other workers)."""
    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-c", MEASURED, "input=builtin:sphere", "views=12", "image_size=512",
                        f"hydra.run.dir={run}"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    notes = {line.split()[0]: [int(v) for v in line.split()[1:]] for line in r.stderr.splitlines()
             if line.startswith(("ESTIMATE", "PEAK"))}
    (output, peak), (measured,) = notes["ESTIMATE"], notes["PEAK"]
    images = np.load(run / "images.npy")
    assert images.shape == (12, 3, 512, 512) and images.max() > 0.1
    assert (run / "images.npy").stat().st_size == output
    assert images.nbytes == 12 * 3 * 512 * 512 * 4 and 0 < output - images.nbytes <= 128  # (the header)
    assert measured / 2 <= peak <= 2 * measured, (peak, measured)
    assert "warning" not in r.stderr  # a small render says nothing about its size


def test_the_estimate_grows_with_views_and_pixels():
    small = render.estimate(render.RenderAppConfig(input="builtin:box", views=4, image_size=256))
    large = render.estimate(render.RenderAppConfig(input="builtin:box", views=12, image_size=4096))
    assert large.output_bytes - 128 == 12 * 3 * 4096 * 4096 * 4  # 2.4 GB
    assert large.extra_bytes >= 12 * 4096 * 4096 * render.HELD_BYTES > 100 * small.extra_bytes
    explicit = render.RenderAppConfig(input="builtin:box", layout="explicit", azim=[0.0, 90.0], elev=[30.0, 30.0])
    assert render.view_count(explicit) == 2


def test_a_large_render_is_announced_in_one_line_with_both_numbers(monkeypatch, capsys):
    monkeypatch.setattr(render, "available_memory", lambda: 64 * GB)
    render.check_size(render.RenderAppConfig(input="builtin:box", image_size=4096))  # (returns: it renders)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("mvtn-render: warning: image_size=4096 views=12: expected peak memory ~"), err[0]
    assert "images.npy ~2.4 GB" in err[0] and "64.0 GB of memory available" in err[0]
    # memory alone: a small images.npy, but more than half of what is available
    cfg = render.RenderAppConfig(input="builtin:box", image_size=1024)
    room = int(1.5 * render.estimate(cfg).extra_bytes)
    monkeypatch.setattr(render, "available_memory", lambda: room)
    render.check_size(cfg)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mvtn-render: warning: image_size=1024") and "images.npy ~151 MB" in err[0]
    monkeypatch.setattr(render, "available_memory", lambda: 64 * GB)
    render.check_size(cfg)
    assert capsys.readouterr().err == ""


def test_a_render_beyond_the_memory_available_is_refused_unless_allowed(monkeypatch, capsys):
    monkeypatch.setattr(render, "available_memory", lambda: 4 * GB)
    cfg = render.RenderAppConfig(input="builtin:box", image_size=4096)
    with pytest.raises(SystemExit) as e:
        render.check_size(cfg)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1, err
    assert err[0].startswith("mvtn-render: error: image_size=4096 views=12: expected peak memory ~")
    assert "images.npy ~2.4 GB" in err[0] and "4.0 GB of memory available" in err[0] and "allow_large=true" in err[0]
    cfg.allow_large = True
    render.check_size(cfg)  # rendered anyway, with the warning
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mvtn-render: warning: image_size=4096")


def test_the_cli_refuses_a_render_no_machine_holds_before_writing_anything(tmp_path):
    """image_size=65536: 12 views need terabytes; the refusal comes before Hydra makes the run folder."""
    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.render", "input=builtin:box", "image_size=65536",
                        f"hydra.run.dir={run}"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1, r.stderr[-3000:]
    assert err[0].startswith("mvtn-render: error: image_size=65536 views=12: expected peak memory ~")
    assert "images.npy ~618.5 GB" in err[0] and "Traceback" not in r.stderr
    assert not run.exists() and list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- mvtn-report: no runs

def _report(tmp_path, *folders):
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.report", *map(str, folders), "--out",
                           str(tmp_path / "rep")], cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_a_report_over_a_folder_without_runs_is_one_line_and_writes_nothing(tmp_path):
    empty = tmp_path / "empty"
    (empty / "notes").mkdir(parents=True)
    (empty / "notes" / "readme.txt").write_text("no run here\n")
    r = _report(tmp_path, empty)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1, r.stderr
    assert err[0].startswith(f"mvtn-report: error: {empty}: no runs in it (a run is a folder holding metrics.json, "
                             "status.json or .hydra/")
    assert r.stdout == "" and not (tmp_path / "rep").exists()


def test_an_empty_folder_beside_one_with_runs_is_still_named(tmp_path, capsys):
    from mvtn_exp.cli.report import main

    empty, runs, out = tmp_path / "empty", tmp_path / "runs", tmp_path / "rep"
    empty.mkdir()
    (runs / "a" / ".hydra").mkdir(parents=True)  # a run that never finished is a run: listed, not compared
    with pytest.raises(SystemExit) as e:
        main([str(runs), str(empty), "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and err[0].startswith(f"mvtn-report: error: {empty}: no runs in it")
    assert not out.exists()
    main([str(runs), "--out", str(out)])
    assert (out / "report.md").is_file()


def test_a_report_over_a_missing_folder_is_one_line(tmp_path):
    r = _report(tmp_path, tmp_path / "nope")
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [f"mvtn-report: error: {tmp_path / 'nope'}: no such folder"]
    assert not (tmp_path / "rep").exists()


# ----------------------------------------------------------------------------- mvtn-train: backbone.weights

def _small_cnn_state(**kw) -> dict:
    from mvtn_exp.models.backbones import small_cnn

    return small_cnn(10, **kw).state_dict()


def _bad_file(kind: str, path: Path) -> None:
    if kind == "zero-byte":
        path.write_bytes(b"")
    elif kind == "truncated":
        torch.save(_small_cnn_state(), path)
        path.write_bytes(path.read_bytes()[:path.stat().st_size // 2])
    elif kind == "random bytes":
        path.write_bytes(b"\x01" + np.random.default_rng(0).bytes(4095))
    elif kind == "pickle opcode then random bytes":
        path.write_bytes(b"\x80" + np.random.default_rng(1).bytes(4095))
    elif kind == "text":
        path.write_text("resnet18 weights: see the lab's wiki\n")
    elif kind == "whole module":
        torch.save(torch.nn.Linear(2, 2), path)
    elif kind == "no tensors":
        torch.save({"epoch": 3, "name": "x"}, path)
    elif kind == "another network":
        from mvtn_exp.models.backbones import resnet18

        torch.save(resnet18(10).state_dict(), path)
    elif kind == "wrong shapes":
        torch.save(_small_cnn_state(width=16), path)


BAD_FILES = {
    "zero-byte": "an empty file",
    "truncated": "a damaged zip archive",
    "random bytes": "binary data of 4096 bytes",
    "pickle opcode then random bytes": "cannot be read (UnpicklingError: ",
    "text": "a text file (starts with 'resnet18 weights: s",
    "whole module": "holds objects other than tensors and plain data (GLOBAL torch.nn.modules.linear.Linear)",
    "no tensors": "holds no state_dict",
    "another network": "its tensors do not fit backbone=small_cnn: missing keys (20): body.0.weight",
    "wrong shapes": "its tensors do not fit backbone=small_cnn: shape mismatches (22): body.0.weight: file [16, 3, 3, 3] vs model [32, 3, 3, 3]",
}


EXPECTED = ("(expected a state_dict for backbone=small_cnn saved with torch.save: a torchvision/"
            "timm-style .pth or a run's best.pt / last.pt; or one of ['imagenet'])")


def test_each_bad_weights_file_is_named_for_what_it_is(tmp_path):
    for i, (kind, what) in enumerate(BAD_FILES.items()):
        weights = tmp_path / f"{i}.pth"
        _bad_file(kind, weights)
        with pytest.raises(pretrained.WeightsFileError) as exc:
            pretrained.check_file("small_cnn", str(weights))
        text = str(exc.value)
        assert "\n" not in text and "weights_only" not in text, (kind, text)
        assert text.startswith(f"backbone.weights={weights}: {what}") and text.endswith(EXPECTED), (kind, text)


@pytest.mark.parametrize("kind", ["truncated", "wrong shapes"])
def test_a_bad_weights_file_is_one_line_before_any_run_folder(tmp_path, kind):
    weights = tmp_path / "weights.pth"
    _bad_file(kind, weights)
    work = tmp_path / "work"
    work.mkdir()
    run = work / "run"
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *TINY, f"dataset.root={work / 'cache'}",
                        f"backbone.weights={weights}", f"hydra.run.dir={run}"], cwd=work, capture_output=True,
                       text=True, timeout=120)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1, r.stderr[-3000:]
    assert err[0].startswith(f"mvtn-train: error: backbone.weights={weights}: {BAD_FILES[kind]}"), err[0]
    assert err[0].endswith(EXPECTED), err[0]
    assert "weights_only" not in r.stderr and "Traceback" not in r.stderr and r.stdout == ""
    assert not run.exists() and list(work.iterdir()) == []  # no run dir, .hydra, train.log or lock file


def test_weights_that_fit_pass_the_check_and_a_missing_file_or_folder_does_not(tmp_path):
    good, wrapped = tmp_path / "good.pt", tmp_path / "wrapped.pt"
    torch.save(_small_cnn_state(), good)
    torch.save({"state_dict": _small_cnn_state()}, wrapped)  # (a training script's checkpoint)
    pretrained.check_file("small_cnn", str(good))
    pretrained.check_file("small_cnn", str(wrapped))
    with pytest.raises(pretrained.WeightsFileError, match=r"^backbone.weights=\S+good.pt: its tensors do not fit backbone=resnet18"):
        pretrained.check_file("resnet18", str(good))
    with pytest.raises(pretrained.WeightsFileError, match=r"^backbone.weights=\S+nope.pt: no such file \(expected"):
        pretrained.check_file("small_cnn", str(tmp_path / "nope.pt"))
    (tmp_path / "run").mkdir()
    torch.save(_small_cnn_state(), tmp_path / "run" / "best.pt")
    with pytest.raises(pretrained.WeightsFileError, match=r"a folder, not a file; pass \S+run/best.pt"):
        pretrained.check_file("small_cnn", str(tmp_path / "run"))
