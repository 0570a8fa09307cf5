"""Count what a call would cost a GPU in launches and host syncs, on any device.

On CUDA each ATen operator that computes something is (at least) one kernel launch, ~5-10 us of
host time however small its tensors, and an operator whose output size depends on the data
(``nonzero``, a boolean mask, ``.item()``, ``.tolist()``) makes the host wait for the device. So
the number of such operators per call bounds how fast a launch-bound call can run, and it is the
same number on the CPU: ``OpCounter`` counts them with a ``TorchDispatchMode`` here, where no GPU is.

What counts as a kernel op: every dispatched ATen operator except views and metadata
(``OpOverload.is_view``, ``detach``, ``alias``, the ``empty*`` allocations, shape queries).
What counts as a sync: operators whose output size or value the host must read from the device
(``SYNC_OPS``; ``index``/``index_put`` only with a boolean index; ``repeat_interleave`` only
without ``output_size``), plus ``Tensor.tolist`` / ``Tensor.numpy``, which do not dispatch an
operator on the CPU and are counted by wrapping them while the counter is active.
"""
from __future__ import annotations

import collections
import contextlib

import torch
from torch.utils._python_dispatch import TorchDispatchMode

aten = torch.ops.aten

# no kernel: views, aliases, allocations without a fill, metadata
_FREE = {"detach", "alias", "empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided", "lift_fresh",
         "sym_size", "sym_stride", "sym_numel", "sym_storage_offset", "is_nonzero_meta", "_unsafe_view", "set_",
         "resize_", "_reshape_alias", "record_stream"}

# operators whose output size or value the host reads back
SYNC_OPS = {"nonzero", "_local_scalar_dense", "unique_consecutive", "_unique", "_unique2", "unique_dim", "masked_select",
            "bincount", "histc", "nonzero_numpy", "argwhere", "equal", "is_nonzero", "allclose"}


def _bool_index(indices) -> bool:
    return any(t is not None and torch.is_tensor(t) and t.dtype == torch.bool for t in (indices or ()))


def is_sync(func, args, kwargs) -> bool:
    """True when ``func(*args, **kwargs)`` makes the host wait for the device's data."""
    name = func.overloadpacket.__name__
    if name in SYNC_OPS:
        return True
    if name in ("index", "index_put", "index_put_", "_index_put_impl_"):
        return _bool_index(args[1] if len(args) > 1 else kwargs.get("indices"))
    if name == "repeat_interleave":
        return func._overloadname == "Tensor" and kwargs.get("output_size") is None and not (len(args) > 2 and args[2] is not None)
    if name == "_to_copy":
        dev = kwargs.get("device")
        src = args[0]
        return dev is not None and torch.device(dev).type == "cpu" and src.device.type != "cpu"
    return False


class OpCounter(TorchDispatchMode):
    """``with OpCounter() as c: fn()`` -> ``c.ops`` kernel ops, ``c.syncs`` host syncs, and ``c.by_name``
    / ``c.sync_names`` (Counters of operator names) for finding where they come from."""

    def __init__(self):
        super().__init__()
        self.ops = 0
        self.syncs = 0
        self.by_name: collections.Counter = collections.Counter()
        self.sync_names: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = func.overloadpacket.__name__
        if not (func.is_view or name in _FREE):
            self.ops += 1
            self.by_name[name] += 1
        if is_sync(func, args, kwargs):
            self.note_sync(name)
        return func(*args, **kwargs)

    def note_sync(self, name: str) -> None:
        self.syncs += 1
        self.sync_names[name] += 1

    def __enter__(self):
        out = super().__enter__()
        self._patches = contextlib.ExitStack()
        for attr in ("tolist", "numpy"):
            self._patches.enter_context(_counting_method(self, attr))
        return out

    def __exit__(self, *exc):
        self._patches.close()
        return super().__exit__(*exc)


@contextlib.contextmanager
def _counting_method(counter: OpCounter, attr: str):
    """Within the block, ``torch.Tensor.<attr>`` counts one sync per call (it reads the data on the host)."""
    original = getattr(torch.Tensor, attr)

    def wrapped(self, *args, **kwargs):
        counter.note_sync(attr)
        return original(self, *args, **kwargs)

    setattr(torch.Tensor, attr, wrapped)
    try:
        yield
    finally:
        setattr(torch.Tensor, attr, original)


def count_call(forward, loss=None) -> dict:
    """Kernel ops and syncs of ``out = forward()`` and, when ``loss`` is given, of ``loss(out).backward()``:
    ``{"fwd_ops", "fwd_syncs", "bwd_ops", "bwd_syncs", "fwd_top"}`` (the ten commonest forward ops)."""
    with OpCounter() as f:
        out = forward()
    row = {"fwd_ops": f.ops, "fwd_syncs": f.syncs, "fwd_top": f.by_name.most_common(10),
           "fwd_sync_names": dict(f.sync_names)}
    if loss is not None:
        value = loss(out)
        with OpCounter() as b:
            value.backward()
        row.update(bwd_ops=b.ops, bwd_syncs=b.syncs)
    return row
