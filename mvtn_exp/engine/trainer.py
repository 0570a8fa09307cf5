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
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

import torch

from ..config.schema import TrainConfig, as_config, config_dict, resolve_device  # noqa: F401 (as_config: the engine's API)
from ..data.datasets import build_dataset, view_figures
from ..data.datasets import view_headline
from ..data.datasets import view_report as dataset_view_report
from ..model import MVTN, build_mvtn
from ..models import sync_bn
from ..models.precision import grad_scaler
from ..runtime import checkpoint, distributed, seeding
from ..tasks.heads import build_head
from . import cost, loaders
from . import run_dir as run_dir_state
from .ema import ModelEMA
from .epoch import TrainingDiverged, all_ranks_epoch, train_one_epoch  # noqa: F401 (TrainingDiverged: the engine's API)
from .loaders import eval_loader, train_loader
from .provenance import provenance
from .records import epoch_line, epoch_record, log_epoch, run_metrics, say, view_report, write_results  # noqa: F401
from .run_logger import RunLogger
from .step_timer import StepTimer
from .train_state import TrainState

log = logging.getLogger("mvtn-train")
SPLITS = ("train", "val", "test")


# ----------------------------------------------------------------------------- pieces
def make_datasets(cfg: TrainConfig) -> dict:
    datasets = {split: build_dataset(cfg.dataset, split, progress=cfg.logger.progress) for split in SPLITS}
    for split, ds in datasets.items():
        if len(ds) == 0:
            raise ValueError(f"dataset {cfg.dataset.name} at {cfg.dataset.root}: the {split} split is empty"
                             + (" (raise dataset.val_fraction or add shapes)" if split == "val" else ""))
    return datasets


def evaluate_split(model, dataset, cfg: TrainConfig, head, desc: str,
                   world: distributed.World = distributed.World()) -> dict:
    """``head.evaluate`` on ``dataset`` (``tasks/heads.py``); with several processes each evaluates
    its own contiguous share (every shape once) and the results are merged: the same dict, over
    the whole split, in the dataset's order, on every rank."""
    if not world.enabled:
        return head.evaluate(model, eval_loader(cfg, dataset), desc=desc, progress=cfg.logger.progress)
    mine = loaders.shard_of(dataset, world)  # the same Subset every pass: its loader's workers are kept
    res = head.evaluate(model, eval_loader(cfg, mine), desc=desc, progress=cfg.logger.progress and world.main)
    parts = distributed.gather({k: res[k] for k in head.GATHERED}, world)
    if world.main:
        parts[0].update(images=res.get("images"), pictures=res.get("pictures"))
    return head.merge(parts)


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


def check_world(cfg: TrainConfig, world: distributed.World) -> None:
    """One-line errors for settings that several processes cannot share (before any work)."""
    if cfg.batch_size < 2 * world.size:
        raise ValueError(f"batch_size={cfg.batch_size} with {world.size} processes (WORLD_SIZE): batch_size is the global "
                         f"batch and every process needs at least 2 shapes of it; use batch_size >= {2 * world.size}")
    problem = cfg.selector.multi_process_problem(cfg.views, world.size)
    if problem:
        raise ValueError(problem)


def check_split_sizes(datasets: dict, world: distributed.World) -> None:
    """More processes than shapes in a split: one line naming the split (exit 2)."""
    for split, ds in datasets.items():
        if len(ds) < world.size:
            raise ValueError(f"{world.size} processes (WORLD_SIZE) but the {split} split has {len(ds)} shapes: use at "
                             f"most {len(ds)} processes")


def patience_spent(patience: int | None, epoch: int, best_epoch: int) -> bool:
    """Before 0-based ``epoch``: have ``patience`` epochs in a row passed since the best validation
    accuracy (0-based ``best_epoch``; -1: none yet)? Always false without a patience."""
    return patience is not None and epoch - 1 - best_epoch >= patience


def last_stage(cfg: TrainConfig, epoch: int) -> bool:
    """Whether 0-based ``epoch`` lies in the run's last training stage (the multi-view net's
    ``stage_span``: ViewGCN's single-view stage is followed by the whole network's; one stage else)."""
    first, length = cfg.mvnet.stage_span(epoch, cfg.epochs)
    return first + length == cfg.epochs


# ----------------------------------------------------------------------------- the loop
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


def test_best(state: TrainState, cfg: TrainConfig, run_dir: Path, datasets: dict, device, timer: StepTimer,
              train_memory) -> tuple[dict, dict, dict]:
    """``best.pt`` on the test split (read once), with the run's cost record (``engine/cost.py``);
    returns (best.pt's payload, the test results, the costs)."""
    best = checkpoint.load(run_dir / "best.pt", map_location=device)
    state.model.load_state_dict(best["model"])
    with cost.peak_memory(device) as infer_memory:
        t_test = time.perf_counter()
        test = evaluate_split(state.model, datasets["test"], cfg, state.head, "test", state.world)
        infer_seconds = time.perf_counter() - t_test
    first = next(iter(eval_loader(cfg, datasets["test"])), None)
    costs = cost.run_cost(state.model, cfg, infer_seconds=infer_seconds, infer_shapes=test["n"],
                          infer_memory=infer_memory, render_seconds=timer.seconds["render"],
                          flops=cost.flops_per_shape(state.model, first) if first is not None else {},
                          train_seconds=state.train_seconds, train_shapes=state.train_shapes,
                          train_memory=train_memory)
    return best, test, costs


