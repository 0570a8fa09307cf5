"""Processes that start together on a cold cache build it once: the others wait, then load it."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from mvtn_exp.data.packed import cached_arrays

from conftest import run_in_processes

KEYS = ("x",)


def _build_in_process(path: str, log: str, out: str) -> None:
    def build():
        with open(log, "a") as f:
            f.write("built\n")
        time.sleep(1.0)  # long enough for the other process to arrive while this one builds
        return {"x": np.arange(5)}

    arrays = cached_arrays(Path(path), {"v": 1}, KEYS, lambda a: None, build)
    np.save(out, arrays["x"])


def test_two_processes_on_a_cold_cache_build_it_once(tmp_path):
    path, log = tmp_path / "cache.npz", tmp_path / "built.log"
    run_in_processes(_build_in_process, [(str(path), str(log), str(tmp_path / f"out{i}.npy")) for i in range(2)])
    assert log.read_text().count("built") == 1
    for i in range(2):
        assert np.array_equal(np.load(tmp_path / f"out{i}.npy"), np.arange(5))
    assert path.is_file()
