"""Reading labelled point clouds from HDF5 files (ScanObjectNN, ModelNet40 ply_hdf5_2048)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from .mesh_io import ShapeFileError


def read_labelled_clouds(path: Path, num_classes: int, points: Optional[int] = None, optional=(),
                         expected: str = "") -> tuple[np.ndarray, np.ndarray, dict]:
    """``data [N, P, 3]`` float, ``label [N]`` int64 in ``0..num_classes-1`` (stored ``[N]`` or
    ``[N, 1]``, integers or integral floats) and the ``optional`` keys present; ``points``: the
    required P (None: any). Raises ShapeFileError naming the file and the key, and ``expected``."""
    import h5py

    try:
        fh = h5py.File(path, "r")
    except OSError as exc:
        raise ShapeFileError(f"{path}: not a readable HDF5 file ({exc})") from None
    with fh:
        for key in ("data", "label"):
            if key not in fh:
                raise ShapeFileError(f"{path}: no key {key!r} (has {sorted(fh.keys())}); expected {expected}")
        data, label = fh["data"][()], fh["label"][()]
        extra = {k: fh[k][()] for k in optional if k in fh}
    want = f"[N, {points if points else 'P'}, 3]"
    if data.ndim != 3 or data.shape[2] != 3 or (points and data.shape[1] != points) \
            or not np.issubdtype(data.dtype, np.floating):
        raise ShapeFileError(f"{path}: key 'data' has shape {data.shape} dtype {data.dtype}; expected float {want}")
    n = len(data)
    if label.ndim == 2 and label.shape[1] == 1:
        label = label[:, 0]
    if label.shape != (n,):
        raise ShapeFileError(f"{path}: key 'label' has shape {label.shape}; expected [{n}] or [{n}, 1] "
                             f"(one per cloud of 'data')")
    if not np.issubdtype(label.dtype, np.integer) and not (
            np.issubdtype(label.dtype, np.floating) and np.isfinite(label).all() and (label == np.round(label)).all()):
        raise ShapeFileError(f"{path}: key 'label' holds non-integer values (dtype {label.dtype})")
    label = label.astype(np.int64)
    bad = (label < 0) | (label >= num_classes)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ShapeFileError(f"{path}: key 'label' has {int(bad.sum())} values outside 0..{num_classes - 1} "
                             f"(e.g. {int(label[i])} at row {i})")
    return data, label, extra
