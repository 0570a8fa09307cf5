"""What the selector learned: view statistics, camera figures, and the class-averaged-views test.

Conventions (as ``render/cameras.py``): world Y-up, angles in degrees, the camera of view
(a, e, d) sits at ``d * (cos e sin a, sin e, cos e cos a)`` and looks at the origin.

* Azimuth is displayed wrapped to [-180, 180).
* Elevation is displayed in [-90, 90]. A value beyond the pole is *folded*: the camera at
  elevation e > 90 and azimuth a is at the same position as the camera at elevation 180 - e and
  azimuth a + 180 (e < -90: elevation -180 - e, azimuth a + 180). Its image is rotated by 180
  degrees (the analytic up vector flips), but its position is what the histograms count.
* Class-mean views average azimuth circularly (mean of unit vectors, then atan2; result in
  [-180, 180]) and elevation arithmetically, on the raw values the renderer used (no folding: the
  averaged views are rendered again, and a raw elevation beyond 90 is a different image from its
  folded twin). A class without samples gets NaN rows; if a class's azimuths cancel exactly (e.g.
  0 and 180) their circular mean is undefined and atan2 returns 0.

``view_analysis`` is the evaluation mode: per-instance accuracy vs the accuracy when every shape
is rendered from the mean views of its true class (the paper's test that learned views are
per-instance, not just per-class).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from .images import view_grid
from .plots import pyplot, save_figure


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def wrap_azimuth(azim) -> np.ndarray:
    """Degrees -> [-180, 180)."""
    a = _np(azim)
    return (a + 180.0) % 360.0 - 180.0


def fold_views(azim, elev) -> tuple[np.ndarray, np.ndarray]:
    """Camera positions as (azimuth in [-180, 180), elevation in [-90, 90]) for any (azim, elev):
    elevation is first wrapped to [-180, 180); e > 90 becomes (180 - e, a + 180) and e < -90
    becomes (-180 - e, a + 180) -- the same camera position."""
    a, e = _np(azim), _np(elev)
    e = (e + 180.0) % 360.0 - 180.0
    over = e > 90.0
    under = e < -90.0
    e = np.where(over, 180.0 - e, np.where(under, -180.0 - e, e))
    a = np.where(over | under, a + 180.0, a)
    return wrap_azimuth(a), e


def view_histograms_png(azim, elev, labels, classes: Sequence[str], path, bins: int = 36) -> Path:
    """Per-class histograms of the predicted views -> ``path`` (PNG).

    ``azim``, ``elev``: ``[N, M]`` degrees (all M views of a shape are pooled); ``labels [N]``.
    One row per class, columns: azimuth (wrapped to [-180, 180)) and elevation in [-90, 90] (values
    beyond the poles folded, see ``fold_views``). A class without samples gets empty axes."""
    a, e = fold_views(azim, elev)
    lab = _np(labels).astype(np.int64).reshape(-1)
    if a.ndim == 1:
        a, e = a[:, None], e[:, None]
    if a.shape != e.shape or a.shape[0] != lab.shape[0]:
        raise ValueError(f"view_histograms_png: azim {a.shape}, elev {e.shape} and labels {lab.shape} disagree")
    k = len(classes)
    plt = pyplot()
    fig, axes = plt.subplots(k, 2, figsize=(6.0, max(1.6, 1.1 * k + 0.6)), dpi=100, squeeze=False)
    a_bins = np.linspace(-180.0, 180.0, bins + 1)
    e_bins = np.linspace(-90.0, 90.0, bins // 2 + 1)
    for c in range(k):
        sel = lab == c
        ax_a, ax_e = axes[c]
        ax_a.hist(a[sel].ravel(), bins=a_bins, color="tab:blue")
        ax_e.hist(e[sel].ravel(), bins=e_bins, color="tab:orange")
        ax_a.set_xlim(-180, 180)
        ax_e.set_xlim(-90, 90)
        ax_a.set_ylabel(f"{classes[c]} ({int(sel.sum())})", fontsize=7)
        for ax in (ax_a, ax_e):
            ax.tick_params(labelsize=6)
            if c < k - 1:
                ax.set_xticklabels([])
    axes[0, 0].set_title("azimuth (deg)", fontsize=8)
    axes[0, 1].set_title("elevation (deg, folded)", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def detail_angles_png(angles, path, cone=(60.0, 66.0), title: str = "") -> Path:
    """Histogram of ``angles [N, M]`` (degrees between each view and its shape's cup axis,
    ``SyntheticViews.detail_angles``) -> ``path`` (PNG): all views, and each shape's nearest view;
    the band ``cone`` marks the visibility cone's half-angle (the dataset's alpha range)."""
    ang = _np(angles).astype(np.float64)
    ang = ang[:, None] if ang.ndim == 1 else ang
    if ang.ndim != 2 or ang.shape[0] == 0:
        raise ValueError(f"detail_angles_png: expected angles [N, M] with N >= 1, got {ang.shape}")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.0, 2.6), dpi=100)
    bins = np.linspace(0.0, 180.0, 37)
    ax.hist(ang.ravel(), bins=bins, color="tab:blue", alpha=0.6, label=f"all {ang.shape[1]} views")
    ax.hist(ang.min(1), bins=bins, color="tab:orange", alpha=0.6, label="nearest view per shape")
    ax.axvspan(*cone, color="0.7", alpha=0.5, label="visibility cone edge")
    ax.set_xlim(0, 180)
    ax.set_xlabel("angle between view and cup axis (deg)", fontsize=8)
    ax.set_ylabel("views", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7)
    ax.set_title(title or f"{ang.shape[0]} shapes: median nearest {np.median(ang.min(1)):.0f} deg", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def camera_positions(azim, elev, dist) -> np.ndarray:
    """``[M]`` views -> ``[M, 3]`` world positions ``dist * (cos e sin a, sin e, cos e cos a)``."""
    a, e, d = np.radians(_np(azim)), np.radians(_np(elev)), _np(dist)
    return np.stack([d * np.cos(e) * np.sin(a), d * np.sin(e), d * np.cos(e) * np.cos(a)], axis=-1)


def cameras_png(points, azim, elev, dist, images, path, title: str = "") -> Path:
    """One shape and its M cameras -> ``path`` (PNG).

    Top: 3D scatter of ``points [P, 3]`` with the camera positions of ``azim / elev / dist [M]``
    and a line from each camera to the origin (world Y is drawn as matplotlib's vertical z axis).
    Bottom: the M rendered ``images [M, 3, H, W]`` (in [0, 1]) in one row."""
    pts = _np(points).reshape(-1, 3)
    cams = camera_positions(_np(azim).reshape(-1), _np(elev).reshape(-1), _np(dist).reshape(-1))
    imgs = images if isinstance(images, torch.Tensor) else torch.as_tensor(np.asarray(images))
    M = cams.shape[0]
    if imgs.dim() != 4 or imgs.shape[0] != M:
        raise ValueError(f"cameras_png: images {tuple(imgs.shape)} do not match {M} views")
    plt = pyplot()
    fig = plt.figure(figsize=(max(4.5, 1.3 * M), 6.0), dpi=100)
    ax = fig.add_axes([0.05, 0.3, 0.9, 0.65], projection="3d")
    # our (x, y, z) with Y up -> matplotlib (x, z, y) so that the plot's vertical axis is our y
    ax.scatter(pts[:, 0], pts[:, 2], pts[:, 1], s=1, c="gray", alpha=0.5, depthshade=False)
    colors = plt.get_cmap("tab10")
    for m in range(M):
        x, y, z = cams[m]
        ax.plot([x, 0.0], [z, 0.0], [y, 0.0], color=colors(m % 10), lw=1)
        ax.scatter([x], [z], [y], color=colors(m % 10), s=30, depthshade=False)
        ax.text(x, z, y, str(m), fontsize=7)
    r = float(max(np.abs(cams).max(initial=0.0), np.abs(pts).max(initial=0.0), 1e-6))
    ax.set_xlim(-r, r)
    ax.set_ylim(-r, r)
    ax.set_zlim(-r, r)
    ax.set_xlabel("x", fontsize=7)
    ax.set_ylabel("z", fontsize=7)
    ax.set_zlabel("y (up)", fontsize=7)
    ax.tick_params(labelsize=6)
    if title:
        ax.set_title(title, fontsize=9)
    bottom = fig.add_axes([0.02, 0.02, 0.96, 0.25])
    bottom.imshow(view_grid(imgs, cols=M))
    bottom.set_axis_off()
    return save_figure(fig, path)


def class_mean_views(azim, elev, labels, num_classes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``azim / elev [N, M]``, ``labels [N]`` -> per-class mean views ``(azim_c, elev_c)``, each
    ``[K, M]`` float32: azimuth is the circular mean (atan2 of the summed unit vectors, in
    [-180, 180]), elevation the arithmetic mean of the raw values. Rows of classes with no
    samples are NaN."""
    a, e = _np(azim), _np(elev)
    lab = _np(labels).astype(np.int64).reshape(-1)
    if a.ndim != 2 or a.shape != e.shape or a.shape[0] != lab.shape[0]:
        raise ValueError(f"class_mean_views: azim {a.shape}, elev {e.shape} and labels {lab.shape} disagree")
    if lab.size and (lab.min() < 0 or lab.max() >= num_classes):
        raise ValueError(f"class_mean_views: labels outside [0, {num_classes})")
    M = a.shape[1]
    azim_c = np.full((num_classes, M), np.nan)
    elev_c = np.full((num_classes, M), np.nan)
    rad = np.radians(a)
    for c in range(num_classes):
        sel = lab == c
        if not sel.any():
            continue
        azim_c[c] = np.degrees(np.arctan2(np.sin(rad[sel]).sum(0), np.cos(rad[sel]).sum(0)))
        elev_c[c] = e[sel].mean(0)
    return torch.from_numpy(azim_c).float(), torch.from_numpy(elev_c).float()


@torch.no_grad()
def class_averaged_evaluation(model, loader, num_classes: int, azim_c, elev_c, progress: bool = False) -> dict:
    """Accuracy when every shape is rendered from the mean views of its TRUE class.

    Per batch: views ``azim_c[labels], elev_c[labels]`` (``[K, M]``), distance from
    ``model.select(batch)`` (the selector's own per-shape distance), images ``model.render`` and
    logits ``model.mvnet(images)[0]``; eval mode, no gradient. Returns ``classification.summarize``
    of the confusion (``acc``, ``mean_class_acc``, ``per_class_acc``, ``n``). A shape whose class
    has NaN mean views raises ValueError."""
    from ..tasks.classification import summarize

    model.eval()
    azim_c = torch.as_tensor(azim_c)
    elev_c = torch.as_tensor(elev_c)
    conf = torch.zeros(num_classes, num_classes, dtype=torch.long)
    for batch in tqdm(loader, desc="class-mean views", leave=False, disable=None if progress else True):
        labels = batch["labels"].long()
        _, _, dist = model.select(batch)
        azim = azim_c[labels].to(device=dist.device, dtype=dist.dtype)
        elev = elev_c[labels].to(device=dist.device, dtype=dist.dtype)
        if azim.shape != dist.shape:
            raise ValueError(f"class_averaged_evaluation: class views {tuple(azim.shape)} vs selector {tuple(dist.shape)}")
        if bool(torch.isnan(azim).any() | torch.isnan(elev).any()):
            raise ValueError("class_averaged_evaluation: a shape's class has no mean views (NaN)")
        images = model.render(batch, azim, elev, dist)
        pred = model.mvnet_forward(images, (azim, elev, dist), batch)[0].argmax(1).cpu()
        conf.index_put_((labels, pred), torch.ones_like(pred), accumulate=True)
    return summarize(conf)


@torch.no_grad()
def view_analysis(model, loader, classes: Sequence[str], run_dir, progress: bool = False) -> tuple[dict, str]:
    """The view-analysis eval mode: per-instance vs class-averaged views.

    Runs ``classification.evaluate`` once for the per-shape views, writes
    ``run_dir/view_histograms.png`` and ``run_dir/cameras.png`` (the loader's first shape, its
    predicted views and rendered images), evaluates with the class-mean views, and returns
    ``({"view_analysis": {"acc_per_instance", "acc_class_mean_views", "class_mean_azim",
    "class_mean_elev"}}, markdown table)``; class means are nested lists ``[K][M]`` (NaN for a
    class absent from the split)."""
    from ..tasks import classification

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    k = len(classes)
    res = classification.evaluate(model, loader, k, desc="views (per instance)", progress=progress)
    labels = res["labels"]
    view_histograms_png(res["azim"], res["elev"], labels, list(classes), run_dir / "view_histograms.png")

    first = next(iter(loader))
    model.eval()
    out = model(first)
    name = first["names"][0] if first.get("names") else ""
    cls = classes[int(first["labels"][0])]
    cameras_png(first["points"][0], out["azim"][0], out["elev"][0], out["dist"][0], out["images"][0].cpu(),
                run_dir / "cameras.png", title=f"{name} ({cls})")

    azim_c, elev_c = class_mean_views(res["azim"], res["elev"], labels, k)
    avg = class_averaged_evaluation(model, loader, k, azim_c, elev_c, progress=progress)
    metrics = {"view_analysis": {"acc_per_instance": float(res["acc"]), "acc_class_mean_views": float(avg["acc"]),
                                 "class_mean_azim": azim_c.tolist(), "class_mean_elev": elev_c.tolist()}}
    table = ("| views | accuracy |\n|---|---|\n"
             f"| per instance (selector) | {res['acc']:.4f} |\n"
             f"| class-mean of the true class | {avg['acc']:.4f} |")
    return metrics, table
