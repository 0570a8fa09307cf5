"""The assembled MVTN: selector G (points -> views), renderer R (shape, views -> images), multi-view net C."""
from __future__ import annotations

from torch import nn

from .data.shapes import PointClouds
from .models.multiview import build_multiview
from .render.config import RendererConfig
from .render.renderer import MultiViewRenderer
from .selectors import build_selector

SHAPES = ("mesh", "points")


class MVTN(nn.Module):
    """``forward(batch) -> dict(logits [B, K], features [B, D], azim/elev/dist [B, M], images [B, M, 3, H, W])``.

    ``batch`` is a ``collate_shapes`` dict: G reads ``points [B, N, 3]``; R renders ``meshes`` when
    ``shape == "mesh"`` and a ``PointClouds`` of ``points`` when ``shape == "points"``.
    """

    def __init__(self, selector: nn.Module, renderer: MultiViewRenderer, mvnet: nn.Module, shape: str = "mesh"):
        super().__init__()
        if shape not in SHAPES:
            raise ValueError(f"shape={shape!r}: expected one of {list(SHAPES)}")
        self.selector, self.renderer, self.mvnet, self.shape = selector, renderer, mvnet, shape

    def forward(self, batch: dict) -> dict:
        device = next(self.mvnet.parameters()).device
        points = batch["points"].to(device)
        azim, elev, dist = self.selector(points)
        if self.shape == "points":
            shapes = PointClouds.from_padded(points)
        else:
            if batch.get("meshes") is None:
                raise ValueError("MVTN(shape='mesh'): the batch carries no meshes")
            shapes = batch["meshes"].to(device)
        images = self.renderer(shapes, azim, elev, dist).images
        logits, features = self.mvnet(images)
        return {"logits": logits, "features": features, "azim": azim, "elev": elev, "dist": dist, "images": images}

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """``{"mvnet": C's parameters, "selector": G's parameters}`` (G's list is empty for fixed layouts)."""
        return {"mvnet": [p for p in self.mvnet.parameters() if p.requires_grad],
                "selector": [p for p in self.selector.parameters() if p.requires_grad]}


def build_mvtn(*, views: int, selector: str, backbone: str, num_classes: int, renderer: RendererConfig,
               shape: str = "mesh", mvnet: str = "mvcnn") -> MVTN:
    """Build G, R and C from names (see ``selectors.SELECTORS``, ``models.backbones``)."""
    return MVTN(build_selector(selector, views), MultiViewRenderer(renderer),
                build_multiview(mvnet, backbone, num_classes), shape=shape)
