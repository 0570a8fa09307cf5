import subprocess
import sys
from pathlib import Path

import numpy as np


def test_mvtn_render_builtin(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "mvtn_exp.cli.render", "input=builtin:box", "views=3", "layout=circular",
         "image_size=32", f"hydra.run.dir={tmp_path}"],
        capture_output=True, text=True, check=True,
    )
    lines = out.stdout.strip().splitlines()
    png, npy = Path(lines[-3]), Path(lines[-2])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    imgs = np.load(npy)
    assert imgs.shape == (3, 3, 32, 32)
    assert imgs.max() > 0.2
