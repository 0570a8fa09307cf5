"""Part segmentation: the head's targets and loss, and evaluation by instance and class mIoU.

C predicts, for every pixel of every view, one of the dataset's parts or the background (the
last of its ``num_parts + 1`` outputs). The training targets are the views' label images: each
pixel shows a primitive (``MVTN.primitive_index``: a point of a cloud, a face of a mesh) and takes
its part, the background its own class. ``loss=pixels`` (the paper's) is the cross-entropy over
every pixel; ``loss=points`` that of the logits lifted to the points the views saw (``lifting``).

Evaluation lifts C's logits to the points (``task.fuse``), gives each unseen point its nearest
seen point's scores, predicts among the shape's category's parts (``part_metrics.restrict``) and
scores the benchmark's way (``part_metrics``). The result has the classification keys over
points (``acc``: point accuracy, ``mean_class_acc``: mean per-part accuracy, the part confusion),
``n`` shapes, and ``instance_miou``, ``class_miou``, ``per_category``, ``coverage``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor
from torch.nn import functional as F
from tqdm.auto import tqdm

from . import lifting, part_metrics
from .classification import summarize
from .config import TaskConfig

MASKED = -1e4  # an output the shape's category rules out (condition=category)


@dataclass
class Targets:
    """What the loss of a batch compares with: ``pixels [B, M, H, W]`` (part per pixel, the
    background class where no primitive shows), ``index [B, M, H, W]`` (the primitive per pixel,
    -1 background), ``points [B, P]`` (part per point), ``prim_of_point [B, P]`` (a mesh point's
    face; None for clouds), ``num_prims`` and ``categories [B]``. ``len``: the shapes."""

    pixels: Tensor
    index: Tensor
    points: Tensor
    prim_of_point: Optional[Tensor]
    num_prims: int
    categories: Tensor  # [B] the shapes' category indices

    def __len__(self) -> int:
        return len(self.pixels)


def primitives(model, batch: dict) -> tuple[Tensor, Optional[Tensor], int]:
    """``(labels of the primitives [B, N], each point's primitive [B, P] or None, N)``: a cloud's
    primitives are its points, a mesh's its faces (``face_parts``, ``point_faces``)."""
    device = model.device
    points = batch["part_labels"].to(device)
    if model.shape == "points":
        return points, None, points.shape[1]
    counts = batch["meshes"].faces_per_shape
    faces = lifting.per_shape(batch["face_parts"], counts).to(device)
    return faces, batch["point_faces"].to(device), faces.shape[1]


class Segmentation:
    """The segmentation head of a dataset with part labels (``part_names``, ``parts_of``)."""

    score = "instance_miou"  # what model selection maximises on the validation split

    def __init__(self, cfg: TaskConfig, dataset) -> None:
        if not hasattr(dataset, "parts_of"):
            raise ValueError(f"task=segmentation: the dataset {type(dataset).__name__} has no part labels")
        self.cfg = cfg
        self.parts_of = {int(c): list(p) for c, p in dataset.parts_of.items()}
        self.names = list(dataset.part_names)
        self.classes = list(dataset.classes)
        self.background = len(self.names)  # C's last output
        self.num_outputs = len(self.names) + 1
        allowed = torch.zeros(len(self.classes), self.num_outputs, dtype=torch.bool)
        for c, parts in self.parts_of.items():
            allowed[c, parts + [self.background]] = True
        self.allowed = allowed  # [categories, outputs]: each category's parts and the background

    def conditioned(self, logits: Tensor, categories: Tensor) -> Tensor:
        """``logits [B, M, K, H, W]`` with ``condition=category``: every output outside the shape's
        category's parts and the background set to ``MASKED`` (finite: softmax gives it 0)."""
        if self.cfg.condition != "category":
            return logits
        keep = self.allowed.to(logits.device)[categories.to(logits.device)]  # [B, K]
        return logits.masked_fill(~keep[:, None, :, None, None], MASKED)

    def targets(self, model, batch: dict, views) -> Targets:
        """The label images of ``views`` (each ``[B, M]``, as R renders them); no gradient."""
        prim_labels, prim_of_point, n = primitives(model, batch)
        index = model.primitive_index(batch, *views)
        pixels = lifting.pixel_labels(index, prim_labels)
        pixels = pixels.masked_fill(pixels < 0, self.background)
        return Targets(pixels, index, batch["part_labels"].to(model.device), prim_of_point, n,
                       batch["labels"].to(model.device))

    def __call__(self, logits: Tensor, targets: Targets) -> Tensor:
        """C's loss: ``logits [B, M, K, H, W]`` against ``targets`` (``task.loss``, ``task.condition``)."""
        logits = self.conditioned(logits, targets.categories)
        if self.cfg.loss == "pixels":
            return F.cross_entropy(logits.flatten(0, 1), targets.pixels.flatten(0, 1),
                                   weight=self.class_weights(targets.pixels, logits.shape[2]))
        scores, seen = lifting.lift(logits, targets.index, targets.num_prims, targets.prim_of_point, fuse="mean")
        if not bool(seen.any()):
            return logits.sum() * 0.0
        return F.cross_entropy(scores[seen], targets.points[seen],
                               weight=self.class_weights(targets.points[seen], scores.shape[-1]))

    def class_weights(self, labels: Tensor, classes: int) -> Optional[Tensor]:
        """``task.balance``: None (every target alike) or ``[classes]`` weights, 1 / sqrt of each
        class's count in ``labels`` (a class absent from them: weight 1, unused by the loss)."""
        if self.cfg.balance == "none":
            return None
        counts = torch.bincount(labels.flatten(), minlength=classes)[:classes]
        return counts.clamp_min(1).float().rsqrt()

    def hits(self, logits: Tensor, targets: Targets) -> float:
        """The share of the part pixels (not the background) whose argmax is their part."""
        on = targets.pixels != self.background
        right = (self.conditioned(logits.detach(), targets.categories).argmax(2) == targets.pixels) & on
        return float(right.sum()) / max(int(on.sum()), 1)

    def predict(self, logits: Tensor, targets: Targets, batch: dict) -> tuple[Tensor, Tensor]:
        """Per point: the predicted part among the category's ``[B, P]`` and whether a view saw it."""
        logits = self.conditioned(logits.float(), targets.categories)
        scores, seen = lifting.lift(logits, targets.index, targets.num_prims, targets.prim_of_point,
                                    fuse=self.cfg.fuse)
        scores = lifting.fill_unseen(batch["points"].to(scores.device).float(), scores, seen)
        return part_metrics.restrict(scores, batch["labels"], self.parts_of), seen

    @torch.no_grad()
    def evaluate(self, model, loader, desc: str = "eval", progress: bool = True, transform=None) -> dict:
        """Eval mode over ``loader``: see the module docstring; ``loss`` is C's mean loss per
        shape; ``pictures``: the first shape's views, label views and lifted points (``pictures``)."""
        model.eval()
        raw = {k: [] for k in ("shape_iou", "shape_coverage", "azim", "elev", "dist", "labels")}
        raw.update(confusion=torch.zeros(len(self.names), len(self.names), dtype=torch.long), loss_sum=0.0, pictures=None)
        for batch in tqdm(loader, desc=desc, leave=False, disable=None if progress else True):
            batch = transform(batch) if transform is not None else batch
            out = model(batch)
            self.add(raw, model, batch, out)
        raw.update({k: torch.cat(raw[k]) if raw[k] else torch.zeros(0) for k in
                    ("shape_coverage", "azim", "elev", "dist", "labels")},
                   shape_iou=torch.tensor(raw["shape_iou"], dtype=torch.float64))
        return self.merge([raw])

    def add(self, raw: dict, model, batch: dict, out: dict) -> None:
        """One evaluated batch into ``raw`` (``model(batch)`` gave ``out``)."""
        targets = self.targets(model, batch, out["render_views"])
        raw["loss_sum"] += float(self(out["logits"], targets)) * len(targets)
        pred, seen = self.predict(out["logits"], targets, batch)
        true, k = targets.points, len(self.names)
        raw["confusion"] += torch.bincount((true * k + pred).reshape(-1).cpu(), minlength=k * k).view(k, k)
        raw["shape_iou"] += [part_metrics.shape_iou(p, t, self.parts_of[int(c)])
                             for p, t, c in zip(pred, true, batch["labels"])]
        raw["shape_coverage"].append(lifting.coverage(seen).cpu())
        for key in ("azim", "elev", "dist"):
            raw[key].append(torch.as_tensor(out[key]).expand_as(out["azim"]).cpu())
        raw["labels"].append(batch["labels"])
        if raw["pictures"] is None:
            raw["pictures"] = self.pictures(out, targets, pred, batch)

    def pictures(self, out: dict, targets: Targets, pred: Tensor, batch: dict) -> dict:
        """The first shapes' views ``images [B, M, 3, H, W]``, the first shape's predicted and true
        label images ``[M, H, W]`` (part id, -1 background) and its points with the predicted parts."""
        label = lambda x: x.masked_fill(x == self.background, -1).cpu()  # noqa: E731
        shown = self.conditioned(out["logits"][:1], targets.categories[:1])[0].argmax(1)
        return {"images": out["images"].cpu(), "pred_views": label(shown),
                "true_views": label(targets.pixels[0]), "points": batch["points"][0].cpu(),
                "point_parts": pred[0].cpu(), "num_parts": len(self.names)}

    GATHERED = ("shape_iou", "shape_coverage", "azim", "elev", "dist", "labels", "confusion", "loss_sum")

    def merge(self, parts: list[dict]) -> dict:
        """The result over shards (``GATHERED`` of each, in order; the first's pictures): the
        module docstring's keys."""
        cat = {k: torch.cat([torch.as_tensor(p[k]) for p in parts]) for k in
               ("shape_iou", "shape_coverage", "azim", "elev", "dist", "labels")}
        conf = sum(torch.as_tensor(p["confusion"]) for p in parts)
        n, cats = len(cat["labels"]), cat["labels"].long()
        per = {self.classes[c]: {"miou": float(cat["shape_iou"][cats == c].mean()), "shapes": int((cats == c).sum())}
               for c in sorted(set(cats.tolist()))}
        out = summarize(conf)
        pictures = parts[0].get("pictures") or {}
        out.update(cat, n=n, points=out["n"], confusion=conf.tolist(),
                   loss=sum(p["loss_sum"] for p in parts) / max(n, 1),
                   instance_miou=float(cat["shape_iou"].mean()) if n else 0.0,
                   class_miou=sum(v["miou"] for v in per.values()) / max(len(per), 1), per_category=per,
                   coverage=float(cat["shape_coverage"].mean()) if n else 0.0,
                   images=pictures.get("images"), pictures={k: v for k, v in pictures.items() if k != "images"} or None)
        return out

    def headline(self, res: dict) -> dict:
        """The numbers an epoch's line and TensorBoard show beside the accuracy."""
        return {"instance_mIoU": res["instance_miou"], "coverage": res["coverage"]}

    def metrics(self, res: dict) -> dict:
        """``metrics.json``'s entries of the test result beyond the classification keys."""
        return {"test_instance_miou": res["instance_miou"], "test_class_miou": res["class_miou"],
                "test_per_category_miou": res["per_category"], "test_coverage": res["coverage"],
                "test_points": res["points"], "part_names": self.names}

    def summary_line(self, res: dict, best: float, best_epoch: int) -> str:
        """The run's last line: the test result of ``best.pt``, chosen at 1-based ``best_epoch``."""
        return (f"test instance mIoU {res['instance_miou']:.4f} (class mIoU {res['class_miou']:.4f}, point accuracy "
                f"{res['acc']:.4f}, coverage {res['coverage']:.3f}, best val instance mIoU {best:.4f} at epoch "
                f"{best_epoch})")