def validate(model, ema, dataset, cfg: TrainConfig, head, world) -> tuple[dict, dict | None]:
    """The epoch's validation of the raw weights and (with ``optim.ema_decay``) of their average,
    with rank 0's BatchNorm statistics on every rank first."""
    distributed.broadcast_buffers(model, world)
    if ema is not None:
        distributed.broadcast_buffers(ema.model, world)
    val = evaluate_split(model, dataset, cfg, head, "val", world)
    val_ema = evaluate_split(ema.model, dataset, cfg, head, "val (average)", world) if ema is not None else None
    return val, val_ema


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
    resume = accepted_checkpoint(cfg, cfg_dict, device)
    seeding.seed_everything(cfg.seed)
    datasets = make_datasets(cfg)
    if world.enabled:
        check_split_sizes(datasets, world)
    state, g_training = build_state(cfg, run_dir, build_model, datasets, device, cfg_dict, origin, resume)
    if world.main:
        start_record(run_dir, origin, resumed=resume is not None)
    logger = RunLogger(run_dir, cfg.logger if world.main else replace(cfg.logger, tensorboard=False))
    timer = StepTimer(device)
    try:
        with cost.peak_memory(device) as train_memory:
            fit(state, cfg, run_dir, datasets, g_training, logger, timer)
        best, test, costs = test_best(state, cfg, run_dir, datasets, device, timer, train_memory)
        logger.scalars({"test/acc": test["acc"], "test/mean_class_acc": test["mean_class_acc"],
                        **{f"test/{k}": v for k, v in state.head.headline(test).items()},
                        **{f"cost/{k}": v for k, v in costs.items() if isinstance(v, (int, float))}}, state.step)
    finally:
        logger.close()
        loaders.release(*datasets.values())
    metrics = run_metrics(cfg, cfg_dict, state.model, datasets, test, costs, state.history, timer, origin, world,
                          best_acc=state.best_acc, best_epoch=state.best_epoch, step=state.step, skipped=state.skipped,
                          best_weights="average" if best.get("ema_selected") else "raw", head=state.head)
    if world.main:
        view_figures(datasets["test"], test, run_dir)
        write_results(run_dir, metrics, test)
        say(run_dir, state.head.summary_line(test, state.best_acc, state.best_epoch + 1))
    return metrics


def accepted_checkpoint(cfg: TrainConfig, cfg_dict: dict, device) -> dict | None:
    """The checkpoint a resumed run goes on from, checked to build the configured model (None for a
    new run, whose first log lines are written now; a resumed run's once its checkpoint is accepted)."""
    if not cfg.ckpt_path:
        announce(cfg, device)
        return None
    resume = checkpoint.load(cfg.ckpt_path)
    checkpoint.check_compatible(resume["config"], cfg_dict, free=cfg.selector.free_keys())
    return resume


def build_state(cfg: TrainConfig, run_dir: Path, build_model, datasets: dict, device, cfg_dict: dict, origin: dict,
                resume: dict | None) -> tuple[TrainState, object]:
    """The model, G's training, the optimizer, the loss scaler and the weight average in a
    ``TrainState``, resumed from ``resume`` when given; returns it and G's training."""
    world = distributed.from_env()
    classes = list(datasets["train"].classes)
    head = build_head(cfg.task, datasets["train"])  # the task's loss, targets and evaluation (tasks/heads.py)
    factory = build_model or partial(build_mvtn, categories=len(classes))
    model = factory(cfg, num_classes=head.num_outputs).to(device)
    if world.enabled and cfg.sync_bn:  # BatchNorm over the global batch (models/sync_bn.py)
        sync_bn.convert(model)
    g_training = cfg.selector.training()(cfg)  # how G trains (selectors/training.py)
    g_training.start(model, cfg_dict, resumed=resume is not None)
    opt, sched = make_optimizer(cfg, model, g_training)
    ema = ModelEMA(model, cfg.optim.ema_decay) if cfg.optim.ema_decay is not None else None
    state = TrainState(model, opt, sched, grad_scaler(cfg.precision, device), ema, world, cfg_dict, classes, origin,
                       head=head)
    if world.enabled:  # from here on each process draws its own stream (augmentation, light, colour, points)
        seeding.seed_everything(seeding.for_rank(cfg.seed, world.rank, world.size))
    if resume is not None:
        state.resume(resume, cfg.ckpt_path, run_dir, lambda name, epoch: group_factor(cfg, name, epoch), cfg.seed)
        say(run_dir, f"resumed from {cfg.ckpt_path} at epoch {state.start + 1}/{cfg.epochs}" if state.start < cfg.epochs
            else f"resumed from {cfg.ckpt_path}: its {state.start} epochs cover epochs={cfg.epochs}, nothing is left to "
                 f"train; best.pt is tested again (set epochs above {state.start} to train longer)")
        announce(cfg, device)
    return state, g_training


