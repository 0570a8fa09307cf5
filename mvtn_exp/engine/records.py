"""What a run reports: its log lines (``say``), each epoch's record, scalars and line, the views'
offsets and statistics, and the finished run's ``metrics.json`` with its confusion files."""
from __future__ import annotations

import json
import time
from pathlib import Path

import torch

from ..config.schema import TrainConfig
from ..data.datasets import view_report as dataset_view_report
from ..model import MVTN
from ..render.view_stats import view_stats
from ..runtime import distributed
from ..viz import parts
from ..viz.images import write_png
from ..viz.plots import confusion_png
from . import run_dir as run_dir_state
from .run_logger import RunLogger
from .step_timer import StepTimer


def say(run_dir: Path, line: str) -> None:
    """Print ``line`` and append it, time-stamped, to ``<run_dir>/train.log`` (the run's record);
    with several processes only rank 0 does (``distributed``)."""
    if not distributed.from_env().main:
        return
    print(line, flush=True)
    with open(Path(run_dir) / "train.log", "a") as f:
        f.write(f"[{time.strftime('%Y-%m-%d %H:%M:%S')}] {line}\n")


def view_offsets(model: MVTN, azim: torch.Tensor, elev: torch.Tensor) -> dict:
    """Mean |u - u0| in degrees of predicted views ``[N, M]`` (azimuth modulo 360; 0 for fixed selectors)."""
    init = getattr(model.selector, "initial_views", None)
    if init is None or azim.numel() == 0:
        return {"view_offset_azim": 0.0, "view_offset_elev": 0.0}
    with torch.no_grad():
        a0, e0 = (t.detach() for t in init(1)[:2])
    d_azim = torch.remainder(azim - a0.cpu() + 180.0, 360.0) - 180.0  # the same camera 360 deg apart
    return {"view_offset_azim": float(d_azim.abs().mean()),
            "view_offset_elev": float((elev - e0.cpu()).abs().mean())}


def view_report(model: MVTN, azim: torch.Tensor, elev: torch.Tensor) -> dict:
    """``view_offsets`` and ``view_stats`` (spread over shapes, separation within a shape) of views ``[N, M]``."""
    return {**view_offsets(model, azim, elev), **view_stats(azim, elev)}


def epoch_record(epoch: int, tr: dict, val: dict, val_ema, offsets: dict, detail: dict, lrs: dict, seconds: float,
                 extra: dict) -> dict:
    """One epoch's entry of ``history`` (metrics.json and the checkpoints)."""
    return {"epoch": epoch + 1, "train_loss": tr["loss"], "train_acc": tr["acc"],
            "val_acc": val["acc"], "val_mean_class_acc": val["mean_class_acc"], "val_loss": val["loss"],
            "skipped": tr["skipped"], "clipped": tr["clipped"],
            "grad_norm_selector": tr["grad_norm_selector"], "grad_norm_mvnet": tr["grad_norm_mvnet"],
            **offsets, **detail, **lrs, "seconds": seconds,
            **({"val_acc_ema": val_ema["acc"]} if val_ema is not None else {}), **extra}


def log_epoch(logger: RunLogger, step: int, tr: dict, val: dict, offsets: dict, headline: dict,
              task: dict | None = None) -> None:
    """The epoch's scalars, view histograms and view grid in TensorBoard; ``headline``: the numbers
    the dataset puts first about the validation views (``data.datasets.view_headline``); ``task``:
    the task head's (``headline``: instance mIoU, coverage), with its label pictures."""
    logger.scalars({"train/loss_epoch": tr["loss"], "train/acc": tr["acc"], "val/acc": val["acc"],
                    "val/mean_class_acc": val["mean_class_acc"], "val/loss": val["loss"],
                    "views/offset_azim": offsets["view_offset_azim"], "views/offset_elev": offsets["view_offset_elev"],
                    "views/spread": offsets["view_spread"],
                    **({"views/separation": offsets["view_separation"]} if offsets["view_separation"] is not None else {}),
                    **{f"views/{k}": v for k, v in headline.items()},
                    **{f"val/{k}": v for k, v in (task or {}).items()}}, step)
    logger.histogram("views/azim", val["azim"], step)
    logger.histogram("views/elev", val["elev"], step)
    if val["images"] is not None:
        logger.views("views/val", val["images"], step)
    for tag, image in pictures(val.get("pictures")).items():
        logger.image(f"parts/{tag}", image, step)


