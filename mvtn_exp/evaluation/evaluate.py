"""``evaluate_checkpoint``: rebuild MVTN from the config stored in a checkpoint and evaluate one split."""
from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

from ..data.datasets import build_dataset
from ..model import build_mvtn
from ..render import accel
from ..config.schema import TrainConfig, resolve_device
from ..config.eval_schema import EvalConfig
from ..tasks import classification
from ..tasks.heads import build_head
from ..runtime import checkpoint
from . import modes as eval_modes
from ..engine.provenance import provenance
from ..engine.trainer import as_config, config_dict, eval_loader, view_report, write_results


def config_from_checkpoint(state: dict, path) -> TrainConfig:
    """The checkpoint's training config, checked against this version's schema."""
    try:
        return as_config(state["config"])
    except Exception as exc:
        raise checkpoint.CheckpointMismatch(f"checkpoint {str(path)!r}: its stored config does not fit this "
                                            f"version's schema ({str(exc).splitlines()[0]})") from exc


def load_model(cfg: TrainConfig, state: dict, num_classes: int, path, device, categories: int = 0):
    # (the checkpoint holds C's weights: the pretrained ones are neither downloaded nor read)
    model = build_mvtn(cfg, num_classes=num_classes, pretrained_weights=False, categories=categories).to(device)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        detail = " ".join(str(exc).split())[:400]
        raise checkpoint.CheckpointMismatch(f"checkpoint {str(path)!r}: weights do not fit the model its config "
                                            f"builds ({detail})") from exc
    return model


def task_of(ecfg: EvalConfig, cfg: TrainConfig) -> str:
    """The task to evaluate: ``task`` as asked, or the checkpoint's; a segmentation checkpoint
    under another task, or a classifier under segmentation, is refused in one line."""
    trained, asked = cfg.task.name, ecfg.task
    if asked is None:
        return trained
    if (trained == "segmentation") != (asked == "segmentation"):
        raise checkpoint.CheckpointMismatch(
            f"checkpoint {ecfg.ckpt!r} was trained with task={trained}: it cannot be evaluated with task={asked} "
            f"(leave task unset to evaluate its own task)")
    return asked


def evaluate_segmentation(ecfg: EvalConfig, cfg: TrainConfig, state: dict, dataset, device, run_dir: Path) -> dict:
    """A part segmentation checkpoint on ``ecfg.split``: instance and class mIoU, per category,
    coverage, the part confusion and the first shape's pictures (``results.md``, ``metrics.json``,
    ``parts_views.png``, ``parts_points.png``)."""
    if ecfg.views:
        raise ValueError("views=true: the view analysis is made for classification; leave it unset for a "
                         "segmentation checkpoint")
    head = build_head(cfg.task, dataset)
    model = load_model(cfg, state, head.num_outputs, ecfg.ckpt, device, categories=len(dataset.classes))
    t0 = time.perf_counter()
    res = head.evaluate(model, eval_loader(cfg, dataset), desc=ecfg.split, progress=ecfg.progress)
    metrics = {"test_acc": res["acc"], "test_mean_class_acc": res["mean_class_acc"], "test_loss": res["loss"],
               "test_per_class_acc": dict(zip(head.names, res["per_class_acc"])), **head.metrics(res),
               "confusion_matrix": res["confusion"], "classes": list(dataset.classes), "test_size": res["n"],
               "split": ecfg.split, "ckpt": str(ecfg.ckpt), "ckpt_epoch": int(state.get("epoch", 0)),
               **{f"test_{k}": v for k, v in view_report(model, res["azim"], res["elev"]).items()},
               "seconds": {"segmentation": time.perf_counter() - t0}, "config": config_dict(cfg),
               "provenance": provenance(cfg.device), "ckpt_provenance": state.get("provenance")}
    rows = "".join(f"| {name} | {v['miou']:.4f} | {v['shapes']} |\n" for name, v in res["per_category"].items())
    table = (f"## Part segmentation ({ecfg.split}, fuse={cfg.task.fuse})\n\n| instance mIoU | class mIoU | point "
             f"accuracy | coverage | shapes |\n|---|---|---|---|---|\n| {res['instance_miou']:.4f} | "
             f"{res['class_miou']:.4f} | {res['acc']:.4f} | {res['coverage']:.4f} | {res['n']} |\n\n"
             f"| category | mIoU | shapes |\n|---|---|---|\n{rows}")
    (run_dir / "results.md").write_text(table)
    write_results(run_dir, metrics, res)
    print(table)
    return metrics


