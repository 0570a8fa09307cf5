"""The prepared GPU check: everything this project wants to know from a lent GPU, in one run of
at most ``TOTAL_S`` seconds, written as small text records (``device_check.md`` + ``.json``, never
checkpoints) into one folder.

``python scripts/device_check.py OUT_DIR`` (``--dry-run``: tiny sizes on the CPU, as the test
suite runs it). Each stage runs in a child process under its own deadline; a stage that fails or
overruns is recorded with its error and the next one runs. Stages:

1. ``environment``: torch, CUDA, the GPU, its memory;
2. ``parity``: the same renders on the CPU and on CUDA (hard, soft, points): largest image and
   alpha differences, and the relative difference of the camera gradients;
3. ``paper_scale_fp32`` / ``paper_scale_bf16``: ``bench/paper_scale.py``'s rows (kernel ops,
   syncs, memory budget, time per shape against ResNet-18), ResNet-18 in fp32, then under bf16
   autocast (R stays float32);
4. ``train_step``: a paper-scale training step (B = 32, 12 x 224 px, ResNet-18; MVCNN and
   ViewGCN; hard and soft) split into G / R / C with its peak memory;
5. ``options``: what ``renderer.deterministic`` and ``renderer.compile`` cost at B = 8 (soft):
   time per shape against the default, whether two deterministic renders are identical, the first
   compiled call's seconds (compile is skipped in the dry run);
6. ``train_embedded``: a short training of the embedded dataset on the device.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import torch

STAGES = ("environment", "parity", "paper_scale_fp32", "paper_scale_bf16", "train_step", "options", "train_embedded")
DEADLINE_S = {"environment": 60, "parity": 60, "paper_scale_fp32": 120, "paper_scale_bf16": 45, "train_step": 90,
              "options": 75, "train_embedded": 60}
TOTAL_S = 420  # 7 minutes in all
IMAGE_TOL, GRAD_TOL = 1e-4, 1e-3


def _sizes(dry: bool) -> dict:
    """The scale of every stage: the paper's, or a few seconds' worth on a CPU (``dry``)."""
    if dry:
        return dict(batch=2, views=3, size=48, counted_batches=(2,), embedded_epochs=1)
    return dict(batch=32, views=12, size=224, counted_batches=(8, 32), embedded_epochs=3)


def _device(dry: bool) -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() and not dry else "cpu")


# ---------------------------------------------------------------------------- stages
def stage_environment(dry: bool) -> dict:
    from ..engine.provenance import provenance

    dev = _device(dry)
    out = {"provenance": provenance(str(dev)), "cuda_available": torch.cuda.is_available()}
    if dev.type == "cuda":
        free, total = torch.cuda.mem_get_info(dev)
        out.update(gpu=torch.cuda.get_device_name(dev), free_mib=free / 2**20, total_mib=total / 2**20,
                   capability=list(torch.cuda.get_device_capability(dev)), tf32_matmul=torch.backends.cuda.matmul.allow_tf32)
    return out


def _parity_scene(dry: bool):
    from .paper_scale import scale, scene

    with scale(2, 4, 64, "torus-2k" if dry else "torus-20k"):
        return {kind: scene(kind, 2, "cpu") for kind in ("hard", "soft", "points")}


def stage_parity(dry: bool) -> dict:
    """Renders on the CPU and on the device: max |image|, max |alpha| differences, and
    ``|g_dev - g_cpu| / |g_cpu|`` of the camera gradients (dry: CPU against CPU, the code path only)."""
    from ..render.layouts import spherical
    from ..render.renderer import MultiViewRenderer
    from .paper_scale import MODES

    dev = _device(dry)
    size = 64 if dry else 224
    rows = []
    for kind, shapes in _parity_scene(dry).items():
        settings = dict(MODES[kind])
        if kind == "soft":
            settings["sigma"] = 3e-4
        outs = []
        for where, dtype in (("cpu", torch.float32), (dev, torch.float32)):
            azim, elev, dist = spherical(4, batch=2, distance=2.2, device=where, sphere="fibonacci")
            a = azim.to(dtype).requires_grad_(True)
            e = elev.to(dtype).requires_grad_(True)
            r = MultiViewRenderer(image_size=size, **settings).eval()
            o = r(shapes.to(where, dtype), a, e, dist.to(dtype))
            (o.images * torch.linspace(0, 1, size, device=where, dtype=dtype)).sum().add(o.alpha.sum()).backward()
            outs.append([t.detach().double().cpu() for t in (o.images, o.alpha, a.grad, e.grad)])
        (i0, a0, ga0, ge0), (i1, a1, ga1, ge1) = outs
        g0, g1 = torch.cat([ga0.flatten(), ge0.flatten()]), torch.cat([ga1.flatten(), ge1.flatten()])
        image_diff = float(max((i0 - i1).abs().max(), (a0 - a1).abs().max()))
        grad_rel = float((g1 - g0).norm() / g0.norm().clamp(min=1e-30))
        rows.append(dict(kind=kind, image_max_diff=image_diff, grad_rel_diff=grad_rel,
                         images_ok=image_diff <= IMAGE_TOL, grads_ok=grad_rel <= GRAD_TOL))
    return {"device": str(dev), "rows": rows}


def stage_paper_scale(dry: bool, bf16: bool) -> dict:
    from . import paper_scale

    dev = _device(dry)
    s = _sizes(dry)
    with paper_scale.scale(s["batch"], s["views"], s["size"], "torus-2k" if dry else "torus-20k"):
        res = paper_scale.measure(dev, batches=s["counted_batches"], resnet_bf16=bf16,
                                  budget_rows=not bf16)
        res["markdown"] = paper_scale.markdown(res, dev.type == "cuda")
    return res


def stage_train_step(dry: bool) -> dict:
    """One training step of the paper's size per (multi-view net, renderer mode): seconds of G, R,
    C, optimizer (``engine/step_timer.py``) and the step's peak memory, after one warm-up step."""
    from ..runtime.memory import PeakMemory
    from ..data.collate import collate_shapes
    from ..engine.step_timer import StepTimer
    from ..engine.trainer import as_config, make_datasets
    from ..model import build_mvtn

    dev = _device(dry)
    s = _sizes(dry)
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        for mvnet in ("mvcnn", "viewgcn"):
            for mode in ("hard", "soft"):
                cfg = as_config({"views": s["views"], "image_size": s["size"], "batch_size": s["batch"],
                                 "device": str(dev), "backbone": {"name": "small_cnn" if dry else "resnet18"},
                                 "mvnet": {"name": mvnet}, "renderer": {"mode": mode, "shading": "smooth"},
                                 "dataset": {"root": cache, "num_per_class": [4, 1, 1]},
                                 "logger": {"progress": False, "tensorboard": False}})
                ds = make_datasets(cfg)["train"]
                batch = collate_shapes([ds[i % len(ds)] for i in range(s["batch"])])
                model = build_mvtn(cfg, len(ds.classes)).to(dev).train()
                opt = torch.optim.SGD(model.parameters(), lr=1e-3)
                timer = StepTimer(dev)
                for step in range(2):  # a warm-up, then the measured step
                    if step == 1:
                        timer = StepTimer(dev)
                    with PeakMemory(dev) as pm:
                        with timer.stage("selector"):
                            views = model.select(batch)
                        with timer.stage("render"):
                            images = model.render(batch, *views)
                        with timer.stage("backbone"):
                            logits, _ = model.classify(images, views, batch)
                            loss = torch.nn.functional.cross_entropy(logits, batch["labels"].to(dev))
                        timer.backward(loss, views, images)
                        with timer.stage("optimizer"):
                            opt.step()
                            opt.zero_grad(set_to_none=True)
                    timer.step_done()
                means = timer.means()
                rows.append(dict(mvnet=mvnet, mode=mode, peak_mib=pm.peak_mib,
                                 **{f"{k}_ms": 1000 * v for k, v in means.items()}))
    return {"device": str(dev), "batch": s["batch"], "views": s["views"], "size": s["size"], "rows": rows}


