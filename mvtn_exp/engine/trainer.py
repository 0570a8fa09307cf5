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
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from ..data.datasets import build_dataset
from ..model import MVTN, build_mvtn
from ..models.precision import grad_scaler
from ..render import layouts
from ..schema import TrainConfig
from ..selectors.fixed import random_directions
from ..selectors.hypotheses import join_views, split_images, split_views
from ..tasks import classification
from ..tasks.robustness import random_rotations, turn_batch
from ..viz.plots import confusion_png
from ..viz.views import detail_angles_png
from . import checkpoint, cost, distributed, loaders, precise_bn, seeding, view_gradient
from .loaders import eval_loader, train_loader
from .ema import ModelEMA
from .view_stats import view_stats
from .provenance import provenance
from .run_logger import RunLogger
from .step_timer import StepTimer
from . import view_transfer

log = logging.getLogger("mvtn-train")
SPLITS = ("train", "val", "test")


class TrainingDiverged(RuntimeError):
    """The loss became non-finite; the run stops (the last written checkpoints stay intact)."""


def as_config(cfg) -> TrainConfig:
    """TrainConfig | DictConfig | dict -> a validated TrainConfig (type-checked against the schema,
    interpolations resolved)."""
    base = OmegaConf.structured(TrainConfig)
    if isinstance(cfg, TrainConfig):
        node = OmegaConf.merge(base, OmegaConf.structured(cfg))
    else:
        node = OmegaConf.merge(base, cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg))
    obj: TrainConfig = OmegaConf.to_object(node)
    return obj.validate()


PATH_KEYS = (("dataset", "root"), ("dataset", "cache_dir"), ("dataset", "split_csv"), ("dataset", "synset_dict"),
             ("backbone", "weights"), ("paths", "data_dir"), ("paths", "output_dir"), ("paths", "cache_dir"))


def config_dict(cfg: TrainConfig) -> dict:
    """``cfg`` as plain data, with its file and folder paths made absolute (``PATH_KEYS``): what a
    checkpoint and metrics.json record works from any working directory."""
    out = asdict(cfg)
    for group, key in PATH_KEYS:
        value = out.get(group, {}).get(key)
        if isinstance(value, str) and value:
            out[group][key] = str(Path(value).expanduser().resolve())
    return out


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
    from torch.utils.data import Subset

    mine = Subset(dataset, distributed.shard(list(range(len(dataset))), world))
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


def stage_span(cfg: TrainConfig, epoch: int) -> tuple[int, int]:
    """``(first epoch, epochs)`` of the training stage holding ``epoch`` (0-based): the whole run,
    or with ``mvnet.stages=[S1, S2]`` (ViewGCN) the single-view stage or the whole-network stage."""
    stages = cfg.mvnet.stages
    if stages is None:
        return 0, cfg.epochs
    return (0, stages[0]) if epoch < stages[0] else (stages[0], cfg.epochs - stages[0])


def single_view_stage(cfg: TrainConfig, epoch: int) -> bool:
    """Whether ``epoch`` (0-based) is ViewGCN's stage 1 (views classified one at a time, G frozen)."""
    return cfg.mvnet.stages is not None and epoch < cfg.mvnet.stages[0]


