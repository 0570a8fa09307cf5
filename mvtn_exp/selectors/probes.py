"""G trained from probe renders: the smoothed gradient, G's own loss, view flips and raced hypotheses.

``ProbeTraining`` is the training of ``selector=poi`` (this project's recipe) and of any learned
selector with ``grad=smoothed``, ``flip_explore > 0`` or ``hypotheses > 1``:

- ``grad=smoothed``: R is not differentiated; every ``probe_every`` steps G's gradient is the
  task loss smoothed over the views, estimated from ``probe_pairs`` antithetic pairs of renders
  (``selectors/view_gradient.py``) of G's own ``loss`` (``task`` or ``centered_logit``); with
  ``probe_batched`` every probe of a step rendered in one call (not while racing);
- ``train_jitter``: C trains on G's views moved by Gaussian noise (degrees; the probes stay at
  G's views), so that C does not adapt to G's exact view;
- ``flip_explore``: some training views are rendered from their antipodes, and a view whose
  antipode had the lower loss turns round at the end of the epoch (``polarity.py``);
- ``hypotheses`` H > 1 (``mvtn_poi``, ``poi``): for at most ``race_epochs`` epochs all H sets of
  views are rendered, C trains on each (``race_mode``), and the set of lowest G loss is kept
  (``hypotheses.py``); with ``race_batches`` N the race is decided for good after N batches of a
  racing epoch (the rest of the epoch renders the kept set alone); ``race_probes=false``: no
  probes while racing (the hypotheses hold their views; G moves the kept one after the race).
"""
from __future__ import annotations

from typing import Optional

import torch

from . import view_gradient
from ..tasks import classification
from .hypotheses import join_views, split_images, split_views
from .training import LearnedTraining, Step


def hypothesis_losses(model, logits, images, labels, H: int, S: int, selector_loss):
    """Each shape's G loss under each of the H hypotheses, ``[B, H]``. Separate (S = H): read off
    the training logits ``[B * H, classes]``; pooled (S = 1): C in eval mode, without gradients, on
    each hypothesis's M views alone (``images [B, H * M, 3, h, w]``)."""
    if S == H:
        return selector_loss(logits.detach(), labels).reshape(-1, H)
    with torch.no_grad(), view_gradient.eval_mode(model.mvnet):
        alone, _ = model.mvnet(split_images(images.detach(), H))
    return selector_loss(alone, labels.repeat_interleave(H)).reshape(-1, H)


def jittered(views: tuple, degrees: float, generator: torch.Generator) -> tuple:
    """``(azim, elev, dist)`` each ``[B, M]`` -> the same views moved by ``N(0, degrees^2)`` in azimuth
    and elevation (detached: C's training views, not G's)."""
    azim, elev, dist = (v.detach() for v in views)
    noise = torch.randn((2, *azim.shape), generator=generator, dtype=torch.float64).to(azim)
    return azim + degrees * noise[0], elev + degrees * noise[1], dist


def flip_generator(seed: int, step: int) -> torch.Generator:
    """The flip draws' own generator for global step ``step`` (a stream apart from the smoothed noise)."""
    return view_gradient.noise_generator(int(seed) + 7_919, step)


