"""The assembled MVTN: selector G (points -> views), renderer R (shape, views -> images), multi-view net C."""
from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from .data.shapes import PointClouds
from .models import pretrained
from .models.precision import autocast
from .render.renderer import MultiViewRenderer
from .config.schema import TrainConfig
from .data.config import SHAPES
from .selectors.canonical import CanonicalPose, world_views


class MVTN(nn.Module):
    """``forward(batch) -> dict(logits [B, K], features [B, D], azim/elev/dist [B, M], images [B, M, 3, H, W])``.

    ``batch`` is a ``collate_shapes`` dict: G reads ``points [B, N, 3]``; R renders ``meshes`` when
    ``shape == "mesh"`` and a ``PointClouds`` of ``points`` when ``shape == "points"``. ``extra``: the
    per-shape modules of G's training (``SelectorConfig.modules``: named as given, their buffers in
    checkpoints under those names); one with ``transforms_views`` also maps G's views at every
    ``select`` (the view polarity turns views round for good).
    """

    def __init__(self, selector: nn.Module, renderer: MultiViewRenderer, mvnet: nn.Module, shape: str = "mesh",
                 selector_points: Optional[int] = None, canonical: Optional[CanonicalPose] = None, **extra: nn.Module):
        super().__init__()
        self.canonical = canonical  # each shape turned into its principal frame first (selectors/canonical.py)
        for name, module in extra.items():
            self.add_module(name, module)
        self.view_transforms = tuple(name for name, module in extra.items() if getattr(module, "transforms_views", False))
        self.selector_points = selector_points  # a learned G reads the first n points (None: all)
        if shape not in SHAPES:
            raise ValueError(f"shape={shape!r}: expected one of {list(SHAPES)}")
        self.selector, self.renderer, self.mvnet, self.shape = selector, renderer, mvnet, shape
        self.selector_frozen = False  # view transfer: G's weights and statistics fixed (selectors/view_transfer.py)
        self.precision = "fp32"  # C's autocast (engine/precision.py); G and R always run in float32

    def train(self, mode: bool = True) -> "MVTN":
        super().train(mode)
        if self.selector_frozen:
            self.selector.eval()
        return self

    def forward(self, batch: dict) -> dict:
        """The views returned are world directions; with ``canonical`` G and R work in each
        shape's principal frame, and the views are turned back for the record (``render_views``:
        the views as R rendered them, ``(azim, elev, dist)`` each ``[B, M]``)."""
        views = self.select(batch)
        images = self.render(batch, *views)
        logits, features = self.classify(images, views, batch)
        world = views if self.canonical is None else world_views(views, self.canonical(batch)[1])
        return {"logits": logits, "features": features, "azim": world[0], "elev": world[1], "dist": world[2],
                "images": images, "render_views": views}

    def posed(self, batch: dict) -> dict:
        """The batch G and R see: as given, or each shape in its principal frame (``canonical``;
        idempotent, so a batch posed twice is posed once)."""
        return batch if self.canonical is None else self.canonical(batch)[0]

    def classify(self, images, views, batch: Optional[dict] = None):
        """C: ``images [B, M, 3, H, W]`` rendered from ``views`` -> ``(logits [B, K], features [B, D])``,
        under ``precision``'s autocast, returned as float32 (``batch``: see ``mvnet_forward``)."""
        with autocast(self.precision, self.device):
            logits, features = self.mvnet_forward(images, views, batch)
        return logits.float(), features.float()

    def mvnet_forward(self, images, views, batch: Optional[dict] = None):
        """C's forward: ``mvnet(images, views)``; a C that reads the shapes' points too
        (``mvnet.reads_points``: the paper's late fusion) gets the batch's points, posed as R saw them."""
        if not getattr(self.mvnet, "reads_points", False):
            return self.mvnet(images, views)
        if batch is None:
            raise ValueError(f"{type(self.mvnet).__name__} reads the shapes' points: call C with the batch")
        return self.mvnet(images, views, points=self.posed(batch)["points"].to(self.device))

    @property
    def device(self):
        return next(self.mvnet.parameters()).device

    def select(self, batch: dict, all_hypotheses: bool = False, refine: bool = True):
        """G: ``batch["points"] [B, N, 3]`` -> ``(azim, elev, dist)``, each ``[B, M]`` (degrees, world
        units); with ``all_hypotheses`` (a G holding H hypotheses) each ``[B, H * M]``; ``refine``:
        the selector's per-batch work against R and C (``ViewSelector.refine``) included, given
        the batch's labels only while training."""
        batch = self.posed(batch)
        points = batch["points"]
        n = self.selector_points
        if n is not None and getattr(self.selector, "learned", False):
            points = points[:, :n]  # the points are uniform surface samples in random order
        if all_hypotheses:
            return self.selector(points.to(self.device), all_hypotheses=True)
        if getattr(self.selector, "categories", 0):  # G conditioned on the shape's category (segmentation)
            views = self.selector(points.to(self.device), category=batch["labels"].to(self.device))
        else:
            views = self.selector(points.to(self.device))
        if refine:  # evaluation reads no labels: the selector gets the batch without them
            seen = batch if self.training else {k: v for k, v in batch.items() if k != "labels"}
            views = self.selector.refine(self, seen, views)
        for name in self.view_transforms:
            views = getattr(self, name)(views)
        return views

    def shapes(self, batch: dict):
        """What R renders of the batch, posed: its ``meshes`` (``shape == "mesh"``) or a
        ``PointClouds`` of its ``points``, on C's device."""
        batch = self.posed(batch)
        if self.shape == "points":
            return PointClouds.from_padded(batch["points"].to(self.device))
        if batch.get("meshes") is None:
            raise ValueError("MVTN(shape='mesh'): the batch carries no meshes")
        return batch["meshes"].to(self.device)

    def render_output(self, batch: dict, azim, elev, dist):
        """R: the batch's shapes seen from ``[B, M]`` views -> ``RenderOutput`` (images and coverage)."""
        return self.renderer(self.shapes(batch), azim, elev, dist)

    def primitive_index(self, batch: dict, azim, elev, dist):
        """What each pixel of R's views ``[B, M]`` shows: ``[B, M, H, W]`` long, the shape-local face
        (meshes) or point (clouds) index, -1 on the background; no gradient (``render/picking.py``)."""
        with torch.no_grad():
            return self.renderer.primitive_index(self.shapes(batch), azim.detach(), elev.detach(),
                                                 torch.as_tensor(dist).detach())

    def render(self, batch: dict, azim, elev, dist):
        """R: the batch's shapes seen from ``[B, M]`` views -> images ``[B, M, 3, H, W]``; for a C that
        reads no images (``mvnet.reads_images`` False: a point classifier) nothing is rendered and
        the images are ``[B, M, 3, 0, 0]``."""
        if not getattr(self.mvnet, "reads_images", True):
            return azim.new_zeros(*azim.shape, 3, 0, 0)
        return self.render_output(batch, azim, elev, dist).images

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """``{"mvnet": C's parameters, "selector": G's parameters}`` (G's list is empty for fixed layouts)."""
        return {"mvnet": [p for p in self.mvnet.parameters() if p.requires_grad],
                "selector": [p for p in self.selector.parameters() if p.requires_grad]}


