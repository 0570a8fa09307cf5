"""Classification: the loss, and evaluation (overall accuracy, mean per-class accuracy, confusion matrix)."""
from __future__ import annotations

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from .config import TaskConfig


def loss_fn(cfg: TaskConfig, reduction: str = "mean"):
    """``(logits [B, K], labels [B]) -> scalar`` cross-entropy (with ``label_smoothing``);
    ``reduction="none"``: the ``[B]`` per-shape losses."""
    return nn.CrossEntropyLoss(label_smoothing=cfg.label_smoothing, reduction=reduction)


def centered_logit_loss(logits: Tensor, labels: Tensor) -> Tensor:
    """``[B, K], [B] -> [B]``: ``mean_c z_c - z_y``, minus the true class's logit above the mean.

    Cross-entropy is this plus ``logsumexp z - mean z``, a term that does not depend on the label:
    it is smallest where the logits are flat. While C is at chance that term is all the loss can
    change, so a G trained on cross-entropy is drawn to views where C's output is most uniform
    (on ``synthetic_views``: the cup's axis from either side, measured). This loss keeps only the
    label's part: if the logits do not depend on the label, its expectation is 0 for every view."""
    return logits.mean(1) - logits.gather(1, labels[:, None]).squeeze(1)


def selector_loss_fn(name: str, cfg: TaskConfig):
    """G's per-shape loss ``(logits [B, K], labels [B]) -> [B]`` for ``selector.loss=name``:
    ``task`` (C's own loss, the paper's) or ``centered_logit`` (``centered_logit_loss``)."""
    if name == "task":
        return loss_fn(cfg, reduction="none")
    if name == "centered_logit":
        return centered_logit_loss
    raise ValueError(f"selector.loss={name!r}: expected task or centered_logit")


def summarize(confusion: Tensor) -> dict:
    """``confusion [K, K]`` (rows: true, columns: predicted) -> acc, mean per-class acc (over the
    classes present), per-class acc (None for an absent class) and n."""
    conf = confusion.long()
    total = int(conf.sum())
    support = conf.sum(1)
    per_class = conf.diag().double() / support.clamp(min=1).double()
    present = support > 0
    return {"acc": float(conf.diag().sum()) / max(total, 1),
            "mean_class_acc": float(per_class[present].mean()) if bool(present.any()) else 0.0,
            "per_class_acc": [float(a) if bool(p) else None for a, p in zip(per_class, present)],
            "n": total}


@torch.no_grad()
def evaluate(model, loader, num_classes: int, desc: str = "eval", progress: bool = True, transform=None) -> dict:
    """Eval mode (renderer: camera light, white object): loss, ``summarize`` metrics, the confusion
    matrix as nested lists, the predicted views ``azim`` / ``elev`` / ``dist`` ``[N, M]`` (degrees,
    world units; CPU), the ``labels [N]`` and predicted classes ``pred [N]`` in the same order.
    ``transform(batch) -> batch`` (e.g. a rotation or a crop) is applied to every batch first, so
    the selector and the renderer both see the transformed shapes."""
    model.eval()
    conf = torch.zeros(num_classes, num_classes, dtype=torch.long)
    loss_sum, azim, elev, dist, seen, preds = 0.0, [], [], [], [], []
    first_images = None
    for batch in tqdm(loader, desc=desc, leave=False, disable=None if progress else True):
        if transform is not None:
            batch = transform(batch)
        labels = batch["labels"].to(model.device)
        out = model(batch)
        loss_sum += float(nn.functional.cross_entropy(out["logits"], labels, reduction="sum"))
        pred = out["logits"].argmax(1).cpu()
        conf.index_put_((batch["labels"], pred), torch.ones_like(pred), accumulate=True)
        seen.append(batch["labels"])
        preds.append(pred)
        azim.append(out["azim"].cpu())
        elev.append(out["elev"].cpu())
        dist.append(torch.as_tensor(out["dist"]).expand_as(out["azim"]).cpu())
        if first_images is None:
            first_images = out["images"].cpu()
    result = summarize(conf)
    result.update(loss=loss_sum / max(result["n"], 1), confusion=conf.tolist(),
                  azim=torch.cat(azim) if azim else torch.zeros(0), elev=torch.cat(elev) if elev else torch.zeros(0),
                  dist=torch.cat(dist) if dist else torch.zeros(0),
                  labels=torch.cat(seen) if seen else torch.zeros(0, dtype=torch.long),
                  pred=torch.cat(preds) if preds else torch.zeros(0, dtype=torch.long),
                  images=first_images)
    return result


class Classification:
    """The classification head (``tasks/heads.py``): C's logits ``[B, K]`` against the shapes'
    class labels ``[B]``, scored by accuracy."""

    score = "acc"  # what model selection maximises on the validation split

    def __init__(self, cfg: TaskConfig, dataset) -> None:
        self.cfg = cfg
        self.names = list(dataset.classes)
        self.num_outputs = len(self.names)
        self.loss = loss_fn(cfg)

    def targets(self, model, batch: dict, views) -> Tensor:
        """The batch's class labels ``[B]`` (``views`` unused)."""
        return batch["labels"].to(model.device)

    def __call__(self, logits: Tensor, labels: Tensor) -> Tensor:
        return self.loss(logits, labels)

    def hits(self, logits: Tensor, labels: Tensor) -> float:
        """The share of shapes whose argmax is their class."""
        return float((logits.detach().argmax(1) == labels).float().mean()) if len(labels) else 0.0

    def evaluate(self, model, loader, desc: str = "eval", progress: bool = True, transform=None) -> dict:
        return evaluate(model, loader, self.num_outputs, desc=desc, progress=progress, transform=transform)

    GATHERED = ("confusion", "loss", "n", "azim", "elev", "dist", "labels", "pred")

    def merge(self, parts: list[dict]) -> dict:
        """The result over shards (``GATHERED`` of each, in order), as ``evaluate`` gives it (the
        first shard's images)."""
        conf = sum(torch.tensor(p["confusion"]) for p in parts)
        out = summarize(conf)
        out.update(loss=sum(p["loss"] * p["n"] for p in parts) / max(out["n"], 1), confusion=conf.tolist(),
                   **{k: torch.cat([p[k] for p in parts]) for k in ("azim", "elev", "dist", "labels", "pred")},
                   images=parts[0].get("images"))
        return out

    def headline(self, res: dict) -> dict:
        return {}

    def metrics(self, res: dict) -> dict:
        return {}

    def summary_line(self, res: dict, best: float, best_epoch: int) -> str:
        """The run's last line: the test result of ``best.pt``, chosen at 1-based ``best_epoch``."""
        return (f"test accuracy {res['acc']:.4f} (mean per-class {res['mean_class_acc']:.4f}, best val {best:.4f} at "
                f"epoch {best_epoch})")
