"""Dotted keys into nested records: ``lookup({"a": {"b": 1}}, "a.b") -> 1``, the one reading of a
dotted key that configs, checkpoints and metrics share."""
from __future__ import annotations

MISSING = object()


def lookup(node, dotted: str, default=None):
    """``node["a"]["b"]`` for ``"a.b"``, else ``default``. A key may hold dots itself (``"0.5"`` in
    ``{"acc": {"0.5": 1}}``): at each level the longest key that matches the rest is taken."""
    rest = dotted
    while rest:
        if not isinstance(node, dict):
            return default
        key = next((k for k in sorted(node, key=lambda k: len(str(k)), reverse=True)
                    if rest == str(k) or rest.startswith(f"{k}.")), MISSING)
        if key is MISSING:
            return default
        node, rest = node[key], rest[len(str(key)) + 1:]
    return node