class ProbeTraining(LearnedTraining):
    """``LearnedTraining`` plus the probes of the module docstring."""

    def __init__(self, cfg) -> None:
        super().__init__(cfg)
        self.per_shape_loss = classification.loss_fn(cfg.task, reduction="none")
        self.selector_loss = classification.selector_loss_fn(self.s.loss, cfg.task)
        self.H = self.S = 1
        self.flips = self.smoothed = False

    def exploring_flips(self, model, epoch: int) -> bool:
        return (model.polarity is not None and epoch < self.s.flip_epochs and epoch >= self.s.warmup_epochs)

    def racing(self, model, epoch: int) -> bool:
        race = model.hypotheses
        return (race is not None and not bool(race.done) and epoch < self.s.race_epochs
                and epoch >= self.s.warmup_epochs)

    def start_epoch(self, model, epoch: int, g_lr: Optional[float], hold_views: bool) -> None:
        super().start_epoch(model, epoch, g_lr, hold_views)
        self.epoch = epoch
        self.smoothed = self.learning and self.s.grad == "smoothed"
        self.flips = self.exploring_flips(model, epoch)
        # H > 1: all of G's hypotheses are rendered; C classifies each as a shape of its own (S = H:
        # race_mode=separate) or all H x M views of a shape pooled as one (S = 1: pooled)
        self.H = model.hypotheses.hypotheses if self.racing(model, epoch) else 1
        self.S = self.H if self.H == 1 or self.s.race_mode == "separate" else 1
        self.race_steps, self.race_losses, self.race_lines, self.race_end = 0, None, [], None

    def decide_race(self, model, epoch: int, final: bool) -> None:
        """The hypothesis of lowest mean G loss so far becomes the active one; the race ends when it
        leads clearly (``race_end`` "lead"), at its last epoch ("cap": the pick may be chance), or
        when ``final`` ("batches"); a line for the log."""
        active, self.race_losses, clear = model.hypotheses.decide(self.s.race_z)
        if active is not None:
            model.selector.active.fill_(active)
        last = epoch + 1 == self.s.race_epochs
        self.race_end = "batches" if final else "lead" if clear else "cap" if last else None
        if self.race_end:
            model.hypotheses.finish()
        how = {"batches": f" (after {self.race_steps} batches: kept from now on)",
               "lead": " (a clear lead: kept from now on)",
               "cap": " (the race's last epoch, no clear lead: kept from now on)", None: ""}[self.race_end]
        self.race_lines.append(f"epoch {epoch + 1}: hypotheses' mean {self.s.loss} loss "
                               f"{' / '.join(f'{x:.4f}' for x in self.race_losses)}: hypothesis {active} active{how}")

    def train_step(self, model, batch: dict, step: int, loss_fn, timer) -> Step:
        self.timer = timer
        if self.H > 1 and self.s.race_batches is not None and self.race_steps >= self.s.race_batches:
            self.decide_race(model, self.epoch, final=True)  # decided on the batches so far
            self.H = self.S = 1
        self.race_steps += self.H > 1
        H, S = self.H, self.S
        with timer.stage("selector"), torch.set_grad_enabled(not self.frozen):
            views = self.warmup_views(model, batch) if self.warm else model.select(batch, all_hypotheses=H > 1)
            if self.flips:  # some views from their antipodes (polarity.py)
                views, flip_mask = model.polarity.explore(views, self.s.flip_explore, flip_generator(self.cfg.seed, step))
        labels = batch["labels"].to(model.device).repeat_interleave(S)  # [B * S]
        seen = views
        if self.smoothed and self.s.train_jitter > 0:  # C's views off G's (G's probes stay at G's)
            seen = jittered(views, self.s.train_jitter, view_gradient.noise_generator(self.cfg.seed + 15_485_863, step))
        with timer.stage("render"), torch.set_grad_enabled(not self.smoothed):
            images = model.render(batch, *seen)  # smoothed: R is not differentiated
            if S > 1:
                images = split_images(images, S)  # [B * H, M, 3, h, w]
        with timer.stage("backbone"):
            logits, _ = model.classify(images, seen if S == 1 else split_views(seen, S))
            loss = model.mvnet.training_loss(logits, labels, loss_fn)
        if self.flips:
            model.polarity.record(self.per_shape_loss(logits.detach(), labels), flip_mask)
        if H > 1:  # each shape's loss under each hypothesis: G's own loss (hypotheses.py)
            with timer.stage("selector"):
                model.hypotheses.record(hypothesis_losses(model, logits, images, labels, H, S, self.selector_loss))
        objective = loss
        if self.smoothed and step % self.s.probe_every == 0 and (H == 1 or self.s.race_probes):
            # G's gradient from the loss at perturbed views
            # (view_gradient.py), charged to G; on the other steps G gets no gradient and AdamW leaves it
            with timer.stage("selector"):
                g = view_gradient.smoothed_view_gradient(
                    view_gradient.model_render_loss(model, batch, labels, self.selector_loss, hypotheses=S),
                    split_views(views, S) if S > 1 else views,
                    self.s.probe_pairs, self.s.probe_sigma, view_gradient.noise_generator(self.cfg.seed, step),
                    batched=self.s.probe_batched and S == 1)
                objective = loss + view_gradient.surrogate(views, *(join_views(g, S) if S > 1 else g))
        return Step(views, images, logits, labels, loss, objective)

    def end_epoch(self, model, epoch: int) -> list[str]:
        lines = []
        if self.exploring_flips(model, epoch):
            turned = model.polarity.decide()
            if turned:
                lines.append(f"epoch {epoch + 1}: view(s) {turned} turned round (their antipodes had the lower loss)")
        if self.racing(model, epoch):
            self.decide_race(model, epoch, final=False)
        return lines + self.race_lines

    def history(self, model) -> dict:
        out = {}
        if model.polarity is not None:
            out["views_flipped"] = model.polarity.flipped.tolist()
        if model.hypotheses is not None:
            out.update(hypothesis_active=int(model.selector.active), hypothesis_losses=getattr(self, "race_losses", None),
                       race_end=getattr(self, "race_end", None))
        return out