def stage_train_embedded(dry: bool) -> dict:
    """``mvtn-train``'s default experiment, shortened, on the device: test accuracy and seconds."""
    from ..engine.trainer import train

    dev = _device(dry)
    s = _sizes(dry)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = {"device": str(dev), "epochs": s["embedded_epochs"], "dataset": {"root": str(Path(tmp) / "cache")},
               "logger": {"progress": False, "tensorboard": False}}
        if dry:
            cfg.update(views=2, image_size=32, dataset={**cfg["dataset"], "num_per_class": [4, 2, 2]})
        t0 = time.perf_counter()
        metrics = train(cfg, Path(tmp) / "run")
        seconds = time.perf_counter() - t0
    return {"device": str(dev), "epochs": s["embedded_epochs"], "test_acc": metrics["test_acc"],
            "best_val_acc": metrics["best_val_acc"], "seconds": seconds}


def stage_options(dry: bool) -> dict:
    """Soft renders at B = 8 (dry: 2) with ``deterministic`` and ``compile`` against the default."""
    from ..render import accel
    from ..render.layouts import spherical
    from ..render.renderer import MultiViewRenderer
    from .paper_scale import MODES, scale, scene

    dev = _device(dry)
    s = _sizes(dry)
    B = 2 if dry else 8
    with scale(s["batch"], s["views"], s["size"], "torus-2k" if dry else "torus-20k"):
        shapes = scene("soft", B, dev)
    azim, elev, dist = spherical(s["views"], batch=B, distance=2.2, device=dev, sphere="fibonacci")

    def render(**extra):
        a = azim.clone().requires_grad_(True)
        out = MultiViewRenderer(image_size=s["size"], **MODES["soft"], **extra)(shapes, a, elev, dist)
        out.images.sum().backward()
        return out.images.detach(), a.grad

    def timed(**extra):
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        t0 = time.perf_counter()
        out = render(**extra)
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        return out, 1000 * (time.perf_counter() - t0) / B

    render()  # warm-up
    (img, grad), base_ms = timed()
    (img1, grad1), det_ms = timed(deterministic=True)
    (img2, grad2), _ = timed(deterministic=True)
    out = {"device": str(dev), "batch": B, "default_ms": base_ms, "deterministic_ms": det_ms,
           "deterministic_repeats": bool(torch.equal(img1, img2) and torch.equal(grad1, grad2)),
           "default_repeats": bool(torch.equal(img, render()[0]))}
    problem = "skipped in the dry run" if dry else accel.unavailable(dev.type)
    if problem:
        out["compile"] = problem
        return out
    t0 = time.perf_counter()
    render(compile=True)
    out["compile_first_s"] = time.perf_counter() - t0
    (imgc, _), out["compiled_ms"] = timed(compile=True)
    out["compiled_max_diff"] = float((imgc - img).abs().max())
    out["compile"] = accel.failure() or "ok"
    return out


