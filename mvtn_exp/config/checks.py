"""Value checks shared by every config schema: each raises ``ValueError`` whose message starts
with ``key=value:`` and says what was expected (the CLI prints it as one line, exit code 2)."""
from __future__ import annotations

from typing import Any


def one_of(key: str, value: Any, allowed) -> None:
    if value not in allowed:
        raise ValueError(f"{key}={value!r}: expected one of {', '.join(map(str, allowed))}")


def fraction(key: str, value: float) -> None:
    """``value`` in [0, 1)."""
    if not 0.0 <= value < 1.0:
        raise ValueError(f"{key}={value!r}: must be in [0, 1)")


def at_least(key: str, value, low, strict: bool = False) -> None:
    bad = value <= low if strict else value < low
    if value is None or bad:
        raise ValueError(f"{key}={value!r}: must be {'>' if strict else '>='} {low}")
