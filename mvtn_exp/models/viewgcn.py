"""ViewGCN (Wei et al., CVPR 2020): the views as a graph over their camera positions.

``forward(images [B, M, 3, H, W], views=(azim, elev, dist) each [B, M]) -> (logits [B, K],
features [B, 3 D])``, M >= 2, D the backbone's feature size. Three levels of ``M -> S2 -> S3`` views
(``level_views``; the official counts by default: 12 -> 6 -> 4, 20 -> 10 -> 5, else M // 2 and
M // 4, at least one):

    f = backbone.features(view)                 [B, n, D]   level 1: n = M
    f = LocalGCN(f, v)                          kNN graph (k nearest views, self included) over the
                                                unit view directions v; edge weights from an MLP of
                                                (v_i, v_j, v_i - v_j, |v_i - v_j|); then Linear-BN-LeakyReLU
    pooled_l = max_n f                          [B, D]
    f = NonLocalMP(f)                           messages MLP(f_i, f_j) summed over all j, fused with f_i
    f, v = ViewSelector(f, v)                   farthest-point sampling of S2 (then S3) views; each sampled view
                                                is replaced by whichever of its k nearest views a scoring MLP
                                                rates most confidently; the scores are trained by
                                                cross-entropy against the shape's label
    ... level 2 as level 1; level 3 is LocalGCN only
    features = cat(pooled_1, pooled_2, pooled_3); logits = MLP(features)

The edge weights depend on the view positions, so in MVTN the camera parameters that G predicts
get a gradient through C's graph as well as through the renderer.

Training in two stages (``mvnet.stages=[S1, S2]``, the paper's schedule): in stage 1 (``stage``
buffer = 1) every view is classified on its own by ``single_view_head`` (logits: their mean) and
the loss is the cross-entropy of every view; in stage 2 the graph trains on top. The buffer
travels with the checkpoint, so a checkpoint is evaluated in the stage it was saved in.

Differences from the official code (weixmath/view-GCN), on purpose:
- any M >= 2 (the official code hard-codes the 12 and 20 view positions) and views from any
  selector: the graph is built from the views actually rendered;
- farthest-point sampling starts, as in the official code, from a random view in training
  (``fps_start="random"``, the default); at evaluation, and always with ``fps_start="fixed"``,
  from the view furthest along a fixed generic direction (the official code takes view 0 there),
  so the output is deterministic and independent of the order of the views;
- the view selector scores each candidate view with one shared MLP ``D -> D/2 -> K`` and ranks
  them by their largest class probability, as the paper describes it; the official code feeds
  the candidates of all sampled views concatenated to one MLP whose size depends on M, and takes
  its softmax over the sampled views instead of over the classes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..config.checks import at_least, one_of
from .backbones import PathLike
from .multiview import MVCNN, MVNetConfig, register

if TYPE_CHECKING:  # pragma: no cover
    from ..config.schema import TrainConfig

_START = torch.tensor([0.5772, 0.7071, 0.4082])  # a generic direction: farthest-point sampling starts from it


def view_directions(azim: Tensor, elev: Tensor) -> Tensor:
    """Unit camera directions ``[B, M, 3]`` (Y-up) from azimuth and elevation ``[B, M]`` (degrees)."""
    a, e = torch.deg2rad(azim), torch.deg2rad(elev)
    return torch.stack((torch.cos(e) * torch.sin(a), torch.sin(e), torch.cos(e) * torch.cos(a)), -1)


def gather_views(x: Tensor, idx: Tensor) -> Tensor:
    """``x [B, N, C]`` at ``idx [B, ...]`` -> ``[B, ..., C]``."""
    b = idx.shape[0]
    flat = idx.reshape(b, -1)
    return torch.gather(x, 1, flat[..., None].expand(-1, -1, x.shape[-1])).reshape(*idx.shape, x.shape[-1])


def knn_views(v: Tensor, query: Tensor, k: int) -> Tensor:
    """Indices ``[B, S, k]`` of the k views of ``v [B, N, 3]`` nearest to each of ``query [B, S, 3]``
    (nearest first: a query that is one of the views finds itself first)."""
    d2 = (query[:, :, None] - v[:, None]).square().sum(-1)  # [B, S, N]
    return d2.topk(k, dim=-1, largest=False).indices


FPS_STARTS = ("random", "fixed")
OFFICIAL_LEVEL_VIEWS = {12: (6, 4), 20: (10, 5)}  # weixmath/view-GCN (20) and MVTN's ViewGCN (12)


def level_views(m: int, given: Optional[tuple[int, int]] = None) -> tuple[int, int]:
    """Views kept at levels 2 and 3 for M views: ``given``, else the official counts, else
    ``(M // 2, M // 4)``; each at least 1 and at most the level before."""
    s2, s3 = given if given is not None else OFFICIAL_LEVEL_VIEWS.get(m, (m // 2, m // 4))
    s2 = min(max(1, int(s2)), m)
    return s2, min(max(1, int(s3)), s2)


def farthest_views(v: Tensor, s: int, random_start: bool = False) -> Tensor:
    """``[B, N, 3] -> [B, s]`` farthest-point sampling, started from a random view (``random_start``,
    drawn from torch's global generator) or from the view furthest along ``_START``."""
    b, n, _ = v.shape
    with torch.no_grad():
        idx = torch.empty(b, s, dtype=torch.long, device=v.device)
        if random_start:
            idx[:, 0] = torch.randint(0, n, (b,)).to(v.device)
        else:
            idx[:, 0] = (v @ _START.to(v)).argmax(1)
        nearest = torch.full((b, n), float("inf"), dtype=v.dtype, device=v.device)
        for i in range(1, s):
            last = gather_views(v, idx[:, i - 1:i])  # [B, 1, 3]
            nearest = torch.minimum(nearest, (v - last).square().sum(-1))
            idx[:, i] = nearest.argmax(1)
    return idx


def _safe_norm(x: Tensor) -> Tensor:
    """``|x|`` over the last axis with a zero (not NaN) gradient at x = 0 (a view and itself)."""
    sq = x.square().sum(-1, keepdim=True)
    return torch.where(sq > 0, sq.clamp_min(1e-20).sqrt(), torch.zeros_like(sq))


class LocalGCN(nn.Module):
    """``f [B, n, D], v [B, n, 3] -> [B, n, D]``: features summed over each view's k nearest views
    with weights from their relative positions, then Linear-BatchNorm-LeakyReLU."""

    def __init__(self, dim: int, k: int) -> None:
        super().__init__()
        self.k = k
        self.edge = nn.Sequential(nn.Linear(10, 10), nn.LeakyReLU(0.2), nn.Linear(10, 10), nn.LeakyReLU(0.2),
                                  nn.Linear(10, 1))
        self.conv = nn.Sequential(nn.Linear(dim, dim), nn.BatchNorm1d(dim), nn.LeakyReLU(0.2))

    def forward(self, f: Tensor, v: Tensor) -> Tensor:
        b, n, d = f.shape
        idx = knn_views(v, v, min(self.k, n))                  # [B, n, k]
        vj = gather_views(v, idx)                              # [B, n, k, 3]
        vi = v[:, :, None].expand_as(vj)
        w = self.edge(torch.cat((vi, vj, vi - vj, _safe_norm(vi - vj)), -1))  # [B, n, k, 1]
        f = (w * gather_views(f, idx)).sum(2)                  # [B, n, D]
        return self.conv(f.reshape(b * n, d)).reshape(b, n, d)


class NonLocalMP(nn.Module):
    """``[B, n, D] -> [B, n, D]``: every view receives ``sum_j MLP(f_i, f_j)`` over all views j,
    fused with its own feature (Linear-BatchNorm-LeakyReLU on the concatenation)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.relation = nn.Sequential(nn.Linear(2 * dim, dim), nn.LeakyReLU(0.2), nn.Linear(dim, dim), nn.LeakyReLU(0.2),
                                      nn.Linear(dim, dim), nn.LeakyReLU(0.2))
        self.fusion = nn.Sequential(nn.Linear(2 * dim, dim), nn.BatchNorm1d(dim), nn.LeakyReLU(0.2))

    def forward(self, f: Tensor) -> Tensor:
        b, n, d = f.shape
        pairs = torch.cat((f[:, :, None].expand(b, n, n, d), f[:, None].expand(b, n, n, d)), -1)
        messages = self.relation(pairs).sum(2)                 # [B, n, D]
        return self.fusion(torch.cat((f, messages), -1).reshape(b * n, 2 * d)).reshape(b, n, d)


class ViewSelector(nn.Module):
    """``f [B, n, D], v [B, n, 3] -> (f [B, s, D], v [B, s, 3], scores [B, s, k, K])``: s views by
    farthest-point sampling, each replaced by its most confidently scored neighbour (of k)."""

    def __init__(self, dim: int, num_classes: int, k: int, fps_start: str = "random") -> None:
        super().__init__()
        self.k = k
        self.fps_start = fps_start
        self.score = nn.Sequential(nn.Linear(dim, dim // 2), nn.LeakyReLU(0.2), nn.Linear(dim // 2, num_classes))

    def forward(self, f: Tensor, v: Tensor, s: int) -> tuple[Tensor, Tensor, Tensor]:
        random_start = self.training and self.fps_start == "random"
        centres = gather_views(v, farthest_views(v, s, random_start))  # [B, s, 3]
        idx = knn_views(v, centres, min(self.k, v.shape[1]))   # [B, s, k]
        cand_f, cand_v = gather_views(f, idx), gather_views(v, idx)
        scores = self.score(cand_f)                            # [B, s, k, K]
        best = scores.detach().softmax(-1).amax(-1).argmax(-1)  # [B, s]
        pick = best[..., None, None]
        return (cand_f.gather(2, pick.expand(-1, -1, 1, f.shape[-1]))[:, :, 0],
                cand_v.gather(2, pick.expand(-1, -1, 1, 3))[:, :, 0], scores)


class ViewGCN(MVCNN):
    """MVCNN's shared backbone, then the view graph of the module docstring (M >= 2).

    Args (besides MVCNN's ``backbone``, ``num_classes``, ``weights``, ``dropout``):
        k: neighbours of each view in the local graph and candidates in view selection (the
            paper: 4, self included).
        pool: only ``"max"`` (the paper's pooling of each level).
        fps_start: ``"random"`` (the official code: a random first view in training) or ``"fixed"``.
        level_views: views kept at levels 2 and 3 (``None``: ``level_views(M)``, the official counts).
    """

    needs_views = True
    LEVELS = 3

    def __init__(self, backbone: Union[nn.Module, str], num_classes: int, weights: Optional[PathLike] = None,
                 pool: str = "max", dropout: float = 0.5, k: int = 4, fps_start: str = "random",
                 level_views: Optional[tuple[int, int]] = None) -> None:
        if pool != "max":
            raise ValueError(f"mvnet.pool={pool!r}: ViewGCN max-pools each level; use pool=max")
        if k < 1:
            raise ValueError(f"mvnet.k={k}: ViewGCN needs k >= 1 neighbours")
        if fps_start not in FPS_STARTS:
            raise ValueError(f"mvnet.fps_start={fps_start!r}: expected one of {', '.join(FPS_STARTS)}")
        super().__init__(backbone, num_classes, weights=weights, pool="max", dropout=dropout)
        self.level_views = tuple(level_views) if level_views is not None else None
        d = self.feature_dim
        self.local = nn.ModuleList(LocalGCN(d, k) for _ in range(self.LEVELS))
        self.nonlocal_mp = nn.ModuleList(NonLocalMP(d) for _ in range(self.LEVELS - 1))
        self.selectors = nn.ModuleList(ViewSelector(d, num_classes, k, fps_start) for _ in range(self.LEVELS - 1))
        self.single_view_head = self.head  # stage 1 (MVCNN's Linear(D, K)), one view at a time
        self.head = nn.Sequential(nn.Linear(self.LEVELS * d, 512), nn.LeakyReLU(0.2), nn.Linear(512, 512),
                                  nn.Dropout(dropout), nn.LeakyReLU(0.2), nn.Linear(512, num_classes))
        self.dropout = nn.Identity()  # the head holds the paper's dropout
        self.feature_dim = self.LEVELS * d
        self.register_buffer("stage", torch.tensor(2))
        self._aux: Optional[dict] = None  # the last training forward's extra outputs (training_loss)
        for m in (*self.local, *self.nonlocal_mp, *self.selectors, self.head):
            for layer in m.modules():
                if isinstance(layer, nn.Linear):
                    nn.init.kaiming_uniform_(layer.weight)  # as the official code

    def forward(self, images: Tensor, views=None) -> tuple[Tensor, Tensor]:
        """``[B, M, 3, H, W]`` and ``views`` ``(azim, elev, dist)`` ``[B, M]`` -> (logits, features)."""
        f = self.view_features(images)                          # [B, M, D]
        b, m = f.shape[:2]
        if int(self.stage) == 1:
            per_view = self.single_view_head(f)                 # [B, M, K]
            self._aux = {"per_view": per_view} if self.training else None
            return per_view.mean(1), f.mean(1)
        if views is None:
            raise ValueError("ViewGCN needs the views (azim, elev, dist) [B, M] of its images")
        if m < 2:
            raise ValueError(f"ViewGCN needs M >= 2 views, got {m}")
        v = view_directions(views[0], views[1]).to(f)           # [B, M, 3]
        keep = level_views(m, self.level_views)
        pooled, scores = [], []
        for level in range(self.LEVELS):
            f = self.local[level](f, v)
            pooled.append(f.amax(1))
            if level < self.LEVELS - 1:
                f, v, s = self.selectors[level](self.nonlocal_mp[level](f), v, keep[level])
                scores.append(s.reshape(b, -1, s.shape[-1]))
        features = torch.cat(pooled, 1)                         # [B, 3 D]
        self._aux = {"scores": torch.cat(scores, 1)} if self.training else None
        return self.head(features), features

    def training_loss(self, logits: Tensor, labels: Tensor, loss_fn) -> Tensor:
        """Stage 1: ``loss_fn`` over every view's own logits. Stage 2: ``loss_fn(logits, labels)``
        plus ``loss_fn`` over the view selectors' scores of every candidate (the official code's
        loss). ``loss_fn``: mean-reduced ``(logits [N, K], labels [N]) -> scalar``."""
        aux = self._aux
        key = "per_view" if int(self.stage) == 1 else "scores"
        if aux is None or key not in aux or aux[key].shape[0] != labels.shape[0]:
            raise RuntimeError("ViewGCN.training_loss: call it right after a forward in training mode on the same batch")
        extra = aux[key]                                        # [B, n, K]
        extra_loss = loss_fn(extra.reshape(-1, extra.shape[-1]), labels.repeat_interleave(extra.shape[1]))
        return extra_loss if key == "per_view" else loss_fn(logits, labels) + extra_loss


@register("viewgcn")
@dataclass
class ViewGCNConfig(MVNetConfig):
    """ViewGCN: ``k`` neighbours per view (any M >= 2; max-pooled levels). ``fps_start``: ``random``
    (the official code: farthest-point sampling from a random view in training) or ``fixed`` (always
    from one generic direction). ``level_views``: ``[S2, S3]`` views kept at levels 2 and 3 (null: the
    official counts, 12 -> 6 -> 4 and 20 -> 10 -> 5, else M // 2 and M // 4). ``stages``: ``[S1, S2]``
    trains S1 epochs on single views (G frozen on its initial views), then S2 epochs of the whole
    network; S1 + S2 = ``epochs``; the learning-rate schedule runs over each stage on its own and
    model selection counts stage 2 only (null: one stage)."""

    name: str = "viewgcn"
    dropout: float = 0.5
    any_view_set = False  # a graph over the views with its own selection levels
    k: int = 4
    fps_start: str = "random"
    level_views: Optional[list[int]] = None
    stages: Optional[list[int]] = None
    network = ViewGCN

    def validate(self) -> "ViewGCNConfig":
        super().validate()
        at_least("mvnet.k", self.k, 1)
        one_of("mvnet.fps_start", self.fps_start, FPS_STARTS)
        lv = self.level_views
        if lv is not None and (len(lv) != 2 or any(int(x) != x or x < 1 for x in lv) or lv[1] > lv[0]):
            raise ValueError(f"mvnet.level_views={list(lv)}: expected [S2, S3], whole numbers with 1 <= S3 <= S2 "
                             "(views kept at levels 2 and 3), or null for the official counts")
        if self.stages is not None and (len(self.stages) != 2 or any(int(s) != s or s < 1 for s in self.stages)):
            raise ValueError(f"mvnet.stages={list(self.stages)}: expected [S1, S2], two whole numbers of epochs >= 1 "
                             "(single views, then the whole network)")
        return self

    def check(self, cfg: "TrainConfig") -> None:
        """One-line errors naming the keys for settings ViewGCN cannot take (its graph needs M >= 2)."""
        if cfg.views < 2:
            raise ValueError(f"views={cfg.views}: mvnet=viewgcn builds a graph over the views and needs views >= 2")
        if self.level_views is not None and self.level_views[0] > cfg.views:
            raise ValueError(f"mvnet.level_views={list(self.level_views)}: level 2 cannot keep more than views={cfg.views}")
        n_warm = getattr(cfg.selector, "warmup_num_views", None)
        if n_warm is not None and n_warm < 2:
            raise ValueError(f"selector.warmup_num_views={n_warm}: mvnet=viewgcn needs at least 2 views")
        if self.stages is not None and sum(self.stages) != cfg.epochs:
            raise ValueError(f"mvnet.stages={list(self.stages)} sums to {sum(self.stages)} epochs but "
                             f"epochs={cfg.epochs}: set epochs={sum(self.stages)} or change the stages")

    def kwargs(self) -> dict:
        lv = tuple(int(x) for x in self.level_views) if self.level_views is not None else None
        return {"dropout": self.dropout, "k": self.k, "fps_start": self.fps_start, "level_views": lv}

    def stage_span(self, epoch: int, epochs: int) -> tuple[int, int]:
        """The single-view stage or the whole-network stage holding 0-based ``epoch``."""
        if self.stages is None:
            return 0, epochs
        return (0, self.stages[0]) if epoch < self.stages[0] else (self.stages[0], epochs - self.stages[0])

    def holds_views(self, epoch: int) -> bool:
        """Stage 1 trains C on G's initial views with G frozen."""
        return self.stages is not None and epoch < self.stages[0]

    def start_epoch(self, mvnet: nn.Module, epoch: int) -> Optional[str]:
        """Set the net's stage for ``epoch``; a line to log when stage 2 starts (model selection restarts)."""
        if self.stages is None:
            return None
        mvnet.stage.fill_(1 if self.holds_views(epoch) else 2)
        if epoch == self.stages[0]:
            return f"epoch {epoch + 1}: ViewGCN stage 2 (the whole network); model selection counts from here"
        return None
