"""Where a result came from: package and library versions, the code's git commit, device, host, command."""
from __future__ import annotations

from ..config.help_text import package_version

import platform
import socket
import subprocess
import sys
import time
from pathlib import Path

import torch

PACKAGE_DIR = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(PACKAGE_DIR), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def git_state() -> dict:
    """``{"commit": sha or None, "dirty": bool or None}`` of the repository holding this code (None outside one)."""
    commit = _git("rev-parse", "HEAD")
    if commit is None:
        return {"commit": None, "dirty": None}
    status = _git("status", "--porcelain", "--untracked-files=no")
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux; else what ``platform`` knows)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name") and ":" in line:
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cpu_capability() -> str:
    """The vector instruction set torch's CPU kernels dispatch to (``AVX2``, ``AVX512``, ...): with the
    CPU model, what decides the float rounding of a CPU run."""
    try:
        return str(torch.backends.cpu.get_cpu_capability())
    except (AttributeError, RuntimeError):
        return "unknown"


def machine(prov: dict) -> str | None:
    """One string naming the hardware a run's float rounding came from: the GPU for a CUDA run, the
    CPU model and torch's CPU capability else; None for records made before these were kept."""
    if str(prov.get("device", "")).startswith("cuda"):
        return prov.get("device_name")
    return f"{prov['cpu']} ({prov.get('cpu_capability', 'unknown')})" if prov.get("cpu") else None


def provenance(device: str = "cpu") -> dict:
    """Everything needed to say which code, libraries and machine produced a run."""
    dev = torch.device(device)
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" and torch.cuda.is_available() else platform.processor() or platform.machine()
    return {"package": "mvtn-exp", "version": package_version(), **git_state(), "torch": str(torch.__version__),
            "cuda": None if torch.version.cuda is None else str(torch.version.cuda), "python": platform.python_version(), "device": str(dev), "device_name": name,
            "cpu": cpu_name(), "cpu_capability": cpu_capability(),
            "threads": torch.get_num_threads(), "host": socket.gethostname(), "command": [Path(sys.argv[0]).name, *sys.argv[1:]],
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