def fit(state: TrainState, cfg: TrainConfig, run_dir: Path, datasets: dict, g_training, logger: RunLogger,
        timer: StepTimer) -> None:
    """The epochs from ``state.start`` on (each trains, validates and checkpoints), then a
    ``best.pt`` made sure of (a run resumed at its last epoch may have none)."""
    for epoch in range(state.start, cfg.epochs):
        if not begin_epoch(state, cfg, run_dir, epoch):
            break
        run_epoch(state, cfg, run_dir, epoch, datasets, g_training, logger, timer)
    distributed.barrier(state.world)  # rank 0's files are written before anyone reads them
    if not (run_dir / "best.pt").is_file():  # resumed at the last epoch without a best.pt
        log.warning("no best.pt in %s: testing the last model", run_dir)
        state.best_acc = state.history[-1]["val_acc"] if state.history else -1.0
        state.best_epoch = state.start - 1
        if state.world.main:
            checkpoint.save_atomic(run_dir / "best.pt", state.payload(state.start - 1))
        distributed.barrier(state.world)


def begin_epoch(state: TrainState, cfg: TrainConfig, run_dir: Path, epoch: int) -> bool:
    """Before 0-based ``epoch``: a new training stage of the multi-view net restarts model
    selection (ViewGCN: single views first, then the whole net); False when patience is spent in
    the last stage (a resumed run that stopped stops again)."""
    restart = cfg.mvnet.start_epoch(state.model.mvnet, epoch)
    if restart:
        state.best_acc, state.best_epoch = -1.0, -1
        say(run_dir, restart)
        return True
    if patience_spent(cfg.patience, epoch, state.best_epoch) and last_stage(cfg, epoch):
        say(run_dir, f"stopped after epoch {epoch}/{cfg.epochs}: validation accuracy has not improved for "
                     f"{epoch - 1 - state.best_epoch} epochs (patience={cfg.patience}; best {state.best_acc:.4f} at "
                     f"epoch {state.best_epoch + 1})")
        return False
    return True


def run_epoch(state: TrainState, cfg: TrainConfig, run_dir: Path, epoch: int, datasets: dict, g_training,
              logger: RunLogger, timer: StepTimer) -> None:
    """Train one epoch, let G's training decide, validate (raw weights and their average), step the
    schedule, record the epoch and write the checkpoints."""
    t0, world, model = time.perf_counter(), state.world, state.model
    lrs = {f"lr_{g['name']}": g["lr"] for g in state.opt.param_groups}
    batches = lambda: train_loader(cfg, datasets["train"], epoch, world)  # noqa: E731
    tr, state.step = train_one_epoch(model, batches(), state.opt, cfg, epoch, state.head, timer,
                                     logger, state.step, g_training, scaler=state.scaler, ema=state.ema, world=world)
    state.train_seconds += time.perf_counter() - t0
    if world.enabled:  # the epoch's sums over every rank's share
        tr = all_ranks_epoch(tr, world, model.device)
    state.train_shapes += tr["seen"]
    state.skipped += tr["skipped"]
    for line in g_training.end_epoch(model, epoch):
        say(run_dir, line)
    train_bn = g_training.before_validation(model, batches)
    val, val_ema = validate(model, state.ema, datasets["val"], cfg, state.head, world)
    state.sched.step()
    seconds = time.perf_counter() - t0
    offsets = view_report(model, val["azim"], val["elev"])
    report = dataset_view_report(datasets["val"], val)
    headline = view_headline(datasets["val"], report)
    task_line = state.head.headline(val)
    detail = {f"val_{k.lower()}": v for k, v in {**task_line, **report}.items()}
    state.history.append(epoch_record(epoch, tr, val, val_ema, offsets, detail, lrs, seconds, g_training.history(model)))
    log_epoch(logger, state.step, tr, val, offsets, headline, task_line)
    score = state.head.score  # what model selection maximises (accuracy; instance mIoU)
    use_ema = val_ema is not None and val_ema[score] > val[score]  # the average is the better model now
    improved = state.improve(val_ema[score] if use_ema else val[score], epoch)
    state.save(run_dir, epoch, improved, use_ema, train_bn)
    g_training.after_validation(model, train_bn)
    say(run_dir, epoch_line(epoch, cfg, tr, val, val_ema, improved, use_ema, offsets, {**task_line, **headline},
                            seconds))
