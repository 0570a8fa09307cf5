"""``PeakMemory``: the *extra* peak memory used by a block of code, in MiB.

CUDA: ``torch.cuda.reset_peak_memory_stats`` at entry, ``max_memory_allocated - memory_allocated(at
entry)`` at exit (tensor memory only; the caching allocator's reserve is not counted).

CPU: a background thread reads the resident set size from ``/proc/self/statm`` every ``interval_s``
(0.5 ms) and keeps the maximum; the result is that maximum minus the RSS at entry. Where the kernel
allows it, the peak is also read exactly: writing ``5`` to ``/proc/self/clear_refs`` resets the
process high-water mark ``VmHWM`` at entry, and ``VmHWM`` at exit is the true peak RSS; the reported
peak is the larger of the two readings (the sampler can miss a peak shorter than its interval or
while the main thread holds the GIL).

RSS only falls when freed memory goes back to the kernel. glibc serves large allocations with
``mmap`` and unmaps them on free, but its threshold for that grows dynamically (up to 32 MiB) after
big blocks are freed, after which freed memory stays in the heap and a later peak looks smaller than
it is (the memory is reused without the RSS moving). Run with ``MALLOC_MMAP_THRESHOLD_=65536`` in the
environment (``mvtn-bench`` re-executes itself with it) so every block of 64 KiB or more is mapped
and unmapped and the RSS follows the live tensors. Not reentrant: do not nest two on the CPU.

That setting costs speed (every large tensor is a fresh mapping to fault in: the renderer's CPU
forward+backward ran ~2.5x slower, ResNet-18 ~1.6x), so ``set_malloc_mode("speed")`` switches a
running process to the thresholds glibc's dynamic rule settles at after large frees (mmap 32 MiB,
trim 64 MiB) for timing; ``mvtn-bench`` measures all memory first, then switches once and times.
On CPU, ``PeakMemory`` also calls ``malloc_trim(0)`` at entry, so free heap memory left by earlier
code is returned before the baseline is read (without the pinned threshold this narrows, but does
not close, the gap: heap reuse and fragmentation still differ from the live-tensor peak).
"""
from __future__ import annotations

import ctypes
import os
import threading
import time

import torch

MiB = float(1 << 20)
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def _statm_fd() -> int | None:
    try:
        return os.open("/proc/self/statm", os.O_RDONLY)
    except OSError:
        return None


def _rss_bytes(fd: int) -> int:
    # statm: size resident shared text lib data dt (pages)
    return int(os.pread(fd, 128, 0).split()[1]) * _PAGE


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _hwm_bytes() -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameters
MALLOC_MODES = {"measure": (64 << 10, 128 << 10), "speed": (32 << 20, 64 << 20)}  # (mmap, trim) thresholds


def _libc():
    try:
        lib = ctypes.CDLL(None)
        lib.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        lib.malloc_trim.argtypes = [ctypes.c_size_t]
        return lib
    except (OSError, AttributeError):  # not glibc
        return None


_LIBC = _libc()


def malloc_trim() -> bool:
    """Return free heap memory to the kernel (glibc ``malloc_trim(0)``); False where unavailable."""
    return bool(_LIBC is not None and _LIBC.malloc_trim(0) >= 0)


def set_malloc_mode(mode: str) -> bool:
    """glibc thresholds: ``measure`` = pinned 64 KiB mmap threshold (as ``MALLOC_MMAP_THRESHOLD_=65536``),
    ``speed`` = 32 MiB mmap / 64 MiB trim (where the dynamic rule ends up after large tensors are freed).
    Returns False where mallopt is unavailable (non-glibc); the process keeps its settings then."""
    if mode not in MALLOC_MODES:
        raise ValueError(f"malloc mode {mode!r}: expected one of {list(MALLOC_MODES)}")
    if _LIBC is None:
        return False
    mmap_t, trim_t = MALLOC_MODES[mode]
    ok = _LIBC.mallopt(_M_MMAP_THRESHOLD, mmap_t) == 1 and _LIBC.mallopt(_M_TRIM_THRESHOLD, trim_t) == 1
    if mode == "measure":
        malloc_trim()
    return ok


def malloc_threshold_note() -> str:
    """One line describing whether the glibc mmap threshold is pinned (CPU memory numbers are exact)."""
    v = os.environ.get("MALLOC_MMAP_THRESHOLD_")
    return f"MALLOC_MMAP_THRESHOLD_={v}" if v else "MALLOC_MMAP_THRESHOLD_ unset (CPU peaks may be under-reported)"


class PeakMemory:
    """Context manager: ``with PeakMemory(device) as pm: ...`` then ``pm.peak_mib`` (extra peak, MiB).

    Also sets ``baseline_mib`` (memory at entry), ``samples`` (CPU sampler readings taken) and
    ``method`` (``cuda``, ``rss-sampled`` or ``rss-sampled+hwm``).
    """

    def __init__(self, device: torch.device | str | None = None, interval_s: float = 5e-4):
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.interval_s = float(interval_s)
        self.peak_mib = float("nan")
        self.baseline_mib = float("nan")
        self.samples = 0
        self.method = ""
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._peak = 0
        self._fd: int | None = None
        self._hwm = False

    # ---------------------------------------------------------------- CUDA
    def _enter_cuda(self) -> None:
        torch.cuda.synchronize(self.device)
        self._base = torch.cuda.memory_allocated(self.device)
        torch.cuda.reset_peak_memory_stats(self.device)
        self.baseline_mib = self._base / MiB
        self.method = "cuda"

    def _exit_cuda(self) -> None:
        torch.cuda.synchronize(self.device)
        self.peak_mib = max(0, torch.cuda.max_memory_allocated(self.device) - self._base) / MiB

    # ---------------------------------------------------------------- CPU
    def _sample(self) -> None:
        fd, stop, wait = self._fd, self._stop, self.interval_s
        while not stop.is_set():
            rss = _rss_bytes(fd)
            if rss > self._peak:
                self._peak = rss
            self.samples += 1
            time.sleep(wait)

    def _enter_cpu(self) -> None:
        malloc_trim()
        self._fd = _statm_fd()
        if self._fd is None:
            raise RuntimeError("PeakMemory: /proc/self/statm is not readable; CPU memory needs Linux procfs")
        self._base = _rss_bytes(self._fd)
        self._peak = self._base
        self.baseline_mib = self._base / MiB
        self._hwm = _reset_hwm()
        self.method = "rss-sampled+hwm" if self._hwm else "rss-sampled"
        self._stop.clear()
        self._thread = threading.Thread(target=self._sample, name="PeakMemory", daemon=True)
        self._thread.start()

    def _exit_cpu(self) -> None:
        self._stop.set()
        self._thread.join()
        peak = max(self._peak, _rss_bytes(self._fd))
        if self._hwm:
            hwm = _hwm_bytes()
            if hwm is not None:
                peak = max(peak, hwm)
        os.close(self._fd)
        self._fd = None
        self.peak_mib = max(0, peak - self._base) / MiB

    # ---------------------------------------------------------------- protocol
    def __enter__(self) -> "PeakMemory":
        if self.device.type == "cuda":
            self._enter_cuda()
        else:
            self._enter_cpu()
        return self

    def __exit__(self, *exc) -> None:
        if self.device.type == "cuda":
            self._exit_cuda()
        else:
            self._exit_cpu()
