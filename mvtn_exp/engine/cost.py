"""What a run costs: time and peak memory of training and inference, parameters and FLOPs of G and C.

``metrics.json["cost"]`` of every training run (and ``cost/*`` in TensorBoard):

- ``train_seconds_per_shape``: wall seconds of the training passes (no validation) per training
  shape seen, over the epochs this process ran (a resumed run counts its own epochs);
- ``infer_ms_per_shape``: the test pass (G, R, C at the configured batch size, data loading
  included) in milliseconds per test shape;
- ``train_peak_mib`` / ``infer_peak_mib``: the process's peak memory during the epochs (training
  and validation) and during the test pass: resident set size on CPU (``runtime.memory.PeakMemory``:
  sampled, and exact where the kernel lets the high-water mark be reset), ``max_memory_allocated``
  on CUDA (tensors only); ``memory_method`` says which;
- ``params_selector`` / ``params_mvnet``: trainable parameters of G and C;
- ``flops_selector_per_shape`` / ``flops_mvnet_per_shape``: forward FLOPs per shape counted by
  ``torch.utils.flop_counter`` (matrix products and convolutions; element-wise work is not counted)
  on one test batch in eval mode;
- the renderer is not described by FLOPs (its work is searching, sorting and scattering candidate
  faces per pixel), so its cost is given as ``render_ms_per_shape`` (forward and backward of
  training, from the step timer) and ``render_pixels_per_shape`` (M x H x W).
"""
from __future__ import annotations

import torch
from torch.utils.flop_counter import FlopCounterMode

from ..runtime.memory import PeakMemory

RENDERER_NOTE = ("FLOPs do not describe the renderer (face search, sorting and scattering per pixel): "
                 "its cost is render_ms_per_shape and render_pixels_per_shape")


def parameter_counts(model) -> dict[str, int]:
    """Trainable parameters of G and C (``MVTN.parameter_groups``)."""
    return {f"params_{name}": sum(p.numel() for p in params) for name, params in model.parameter_groups().items()}


def flops_per_shape(model, batch: dict) -> dict[str, float]:
    """Forward FLOPs per shape of G (``model.select``) and C (``model.mvnet``) on ``batch``, eval mode.

    ``selector=optimized``: G counts its starting layout only (no FLOPs); its per-batch steps
    (``selector.steps`` renders with C forward and backward) show in the run's seconds, not here."""
    B = len(batch["labels"])
    was = model.training
    model.eval()
    try:
        # G with autograd on: under no_grad a view of a parameter (``p.expand(B, M)``) requires grad
        # without a grad_fn, which FlopCounterMode's module hooks refuse
        with FlopCounterMode(display=False) as g_count:
            model.select(batch, refine=False)
        with torch.no_grad():
            views = tuple(v.detach() for v in model.select(batch))
            images = model.render(batch, *views)
            with FlopCounterMode(display=False) as c_count:
                model.mvnet_forward(images, views, batch)
    finally:
        model.train(was)
    return {"flops_selector_per_shape": g_count.get_total_flops() / B,
            "flops_mvnet_per_shape": c_count.get_total_flops() / B}


def peak_memory(device) -> PeakMemory:
    """A run-level peak-memory meter: samples every 20 ms (a training loop, not a micro-benchmark)."""
    return PeakMemory(device, interval_s=0.02)


def peak_total_mib(meter: PeakMemory) -> float:
    """The absolute peak of a finished ``PeakMemory`` (baseline + extra), MiB."""
    return float(meter.baseline_mib + meter.peak_mib)


def run_cost(model, cfg, *, train_seconds: float, train_shapes: int, infer_seconds: float, infer_shapes: int,
             train_memory: PeakMemory, infer_memory: PeakMemory, render_seconds: float,
             flops: dict) -> dict:
    """The ``cost`` block of ``metrics.json`` (module docstring)."""
    return {
        "train_seconds_per_shape": train_seconds / max(train_shapes, 1),
        "infer_ms_per_shape": 1000.0 * infer_seconds / max(infer_shapes, 1),
        "train_peak_mib": peak_total_mib(train_memory), "infer_peak_mib": peak_total_mib(infer_memory),
        "memory_method": train_memory.method,
        **parameter_counts(model), **flops,
        "render_ms_per_shape": 1000.0 * render_seconds / max(train_shapes, 1),
        "render_pixels_per_shape": cfg.views * cfg.image_size ** 2,
        "renderer_note": RENDERER_NOTE,
    }
