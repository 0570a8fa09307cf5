"""The one training loop: ``train(cfg, run_dir) -> metrics`` (a plain, testable function).

Per epoch: train (AdamW, two groups C/G, G's gradients clipped before the step, non-finite steps
skipped and counted), validate, step the LR schedule, write ``last.pt`` (and ``best.pt`` on a new
best validation accuracy: model selection never looks at the test split). At the end ``best.pt``
is evaluated on the test split and ``metrics.json``, ``confusion.json`` and ``confusion.png`` are
written. Data flows shape -> G -> R -> C -> loss (see ``MVTN``).
"""
from __future__ import annotations

import json
import logging
import math
import shutil
import time
from dataclasses import replace
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ..data.datasets import build_dataset, view_figures
from ..data.datasets import view_report as dataset_view_report
from ..model import MVTN, build_mvtn
from ..models import sync_bn
from ..models.precision import grad_scaler
from ..config.schema import TrainConfig, as_config, config_dict, resolve_device  # noqa: F401 (as_config: the engine's API)
from ..tasks import classification
from ..tasks.robustness import random_rotations, turn_batch
from ..viz.plots import confusion_png
from ..runtime import checkpoint, distributed, seeding
from . import cost, loaders
from ..models import precise_bn
from . import run_dir as run_dir_state
from .loaders import eval_loader, train_loader
from .ema import ModelEMA
from ..render.view_stats import view_stats
from .provenance import provenance
from .run_logger import RunLogger
from .step_timer import StepTimer

log = logging.getLogger("mvtn-train")
SPLITS = ("train", "val", "test")


class TrainingDiverged(RuntimeError):
    """The loss became non-finite; the run stops (the last written checkpoints stay intact)."""


# ----------------------------------------------------------------------------- pieces
def make_datasets(cfg: TrainConfig) -> dict:
    datasets = {split: build_dataset(cfg.dataset, split, progress=cfg.logger.progress) for split in SPLITS}
    for split, ds in datasets.items():
        if len(ds) == 0:
            raise ValueError(f"dataset {cfg.dataset.name} at {cfg.dataset.root}: the {split} split is empty"
                             + (" (raise dataset.val_fraction or add shapes)" if split == "val" else ""))
    return datasets


def evaluate_split(model, dataset, cfg: TrainConfig, num_classes: int, desc: str,
                   world: distributed.World = distributed.World()) -> dict:
    """``classification.evaluate`` on ``dataset``; with several processes each classifies its own
    contiguous share (every shape once) and the results are gathered: the same dict, over the whole
    split, in the dataset's order, on every rank."""
    if not world.enabled:
        return classification.evaluate(model, eval_loader(cfg, dataset), num_classes, desc=desc,
                                       progress=cfg.logger.progress)
    mine = loaders.shard_of(dataset, world)  # the same Subset every pass: its loader's workers are kept
    res = classification.evaluate(model, eval_loader(cfg, mine), num_classes, desc=desc,
                                  progress=cfg.logger.progress and world.main)
    parts = distributed.gather({k: res[k] for k in ("confusion", "loss", "n", "azim", "elev", "dist", "labels", "pred")},
                               world)
    conf = sum(torch.tensor(p["confusion"]) for p in parts)
    out = classification.summarize(conf)
    out.update(loss=sum(p["loss"] * p["n"] for p in parts) / max(out["n"], 1), confusion=conf.tolist(),
               **{k: torch.cat([p[k] for p in parts]) for k in ("azim", "elev", "dist", "labels", "pred")},
               images=res["images"] if world.main else None)
    return out


