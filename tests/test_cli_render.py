"""mvtn-render end to end: the documented command on a real file, explicit views, bad input."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest


def _run(tmp_path, *args):
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.render", *args, f"hydra.run.dir={tmp_path}"],
                          capture_output=True, text=True)


def test_documented_command_on_real_modelnet_file(tmp_path, real_samples):
    path = real_samples / "ModelNet40" / "monitor" / "train" / "monitor_0001.off"
    out = _run(tmp_path, f"input={path}", "views=12", "layout=spherical", "image_size=128", "zup=true")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    written = [Path(p) for p in lines[-3:]]
    assert [p.name for p in written] == ["views.png", "images.npy", "views.csv"]
    assert all(p.is_file() and p.parent == tmp_path for p in written)
    imgs = np.load(written[1])
    assert imgs.shape == (12, 3, 128, 128)
    assert (imgs.reshape(12, -1).max(1) > 0.1).all(), "every view shows the monitor"
    assert len(written[2].read_text().splitlines()) == 13


def test_explicit_angles_and_points(tmp_path):
    pts = np.random.default_rng(0).normal(size=(500, 3))
    np.save(tmp_path / "cloud.npy", pts)
    out = _run(tmp_path / "run", f"input={tmp_path / 'cloud.npy'}", "azim=[0,90,180]", "elev=[0,45,90]", "image_size=32")
    assert out.returncode == 0, out.stderr
    imgs = np.load(out.stdout.strip().splitlines()[-2])
    assert imgs.shape == (3, 3, 32, 32) and imgs.max() > 0.5


@pytest.mark.parametrize("args,match", [
    (["input=/no/such/mesh.off"], "no such file"),
    (["input=builtin:teapot"], "unknown built-in shape"),
    (["input=builtin:box", "layout=grid"], "layout='grid'"),
    (["input=builtin:box", "azim=[0,90]", "elev=[0]"], "equal length"),
    (["input=builtin:box", "renderer.mode=wire"], "renderer.mode"),
])
def test_bad_input_is_one_clear_line(tmp_path, args, match):
    out = _run(tmp_path, *args)
    assert out.returncode == 2
    assert match in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize("arg,match", [
    ("renderer.mdoe=soft", "allowed keys here: "),
    ("viewz=3", "allowed keys here: "),
    ("image_size=big", "key 'image_size'"),
])
def test_config_errors_are_one_line_with_exit_code_2(tmp_path, arg, match):
    out = _run(tmp_path, "input=builtin:box", arg)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in out.stderr
    assert "mvtn_exp/conf/render.yaml" in lines[0] and match in lines[0]
    if "allowed" in match:
        assert " mode," in lines[0] or "views" in lines[0]
