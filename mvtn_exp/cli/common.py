"""What every command shares beyond its config: the output folder checked writable, an OSError in
one line, a failed run dir marked."""
from __future__ import annotations

import sys
from pathlib import Path

from ..config.compose import given



def check_writable(prog: str, argv: list[str], default: str = "outputs") -> None:
    """Before Hydra makes a run dir: the output folder (``hydra.run.dir=``/``hydra.sweep.dir=``, else
    ``paths.output_dir=``, else ``default``) must be creatable and writable; else one line, exit 2."""
    import os
    import tempfile

    keys = given(argv)
    target = Path(keys.get("hydra.run.dir") or keys.get("hydra.sweep.dir") or keys.get("paths.output_dir") or default)
    probe = target
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent  # the nearest existing folder decides whether target can be made
    try:
        if not probe.is_dir():
            raise NotADirectoryError(f"{probe} is not a folder")
        fd, tmp = tempfile.mkstemp(dir=probe, prefix=".mvtn-write-test-")
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        print(f"{prog}: error: cannot write the run's output under {str(target)!r} ({exc.strerror or exc}); "
              "set paths.output_dir=DIR to a writable folder", file=sys.stderr)
        sys.exit(2)


def os_error_text(exc: OSError) -> str:
    """One line for an OSError: a full disk says so, naming the file being written."""
    import errno

    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        where = f" (writing {exc.filename})" if exc.filename else ""
        return f"no space left on the device{where}: free some space, or set paths.output_dir to another disk"
    return str(exc)


def mark_failed(run_dir: Path, status: str, error: str) -> None:
    """``<run_dir>/status.json`` = ``{"status", "error"}``: a run dir left by a failed command says so
    (the sweep summary reads the same file)."""
    from ..engine.run_dir import write_status

    write_status(run_dir, status, error)