def evaluate_checkpoint(ecfg: EvalConfig, run_dir) -> dict:
    """Evaluate ``ecfg.ckpt`` on ``ecfg.split``; writes metrics.json / confusion.{json,png} into ``run_dir``."""
    ecfg.validate()
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    state = checkpoint.load(ecfg.ckpt)
    cfg = config_from_checkpoint(state, ecfg.ckpt)
    if ecfg.device is not None:
        cfg.device = ecfg.device
    if ecfg.batch_size is not None:
        cfg.batch_size = ecfg.batch_size
    if ecfg.root is not None:
        cfg.dataset = replace(cfg.dataset, root=ecfg.root)
    cfg.logger.progress = ecfg.progress
    cfg.device = resolve_device(cfg.device)
    device = torch.device(cfg.device)
    problem = accel.unavailable(device.type) if cfg.renderer.compile else None
    if problem:  # compile is an accelerator of the same renderer, not part of the model: evaluate eagerly
        print(f"mvtn-eval: note: {problem}; rendering eagerly (the same images to float rounding)", file=sys.stderr)
        cfg.renderer.compile = False

    dataset = build_dataset(cfg.dataset, ecfg.split, progress=ecfg.progress)
    classes = list(dataset.classes)
    if state.get("classes") is not None and list(state["classes"]) != classes:
        raise checkpoint.CheckpointMismatch(f"checkpoint {ecfg.ckpt!r} was trained on classes {state['classes']} "
                                            f"but dataset {cfg.dataset.name} at {cfg.dataset.root} has {classes}")
    if task_of(ecfg, cfg) == "segmentation":
        return evaluate_segmentation(ecfg, cfg, state, dataset, device, run_dir)
    model = load_model(cfg, state, len(classes), ecfg.ckpt, device)
    loader = eval_loader(cfg, dataset)
    t0 = time.perf_counter()
    res = classification.evaluate(model, loader, len(classes), desc=ecfg.split, progress=ecfg.progress)
    seconds = {"classification": time.perf_counter() - t0}
    offsets = view_report(model, res["azim"], res["elev"])
    metrics = {"test_acc": res["acc"], "test_mean_class_acc": res["mean_class_acc"], "test_loss": res["loss"],
               "test_per_class_acc": dict(zip(classes, res["per_class_acc"])), "confusion_matrix": res["confusion"],
               "classes": classes, "test_size": res["n"], "split": ecfg.split, "ckpt": str(ecfg.ckpt),
               "ckpt_epoch": int(state.get("epoch", 0)), **{f"test_{k}": v for k, v in offsets.items()},
               "config": config_dict(cfg), "provenance": provenance(cfg.device),
               "ckpt_provenance": state.get("provenance")}
    tables = [f"## Classification ({ecfg.split})\n\n| accuracy | mean per-class | n |\n|---|---|---|\n"
              f"| {res['acc']:.4f} | {res['mean_class_acc']:.4f} | {res['n']} |"]
    mode = ecfg.robustness if ecfg.robustness != "none" else (ecfg.task or "classification")
    if mode != "classification":
        t0 = time.perf_counter()
        if mode == "rotation":
            extra, table = eval_modes.rotation(model, loader, len(classes), ecfg)
        elif mode == "occlusion":
            extra, table = eval_modes.occlusion(model, loader, len(classes), ecfg, run_dir)
        else:
            extra, table = eval_modes.retrieval_eval(model, cfg, ecfg, dataset, run_dir)
        seconds[mode] = time.perf_counter() - t0
        metrics.update(extra)
        tables.append(f"## {mode.capitalize()}\n\n{table}")
    if ecfg.views:
        from ..viz.views import view_analysis

        t0 = time.perf_counter()
        extra, table = view_analysis(model, loader, classes, run_dir, progress=ecfg.progress)
        seconds["views"] = time.perf_counter() - t0
        metrics.update(extra)
        tables.append(f"## Views\n\n{table}")
    metrics["seconds"] = seconds
    (run_dir / "results.md").write_text("\n\n".join(tables) + "\n")
    write_results(run_dir, metrics)
    print("\n\n".join(tables))
    return metrics
