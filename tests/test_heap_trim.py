"""scripts/studies/heap_trim.py: one row per heap setting and target, each timed against ResNet-18 (in child processes)."""
from __future__ import annotations

import subprocess
import sys

import pytest

from studies import STUDIES


@pytest.mark.slow  # (longer than 5 s on 2 cores and covered in part elsewhere: make test-all)
def test_each_setting_times_every_target_in_its_own_process():
    out = subprocess.run([sys.executable, str(STUDIES / "heap_trim.py"), "--trim-mib", "64", "256", "--size", "32",
                          "--views", "2"], capture_output=True, text=True, check=True, timeout=300).stdout
    rows = [line.split("|")[1:-1] for line in out.splitlines()[2:]]
    assert [(r[0].strip(), r[1].strip()) for r in rows] == [(m, c) for m in ("64", "256") for c in ("points", "hard", "smooth")]
    assert all(float(r[2]) > 0 and float(r[3]) > 0 and abs(float(r[4]) - float(r[2]) / float(r[3])) < 5 * float(r[4]) for r in rows)
