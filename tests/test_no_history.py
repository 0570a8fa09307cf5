"""The code states contracts; dates, issue numbers and measured results live in docs/results/.

Every Python file and config comment of the package is read: a date (``2026-12-01``), an issue
number (``issue 9``) or a result with its spread (``0.962 +- 0.009``, ``93.4 ± 0.3``) fails, naming
the file and line. ``paper_tables.yaml`` is exempt: it is the paper's numbers, data of the report.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mvtn_exp"
EXEMPT = {"paper_tables.yaml"}
PATTERNS = {
    "a date": re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b"),
    "an issue number": re.compile(r"\b[Ii]ssues? ?#?\d+\b"),
    "a result with its spread": re.compile(r"\d\.\d+ ?(\+-|±|\+/-) ?\d"),
}


def _files() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*") if p.suffix in (".py", ".yaml") and p.name not in EXEMPT)


def history(text: str) -> list[tuple[int, str]]:
    """(line, what) for every date, issue number or quoted result in ``text``."""
    return [(n, what) for n, line in enumerate(text.splitlines(), 1) for what, rx in PATTERNS.items() if rx.search(line)]


def test_the_detector_finds_each_kind_and_passes_contracts():
    assert [w for _, w in history("measured 2026-12-02 on 3 seeds")] == ["a date"]
    assert [w for _, w in history("Issue 9 asks for both")] == ["an issue number"]
    assert [w for _, w in history("# test accuracy 0.962 +- 0.009")] == ["a result with its spread"]
    assert [w for _, w in history("93.4 ± 0.3")] == ["a result with its spread"]
    assert history("offsets (+-180/M azimuth, +-90 elevation); ``[B, M]`` degrees; lr 1e-3") == []


@pytest.mark.parametrize("path", _files(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_dates_issue_numbers_or_quoted_results_in_the_package(path):
    found = history(path.read_text())
    assert not found, "; ".join(f"{path.relative_to(PACKAGE.parent)}:{n}: {what}" for n, what in found)
