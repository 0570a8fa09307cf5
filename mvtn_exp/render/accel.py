"""Opt-in ``torch.compile`` of the renderer's per-candidate maths (``renderer.compile=true``).

The soft search spends most of its time in chains of small element-wise ops over millions of
(pixel, face) candidates, each op reading and writing whole arrays; compiled, a chain becomes one
loop that gathers its inputs and keeps the intermediates in registers. Only functions marked
``@fused`` are compiled (``dynamic=True``: candidate counts change every call), each once per
process on first use, and only inside ``compiled(True)`` (the renderer's forward with
``renderer.compile=true``); everywhere else they run eagerly, so the eager code stays the
definition. Compiled results agree with eager ones to float rounding (the compiler may fuse a
multiply-add), not bit for bit.
"""
from __future__ import annotations

import contextlib
import contextvars
import functools
import shutil
from typing import Callable

import torch

_ENABLED = contextvars.ContextVar("mvtn_render_compile", default=False)


def fused(fn: Callable) -> Callable:
    """Mark ``fn`` (pure tensor maths, no Python side effects) for ``torch.compile`` under ``compiled(True)``."""
    compiled_fn = None

    @functools.wraps(fn)
    def call(*args, **kwargs):
        nonlocal compiled_fn
        if torch.compiler.is_compiling() or not _ENABLED.get():  # (inside a compiled caller: traced into it)
            return fn(*args, **kwargs)
        if compiled_fn is None:
            compiled_fn = torch.compile(fn, dynamic=True)
        return compiled_fn(*args, **kwargs)

    call.eager = fn
    return call


def enabled() -> bool:
    """True inside ``compiled(True)``: callers may then prefer a structure that fuses well."""
    return _ENABLED.get()


@contextlib.contextmanager
def compiled(on: bool):
    """Within the block, ``@fused`` functions run compiled when ``on``."""
    token = _ENABLED.set(bool(on))
    try:
        yield
    finally:
        _ENABLED.reset(token)


def unavailable(device_type: str) -> str | None:
    """Why ``torch.compile`` cannot run the renderer on this machine (None when it can): on CPU its
    code generator needs a C++ compiler; on CUDA it needs Triton."""
    if device_type == "cpu":
        import os

        cxx = os.environ.get("CXX", "g++")
        return None if shutil.which(cxx) else f"renderer.compile=true needs a C++ compiler on CPU ({cxx!r} is not on PATH)"
    if device_type == "cuda":
        try:
            import triton  # noqa: F401
        except ImportError:
            return "renderer.compile=true needs Triton on CUDA (not installed)"
    return None
