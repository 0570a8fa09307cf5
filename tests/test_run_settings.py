"""One definition of a setting (``runs/settings.py``) for every reader of finished runs."""
from __future__ import annotations

import json
import re
from pathlib import Path

from mvtn_exp.runs import settings as run_keys, sweep
from mvtn_exp.runs.folders import find_runs

PACKAGE = Path(__file__).resolve().parents[1] / "mvtn_exp"


def test_where_and_how_a_run_ran_is_not_its_setting():
    for key in ("seed", "threads", "overwrite", "device", "+logger.tensorboard", "paths.data_dir", "dataset.root",
                "dataset.num_workers", "hydra.launcher.n_jobs"):
        assert run_keys.is_local(key), key
    for key in ("views", "dataset.name", "dataset.rootless", "selector.seedling", "threadsafe"):
        assert not run_keys.is_local(key), key


def test_sweep_summaries_and_compare_agree_on_threads_and_overwrite(tmp_path):
    # a sweep's setting: jobs that differ only in threads, overwrite or seed are one
    assert sweep._setting(["views=4", "threads=1", "overwrite=true", "seed=3"]) == "views=4"
    assert sweep._setting(["threads=2", "seed=0"]) == "(defaults)"
    # mvtn-compare's reader drops the same keys from a run's stored config
    run = tmp_path / "r"
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps({"config": {"views": 4, "threads": 1, "overwrite": True, "seed": 3},
                                                  "test_acc": 0.5}))
    (read,) = find_runs([tmp_path])
    assert read.settings == {"views": 4} and read.seed == 3


def test_no_second_list_of_run_local_keys_in_the_package():
    second = [p.relative_to(PACKAGE).as_posix() for p in PACKAGE.rglob("*.py") if p.name != "settings.py"
              and re.search(r"""\(\s*["']seed["']\s*,\s*["'](device|ckpt_path|threads)""", p.read_text())]
    assert not second, f"a second definition of what is not a setting in {second}: use runs/settings.py"


def test_one_reading_of_a_dotted_key():
    """Configs, checkpoints and metrics read dotted keys one way (runtime/dotted.py), keys with
    dots of their own included; no second walker in the package."""
    from mvtn_exp.runtime.dotted import lookup

    record = {"cost": {"infer_ms": 2.0}, "acc_at": {"0.5": 0.9, "0": 0.1}, "a": {"b": {"c": None}}}
    assert lookup(record, "cost.infer_ms") == 2.0 and lookup(record, "acc_at.0.5") == 0.9
    assert lookup(record, "acc_at.0") == 0.1 and lookup(record, "cost.nope") is None
    assert lookup(record, "a.b.c", default="x") is None and lookup(record, "a.z", default="x") == "x"
    walkers = [p.relative_to(PACKAGE).as_posix() for p in PACKAGE.rglob("*.py")
               if re.search(r"for \w+ in [\w.()]*\.split\(\"\.\"\):", p.read_text())]
    assert walkers == [], f"a second dotted-key walker in {walkers}: use runtime/dotted.lookup"
