"""mvtn_exp.viz.views: class-mean views (circular azimuth), view figures, class-averaged evaluation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mvtn_exp.viz.views import (cameras_png, class_averaged_evaluation, class_mean_views, fold_views,
                                view_analysis, view_histograms_png)

PNG = b"\x89PNG\r\n\x1a\n"


def _azim_close(a, b, tol=1e-4):
    d = (np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64) + 180.0) % 360.0 - 180.0
    return np.all(np.abs(d) < tol)


def test_class_mean_views_circular_and_per_class():
    azim = torch.tensor([[170.0, 10.0], [-170.0, 30.0],       # class 0: seam -> 180; 20
                         [90.0, -100.0], [0.0, -80.0],         # class 2: 45; -90
                         [350.0, 720.0]])                      # class 3: -10 (wrapped input); 0
    elev = torch.tensor([[10.0, 100.0], [30.0, 120.0], [-20.0, 0.0], [20.0, 0.0], [5.0, -5.0]])
    labels = torch.tensor([0, 0, 2, 2, 3])
    a, e = class_mean_views(azim, elev, labels, num_classes=4)
    assert a.shape == e.shape == (4, 2) and a.dtype == torch.float32
    assert abs(abs(float(a[0, 0])) - 180.0) < 1e-4        # not 0: the seam is averaged circularly
    assert abs(float(a[0, 1]) - 20.0) < 1e-4
    assert abs(float(a[2, 0]) - 45.0) < 1e-4 and abs(float(a[2, 1]) + 90.0) < 1e-4
    assert _azim_close(a[3], [-10.0, 0.0])
    assert torch.all(a[~torch.isnan(a)].abs() <= 180.0)
    # elevation: arithmetic mean of the raw values
    assert torch.allclose(e[0], torch.tensor([20.0, 110.0])) and torch.allclose(e[2], torch.tensor([0.0, 0.0]))
    # class 1 has no samples -> NaN rows
    assert torch.isnan(a[1]).all() and torch.isnan(e[1]).all()
    assert not torch.isnan(a[[0, 2, 3]]).any()


def test_fold_views_same_camera_position():
    a, e = fold_views(np.array([10.0, 10.0, -170.0, 200.0]), np.array([100.0, -120.0, 30.0, 270.0]))
    assert np.allclose(e, [80.0, -60.0, 30.0, -90.0]) and _azim_close(a[:3], [-170.0, -170.0, -170.0])
    assert np.all((a >= -180.0) & (a < 180.0)) and np.all(np.abs(e) <= 90.0)
    # the folded view is the same position on the sphere
    def pos(az, el):
        az, el = np.radians(az), np.radians(el)
        return np.stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)], -1)
    assert np.allclose(pos(a, e), pos(np.array([10.0, 10.0, -170.0, 200.0]), np.array([100.0, -120.0, 30.0, 270.0])),
                       atol=1e-9)


def test_pngs(tmp_path):
    g = torch.Generator().manual_seed(0)
    azim = torch.rand(10, 3, generator=g) * 720 - 360
    elev = torch.rand(10, 3, generator=g) * 260 - 130        # beyond the poles on both sides
    labels = torch.tensor([0, 0, 1, 1, 1, 0, 1, 1, 0, 0])
    p = view_histograms_png(azim, elev, labels, ["a", "b", "empty"], tmp_path / "sub" / "h.png")
    assert p.read_bytes()[:8] == PNG
    c = cameras_png(torch.rand(200, 3, generator=g) - 0.5, torch.tensor([0.0, 120.0, 240.0]),
                    torch.tensor([30.0, 100.0, -95.0]), torch.tensor([2.2, 2.0, 2.5]),
                    torch.rand(3, 3, 16, 16, generator=g), tmp_path / "c.png", title="t")
    assert c.read_bytes()[:8] == PNG
    with pytest.raises(ValueError):
        cameras_png(torch.zeros(5, 3), torch.zeros(2), torch.zeros(2), torch.ones(2), torch.zeros(3, 3, 8, 8),
                    tmp_path / "bad.png")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    torch.set_num_threads(1)
    torch.manual_seed(0)
    from mvtn_exp.data.datasets import build_dataset
    from mvtn_exp.engine.trainer import as_config, eval_loader
    from mvtn_exp.model import build_mvtn

    cfg = as_config({"views": 2, "image_size": 32, "selector": {"name": "circular"}, "batch_size": 8,
                     "dataset": {"root": str(tmp_path_factory.mktemp("cache")), "num_per_class": [2, 1, 2]},
                     "logger": {"progress": False, "tensorboard": False}})
    ds = build_dataset(cfg.dataset, "test", progress=False)
    model = build_mvtn(cfg, num_classes=len(ds.classes)).eval()
    return model, eval_loader(cfg, ds), list(ds.classes)


def test_class_averaged_equals_plain_for_fixed_views(tiny):
    from mvtn_exp.tasks.classification import evaluate

    model, loader, classes = tiny
    k = len(classes)
    res = evaluate(model, loader, k, progress=False)
    labels = torch.cat([b["labels"] for b in loader])
    azim_c, elev_c = class_mean_views(res["azim"], res["elev"], labels, k)
    # a fixed selector: every class-mean view is the selector's view
    assert _azim_close(azim_c, res["azim"][:1].expand(k, -1)) and torch.allclose(elev_c, res["elev"][:1].expand(k, -1))
    # ... so the shapes rendered from their class-mean views are the per-instance images
    batch = next(iter(loader))
    with torch.no_grad():
        out = model(batch)
        again = model.render(batch, azim_c[batch["labels"]], elev_c[batch["labels"]], out["dist"])
    assert torch.allclose(again, out["images"], atol=1e-5)
    avg = class_averaged_evaluation(model, loader, k, azim_c, elev_c)
    assert avg["n"] == res["n"] == len(labels) and avg["acc"] == res["acc"]
    # a class without mean views cannot be rendered
    azim_c[int(labels[0])] = math.nan
    with pytest.raises(ValueError):
        class_averaged_evaluation(model, loader, k, azim_c, elev_c)


def test_view_analysis(tiny, tmp_path):
    model, loader, classes = tiny
    metrics, table = view_analysis(model, loader, classes, tmp_path)
    va = metrics["view_analysis"]
    assert set(va) == {"acc_per_instance", "acc_class_mean_views", "class_mean_azim", "class_mean_elev"}
    assert va["acc_per_instance"] == va["acc_class_mean_views"]  # fixed (circular) views
    assert np.asarray(va["class_mean_azim"]).shape == (len(classes), 2)
    for name in ("view_histograms.png", "cameras.png"):
        assert (tmp_path / name).read_bytes()[:8] == PNG
    assert table.startswith("| views | accuracy |") and "class-mean" in table
