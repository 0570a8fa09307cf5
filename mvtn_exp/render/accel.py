"""``torch.compile`` of the renderer's per-candidate maths (``renderer.compile``: true, false, or null:
automatic, compiled where measured faster, ``auto_compiles``).

The soft search spends most of its time in chains of small element-wise ops over millions of
(pixel, face) candidates, each op reading and writing whole arrays; compiled, a chain becomes one
loop that gathers its inputs and keeps the intermediates in registers. Only functions marked
``@fused`` are compiled (``dynamic=True``: candidate counts change every call), each once per
process on first use, and only inside ``compiled(True)`` (the renderer's forward with
``renderer.compile=true``, or null where ``auto_compiles``); everywhere else they run eagerly, so the eager code stays the
definition. Compiled results agree with eager ones to float rounding (the compiler may fuse a
multiply-add), not bit for bit.
"""
from __future__ import annotations

import contextlib
import contextvars
import functools
import logging
import shutil
from pathlib import Path
from typing import Callable

import torch

_ENABLED = contextvars.ContextVar("mvtn_render_compile", default=False)
log = logging.getLogger(__name__)


_FAILED: list[str] = []  # why torch.compile failed in this process (then everything runs eagerly)


def fused(fn: Callable) -> Callable:
    """Mark ``fn`` (pure tensor maths, no Python side effects) for ``torch.compile`` under ``compiled(True)``.

    When the machine's compiler fails, the process says so in one log line and renders eagerly
    from then on (the same images to float rounding), never a traceback."""
    compiled_fn = None

    @functools.wraps(fn)
    def call(*args, **kwargs):
        nonlocal compiled_fn
        if torch.compiler.is_compiling() or not _ENABLED.get() or _FAILED:  # (in a compiled caller: traced into it)
            return fn(*args, **kwargs)
        if compiled_fn is None:
            compiled_fn = torch.compile(fn, dynamic=True)
        try:
            return compiled_fn(*args, **kwargs)
        except _compile_errors() as exc:  # the machine's compiler failed, not the maths: one line, then eager
            first = " ".join(str(exc).split()) or type(exc).__name__  # (one line)
            _FAILED.append(first[:200])
            log.warning("renderer.compile: torch.compile failed on this machine (%s); rendering eagerly "
                        "(the same images to float rounding)", first[:200])
            return fn(*args, **kwargs)

    call.eager = fn
    return call


def _compile_errors() -> tuple:
    """The exception types of a failed compile (backend or code generator), as this torch names them."""
    import torch._dynamo.exc as dynamo_exc

    kinds = [dynamo_exc.BackendCompilerFailed]
    try:
        from torch._inductor.exc import InductorError
        kinds.append(InductorError)
    except ImportError:  # (older torch)
        pass
    return tuple(kinds)


def enabled() -> bool:
    """True inside ``compiled(True)`` (and compiling works here): callers may then prefer a structure that fuses well."""
    return _ENABLED.get() and not _FAILED


def failure() -> str | None:
    """Why torch.compile failed in this process (it then renders eagerly), or None."""
    return _FAILED[0] if _FAILED else None


@contextlib.contextmanager
def compiled(on: bool):
    """Within the block, ``@fused`` functions run compiled when ``on``."""
    token = _ENABLED.set(bool(on))
    try:
        yield
    finally:
        _ENABLED.reset(token)


# renderer.compile=null compiles soft renders of at least this size (the compiled soft rows at 224
# px are the ones measured faster; smaller images are not measured, and their compile would not pay)
AUTO_MIN_SIZE = 192


def auto_compiles(device_type: str, soft: bool, image_size: int) -> bool:
    """What ``renderer.compile=null`` does for a call: compile where it was measured faster, i.e. a
    soft render of at least ``AUTO_MIN_SIZE`` px with autograd recording (a training step, where the
    one-time compile is paid once per process and every step gains), on a CPU that can compile.
    CUDA: eager until a GPU measures compiled against eager (``scripts/device_check.py``'s options
    stage). One-off renders (``mvtn-render``, evaluation: no autograd) stay eager."""
    return (device_type == "cpu" and soft and image_size >= AUTO_MIN_SIZE and torch.is_grad_enabled()
            and _unavailable_cached(device_type) is None)


@functools.lru_cache(maxsize=None)
def _unavailable_cached(device_type: str) -> str | None:
    return unavailable(device_type)


def require(device: str) -> None:
    """Raise ``ValueError`` (one line) when ``renderer.compile=true`` cannot run on ``device`` (``cpu``, ``cuda:N``)."""
    problem = unavailable(device.split(":")[0])
    if problem:
        raise ValueError(problem)


def unavailable(device_type: str) -> str | None:
    """Why ``torch.compile`` cannot run the renderer on this machine (None when it can): on CPU its
    code generator needs a C++ compiler; on CUDA it needs Triton."""
    if device_type == "cpu":
        import os
        import sysconfig

        cxx = os.environ.get("CXX", "g++")
        if not shutil.which(cxx):
            return f"renderer.compile=true needs a C++ compiler on CPU ({cxx!r} is not on PATH)"
        header = Path(sysconfig.get_paths()["include"]) / "Python.h"
        if not header.is_file():
            return f"renderer.compile=true needs Python's C headers on CPU ({header} is missing: install python3-dev)"
    if device_type == "cuda":
        try:
            from torch.utils._triton import has_triton
        except ImportError:  # (older torch)
            has_triton = None
        if has_triton is None or not has_triton():
            return "renderer.compile=true needs Triton for this GPU on CUDA (not installed, or the GPU is too old for it)"
    return None