def pictures(pics: dict | None) -> dict:
    """A segmentation result's ``pictures`` as uint8 RGB images: ``views`` (the first shape's
    predicted label views above the true ones) and ``points`` (its points coloured by the
    predicted part); none for other tasks."""
    if not pics:
        return {}
    n = pics["num_parts"]
    return {"views": parts.label_views(pics["pred_views"], pics["true_views"], n),
            "points": parts.points_image(pics["points"], pics["point_parts"], n)}


def epoch_line(epoch: int, cfg: TrainConfig, tr: dict, val: dict, val_ema, improved: bool, use_ema: bool,
               offsets: dict, headline: dict, seconds: float) -> str:
    return (f"epoch {epoch + 1}/{cfg.epochs}: train loss {tr['loss']:.4f} acc {tr['acc']:.3f} | val acc {val['acc']:.3f}"
            + (f" average {val_ema['acc']:.3f}" if val_ema is not None else "")
            + f"{' (best' + (': the average)' if use_ema else ')') if improved else ''} | "
            f"|u-u0| {offsets['view_offset_azim']:.1f}/{offsets['view_offset_elev']:.1f} deg | "
            + "".join(f"{k.replace('_', ' ')} {v:.2f} | " for k, v in headline.items())
            + f"{seconds:.1f}s")


def write_results(run_dir: Path, metrics: dict, result: dict | None = None) -> Path:
    """``metrics.json``, ``confusion.json`` and ``confusion.png`` in ``run_dir`` (the confusion of
    the classes, or of the parts over points for segmentation) and a segmentation ``result``'s
    pictures as ``parts_views.png`` / ``parts_points.png``; returns metrics.json's path."""
    names = metrics.get("part_names", metrics["classes"])
    what = "part" if "part_names" in metrics else "class"
    conf = {"classes": names, "rows": f"true {what}", "columns": f"predicted {what}",
            "matrix": metrics["confusion_matrix"]}
    (run_dir / "confusion.json").write_text(json.dumps(conf, indent=1))
    confusion_png(metrics["confusion_matrix"], names, run_dir / "confusion.png",
                  title=f"{metrics.get('split', 'test')}: acc {metrics['test_acc']:.3f}")
    for tag, image in pictures((result or {}).get("pictures")).items():
        write_png(run_dir / f"parts_{tag}.png", image)
    path = run_dir / "metrics.json"
    path.write_text(json.dumps(metrics, indent=2))
    run_dir_state.write_status(run_dir, "ok")
    return path


def run_metrics(cfg: TrainConfig, cfg_dict: dict, model, datasets: dict, test: dict, costs: dict, history: list,
                timer: StepTimer, origin: dict, world, *, best_acc: float, best_epoch: int, step: int, skipped: int,
                best_weights: str, head) -> dict:
    """The run's ``metrics.json``: the test split's results for ``best.pt``, model selection (the
    best validation score: ``best_val_acc``, or ``best_val_<score>`` of a head scored otherwise),
    the per-epoch history, time per stage, the cost record, the config and the provenance."""
    classes = list(datasets["train"].classes)
    best_key = "best_val_acc" if head.score == "acc" else f"best_val_{head.score}"
    seconds = [h["seconds"] for h in history]  # every epoch, resumed ones too
    return {
        "test_acc": test["acc"], "test_mean_class_acc": test["mean_class_acc"], "test_loss": test["loss"],
        "test_per_class_acc": dict(zip(head.names, test["per_class_acc"])), **head.metrics(test),
        "confusion_matrix": test["confusion"], "classes": classes, "test_size": test["n"], "split": "test",
        best_key: best_acc, "best_epoch": best_epoch + 1, "epochs": cfg.epochs, "epochs_trained": len(history),
        "stopped_early": len(history) < cfg.epochs, "steps": step,
        "best_weights": best_weights, "skipped_steps": skipped, "epoch_seconds": seconds,
        "mean_epoch_seconds": sum(seconds) / max(len(seconds), 1), "train_wall_seconds": sum(seconds),
        "step_seconds": timer.means(), "cost": costs,
        **{f"test_{k}": v for k, v in view_report(model, test["azim"], test["elev"]).items()},
        **{f"test_{k}": v for k, v in dataset_view_report(datasets["test"], test).items()},
        "history": history, "config": cfg_dict, "provenance": origin, "world_size": world.size,
    }
