"""The one training loop: ``train(cfg, run_dir) -> metrics`` (a plain, testable function).

Per epoch: train (AdamW, two groups C/G, G's gradients clipped, non-finite steps skipped),
validate, step the LR schedule, write ``last.pt`` (and ``best.pt`` on a new best val accuracy).
At the end ``best.pt`` is evaluated on the test split and ``metrics.json`` is written.
"""
from __future__ import annotations

import json
import logging
import math
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn
from torch.utils.data import DataLoader
from tqdm.auto import tqdm

from ..data.collate import collate_shapes
from ..data.synthetic import ROTATIONS, SyntheticShapes
from ..model import SHAPES, MVTN, build_mvtn
from ..render.config import RendererConfig
from ..selectors import SELECTORS
from . import checkpoint, seeding

log = logging.getLogger("mvtn-train")
SCHEDULES = ("cosine", "step")


class TrainingDiverged(RuntimeError):
    """The loss became non-finite; the run stops (the last written checkpoints stay intact)."""


@dataclass
class TrainConfig:
    """``mvtn-train`` settings (also the Hydra schema). ``renderer.image_size`` follows ``image_size``."""

    views: int = 4
    image_size: int = 64
    epochs: int = 8
    batch_size: int = 16
    seed: int = 0
    device: str = "cpu"
    ckpt_path: Optional[str] = None
    shape: str = "mesh"
    selector: str = "mvtn_spherical"
    backbone: str = "small_cnn"
    lr: float = 1e-3
    lr_selector: float = 1e-4
    weight_decay: float = 0.01
    clip_selector: float = 30.0
    schedule: str = "cosine"
    step_size: int = 3
    step_gamma: float = 0.1
    num_per_class: list[int] = field(default_factory=lambda: [24, 6, 12])
    rotate: str = "none"
    data_dir: str = "outputs/cache/synthetic"
    num_workers: int = 0
    progress: bool = True
    renderer: RendererConfig = field(default_factory=RendererConfig)


def as_config(cfg) -> TrainConfig:
    """TrainConfig | DictConfig | dict -> a validated TrainConfig (type-checked against the schema)."""
    if isinstance(cfg, TrainConfig):
        node = OmegaConf.structured(cfg)
    else:
        if isinstance(cfg, DictConfig):
            cfg = OmegaConf.to_container(cfg, resolve=True)
        node = OmegaConf.merge(OmegaConf.structured(TrainConfig), cfg)
    obj: TrainConfig = OmegaConf.to_object(node)
    if not isinstance(obj.renderer, RendererConfig):  # pragma: no cover - OmegaConf always builds it
        obj.renderer = RendererConfig(**obj.renderer)
    obj.renderer = RendererConfig(**{**asdict(obj.renderer), "image_size": obj.image_size}).validate()
    for key, allowed in (("shape", SHAPES), ("selector", tuple(SELECTORS)), ("schedule", SCHEDULES),
                         ("rotate", ROTATIONS)):
        if getattr(obj, key) not in allowed:
            raise ValueError(f"{key}={getattr(obj, key)!r}: expected one of {sorted(allowed)}")
    for key in ("views", "image_size", "epochs", "batch_size", "step_size"):
        if getattr(obj, key) < 1:
            raise ValueError(f"{key}={getattr(obj, key)!r}: must be >= 1")
    if obj.seed < 0 or obj.num_workers < 0 or obj.clip_selector <= 0 or obj.lr <= 0 or obj.lr_selector < 0:
        raise ValueError("need seed >= 0, num_workers >= 0, clip_selector > 0, lr > 0, lr_selector >= 0")
    if len(obj.num_per_class) != 3 or min(obj.num_per_class) < 1:
        raise ValueError(f"num_per_class={obj.num_per_class}: expected 3 counts >= 1 (train, val, test)")
    return obj


def config_dict(cfg: TrainConfig) -> dict:
    return asdict(cfg)


# ----------------------------------------------------------------------------- pieces
def make_loaders(cfg: TrainConfig) -> dict[str, DataLoader]:
    loaders = {}
    for split in ("train", "val", "test"):
        ds = SyntheticShapes(cfg.data_dir, split, num_per_class=cfg.num_per_class, seed=cfg.seed, rotate=cfg.rotate,
                             as_points=cfg.shape == "points", progress=cfg.progress)
        loaders[split] = DataLoader(ds, batch_size=cfg.batch_size, shuffle=False, collate_fn=collate_shapes,
                                    num_workers=cfg.num_workers)
    return loaders