def lr_factor(cfg: TrainConfig, epoch: int) -> float:
    """Multiplier of the base learning rates during ``epoch`` (0-based); the schedule runs over the
    epoch's training stage (``cfg.mvnet.stage_span``: the whole run unless the net has stages)."""
    first, length = cfg.mvnet.stage_span(epoch, cfg.epochs)
    e = epoch - first
    if cfg.optim.schedule == "cosine":
        return 0.5 * (1.0 + math.cos(math.pi * e / length))
    return cfg.optim.step_gamma ** (e // cfg.optim.step_size)


def group_factor(cfg: TrainConfig, name: str, epoch: int) -> float:
    """``lr_factor`` for parameter group ``name`` ("mvnet" | "selector"), G's scaled by the
    selector's own ``lr_scale`` (0 from ``selector.stop_epoch`` on: G frozen, C trains on) and
    undecayed with ``optim.decay_selector=false`` (the official code)."""
    if name != "selector":
        return lr_factor(cfg, epoch)
    return (lr_factor(cfg, epoch) if cfg.optim.decay_selector else 1.0) * cfg.selector.lr_scale(epoch)


def make_optimizer(cfg: TrainConfig, model: MVTN, g_training):
    """AdamW over C's group and, if G has parameters, G's group (``g_training.param_group``)."""
    groups = model.parameter_groups()
    params = [{"params": groups["mvnet"], "lr": cfg.optim.lr, "name": "mvnet"}]
    if groups["selector"]:
        params.append(g_training.param_group(groups["selector"]))
    opt = torch.optim.AdamW(params, lr=cfg.optim.lr, weight_decay=cfg.optim.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, [lambda e, n=g["name"]: group_factor(cfg, n, e) for g in params])
    return opt, sched


def selector_lr(opt) -> float | None:
    """G's learning rate in ``opt`` now (None: no G group)."""
    return next((g["lr"] for g in opt.param_groups if g["name"] == "selector"), None)


def _grads_finite(params) -> bool:
    """True when every gradient is finite: one host sync for all of them (not one per parameter)."""
    flags = [torch.isfinite(p.grad).all() for p in params if p.grad is not None]
    return bool(torch.stack(flags).all()) if flags else True


def _grad_norm(params) -> float:
    grads = [p.grad.detach().pow(2).sum() for p in params if p.grad is not None]
    return float(torch.stack(grads).sum().sqrt()) if grads else 0.0


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


def augment(batch: dict, cfg: TrainConfig) -> dict:
    """Training augmentation (``cfg.augment``): a new random rotation of every shape, from torch's RNG."""
    if cfg.augment.rotate == "none":
        return batch
    return turn_batch(batch, random_rotations(len(batch["points"]), cfg.augment.rotate))


def say(run_dir: Path, line: str) -> None:
    """Print ``line`` and append it, time-stamped, to ``<run_dir>/train.log`` (the run's record);
    with several processes only rank 0 does (``distributed``)."""
    if not distributed.from_env().main:
        return
    print(line, flush=True)
    with open(Path(run_dir) / "train.log", "a") as f:
        f.write(f"[{time.strftime('%Y-%m-%d %H:%M:%S')}] {line}\n")


class _Epoch:
    """Running sums of one training epoch."""

    def __init__(self):
        self.loss, self.correct, self.seen, self.skipped, self.clipped = 0.0, 0, 0, 0, 0
        self.g_norm_sum, self.c_norm_sum, self.steps = 0.0, 0.0, 0

    def add(self, loss, logits, labels, g_norm: float, c_norm: float) -> None:
        """One finished step: C's mean ``loss`` over ``labels [B']`` and the gradient norms."""
        n = len(labels)
        self.loss += float(loss.detach()) * n
        self.correct += int((logits.detach().argmax(1) == labels).sum())
        self.seen += n
        self.steps += 1
        self.g_norm_sum += g_norm
        self.c_norm_sum += c_norm

    def result(self) -> dict:
        n, s = max(self.seen, 1), max(self.steps, 1)
        return {"loss": self.loss / n, "acc": self.correct / n, "seen": self.seen, "skipped": self.skipped, "clipped": self.clipped,
                "grad_norm_selector": self.g_norm_sum / s, "grad_norm_mvnet": self.c_norm_sum / s}


def train_one_epoch(model: MVTN, loader, opt, cfg: TrainConfig, epoch: int, loss_fn, timer: StepTimer,
                    logger: RunLogger, step: int, g_training, scaler=None, ema=None,
                    world: distributed.World = distributed.World()) -> tuple[dict, int]:
    """One pass over ``loader``; returns (epoch sums, global step after it). ``g_training``: how G
    trains (``selectors/training.py``: its ``train_step`` is the forward and the objective);
    ``scaler``: fp16's loss scaler (``models/precision.py``); ``ema``: a ``ModelEMA`` updated after
    every step."""
    model.train()
    groups = model.parameter_groups()
    all_params = groups["mvnet"] + groups["selector"]
    g_training.start_epoch(model, epoch, selector_lr(opt), hold_views=cfg.mvnet.holds_views(epoch))
    acc = _Epoch()
    scaling = scaler is not None and scaler.is_enabled()
    bar = tqdm(loader, desc=f"train {epoch + 1}/{cfg.epochs}", leave=False, disable=None if cfg.logger.progress else True)
    it = iter(bar)
    while True:
        with timer.stage("data"):
            batch = next(it, None)
            if batch is not None:
                batch = augment(batch, cfg)
        if batch is None:
            break
        out = g_training.train_step(model, batch, step, loss_fn, timer)
        loss = out.loss
        if not bool(torch.isfinite(loss.detach())):
            raise TrainingDiverged(f"epoch {epoch + 1}, step {step + 1}: non-finite loss {float(loss.detach())} "
                                   f"(batch {batch['names'][:3]}...); stopping, the last written checkpoint is intact")
        with timer.stage("optimizer"):
            opt.zero_grad(set_to_none=True)
        objective = out.objective
        if world.enabled:  # each rank's loss weighted by its share: the sum over ranks is the whole batch's mean
            n_all = float(distributed.all_sum(torch.tensor(float(len(out.labels)), device=model.device), world))
            objective = objective * (len(out.labels) / n_all)
        timer.backward(scaler.scale(objective) if scaling else objective, out.views, out.images)
        with timer.stage("optimizer"):
            if world.enabled:  # every rank's gradient of its weighted share -> the whole batch's, on every rank
                distributed.average_gradients(all_params, 1.0, world)
            if scaling:
                scaler.unscale_(opt)
            if not _grads_finite(all_params):
                acc.skipped += 1
                opt.zero_grad(set_to_none=True)
                if scaling:  # fp16: the scale was too high for this step; it is lowered (expected now and then)
                    scaler.update()
                else:
                    log.warning("epoch %d step %d: non-finite gradients, step skipped", epoch + 1, step + 1)
                step += 1
                timer.step_done()  # its time was spent: count the step in the per-step means
                continue
            c_norm = _grad_norm(groups["mvnet"])
            g_norm = 0.0
            if groups["selector"]:
                g_norm = float(torch.nn.utils.clip_grad_norm_(groups["selector"], g_training.clip))
                acc.clipped += int(g_norm > g_training.clip)
            if scaling:
                scaler.step(opt)
                scaler.update()
            else:
                opt.step()
            if ema is not None:
                ema.update(model, step)
        timer.step_done()
        acc.add(loss, out.logits, out.labels, g_norm, c_norm)
        step += 1
        if step % cfg.logger.log_every == 0:
            logger.scalars({"train/loss": float(loss.detach()), "grad_norm/selector": g_norm,
                            "grad_norm/mvnet": c_norm,
                            **{f"lr/{g['name']}": g["lr"] for g in opt.param_groups}}, step)
        bar.set_postfix(loss=f"{acc.loss / max(acc.seen, 1):.3f}", acc=f"{acc.correct / max(acc.seen, 1):.3f}")
    return acc.result(), step


def check_world(cfg: TrainConfig, world: distributed.World) -> None:
    """One-line errors for settings that several processes cannot share (before any work)."""
    if cfg.batch_size < 2 * world.size:
        raise ValueError(f"batch_size={cfg.batch_size} with {world.size} processes (WORLD_SIZE): batch_size is the global "
                         f"batch and every process needs at least 2 shapes of it; use batch_size >= {2 * world.size}")
    extra = cfg.selector.modules(cfg.views)  # per-shape statistics of G's training (hypotheses, polarity)
    if extra:
        key = "hypotheses" if "hypotheses" in extra else "flip_explore"
        raise ValueError(f"selector.{key}={getattr(cfg.selector, key)} with {world.size} processes: selector={cfg.selector.name}'s per-shape statistics "
                         f"({', '.join(extra)}) are not shared between processes yet; run it in one process")


def check_split_sizes(datasets: dict, world: distributed.World) -> None:
    """More processes than shapes in a split: one line naming the split (exit 2)."""
    for split, ds in datasets.items():
        if len(ds) < world.size:
            raise ValueError(f"{world.size} processes (WORLD_SIZE) but the {split} split has {len(ds)} shapes: use at "
                             f"most {len(ds)} processes")


def all_ranks_epoch(tr: dict, world: distributed.World, device) -> dict:
    """One epoch's ``_Epoch.result`` over every rank: sums of losses, hits and shapes (the gradient
    norms and counts are the same on every rank, taken after the gradients were averaged)."""
    sums = distributed.all_sum(torch.tensor([tr["loss"] * tr["seen"], tr["acc"] * tr["seen"], float(tr["seen"])],
                                            dtype=torch.float64, device=device), world).tolist()
    n = max(sums[2], 1.0)
    return {**tr, "loss": sums[0] / n, "acc": sums[1] / n, "seen": int(sums[2])}


def _resume(cfg: TrainConfig, run_dir: Path, model, opt, sched, state: dict, scaler, ema, classes: list,
            world: distributed.World) -> tuple:
    """Load ``state`` (a last.pt) into the run; returns ``(start epoch, best val acc, best epoch
    (0-based), skipped steps, history, global step)``."""
    saved = int(state.get("world_size", 1))
    if saved != world.size:  # each process's random stream is in the checkpoint: the same number of processes
        raise checkpoint.CheckpointMismatch(
            f"checkpoint {cfg.ckpt_path!r} was written by a run of {saved} process(es) and this run has {world.size}: "
            f"resume it with {saved} (torchrun --nproc_per_node={saved}, or no torchrun for 1) to go on exactly, or "
            f"start a new run")
    if list(state.get("classes", classes)) != classes:
        raise checkpoint.CheckpointMismatch(f"checkpoint {cfg.ckpt_path!r} was trained on classes "
                                            f"{state['classes']} but the dataset has {classes}")
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:  # weights of another shape: one line, not a traceback
        raise checkpoint.CheckpointMismatch(f"checkpoint {cfg.ckpt_path!r}: weights do not fit the model its config "
                                            f"builds ({' '.join(str(exc).split())[:300]})") from exc
    if "scaler" in state:
        scaler.load_state_dict(state["scaler"])
    if ema is not None:
        if "ema" not in state:
            raise checkpoint.CheckpointMismatch(f"checkpoint {cfg.ckpt_path!r} holds no weight average: it was trained "
                                                "without optim.ema_decay; resume without it or start a new run")
        ema.load_state_dict(state["ema"])
    if "train_bn" in state:  # bn_recalibrate_scope=eval: training goes on from its own statistics
        precise_bn.restore(model, state["train_bn"])
    opt.load_state_dict(state["optimizer"])
    sched.load_state_dict(state["scheduler"])
    start = int(state["epoch"])  # epochs completed = the 0-based index of the next one
    # the schedule is a function of (epoch, epochs): re-derive it (epochs may have grown)
    for g, base in zip(opt.param_groups, sched.base_lrs):
        g["lr"] = base * group_factor(cfg, g["name"], start)
    sched.last_epoch = start
    if not world.enabled:
        seeding.set_rng_state(state["rng"])
    elif "rng_ranks" in state:
        seeding.set_rng_state(state["rng_ranks"][world.rank])
    else:  # a best.pt written at the end without the other ranks' streams: a fresh stream per rank
        seeding.seed_everything(seeding.for_rank(cfg.seed + start, world.rank, world.size))
    src_best = Path(cfg.ckpt_path).with_name("best.pt")
    if (distributed.from_env().main and src_best.is_file()
            and src_best.resolve() != (run_dir / "best.pt").resolve()):
        shutil.copyfile(src_best, run_dir / "best.pt")
    say(run_dir, f"resumed from {cfg.ckpt_path} at epoch {start + 1}/{cfg.epochs}")
    distributed.barrier(world)  # rank 0 has copied best.pt beside the run
    best_acc, best_epoch = float(state["best_val_acc"]), int(state["best_epoch"]) - 1
    if not (run_dir / "best.pt").is_file():  # best.pt did not travel with last.pt: select anew
        log.warning("no best.pt beside %s: model selection starts again from the resumed epoch", cfg.ckpt_path)
        best_acc, best_epoch = -1.0, -1
    return start, best_acc, best_epoch, int(state["skipped_steps"]), list(state["history"]), int(state.get("step", 0))


def patience_spent(patience: int | None, epoch: int, best_epoch: int) -> bool:
    """Before 0-based ``epoch``: have ``patience`` epochs in a row passed since the best validation
    accuracy (0-based ``best_epoch``; -1: none yet)? Always false without a patience."""
    return patience is not None and epoch - 1 - best_epoch >= patience


def last_stage(cfg: TrainConfig, epoch: int) -> bool:
    """Whether 0-based ``epoch`` lies in the run's last training stage (the multi-view net's
    ``stage_span``: ViewGCN's single-view stage is followed by the whole network's; one stage else)."""
    first, length = cfg.mvnet.stage_span(epoch, cfg.epochs)
    return first + length == cfg.epochs


def write_results(run_dir: Path, metrics: dict) -> Path:
    """``metrics.json``, ``confusion.json`` and ``confusion.png`` in ``run_dir``; returns metrics.json's path."""
    conf = {"classes": metrics["classes"], "rows": "true class", "columns": "predicted class",
            "matrix": metrics["confusion_matrix"]}
    (run_dir / "confusion.json").write_text(json.dumps(conf, indent=1))
    confusion_png(metrics["confusion_matrix"], metrics["classes"], run_dir / "confusion.png",
                  title=f"{metrics.get('split', 'test')}: acc {metrics['test_acc']:.3f}")
    path = run_dir / "metrics.json"
    path.write_text(json.dumps(metrics, indent=2))
    run_dir_state.write_status(run_dir, "ok")
    return path


# ----------------------------------------------------------------------------- the loop
def epoch_record(epoch: int, tr: dict, val: dict, val_ema, offsets: dict, detail: dict, lrs: dict, seconds: float,
                 extra: dict) -> dict:
    """One epoch's entry of ``history`` (metrics.json and the checkpoints)."""
    return {"epoch": epoch + 1, "train_loss": tr["loss"], "train_acc": tr["acc"],
            "val_acc": val["acc"], "val_mean_class_acc": val["mean_class_acc"], "val_loss": val["loss"],
            "skipped": tr["skipped"], "clipped": tr["clipped"],
            "grad_norm_selector": tr["grad_norm_selector"], "grad_norm_mvnet": tr["grad_norm_mvnet"],
            **offsets, **detail, **lrs, "seconds": seconds,
            **({"val_acc_ema": val_ema["acc"]} if val_ema is not None else {}), **extra}


def log_epoch(logger: RunLogger, step: int, tr: dict, val: dict, offsets: dict, detail: dict) -> None:
    """The epoch's scalars, view histograms and view grid in TensorBoard."""
    logger.scalars({"train/loss_epoch": tr["loss"], "train/acc": tr["acc"], "val/acc": val["acc"],
                    "val/mean_class_acc": val["mean_class_acc"], "val/loss": val["loss"],
                    "views/offset_azim": offsets["view_offset_azim"], "views/offset_elev": offsets["view_offset_elev"],
                    "views/spread": offsets["view_spread"],
                    **({"views/separation": offsets["view_separation"]} if offsets["view_separation"] is not None else {}),
                    **({"views/detail_seen": detail["val_detail_seen"]} if "val_detail_seen" in detail else {})}, step)
    logger.histogram("views/azim", val["azim"], step)
    logger.histogram("views/elev", val["elev"], step)
    if val["images"] is not None:
        logger.views("views/val", val["images"], step)


def epoch_line(epoch: int, cfg: TrainConfig, tr: dict, val: dict, val_ema, improved: bool, use_ema: bool,
               offsets: dict, detail: dict, seconds: float) -> str:
    return (f"epoch {epoch + 1}/{cfg.epochs}: train loss {tr['loss']:.4f} acc {tr['acc']:.3f} | val acc {val['acc']:.3f}"
            + (f" average {val_ema['acc']:.3f}" if val_ema is not None else "")
            + f"{' (best' + (': the average)' if use_ema else ')') if improved else ''} | "
            f"|u-u0| {offsets['view_offset_azim']:.1f}/{offsets['view_offset_elev']:.1f} deg | "
            + (f"detail seen {detail['val_detail_seen']:.2f} | " if "val_detail_seen" in detail else "") + f"{seconds:.1f}s")


def _device_name(device: torch.device) -> str:
    return f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else ""


def prepare_run(cfg: TrainConfig, run_dir: Path, world: distributed.World):
    """The device and the run's provenance record (a resumed run's is written by ``start_record``
    once the resume is accepted)."""
    if world.enabled:
        check_world(cfg, world)
    device = torch.device(distributed.init(world, resolve_device(cfg.device)))
    if world.main:
        run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    origin = {**provenance(str(device)), "device_requested": cfg.device, "world_size": world.size}
    if world.main and not cfg.ckpt_path:  # a new run's folder says what made it from the start
        (run_dir / "provenance.json").write_text(json.dumps(origin, indent=1))
    return device, origin


def announce(cfg: TrainConfig, device: torch.device) -> None:
    """The log's first lines, once the run is accepted (a refused resume writes nothing): the
    device that runs it, and a warning for a learned G on a renderer without a useful camera gradient."""
    log.info("device: %s%s (device=%s)", device, _device_name(device), cfg.device)
    problem = (cfg.renderer.camera_gradient_problem()
               if cfg.selector.uses_camera_gradient() and cfg.dataset.shape == "mesh" else None)
    if problem:
        log.warning("selector=%s with %s", cfg.selector.name, problem)


def start_record(run_dir: Path, origin: dict, resumed: bool) -> None:
    """The run is accepted and starts training: a resumed run's earlier ``metrics.json`` is kept
    aside (``metrics-before-resume-<time>.json``), the folder's earlier outcome cleared, and this
    run's provenance written. Nothing before this point writes into a resumed run's folder, so a
    refused resume changes nothing there."""
    if resumed and (run_dir / "metrics.json").is_file():
        (run_dir / "metrics.json").rename(run_dir / f"metrics-before-resume-{time.strftime('%Y%m%d-%H%M%S')}.json")
    run_dir_state.clear_status(run_dir)
    (run_dir / "provenance.json").write_text(json.dumps(origin, indent=1))


def test_best(model, cfg: TrainConfig, run_dir: Path, datasets: dict, classes: list, world, device, timer, costs_in):
    """``best.pt`` on the test split (read once), with the run's cost record (``engine/cost.py``)."""
    best = checkpoint.load(run_dir / "best.pt", map_location=device)
    model.load_state_dict(best["model"])
    with cost.peak_memory(device) as infer_memory:
        t_test = time.perf_counter()
        test = evaluate_split(model, datasets["test"], cfg, len(classes), "test", world)
        infer_seconds = time.perf_counter() - t_test
    first = next(iter(eval_loader(cfg, datasets["test"])), None)
    costs = cost.run_cost(model, cfg, infer_seconds=infer_seconds, infer_shapes=test["n"], infer_memory=infer_memory,
                          render_seconds=timer.seconds["render"],
                          flops=cost.flops_per_shape(model, first) if first is not None else {}, **costs_in)
    return best, test, costs


def validate(model, ema, dataset, cfg: TrainConfig, num_classes: int, world) -> tuple[dict, dict | None]:
    """The epoch's validation of the raw weights and (with ``optim.ema_decay``) of their average,
    with rank 0's BatchNorm statistics on every rank first."""
    distributed.broadcast_buffers(model, world)
    if ema is not None:
        distributed.broadcast_buffers(ema.model, world)
    val = evaluate_split(model, dataset, cfg, num_classes, "val", world)
    val_ema = evaluate_split(ema.model, dataset, cfg, num_classes, "val (average)", world) if ema is not None else None
    return val, val_ema


def run_metrics(cfg: TrainConfig, cfg_dict: dict, model, datasets: dict, test: dict, costs: dict, history: list,
                timer: StepTimer, origin: dict, world, *, best_acc: float, best_epoch: int, step: int, skipped: int,
                best_weights: str) -> dict:
    """The run's ``metrics.json``: the test split's results for ``best.pt``, model selection, the
    per-epoch history, time per stage, the cost record, the config and the provenance."""
    classes = list(datasets["train"].classes)
    seconds = [h["seconds"] for h in history]  # every epoch, resumed ones too
    return {
        "test_acc": test["acc"], "test_mean_class_acc": test["mean_class_acc"], "test_loss": test["loss"],
        "test_per_class_acc": dict(zip(classes, test["per_class_acc"])),
        "confusion_matrix": test["confusion"], "classes": classes, "test_size": test["n"], "split": "test",
        "best_val_acc": best_acc, "best_epoch": best_epoch + 1, "epochs": cfg.epochs, "epochs_trained": len(history),
        "stopped_early": len(history) < cfg.epochs, "steps": step,
        "best_weights": best_weights, "skipped_steps": skipped, "epoch_seconds": seconds,
        "mean_epoch_seconds": sum(seconds) / max(len(seconds), 1), "train_wall_seconds": sum(seconds),
        "step_seconds": timer.means(), "cost": costs,
        **{f"test_{k}": v for k, v in view_report(model, test["azim"], test["elev"]).items()},
        **{f"test_{k}": v for k, v in dataset_view_report(datasets["test"], test).items()},
        "history": history, "config": cfg_dict, "provenance": origin, "world_size": world.size,
    }


def train(cfg, run_dir, build_model=None) -> dict:
    """Train MVTN per ``cfg`` (TrainConfig / dict / DictConfig) writing into ``run_dir``; return the metrics.
    ``build_model(cfg, num_classes)``: the model factory (default ``build_mvtn``; diagnostics such as
    ``scripts/studies`` pass their own). ``deterministic=true``: the run under torch's deterministic
    algorithms (``seeding.deterministic``)."""
    cfg = as_config(cfg)
    if cfg.deterministic:
        cfg.renderer.deterministic = True
    with seeding.deterministic(cfg.deterministic):
        return _train(cfg, Path(run_dir), build_model)


def _train(cfg: TrainConfig, run_dir: Path, build_model) -> dict:
    world = distributed.from_env()  # torchrun: several processes, one run (runtime/distributed.py)
    device, origin = prepare_run(cfg, run_dir, world)
    cfg_dict = config_dict(cfg)
    resume = None
    if cfg.ckpt_path:
        resume = checkpoint.load(cfg.ckpt_path)
        checkpoint.check_compatible(resume["config"], cfg_dict, free=cfg.selector.free_keys())
    else:
        announce(cfg, device)  # (a resumed run's, once its checkpoint is accepted whole)

    seeding.seed_everything(cfg.seed)
    datasets = make_datasets(cfg)
    classes = list(datasets["train"].classes)
    if world.enabled:
        check_split_sizes(datasets, world)
    model = (build_model or build_mvtn)(cfg, num_classes=len(classes)).to(device)
    if world.enabled and cfg.sync_bn:  # BatchNorm over the global batch (models/sync_bn.py)
        sync_bn.convert(model)
    g_training = cfg.selector.training()(cfg)  # how G trains (selectors/training.py)
    g_training.start(model, cfg_dict, resumed=resume is not None)
    opt, sched = make_optimizer(cfg, model, g_training)
    scaler = grad_scaler(cfg.precision, device)
    ema = ModelEMA(model, cfg.optim.ema_decay) if cfg.optim.ema_decay is not None else None
    loss_fn = classification.loss_fn(cfg.task)

    if world.enabled:  # from here on each process draws its own stream (augmentation, light, colour, points)
        seeding.seed_everything(seeding.for_rank(cfg.seed, world.rank, world.size))
    start, best_acc, best_epoch, skipped, history, step = 0, -1.0, -1, 0, [], 0
    train_seconds, train_shapes = 0.0, 0  # this process's training passes (engine/cost.py)
    if resume is not None:
        start, best_acc, best_epoch, skipped, history, step = _resume(cfg, run_dir, model, opt, sched, resume, scaler,
                                                                      ema, classes, world)
        announce(cfg, device)
    if world.main:
        start_record(run_dir, origin, resumed=resume is not None)

    def payload(epoch, rngs=None):
        """``rngs``: every process's RNG state in rank order (``distributed.gather``; this one's alone by default)."""
        rngs = rngs or [seeding.rng_state()]
        return {"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                # epochs count from 1 as in metrics.json: "epoch" = epochs completed, "best_epoch" 1-based (0: none)
                "format": checkpoint.FORMAT, "epoch": epoch + 1, "step": step, "rng": rngs[0],
                "world_size": world.size, **({"rng_ranks": rngs} if world.enabled and len(rngs) == world.size else {}),
                "config": cfg_dict, "best_val_acc": best_acc, "best_epoch": best_epoch + 1, "skipped_steps": skipped,
                "history": history, "scaler": scaler.state_dict(), **({"ema": ema.state_dict()} if ema else {}),
                "classes": classes, "provenance": origin}

    logger = RunLogger(run_dir, cfg.logger if world.main else replace(cfg.logger, tensorboard=False))
    timer = StepTimer(device)
    try:
        with cost.peak_memory(device) as train_memory:
            for epoch in range(start, cfg.epochs):
                t0 = time.perf_counter()
                restart = cfg.mvnet.start_epoch(model.mvnet, epoch)  # ViewGCN: single views first, then the whole net
                if restart:
                    best_acc, best_epoch = -1.0, -1
                    say(run_dir, restart)
                elif patience_spent(cfg.patience, epoch, best_epoch) and last_stage(cfg, epoch):
                    # (a resumed run that stopped stops again)
                    say(run_dir, f"stopped after epoch {epoch}/{cfg.epochs}: validation accuracy has not improved for "
                                 f"{epoch - 1 - best_epoch} epochs (patience={cfg.patience}; best {best_acc:.4f} at "
                                 f"epoch {best_epoch + 1})")
                    break
                lrs = {f"lr_{g['name']}": g["lr"] for g in opt.param_groups}
                tr, step = train_one_epoch(model, train_loader(cfg, datasets["train"], epoch, world), opt, cfg, epoch,
                                           loss_fn, timer, logger, step, g_training, scaler=scaler, ema=ema, world=world)
                train_seconds += time.perf_counter() - t0
                if world.enabled:  # the epoch's sums over every rank's share
                    tr = all_ranks_epoch(tr, world, model.device)
                train_shapes += tr["seen"]
                skipped += tr["skipped"]
                for line in g_training.end_epoch(model, epoch):
                    say(run_dir, line)
                train_bn = g_training.before_validation(model, lambda: train_loader(cfg, datasets["train"], epoch, world))
                val, val_ema = validate(model, ema, datasets["val"], cfg, len(classes), world)
                sched.step()
                seconds = time.perf_counter() - t0
                offsets = view_report(model, val["azim"], val["elev"])
                detail = {f"val_{k}": v for k, v in dataset_view_report(datasets["val"], val).items()}
                history.append(epoch_record(epoch, tr, val, val_ema, offsets, detail, lrs, seconds,
                                            g_training.history(model)))
                log_epoch(logger, step, tr, val, offsets, detail)
                use_ema = val_ema is not None and val_ema["acc"] > val["acc"]  # the average is the better model now
                score = val_ema["acc"] if use_ema else val["acc"]
                improved = score > best_acc
                if improved:
                    best_acc, best_epoch = score, epoch
                rngs = distributed.gather(seeding.rng_state(), world)  # (every rank takes part)
                state = {**payload(epoch, rngs), **({"train_bn": train_bn} if train_bn is not None else {})}
                if improved and world.main:
                    checkpoint.save_atomic(run_dir / "best.pt", {**state, "model": ema.state_dict(), "ema_selected": True}
                                           if use_ema else state)
                if world.main:
                    checkpoint.save_atomic(run_dir / "last.pt", state)
                g_training.after_validation(model, train_bn)
                say(run_dir, epoch_line(epoch, cfg, tr, val, val_ema, improved, use_ema, offsets, detail, seconds))

        distributed.barrier(world)  # rank 0's files are written before anyone reads them
        if not (run_dir / "best.pt").is_file():  # resumed at the last epoch without a best.pt
            log.warning("no best.pt in %s: testing the last model", run_dir)
            best_acc, best_epoch = history[-1]["val_acc"] if history else -1.0, start - 1
            if world.main:
                checkpoint.save_atomic(run_dir / "best.pt", payload(start - 1))
            distributed.barrier(world)
        best, test, costs = test_best(model, cfg, run_dir, datasets, classes, world, device, timer,
                                      dict(train_seconds=train_seconds, train_shapes=train_shapes,
                                           train_memory=train_memory))
        logger.scalars({"test/acc": test["acc"], "test/mean_class_acc": test["mean_class_acc"],
                        **{f"cost/{k}": v for k, v in costs.items() if isinstance(v, (int, float))}}, step)
    finally:
        logger.close()
        loaders.release(*datasets.values())

    metrics = run_metrics(cfg, cfg_dict, model, datasets, test, costs, history, timer, origin, world,
                          best_acc=best_acc, best_epoch=best_epoch, step=step, skipped=skipped,
                          best_weights="average" if best.get("ema_selected") else "raw")
    if not world.main:
        return metrics
    view_figures(datasets["test"], test, run_dir)
    write_results(run_dir, metrics)
    say(run_dir, f"test accuracy {test['acc']:.4f} (mean per-class {test['mean_class_acc']:.4f}, best val {best_acc:.4f} "
          f"at epoch {best_epoch + 1})")
    return metrics