def build_mvtn(cfg: TrainConfig, num_classes: int, pretrained_weights: bool = True, categories: int = 0) -> MVTN:
    """G, R and C as ``cfg`` (a validated ``TrainConfig``) describes them, C with ``num_classes``
    outputs (the task head's ``num_outputs``); C is ``cfg.mvnet``'s, or ``cfg.segnet``'s over every
    view under ``task=segmentation``.

    C is built first and G's initialisation draws from a forked RNG, so that at the same seed C's
    initial weights and every later random draw (order, light, colour) are the same whichever
    selector is chosen: fixed and learned views are compared on equal terms.
    pretrained_weights: load ``backbone.weights`` (``imagenet`` from torch's hub cache, downloaded
    once: ``models/pretrained.py``); False when a checkpoint's weights replace them anyway (evaluation).
    categories: the dataset's category count, for a G that reads the shape's category
    (``selector.category_input``)."""
    weights = pretrained.resolve(cfg.backbone.name, cfg.backbone.weights) if pretrained_weights else None
    if cfg.task.name == "segmentation":  # C: the 2D segmentation network over every view
        mvnet = cfg.segnet.build_c(num_classes, cfg.backbone.name, weights=weights, input_norm=cfg.backbone.input_norm)
    else:
        mvnet = cfg.mvnet.build(cfg.backbone.name, num_classes, weights=weights, input_norm=cfg.backbone.input_norm,
                                point_encoder=cfg.point_encoder)
    with torch.random.fork_rng(devices=[]):
        conditioned = {"categories": categories} if getattr(cfg.selector, "category_input", False) else {}
        selector = cfg.selector.build(cfg.views, seed=cfg.seed, point_encoder=cfg.point_encoder, **conditioned)
    model = MVTN(selector, MultiViewRenderer(cfg.renderer), mvnet, shape=cfg.dataset.shape,
                 selector_points=cfg.selector.kept_points(), **cfg.selector.modules(cfg.views),
                 canonical=CanonicalPose() if cfg.selector.canonical == "pca" else None)
    model.precision = cfg.precision
    return model