def train_loader(cfg: TrainConfig, dataset, epoch: int) -> DataLoader:
    """The shuffled train loader of ``epoch``: its order depends only on (seed, epoch), so resume is exact."""
    g = torch.Generator().manual_seed(cfg.seed * 100003 + epoch)
    return DataLoader(dataset, batch_size=cfg.batch_size, shuffle=True, generator=g, collate_fn=collate_shapes,
                      num_workers=cfg.num_workers)


def lr_factor(cfg: TrainConfig, epoch: int) -> float:
    """Multiplier of the base learning rates during ``epoch`` (0-based)."""
    if cfg.schedule == "cosine":
        return 0.5 * (1.0 + math.cos(math.pi * epoch / cfg.epochs))
    return cfg.step_gamma ** (epoch // cfg.step_size)


def make_optimizer(cfg: TrainConfig, model: MVTN):
    groups = model.parameter_groups()
    params = [{"params": groups["mvnet"], "lr": cfg.lr, "name": "mvnet"}]
    if groups["selector"]:
        params.append({"params": groups["selector"], "lr": cfg.lr_selector, "name": "selector"})
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: lr_factor(cfg, e))
    return opt, sched


def _grads_finite(params) -> bool:
    return all(bool(torch.isfinite(p.grad).all()) for p in params if p.grad is not None)


def train_one_epoch(model: MVTN, loader, opt, cfg: TrainConfig, epoch: int, device) -> dict:
    model.train()
    sel_params = model.parameter_groups()["selector"]
    all_params = [p for g in opt.param_groups for p in g["params"]]
    loss_sum, correct, seen, skipped = 0.0, 0, 0, 0
    bar = tqdm(loader, desc=f"train {epoch + 1}/{cfg.epochs}", leave=False, disable=not cfg.progress)
    for batch in bar:
        labels = batch["labels"].to(device)
        out = model(batch)
        loss = nn.functional.cross_entropy(out["logits"], labels)
        if not bool(torch.isfinite(loss.detach())):
            raise TrainingDiverged(f"epoch {epoch + 1}: non-finite loss {float(loss.detach())} (batch {batch['names'][:3]}...); "
                                   "stopping, the last written checkpoint is intact")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if not _grads_finite(all_params):
            skipped += 1
            opt.zero_grad(set_to_none=True)
            log.warning("epoch %d: non-finite gradients, step skipped", epoch + 1)
            continue
        if sel_params:
            torch.nn.utils.clip_grad_norm_(sel_params, cfg.clip_selector)
        opt.step()
        n = len(labels)
        loss_sum += float(loss.detach()) * n
        correct += int((out["logits"].argmax(1) == labels).sum())
        seen += n
        bar.set_postfix(loss=f"{loss_sum / max(seen, 1):.3f}", acc=f"{correct / max(seen, 1):.3f}")
    return {"loss": loss_sum / max(seen, 1), "acc": correct / max(seen, 1), "skipped": skipped}


@torch.no_grad()
def evaluate(model: MVTN, loader, num_classes: int, device, desc: str = "eval", progress: bool = True) -> dict:
    """Eval mode (renderer: camera light, white) -> overall acc, mean per-class acc, confusion [true][pred]."""
    model.eval()
    conf = torch.zeros(num_classes, num_classes, dtype=torch.long)
    loss_sum = 0.0
    for batch in tqdm(loader, desc=desc, leave=False, disable=not progress):
        labels = batch["labels"].to(device)
        logits = model(batch)["logits"]
        loss_sum += float(nn.functional.cross_entropy(logits, labels, reduction="sum"))
        pred = logits.argmax(1).cpu()
        conf.index_put_((batch["labels"], pred), torch.ones_like(pred), accumulate=True)
    total = int(conf.sum())
    per_class = conf.diag().double() / conf.sum(1).clamp(min=1).double()
    present = conf.sum(1) > 0
    return {"acc": float(conf.diag().sum()) / max(total, 1),
            "mean_class_acc": float(per_class[present].mean()) if bool(present.any()) else 0.0,
            "loss": loss_sum / max(total, 1), "confusion": conf.tolist(), "n": total}