def run_stage(name: str, dry: bool) -> dict:
    fn = {"environment": stage_environment, "parity": stage_parity,
          "paper_scale_fp32": lambda d: stage_paper_scale(d, bf16=False),
          "paper_scale_bf16": lambda d: stage_paper_scale(d, bf16=True),
          "train_step": stage_train_step, "options": stage_options, "train_embedded": stage_train_embedded}[name]
    return fn(dry)


# ---------------------------------------------------------------------------- driver
def _child(name: str, dry: bool, out_json: Path) -> None:
    try:
        res = {"ok": True, "result": run_stage(name, dry)}
    except BaseException as exc:  # recorded, never raised: the next stage runs
        res = {"ok": False, "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()[-4000:]}
    out_json.write_text(json.dumps(res, default=str))


def run(out_dir: Path, dry: bool = False, stages=STAGES, total_s: float = TOTAL_S) -> dict:
    """Every stage in its own process under its deadline (and the total's); returns the records
    and writes ``device_check.json`` / ``device_check.md`` into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    records, start = {}, time.perf_counter()
    for name in stages:
        left = total_s - (time.perf_counter() - start)
        limit = min(DEADLINE_S[name], left)
        if limit <= 5:
            records[name] = {"ok": False, "error": f"skipped: the {total_s:.0f} s budget is spent"}
            _write(out_dir, records, dry)
            continue
        part = out_dir / f".{name}.json"
        t0 = time.perf_counter()
        cmd = [sys.executable, "-m", "mvtn_exp.bench.device_check", "--stage", name, "--json", str(part)]
        try:
            proc = subprocess.run(cmd + (["--dry-run"] if dry else []), capture_output=True, text=True, timeout=limit)
            rec = json.loads(part.read_text()) if part.is_file() else {
                "ok": False, "error": f"exit {proc.returncode}: {(proc.stderr or '').strip()[-800:]}"}
        except subprocess.TimeoutExpired:
            rec = {"ok": False, "error": f"timeout: over its deadline of {limit:.0f} s"}
        part.unlink(missing_ok=True)
        rec["seconds"] = time.perf_counter() - t0
        records[name] = rec
        _write(out_dir, records, dry)  # after every stage: what ran survives a later hang
    return records


def _write(out_dir: Path, records: dict, dry: bool) -> None:
    (out_dir / "device_check.json").write_text(json.dumps(records, indent=1, default=str))
    (out_dir / "device_check.md").write_text(markdown(records, dry))


def markdown(records: dict, dry: bool) -> str:
    lines = [f"# Device check{' (dry run, CPU)' if dry else ''}", ""]
    lines += ["| stage | status | seconds |", "|---|---|---|"]
    for name, rec in records.items():
        status = "ok" if rec.get("ok") else f"FAILED: {rec.get('error', '')[:200]}"
        lines.append(f"| {name} | {status} | {rec.get('seconds', 0):.1f} |")
    env = records.get("environment", {}).get("result")
    if env:
        lines += ["", f"Device: {env.get('gpu', env['provenance'].get('device'))}; torch {env['provenance'].get('torch')}, "
                  f"CUDA {env['provenance'].get('cuda')}"]
    par = records.get("parity", {}).get("result")
    if par:
        lines += ["", f"## CPU against {par['device']}", "", "| mode | max image/alpha difference | camera gradient, relative | within tolerance |",
                  "|---|---|---|---|"]
        lines += [f"| {r['kind']} | {r['image_max_diff']:.2e} | {r['grad_rel_diff']:.2e} | "
                  f"{'yes' if r['images_ok'] and r['grads_ok'] else 'NO'} |" for r in par["rows"]]
    for key, title in (("paper_scale_fp32", "fp32"), ("paper_scale_bf16", "ResNet-18 under bf16 autocast")):
        res = records.get(key, {}).get("result")
        if res:
            lines += ["", f"## Renderer at scale ({title})", "", res["markdown"].replace("## ", "### ")]
    step = records.get("train_step", {}).get("result")
    if step:
        lines += ["", f"## Training step, B = {step['batch']}, {step['views']} x {step['size']} px ({step['device']})", "",
                  "| C | R | G ms | R ms | C ms | optimizer ms | total ms | peak MiB |", "|---|---|---|---|---|---|---|---|"]
        lines += [f"| {r['mvnet']} | {r['mode']} | {r['selector_ms']:.1f} | {r['render_ms']:.1f} | {r['backbone_ms']:.1f} | "
                  f"{r['optimizer_ms']:.1f} | {r['total_ms']:.1f} | {r['peak_mib']:.0f} |" for r in step["rows"]]
    opt = records.get("options", {}).get("result")
    if opt:
        lines += ["", f"## Renderer options, soft, B = {opt['batch']} ({opt['device']})", "",
                  "| setting | ms per shape | note |", "|---|---|---|",
                  f"| default | {opt['default_ms']:.1f} | two renders identical: {opt['default_repeats']} |",
                  f"| renderer.deterministic=true | {opt['deterministic_ms']:.1f} | two renders identical: "
                  f"{opt['deterministic_repeats']} |"]
        if "compiled_ms" in opt:
            lines.append(f"| renderer.compile=true | {opt['compiled_ms']:.1f} | first call {opt['compile_first_s']:.1f} s; "
                         f"max image difference {opt['compiled_max_diff']:.1e}; {opt['compile']} |")
        else:
            lines.append(f"| renderer.compile=true | - | {opt['compile']} |")
    emb = records.get("train_embedded", {}).get("result")
    if emb:
        lines += ["", f"## Embedded dataset, {emb['epochs']} epochs on {emb['device']}: test accuracy "
                  f"{emb['test_acc']:.4f} (best validation {emb['best_val_acc']:.4f}), {emb['seconds']:.1f} s"]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="The prepared GPU check (module docstring).")
    p.add_argument("out_dir", nargs="?", help="folder for device_check.md / .json")
    p.add_argument("--dry-run", action="store_true", help="tiny sizes on the CPU (what the test suite runs)")
    p.add_argument("--stage", choices=STAGES, help=argparse.SUPPRESS)
    p.add_argument("--json", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.stage:
        _child(a.stage, a.dry_run, Path(a.json))
        return 0
    if not a.out_dir:
        p.error("OUT_DIR is required")
    records = run(Path(a.out_dir), dry=a.dry_run)
    print((Path(a.out_dir) / "device_check.md").read_text())
    return 0 if all(r.get("ok") for r in records.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
