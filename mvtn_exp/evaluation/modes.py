"""The ``mvtn-eval`` modes beyond plain classification: rotation and occlusion robustness, retrieval.

Each takes the rebuilt model, the dataset config and the run folder, and returns a metrics dict
plus a Markdown table; PNG figures are written into the run folder.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import ConcatDataset
from tqdm.auto import tqdm

from ..data.datasets import build_dataset
from ..data.datasets import retrieval_report as dataset_retrieval_report
from ..config.schema import TrainConfig
from ..config.eval_schema import EvalConfig
from ..tasks import classification, retrieval, robustness
from ..viz.plots import occlusion_png
from ..engine.trainer import eval_loader


def _std(values: list[float]) -> float:
    return float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


def rotation(model, loader, num_classes: int, ecfg: EvalConfig) -> tuple[dict, str]:
    """Accuracy under random rotations about Y in [-theta, theta], ``repeats`` seeds per theta."""
    rows, out = [], {}
    for theta in ecfg.rotation.thetas:
        accs = []
        for rep in range(ecfg.rotation.repeats):
            gen = torch.Generator().manual_seed(ecfg.rotation.seed + rep)

            def turn(batch, gen=gen, theta=theta):
                angles = robustness.sample_angles(len(batch["labels"]), theta, gen)
                return robustness.rotate_batch(batch, angles)

            res = classification.evaluate(model, loader, num_classes, desc=f"rotation {theta:g} #{rep + 1}",
                                          progress=ecfg.progress, transform=turn)
            accs.append(res["acc"])
        out[f"{theta:g}"] = {"mean_acc": float(np.mean(accs)), "std_acc": _std(accs), "accs": accs}
        rows.append(f"| {theta:g} | {len(accs)} | {np.mean(accs):.4f} ± {_std(accs):.4f} |")
    table = "| theta (deg) | repeats | accuracy (mean ± std) |\n|---|---|---|\n" + "\n".join(rows)
    return {"rotation": out}, table


def occlusion(model, loader, num_classes: int, ecfg: EvalConfig, run_dir: Path) -> tuple[dict, str]:
    """Accuracy with each shape cut at ``ratio`` from each of the six directions, in the frame
    ``occlusion.frame`` (``unit_sphere``: the paper's; ``extent``: each shape's own extent), and
    how many shapes the floor rule kept from becoming empty."""
    out, rows = {}, []
    dirs = robustness.DIRECTIONS
    for ratio in ecfg.occlusion.ratios:
        per_dir, floored = {}, {}
        for d in dirs:
            gen = torch.Generator().manual_seed(ecfg.occlusion.seed)
            count = {"floored": 0}

            def crop(batch, gen=gen, d=d, ratio=ratio, count=count):
                cut = robustness.crop_batch(batch, d, ratio, gen, frame=ecfg.occlusion.frame)
                count["floored"] += int(cut["occlusion_floored"].sum())
                return cut

            per_dir[d] = classification.evaluate(model, loader, num_classes, desc=f"occlusion {ratio:g} {d}",
                                                 progress=ecfg.progress, transform=crop)["acc"]
            floored[d] = count["floored"]
        mean = float(np.mean(list(per_dir.values())))
        out[f"{ratio:g}"] = {"per_direction": per_dir, "mean_acc": mean, "floored_shapes": floored}
        rows.append(f"| {ratio:g} | " + " | ".join(f"{per_dir[d]:.4f}" for d in dirs) + f" | {mean:.4f} | "
                    f"{sum(floored.values())} |")
    table = (f"frame: {ecfg.occlusion.frame}\n\n| ratio | " + " | ".join(dirs) + " | mean | shapes floored (all directions) |\n|---|"
             + "---|" * (len(dirs) + 2) + "\n" + "\n".join(rows))
    occlusion_png(out, dirs, run_dir / "occlusion.png")
    return {"occlusion": out, "occlusion_frame": ecfg.occlusion.frame}, table


@torch.no_grad()
def features(model, loader, progress: bool, desc: str) -> tuple[np.ndarray, np.ndarray]:
    """Shape features (the layer before the classifier) ``[N, D]`` and labels ``[N]``."""
    model.eval()
    feats, labels = [], []
    for batch in tqdm(loader, desc=desc, leave=False, disable=None if progress else True):
        feats.append(model(batch)["features"].float().cpu())
        labels.append(batch["labels"])
    return torch.cat(feats).numpy().astype(np.float64), torch.cat(labels).numpy()


def retrieval_database(cfg: TrainConfig, progress: bool = True):
    """The retrieval database: the whole official train split. Where the val split was carved out
    of it (the dataset's ``val_from_train``: ModelNet40 gives 9,843 shapes, not the 90% left for
    training), it is train + val again; elsewhere (synthetic, ShapeNet) the train split."""
    train = build_dataset(cfg.dataset, "train", progress=progress)
    if not getattr(train, "val_from_train", False):
        return train
    val = build_dataset(cfg.dataset, "val", progress=progress)
    whole = ConcatDataset([train, val])
    whole.classes = train.classes
    return whole


def retrieval_eval(model, cfg: TrainConfig, ecfg: EvalConfig, dataset, run_dir: Path) -> tuple[dict, str]:
    """Every ``split`` shape queries the whole official train split (``retrieval_database``) in the
    LFDA space fitted on it."""
    database = retrieval_database(cfg, ecfg.progress)
    db_x, db_y = features(model, eval_loader(cfg, database), ecfg.progress, "database (train)")
    q_x, q_y = features(model, eval_loader(cfg, dataset), ecfg.progress, f"queries ({ecfg.split})")
    t0 = time.perf_counter()
    proj = retrieval.LFDA(dim=ecfg.retrieval.dim, k=ecfg.retrieval.k, scaling=ecfg.retrieval.scaling).fit(db_x, db_y)
    db_z, q_z = proj.transform(db_x), proj.transform(q_x)
    result = {}
    table_rows = []
    for name, (qa, da) in {"raw": (q_x, db_x), "lfda": (q_z, db_z)}.items():
        m_ap, _ = retrieval.mean_average_precision(qa, q_y, da, db_y)
        result[f"map_{name}"] = float(m_ap)
        table_rows.append(f"| {name} | {qa.shape[1]} | {m_ap:.4f} |")
    curves = {name: retrieval.pr_curve(qa, q_y, da, db_y) for name, (qa, da) in
              {"raw features": (q_x, db_x), "LFDA": (q_z, db_z)}.items()}
    retrieval.pr_curve_png(curves, run_dir / "precision_recall.png")
    result.update(dataset_retrieval_report(dataset, q_z, q_y, ecfg.retrieval.list_length))  # ShapeNet: SHREC'17
    result["lfda_seconds"] = time.perf_counter() - t0
    result["queries"], result["database"] = int(len(q_y)), int(len(db_y))
    table = "| space | dim | mAP |\n|---|---|---|\n" + "\n".join(table_rows)
    return {"retrieval": result}, table
