"""Hydra search-path plugin of mvtn-exp: the working directory's ``configs/`` comes first.

A user adds ``configs/experiment/mine.yaml`` (or ``configs/mvnet/mine.yaml``, ...) beside their
work and runs ``mvtn-train +experiment=mine``; a file there with the name of a packaged one
replaces it. ``MVTN_CONFIGS=DIR`` points elsewhere. Only mvtn-exp's own commands are touched (their
main config source is the package's ``mvtn_exp/conf``).
"""
from __future__ import annotations

import os
from pathlib import Path

from hydra.core.config_search_path import ConfigSearchPath, SearchPathQuery
from hydra.plugins.search_path_plugin import SearchPathPlugin

def _is_mvtn_exp(path: str) -> bool:
    """``pkg://mvtn_exp.conf`` (the compose API) or ``file://.../mvtn_exp/conf`` (``hydra.main``)."""
    return path == "pkg://mvtn_exp.conf" or path.rstrip("/").endswith("mvtn_exp/conf")


class ProjectConfigs(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        if not any(p.provider == "main" and _is_mvtn_exp(p.path) for p in search_path.get_path()):
            return
        folder = Path(os.environ.get("MVTN_CONFIGS", "configs")).resolve()
        if folder.is_dir():
            search_path.prepend(provider="mvtn-exp project configs", path=f"file://{folder}",
                                anchor=SearchPathQuery(provider="main"))
