"""One training epoch: every batch through G's training step (forward and objective), the
backward, the gradients averaged over processes and checked finite, one optimizer step, and the
epoch's running sums (``train_one_epoch``)."""
from __future__ import annotations

import logging

import torch
from tqdm.auto import tqdm

from ..config.schema import TrainConfig
from ..model import MVTN
from ..runtime import distributed
from ..tasks.robustness import random_rotations, turn_batch
from .run_logger import RunLogger
from .step_timer import StepTimer

log = logging.getLogger("mvtn-train")


class TrainingDiverged(RuntimeError):
    """The loss became non-finite; the run stops (the last written checkpoints stay intact)."""


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


def augment(batch: dict, cfg: TrainConfig) -> dict:
    """Training augmentation (``cfg.augment``): a new random rotation of every shape, from torch's RNG."""
    if cfg.augment.rotate == "none":
        return batch
    return turn_batch(batch, random_rotations(len(batch["points"]), cfg.augment.rotate))


class _Epoch:
    """Running sums of one training epoch."""

    def __init__(self):
        self.loss, self.correct, self.seen, self.skipped, self.clipped = 0.0, 0, 0, 0, 0
        self.g_norm_sum, self.c_norm_sum, self.steps = 0.0, 0.0, 0

    def add(self, loss, right: float, n: int, g_norm: float, c_norm: float) -> None:
        """One finished step of ``n`` shapes: C's mean ``loss``, the share ``right`` (the task
        head's ``hits``: shapes classified, part pixels labelled) and the gradient norms."""
        self.loss += float(loss.detach()) * n
        self.correct += right * n
        self.seen += n
        self.steps += 1
        self.g_norm_sum += g_norm
        self.c_norm_sum += c_norm

    def result(self) -> dict:
        n, s = max(self.seen, 1), max(self.steps, 1)
        return {"loss": self.loss / n, "acc": self.correct / n, "seen": self.seen, "skipped": self.skipped, "clipped": self.clipped,
                "grad_norm_selector": self.g_norm_sum / s, "grad_norm_mvnet": self.c_norm_sum / s}


def share_right(loss_fn, logits, labels) -> float:
    """The task head's ``hits`` (``tasks/heads.py``); a plain loss function: classification's."""
    hits = getattr(loss_fn, "hits", None)
    if hits is not None:
        return hits(logits, labels)
    return float((logits.detach().argmax(1) == labels).float().mean()) if len(labels) else 0.0


def train_one_epoch(model: MVTN, loader, opt, cfg: TrainConfig, epoch: int, loss_fn, timer: StepTimer,
                    logger: RunLogger, step: int, g_training, scaler=None, ema=None,
                    world: distributed.World = distributed.World()) -> tuple[dict, int]:
    """One pass over ``loader``; returns (epoch sums, global step after it). ``loss_fn``: the task
    head (``tasks/heads.py``: C's loss, its targets and hits) or a plain loss of classification;
    ``g_training``: how G trains (``selectors/training.py``: its ``train_step`` is the forward and the objective);
    ``scaler``: fp16's loss scaler (``models/precision.py``); ``ema``: a ``ModelEMA`` updated after
    every step."""
    model.train()
    groups = model.parameter_groups()
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
            norms = _optimizer_step(opt, groups, g_training, scaler, world)
        if norms is None:  # non-finite gradients: the step is skipped
            acc.skipped += 1
            if not scaling:
                log.warning("epoch %d step %d: non-finite gradients, step skipped", epoch + 1, step + 1)
            step += 1
            timer.step_done()  # its time was spent: count the step in the per-step means
            continue
        g_norm, c_norm = norms
        acc.clipped += int(bool(groups["selector"]) and g_norm > g_training.clip)
        if ema is not None:
            with timer.stage("optimizer"):
                ema.update(model, step)
        timer.step_done()
        acc.add(loss, share_right(loss_fn, out.logits, out.labels), len(out.labels), g_norm, c_norm)
        step += 1
        if step % cfg.logger.log_every == 0:
            logger.scalars({"train/loss": float(loss.detach()), "grad_norm/selector": g_norm,
                            "grad_norm/mvnet": c_norm,
                            **{f"lr/{g['name']}": g["lr"] for g in opt.param_groups}}, step)
        bar.set_postfix(loss=f"{acc.loss / max(acc.seen, 1):.3f}", acc=f"{acc.correct / max(acc.seen, 1):.3f}")
    return acc.result(), step


def _optimizer_step(opt, groups: dict, g_training, scaler, world) -> tuple[float, float] | None:
    """Average the gradients over the processes, unscale fp16's, and step when every gradient is
    finite; returns (G's gradient norm before clipping to ``g_training.clip``, C's), or None when a
    gradient was not finite (no step; fp16's scale is lowered, as expected now and then)."""
    all_params = groups["mvnet"] + groups["selector"]
    scaling = scaler is not None and scaler.is_enabled()
    if world.enabled:  # every rank's gradient of its weighted share -> the whole batch's, on every rank
        distributed.average_gradients(all_params, 1.0, world)
    if scaling:
        scaler.unscale_(opt)
    if not _grads_finite(all_params):
        opt.zero_grad(set_to_none=True)
        if scaling:
            scaler.update()
        return None
    c_norm = _grad_norm(groups["mvnet"])
    g_norm = float(torch.nn.utils.clip_grad_norm_(groups["selector"], g_training.clip)) if groups["selector"] else 0.0
    if scaling:
        scaler.step(opt)
        scaler.update()
    else:
        opt.step()
    return g_norm, c_norm


def all_ranks_epoch(tr: dict, world: distributed.World, device) -> dict:
    """One epoch's ``_Epoch.result`` over every rank: sums of losses, hits and shapes (the gradient
    norms and counts are the same on every rank, taken after the gradients were averaged)."""
    sums = distributed.all_sum(torch.tensor([tr["loss"] * tr["seen"], tr["acc"] * tr["seen"], float(tr["seen"])],
                                            dtype=torch.float64, device=device), world).tolist()
    n = max(sums[2], 1.0)
    return {**tr, "loss": sums[0] / n, "acc": sums[1] / n, "seen": int(sums[2])}
