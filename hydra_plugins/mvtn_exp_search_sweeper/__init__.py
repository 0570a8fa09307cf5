"""Hydra sweeper plugin of mvtn-exp: ``hydra/sweeper=mvtn_optuna``, Optuna's sweeper with start
points, repeats told without training and resumable job folders (the loop and its rules:
``mvtn_exp/plugins/search_sweeper.py``). Hydra instantiates plugins only from this package."""
from __future__ import annotations

import sys
from typing import List

from hydra_plugins.hydra_optuna_sweeper.optuna_sweeper import OptunaSweeper

from mvtn_exp.plugins import search_sweeper as _conf  # noqa: F401 (stores hydra/sweeper=mvtn_optuna)


class SearchSweeper(OptunaSweeper):
    """``OptunaSweeper`` whose ``sweep`` is ``search_sweeper.search``."""

    def __init__(self, start_points=(), max_repeats: int = 50, **kwargs) -> None:
        super().__init__(**kwargs)
        self.start_points = [dict(p) for p in (start_points or [])]
        self.max_repeats = int(max_repeats)

    def sweep(self, arguments: List[str]) -> None:
        from mvtn_exp.plugins.search_sweeper import SearchRefused, search

        try:
            search(self.sweeper, arguments, self.start_points, self.max_repeats)
        except SearchRefused as exc:
            print(f"mvtn-train: error: {exc}", file=sys.stderr)
            sys.exit(2)