# ----------------------------------------------------------------------------- the loop
def train(cfg, run_dir) -> dict:
    """Train MVTN per ``cfg`` (TrainConfig / dict / DictConfig) writing into ``run_dir``; return the metrics."""
    cfg = as_config(cfg)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    device = torch.device(cfg.device)
    cfg_dict = config_dict(cfg)

    resume = None
    if cfg.ckpt_path:
        resume = checkpoint.load(cfg.ckpt_path)
        checkpoint.check_compatible(resume["config"], cfg_dict)

    seeding.seed_everything(cfg.seed)
    loaders = make_loaders(cfg)
    classes = loaders["train"].dataset.classes
    model = build_mvtn(views=cfg.views, selector=cfg.selector, backbone=cfg.backbone, num_classes=len(classes),
                       renderer=cfg.renderer, shape=cfg.shape).to(device)
    opt, sched = make_optimizer(cfg, model)

    start, best_acc, best_epoch, skipped, history = 0, -1.0, -1, 0, []
    if resume is not None:
        model.load_state_dict(resume["model"])
        opt.load_state_dict(resume["optimizer"])
        sched.load_state_dict(resume["scheduler"])
        start = int(resume["epoch"]) + 1
        best_acc, best_epoch = float(resume["best_val_acc"]), int(resume["best_epoch"])
        skipped, history = int(resume["skipped_steps"]), list(resume["history"])
        # the schedule is a function of (epoch, epochs): re-derive it (epochs may have grown)
        for g, base in zip(opt.param_groups, sched.base_lrs):
            g["lr"] = base * lr_factor(cfg, start)
        sched.last_epoch = start
        seeding.set_rng_state(resume["rng"])
        src_best = Path(cfg.ckpt_path).with_name("best.pt")
        if src_best.is_file() and src_best.resolve() != (run_dir / "best.pt").resolve():
            shutil.copyfile(src_best, run_dir / "best.pt")
        print(f"resumed from {cfg.ckpt_path} at epoch {start + 1}/{cfg.epochs}")

    def payload(epoch):
        return {"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                "epoch": epoch, "rng": seeding.rng_state(), "config": cfg_dict, "best_val_acc": best_acc,
                "best_epoch": best_epoch, "skipped_steps": skipped, "history": history, "classes": classes}

    for epoch in range(start, cfg.epochs):
        t0 = time.perf_counter()
        tr = train_one_epoch(model, train_loader(cfg, loaders["train"].dataset, epoch), opt, cfg, epoch, device)
        skipped += tr["skipped"]
        val = evaluate(model, loaders["val"], len(classes), device, desc="val", progress=cfg.progress)
        sched.step()
        seconds = time.perf_counter() - t0
        history.append({"epoch": epoch + 1, "train_loss": tr["loss"], "train_acc": tr["acc"], "val_acc": val["acc"],
                        "val_loss": val["loss"], "skipped": tr["skipped"], "seconds": seconds})
        improved = val["acc"] > best_acc
        if improved:
            best_acc, best_epoch = val["acc"], epoch
        state = payload(epoch)
        if improved:
            checkpoint.save_atomic(run_dir / "best.pt", state)
        checkpoint.save_atomic(run_dir / "last.pt", state)
        print(f"epoch {epoch + 1}/{cfg.epochs}: train loss {tr['loss']:.4f} acc {tr['acc']:.3f} | "
              f"val acc {val['acc']:.3f}{' (best)' if improved else ''} | {seconds:.1f}s", flush=True)

    best = checkpoint.load(run_dir / "best.pt", map_location=device)
    model.load_state_dict(best["model"])
    test = evaluate(model, loaders["test"], len(classes), device, desc="test", progress=cfg.progress)
    metrics = {
        "test_acc": test["acc"], "test_mean_class_acc": test["mean_class_acc"], "test_loss": test["loss"],
        "confusion_matrix": test["confusion"], "classes": classes, "test_size": test["n"],
        "best_val_acc": best_acc, "best_epoch": best_epoch + 1, "epochs": cfg.epochs, "skipped_steps": skipped,
        "epoch_seconds": [h["seconds"] for h in history],
        "mean_epoch_seconds": sum(h["seconds"] for h in history) / max(len(history), 1),
        "history": history, "config": cfg_dict,
    }
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    print(f"test accuracy {test['acc']:.4f} (mean per-class {test['mean_class_acc']:.4f}, best val {best_acc:.4f} "
          f"at epoch {best_epoch + 1})")
    return metrics