def lr_factor(cfg: TrainConfig, epoch: int) -> float:
    """Multiplier of the base learning rates during ``epoch`` (0-based); the schedule runs over the
    epoch's training stage (``stage_span``: the whole run unless ``mvnet.stages`` is set)."""
    first, length = stage_span(cfg, epoch)
    e = epoch - first
    if cfg.optim.schedule == "cosine":
        return 0.5 * (1.0 + math.cos(math.pi * e / length))
    return cfg.optim.step_gamma ** (e // cfg.optim.step_size)


def group_factor(cfg: TrainConfig, name: str, epoch: int) -> float:
    """``lr_factor`` for parameter group ``name`` ("mvnet" | "selector"): G's is 0 from epoch
    ``optim.selector_epochs`` on (G frozen, C goes on training on G's views)."""
    stop = cfg.optim.selector_epochs
    if name == "selector" and stop is not None and epoch >= stop:
        return 0.0
    return lr_factor(cfg, epoch)


def make_optimizer(cfg: TrainConfig, model: MVTN):
    groups = model.parameter_groups()
    params = [{"params": groups["mvnet"], "lr": cfg.optim.lr, "name": "mvnet"}]
    if groups["selector"]:
        params.append({"params": groups["selector"], "lr": cfg.optim.lr_selector, "name": "selector",
                       "betas": (cfg.optim.selector_beta1, 0.999)})
    opt = torch.optim.AdamW(params, lr=cfg.optim.lr, weight_decay=cfg.optim.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, [lambda e, n=g["name"]: group_factor(cfg, n, e) for g in params])
    return opt, sched


def selector_lr(opt) -> float | None:
    """G's learning rate in ``opt`` now (None: no G group)."""
    return next((g["lr"] for g in opt.param_groups if g["name"] == "selector"), None)


def _grads_finite(params) -> bool:
    return all(bool(torch.isfinite(p.grad).all()) for p in params if p.grad is not None)


def _grad_norm(params) -> float:
    grads = [p.grad.detach().pow(2).sum() for p in params if p.grad is not None]
    return float(torch.stack(grads).sum().sqrt()) if grads else 0.0


def view_offsets(model: MVTN, azim: torch.Tensor, elev: torch.Tensor) -> dict:
    """Mean |u - u0| in degrees of predicted views ``[N, M]`` (azimuth modulo 360; 0 for fixed selectors)."""
    init = getattr(model.selector, "initial_views", None)
    if init is None or azim.numel() == 0:
        return {"view_offset_azim": 0.0, "view_offset_elev": 0.0}
    a0, e0, _ = init(1)
    d_azim = torch.remainder(azim - a0.cpu() + 180.0, 360.0) - 180.0  # the same camera 360 deg apart
    return {"view_offset_azim": float(d_azim.abs().mean()),
            "view_offset_elev": float((elev - e0.cpu()).abs().mean())}


def view_report(model: MVTN, azim: torch.Tensor, elev: torch.Tensor) -> dict:
    """``view_offsets`` and ``view_stats`` (spread over shapes, separation within a shape) of views ``[N, M]``."""
    return {**view_offsets(model, azim, elev), **view_stats(azim, elev)}


def warmup_views(model: MVTN, batch: dict, cfg: TrainConfig):
    """Views of a warm-up step (G frozen), each ``[B, optim.warmup_num_views or views]``: G's initial
    views u0, new uniform random views per shape, or the fixed spherical layout."""
    B, M = batch["points"].shape[0], cfg.optim.warmup_num_views or cfg.views
    if cfg.optim.warmup_views == "random":
        azim, elev = random_directions((B, M))
        azim, elev = azim.float().to(model.device), elev.float().to(model.device)
        return azim, elev, torch.full_like(azim, cfg.selector.distance)
    if cfg.optim.warmup_views == "spherical":
        return layouts.spherical(M, B, cfg.selector.distance, device=model.device, sphere=cfg.selector.sphere)
    return tuple(t.to(model.device) for t in model.selector.initial_views(B))


def detail_report(dataset, res: dict) -> dict:
    """For datasets that know where their class detail shows (``synthetic_views``): the share of
    shapes of which some predicted view sees it, and the accuracy on those and on the rest; ``{}``
    for other datasets. ``res``: a ``classification.evaluate`` result on ``dataset`` (same order)."""
    if not hasattr(dataset, "detail_seen") or res["azim"].numel() == 0:
        return {}
    seen = torch.from_numpy(dataset.detail_seen(res["azim"].double().numpy(), res["elev"].double().numpy(),
                                                res["dist"].double().numpy()).any(1))
    right = res["pred"] == res["labels"]

    def acc(mask):
        return float(right[mask].float().mean()) if bool(mask.any()) else None

    nearest = dataset.detail_angles(res["azim"].double().numpy(), res["elev"].double().numpy(),
                                    res["dist"].double().numpy()).min(1)
    return {"detail_seen": float(seen.float().mean()), "acc_detail_seen": acc(seen), "acc_detail_unseen": acc(~seen),
            "detail_angle_median": float(np.median(nearest))}


def exploring_flips(model: MVTN, cfg: TrainConfig, epoch: int) -> bool:
    """Whether training epoch ``epoch`` (0-based) renders some views from their antipodes."""
    return (model.polarity is not None and epoch < cfg.optim.flip_epochs
            and epoch >= cfg.optim.selector_warmup_epochs)


def exploring_hypotheses(model: MVTN, cfg: TrainConfig, epoch: int) -> bool:
    """Whether training epoch ``epoch`` (0-based) renders all of G's hypotheses (selectors/hypotheses.py)."""
    return (model.hypotheses is not None and not bool(model.hypotheses.done) and epoch < cfg.optim.hypothesis_epochs
            and epoch >= cfg.optim.selector_warmup_epochs)


def hypothesis_losses(model: MVTN, logits: torch.Tensor, images: torch.Tensor, labels: torch.Tensor, H: int, S: int,
                      selector_loss) -> torch.Tensor:
    """Each shape's G loss under each of the H hypotheses, ``[B, H]``. Separate (S = H): read off
    the training logits ``[B * H, classes]``; pooled (S = 1): C in eval mode, without gradients, on
    each hypothesis's M views alone (``images [B, H * M, 3, h, w]``)."""
    if S == H:
        return selector_loss(logits.detach(), labels).reshape(-1, H)
    with torch.no_grad(), view_gradient.eval_mode(model.mvnet):
        alone, _ = model.mvnet(split_images(images.detach(), H))
    return selector_loss(alone, labels.repeat_interleave(H)).reshape(-1, H)


def flip_generator(seed: int, step: int) -> torch.Generator:
    """The flip draws' own generator for global step ``step`` (a stream apart from the smoothed noise)."""
    return view_gradient.noise_generator(int(seed) + 7_919, step)


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

    def result(self) -> dict:
        n, s = max(self.seen, 1), max(self.steps, 1)
        return {"loss": self.loss / n, "acc": self.correct / n, "seen": self.seen, "skipped": self.skipped, "clipped": self.clipped,
                "grad_norm_selector": self.g_norm_sum / s, "grad_norm_mvnet": self.c_norm_sum / s}


def train_one_epoch(model: MVTN, loader, opt, cfg: TrainConfig, epoch: int, loss_fn, timer: StepTimer,
                    logger: RunLogger, step: int, scaler=None, ema=None,
                    world: distributed.World = distributed.World()) -> tuple[dict, int]:
    """One pass over ``loader``; returns (epoch sums, global step after it). ``scaler``: fp16's
    loss scaler (``models/precision.py``); ``ema``: a ``ModelEMA`` updated after every step."""
    model.train()
    groups = model.parameter_groups()
    all_params = groups["mvnet"] + groups["selector"]
    acc = _Epoch()
    # G frozen, C alone: G's warm-up, and ViewGCN's single-view stage (on G's initial views)
    warm = bool(groups["selector"]) and (epoch < cfg.optim.selector_warmup_epochs or single_view_stage(cfg, epoch))
    # G's learning rate is 0 (optim.selector_epochs reached, or lr_selector=0): C trains on G's
    # views, and neither G's gradient nor the smoothed probes are computed (G's weights are the same)
    frozen = bool(groups["selector"]) and not warm and selector_lr(opt) == 0.0
    learning = bool(groups["selector"]) and not warm and not frozen
    smoothed = learning and cfg.optim.selector_grad == "smoothed"
    flips = model.polarity if exploring_flips(model, cfg, epoch) else None
    # H > 1: all of G's hypotheses are rendered; C classifies each as a shape of its own (S = H:
    # hypothesis_mode=separate) or all H x M views of a shape pooled as one (S = 1: pooled)
    H = model.hypotheses.hypotheses if exploring_hypotheses(model, cfg, epoch) else 1
    S = H if cfg.optim.hypothesis_mode == "separate" else 1
    per_shape_loss = classification.loss_fn(cfg.task, reduction="none")
    selector_loss = classification.selector_loss_fn(cfg.optim.selector_loss, cfg.task)
    bar = tqdm(loader, desc=f"train {epoch + 1}/{cfg.epochs}", leave=False, disable=None if cfg.logger.progress else True)
    it = iter(bar)
    while True:
        with timer.stage("data"):
            batch = next(it, None)
            if batch is not None:
                batch = augment(batch, cfg)
        if batch is None:
            break
        labels = batch["labels"].to(model.device).repeat_interleave(S)  # [B * S]
        with timer.stage("selector"), torch.set_grad_enabled(not frozen):
            views = warmup_views(model, batch, cfg) if warm else model.select(batch, all_hypotheses=H > 1)
            if flips is not None:  # some views from their antipodes (selectors/polarity.py)
                views, flip_mask = flips.explore(views, cfg.optim.flip_explore, flip_generator(cfg.seed, step))
        with timer.stage("render"), torch.set_grad_enabled(not smoothed):
            images = model.render(batch, *views)  # smoothed: R is not differentiated
            if S > 1:
                images = split_images(images, S)  # [B * H, M, 3, h, w]
        with timer.stage("backbone"):
            logits, _ = model.classify(images, views if S == 1 else split_views(views, S))
            loss = model.mvnet.training_loss(logits, labels, loss_fn)
        if not bool(torch.isfinite(loss.detach())):
            raise TrainingDiverged(f"epoch {epoch + 1}, step {step + 1}: non-finite loss {float(loss.detach())} "
                                   f"(batch {batch['names'][:3]}...); stopping, the last written checkpoint is intact")
        if flips is not None:
            flips.record(per_shape_loss(logits.detach(), labels), flip_mask)
        if H > 1:  # each shape's loss under each hypothesis: G's own loss (selectors/hypotheses.py)
            with timer.stage("selector"):
                model.hypotheses.record(hypothesis_losses(model, logits, images, labels, H, S, selector_loss))
        objective = loss
        if smoothed and step % cfg.optim.smoothed_every == 0:  # G's gradient from the loss at perturbed views
            # (view_gradient.py), charged to G; on the other steps G gets no gradient and AdamW leaves it
            with timer.stage("selector"):
                g = view_gradient.smoothed_view_gradient(
                    view_gradient.model_render_loss(model, batch, labels, selector_loss, hypotheses=S),
                    split_views(views, S) if S > 1 else views,
                    cfg.optim.smoothed_pairs, cfg.optim.smoothed_sigma, view_gradient.noise_generator(cfg.seed, step))
                objective = loss + view_gradient.surrogate(views, *(join_views(g, S) if S > 1 else g))
        with timer.stage("optimizer"):
            opt.zero_grad(set_to_none=True)
        scaling = scaler is not None and scaler.is_enabled()
        timer.backward(scaler.scale(objective) if scaling else objective, views, images)
        with timer.stage("optimizer"):
            if world.enabled:  # every rank's gradient of its share -> the whole batch's, on every rank
                n_all = float(distributed.all_sum(torch.tensor(float(len(labels)), device=model.device), world))
                distributed.average_gradients(all_params, len(labels) / n_all, world)
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
                g_norm = float(torch.nn.utils.clip_grad_norm_(groups["selector"], cfg.optim.clip_selector))
                acc.clipped += int(g_norm > cfg.optim.clip_selector)
            if scaling:
                scaler.step(opt)
                scaler.update()
            else:
                opt.step()
            if ema is not None:
                ema.update(model, step)
        timer.step_done()
        n = len(labels)
        acc.loss += float(loss.detach()) * n
        acc.correct += int((logits.detach().argmax(1) == labels).sum())
        acc.seen += n
        acc.steps += 1
        acc.g_norm_sum += g_norm
        acc.c_norm_sum += c_norm
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
    if cfg.selector.hypotheses > 1 or cfg.optim.flip_explore > 0:
        raise ValueError(f"selector.hypotheses={cfg.selector.hypotheses} / optim.flip_explore={cfg.optim.flip_explore} "
                         f"with {world.size} processes: their per-shape statistics are not shared between processes "
                         "yet; run them in one process")


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


def _resume(cfg: TrainConfig, run_dir: Path, model, opt, sched, state: dict, scaler, ema) -> None:
    model.load_state_dict(state["model"])
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
    seeding.set_rng_state(state["rng"])
    src_best = Path(cfg.ckpt_path).with_name("best.pt")
    if (distributed.from_env().main and src_best.is_file()
            and src_best.resolve() != (run_dir / "best.pt").resolve()):
        shutil.copyfile(src_best, run_dir / "best.pt")
    say(run_dir, f"resumed from {cfg.ckpt_path} at epoch {start + 1}/{cfg.epochs}")


def write_results(run_dir: Path, metrics: dict) -> Path:
    """``metrics.json``, ``confusion.json`` and ``confusion.png`` in ``run_dir``; returns metrics.json's path."""
    conf = {"classes": metrics["classes"], "rows": "true class", "columns": "predicted class",
            "matrix": metrics["confusion_matrix"]}
    (run_dir / "confusion.json").write_text(json.dumps(conf, indent=1))
    confusion_png(metrics["confusion_matrix"], metrics["classes"], run_dir / "confusion.png",
                  title=f"{metrics.get('split', 'test')}: acc {metrics['test_acc']:.3f}")
    path = run_dir / "metrics.json"
    path.write_text(json.dumps(metrics, indent=2))
    return path


# ----------------------------------------------------------------------------- the loop
def train(cfg, run_dir, build_model=None) -> dict:
    """Train MVTN per ``cfg`` (TrainConfig / dict / DictConfig) writing into ``run_dir``; return the metrics.
    ``build_model(cfg, num_classes)``: the model factory (default ``build_mvtn``; diagnostics such as
    ``bench.axis_views`` pass their own)."""
    cfg = as_config(cfg)
    run_dir = Path(run_dir)
    world = distributed.from_env()  # torchrun: several processes, one run (engine/distributed.py)
    if world.enabled:
        check_world(cfg, world)
    device = torch.device(distributed.init(world, cfg.device))
    if world.main:
        run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    cfg_dict = config_dict(cfg)
    origin = {**provenance(str(device)), "world_size": world.size}
    if world.main:
        (run_dir / "provenance.json").write_text(json.dumps(origin, indent=1))
    steps_on_views = cfg.selector.name == "optimized" and cfg.selector.opt_steps > 0
    problem = (cfg.renderer.camera_gradient_problem()
               if ((cfg.selector.learned and not cfg.selector.from_ckpt and cfg.optim.selector_grad == "autograd")
                   or steps_on_views) and cfg.dataset.shape == "mesh" else None)
    if problem:
        log.warning("%s with %s", "selector=optimized" if steps_on_views else "learned selector", problem)

    resume = None
    if cfg.ckpt_path:
        resume = checkpoint.load(cfg.ckpt_path)
        checkpoint.check_compatible(resume["config"], cfg_dict)

    seeding.seed_everything(cfg.seed)
    datasets = make_datasets(cfg)
    classes = list(datasets["train"].classes)
    if world.enabled:
        check_split_sizes(datasets, world)
    eval_loaders = {s: eval_loader(cfg, datasets[s]) for s in ("val", "test")}
    model = (build_model or build_mvtn)(cfg, num_classes=len(classes)).to(device)
    if cfg.selector.from_ckpt:  # view transfer: G from another run, frozen (a resumed run has it in its own state)
        if resume is None:
            view_transfer.load_frozen_selector(model, cfg_dict, cfg.selector.from_ckpt)
        else:
            view_transfer.freeze_selector(model)
    opt, sched = make_optimizer(cfg, model)
    scaler = grad_scaler(cfg.precision, device)
    ema = ModelEMA(model, cfg.optim.ema_decay) if cfg.optim.ema_decay is not None else None
    loss_fn = classification.loss_fn(cfg.task)

    start, best_acc, best_epoch, skipped, history, step = 0, -1.0, -1, 0, [], 0
    train_seconds, train_shapes = 0.0, 0  # this process's training passes (engine/cost.py)
    if resume is not None:
        if list(resume.get("classes", classes)) != classes:
            raise checkpoint.CheckpointMismatch(f"checkpoint {cfg.ckpt_path!r} was trained on classes "
                                                f"{resume['classes']} but the dataset has {classes}")
        _resume(cfg, run_dir, model, opt, sched, resume, scaler, ema)
        distributed.barrier(world)  # rank 0 has copied best.pt beside the run
        start = int(resume["epoch"])
        best_acc, best_epoch = float(resume["best_val_acc"]), int(resume["best_epoch"]) - 1
        if not (run_dir / "best.pt").is_file():  # best.pt did not travel with last.pt: select anew
            log.warning("no best.pt beside %s: model selection starts again from the resumed epoch", cfg.ckpt_path)
            best_acc, best_epoch = -1.0, -1
        skipped, history, step = int(resume["skipped_steps"]), list(resume["history"]), int(resume.get("step", 0))

    def payload(epoch):
        return {"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                # epochs count from 1 as in metrics.json: "epoch" = epochs completed, "best_epoch" 1-based (0: none)
                "format": checkpoint.FORMAT, "epoch": epoch + 1, "step": step, "rng": seeding.rng_state(),
                "config": cfg_dict, "best_val_acc": best_acc, "best_epoch": best_epoch + 1, "skipped_steps": skipped,
                "history": history, "scaler": scaler.state_dict(), **({"ema": ema.state_dict()} if ema else {}),
                "classes": classes, "provenance": origin}

    logger = RunLogger(run_dir, cfg.logger if world.main else replace(cfg.logger, tensorboard=False))
    timer = StepTimer(device)
    try:
        with cost.peak_memory(device) as train_memory:
            for epoch in range(start, cfg.epochs):
                t0 = time.perf_counter()
                if cfg.mvnet.stages is not None:  # ViewGCN: single views first, then the whole network
                    model.mvnet.stage.fill_(1 if single_view_stage(cfg, epoch) else 2)
                    if epoch == cfg.mvnet.stages[0]:
                        best_acc, best_epoch = -1.0, -1
                        say(run_dir, f"epoch {epoch + 1}: ViewGCN stage 2 (the whole network); model selection "
                                     "counts from here")
                lrs = {f"lr_{g['name']}": g["lr"] for g in opt.param_groups}
                tr, step = train_one_epoch(model, train_loader(cfg, datasets["train"], epoch, world), opt, cfg, epoch,
                                           loss_fn, timer, logger, step, scaler=scaler, ema=ema, world=world)
                train_seconds += time.perf_counter() - t0
                if world.enabled:  # the epoch's sums over every rank's share
                    tr = all_ranks_epoch(tr, world, model.device)
                train_shapes += tr["seen"]
                skipped += tr["skipped"]
                if exploring_flips(model, cfg, epoch):
                    turned = model.polarity.decide()
                    if turned:
                        say(run_dir, f"epoch {epoch + 1}: view(s) {turned} turned round (their antipodes had the lower loss)")
                hypothesis_losses = None
                if exploring_hypotheses(model, cfg, epoch):
                    active, hypothesis_losses, clear = model.hypotheses.decide(cfg.optim.hypothesis_z)
                    if active is not None:
                        model.selector.active.fill_(active)
                    last = epoch + 1 == cfg.optim.hypothesis_epochs
                    if clear or last:
                        model.hypotheses.finish()
                    say(run_dir, f"epoch {epoch + 1}: hypotheses' mean {cfg.optim.selector_loss} loss "
                                 f"{' / '.join(f'{x:.4f}' for x in hypothesis_losses)}: hypothesis {active} active"
                                 + (" (a clear lead: kept from now on)" if clear else " (kept from now on)" if last else ""))
                train_bn = None  # bn_recalibrate_scope=eval: training's own statistics, put back after saving
                if cfg.optim.bn_recalibrate:
                    if cfg.optim.bn_recalibrate_scope == "eval":
                        train_bn = precise_bn.running_statistics(model)
                    precise_bn.recalibrate(model, train_loader(cfg, datasets["train"], epoch, world),
                                           cfg.optim.bn_recalibrate)
                distributed.broadcast_buffers(model, world)  # rank 0's BatchNorm statistics everywhere
                if ema is not None:
                    distributed.broadcast_buffers(ema.model, world)
                val = evaluate_split(model, datasets["val"], cfg, len(classes), "val", world)
                val_ema = (evaluate_split(ema.model, datasets["val"], cfg, len(classes), "val (average)", world)
                           if ema is not None else None)
                sched.step()
                seconds = time.perf_counter() - t0
                offsets = view_report(model, val["azim"], val["elev"])
                detail = {f"val_{k}": v for k, v in detail_report(datasets["val"], val).items()}
                history.append({"epoch": epoch + 1, "train_loss": tr["loss"], "train_acc": tr["acc"],
                                "val_acc": val["acc"], "val_mean_class_acc": val["mean_class_acc"], "val_loss": val["loss"],
                                "skipped": tr["skipped"], "clipped": tr["clipped"],
                                "grad_norm_selector": tr["grad_norm_selector"], "grad_norm_mvnet": tr["grad_norm_mvnet"],
                                **offsets, **detail, **lrs, "seconds": seconds,
                                **({"val_acc_ema": val_ema["acc"]} if val_ema is not None else {}),
                                **({"views_flipped": model.polarity.flipped.tolist()} if model.polarity is not None else {}),
                                **({"hypothesis_active": int(model.selector.active), "hypothesis_losses": hypothesis_losses}
                                   if model.hypotheses is not None else {})})
                logger.scalars({"train/loss_epoch": tr["loss"], "train/acc": tr["acc"], "val/acc": val["acc"],
                                "val/mean_class_acc": val["mean_class_acc"], "val/loss": val["loss"],
                                "views/offset_azim": offsets["view_offset_azim"],
                                "views/offset_elev": offsets["view_offset_elev"],
                                "views/spread": offsets["view_spread"],
                                **({"views/separation": offsets["view_separation"]}
                                   if offsets["view_separation"] is not None else {}),
                                **({"views/detail_seen": detail["val_detail_seen"]} if detail else {})}, step)
                logger.histogram("views/azim", val["azim"], step)
                logger.histogram("views/elev", val["elev"], step)
                if val["images"] is not None:
                    logger.views("views/val", val["images"], step)
                use_ema = val_ema is not None and val_ema["acc"] > val["acc"]  # the average is the better model now
                score = val_ema["acc"] if use_ema else val["acc"]
                improved = score > best_acc
                if improved:
                    best_acc, best_epoch = score, epoch
                state = payload(epoch)
                if train_bn is not None:
                    state["train_bn"] = train_bn
                if improved and world.main:
                    checkpoint.save_atomic(run_dir / "best.pt", {**state, "model": ema.state_dict(), "ema_selected": True}
                                           if use_ema else state)
                if world.main:
                    checkpoint.save_atomic(run_dir / "last.pt", state)
                if train_bn is not None:
                    precise_bn.restore(model, train_bn)
                say(run_dir, f"epoch {epoch + 1}/{cfg.epochs}: train loss {tr['loss']:.4f} acc {tr['acc']:.3f} | "
                      f"val acc {val['acc']:.3f}"
                      + (f" average {val_ema['acc']:.3f}" if val_ema is not None else "")
                      + f"{' (best' + (': the average)' if use_ema else ')') if improved else ''} | "
                      f"|u-u0| {offsets['view_offset_azim']:.1f}/{offsets['view_offset_elev']:.1f} deg | "
                      + (f"detail seen {detail['val_detail_seen']:.2f} | " if detail else "") + f"{seconds:.1f}s")

        distributed.barrier(world)  # rank 0's files are written before anyone reads them
        if not (run_dir / "best.pt").is_file():  # resumed at the last epoch without a best.pt
            log.warning("no best.pt in %s: testing the last model", run_dir)
            best_acc, best_epoch = history[-1]["val_acc"] if history else -1.0, start - 1
            if world.main:
                checkpoint.save_atomic(run_dir / "best.pt", payload(start - 1))
            distributed.barrier(world)
        best = checkpoint.load(run_dir / "best.pt", map_location=device)
        model.load_state_dict(best["model"])
        with cost.peak_memory(device) as infer_memory:
            t_test = time.perf_counter()
            test = evaluate_split(model, datasets["test"], cfg, len(classes), "test", world)
            infer_seconds = time.perf_counter() - t_test
        first = next(iter(eval_loaders["test"]), None)
        costs = cost.run_cost(model, cfg, train_seconds=train_seconds, train_shapes=train_shapes,
                              infer_seconds=infer_seconds, infer_shapes=test["n"], train_memory=train_memory,
                              infer_memory=infer_memory, render_seconds=timer.seconds["render"],
                              flops=cost.flops_per_shape(model, first) if first is not None else {})
        logger.scalars({"test/acc": test["acc"], "test/mean_class_acc": test["mean_class_acc"],
                        **{f"cost/{k}": v for k, v in costs.items() if isinstance(v, (int, float))}}, step)
    finally:
        logger.close()
        loaders.release(*datasets.values())

    metrics = {
        "test_acc": test["acc"], "test_mean_class_acc": test["mean_class_acc"], "test_loss": test["loss"],
        "test_per_class_acc": dict(zip(classes, test["per_class_acc"])),
        "confusion_matrix": test["confusion"], "classes": classes, "test_size": test["n"], "split": "test",
        "best_val_acc": best_acc, "best_epoch": best_epoch + 1, "epochs": cfg.epochs, "steps": step,
        "best_weights": "average" if best.get("ema_selected") else "raw",
        "skipped_steps": skipped, "epoch_seconds": [h["seconds"] for h in history],
        "mean_epoch_seconds": sum(h["seconds"] for h in history) / max(len(history), 1),
        "step_seconds": timer.means(), "cost": costs,
        **{f"test_{k}": v for k, v in view_report(model, test["azim"], test["elev"]).items()},
        **{f"test_{k}": v for k, v in detail_report(datasets["test"], test).items()},
        "history": history, "config": cfg_dict, "provenance": origin, "world_size": world.size,
    }
    if not world.main:
        return metrics
    if hasattr(datasets["test"], "detail_angles") and test["azim"].numel():
        detail_angles_png(datasets["test"].detail_angles(test["azim"].double().numpy(), test["elev"].double().numpy(),
                                                         test["dist"].double().numpy()), run_dir / "detail_angles.png")
    write_results(run_dir, metrics)
    say(run_dir, f"test accuracy {test['acc']:.4f} (mean per-class {test['mean_class_acc']:.4f}, best val {best_acc:.4f} "
          f"at epoch {best_epoch + 1})")
    return metrics
