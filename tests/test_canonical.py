"""selector.canonical=pca: the principal frame is pose-invariant, idempotent, a rotation, finite at the
extremes; a canonical model renders the same images of a shape in any pose and reports world views."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mvtn_exp.data.synthetic import random_rotation
from mvtn_exp.engine.trainer import as_config
from mvtn_exp.selectors.canonical import pca_frames, world_views

from conftest import tiny_config


def _rotations(n, seed):
    rng = np.random.default_rng(seed)
    return torch.tensor(np.stack([random_rotation("so3", rng) for _ in range(n)]))


def _skewed_cloud(n=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(n, 800, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 2.0, 0.7], dtype=torch.float64)
    p[:, :120] += torch.tensor([1.5, -1.0, 0.8], dtype=torch.float64)  # a lump: every axis has a skew
    return p


def test_the_frame_undoes_any_pose():
    p = _skewed_cloud()
    Q = _rotations(4, 1)
    turned = torch.einsum("bij,bnj->bni", Q, p)
    canon = torch.einsum("bij,bnj->bni", pca_frames(p), p)
    canon_turned = torch.einsum("bij,bnj->bni", pca_frames(turned), turned)
    torch.testing.assert_close(canon_turned, canon, atol=1e-8, rtol=0)
    R = pca_frames(turned)
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=R.dtype).expand(4, 3, 3), atol=1e-10, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(4, dtype=R.dtype))


def test_the_frame_is_idempotent_and_orders_the_axes():
    p = _skewed_cloud(seed=3)
    canon = torch.einsum("bij,bnj->bni", pca_frames(p), p)
    torch.testing.assert_close(pca_frames(canon), torch.eye(3, dtype=p.dtype).expand(4, 3, 3), atol=1e-8, rtol=0)
    var = (canon - canon.mean(1, keepdim=True)).pow(2).mean(1)  # [B, 3]: x most spread, y least
    assert (var[:, 0] > var[:, 2]).all() and (var[:, 2] > var[:, 1]).all()
    skew = (canon - canon.mean(1, keepdim=True)).pow(3).mean(1)
    assert (skew[:, :2] >= 0).all()  # the sign rule on x and y (z follows from x cross y)


@pytest.mark.parametrize("points", [torch.zeros(2, 1, 3), torch.ones(2, 50, 3), torch.tensor([[[1e-30, 0, 0], [0, 0, 0]]]),
                                    torch.randn(1, 200, 3, generator=torch.Generator().manual_seed(0)) * 1e6],
                         ids=["one point", "all equal", "tiny", "huge"])
def test_the_frame_is_a_finite_rotation_at_the_extremes(points):
    R = pca_frames(points.float())
    assert R.dtype == torch.float32 and torch.isfinite(R).all()
    torch.testing.assert_close(torch.linalg.det(R.double()), torch.ones(len(points), dtype=torch.float64), atol=1e-5, rtol=0)


def test_world_views_turn_camera_directions_back():
    R = _rotations(3, 2)
    azim = torch.tensor([[0.0, 90.0], [45.0, -120.0], [10.0, 200.0]], dtype=torch.float64)
    elev = torch.tensor([[30.0, 89.0], [-60.0, 0.0], [0.0, 10.0]], dtype=torch.float64)
    a, e, d = world_views((azim, elev, torch.full_like(azim, 2.2)), R)

    def direction(az, el):
        az, el = torch.deg2rad(az), torch.deg2rad(el)
        return torch.stack([torch.cos(el) * torch.sin(az), torch.sin(el), torch.cos(el) * torch.cos(az)], -1)

    torch.testing.assert_close(direction(a, e), torch.einsum("bji,bmj->bmi", R, direction(azim, elev)))
    torch.testing.assert_close(R @ direction(a, e).transpose(1, 2), direction(azim, elev).transpose(1, 2))
    assert torch.equal(d, torch.full_like(azim, 2.2))


def test_a_canonical_model_sees_a_shape_alike_in_any_pose(tmp_path):
    """Same images (up to rendering of the same geometry) for a shape and its turned copy; the
    reported views turn with the shape; without canonical the images differ."""
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.engine.trainer import make_datasets
    from mvtn_exp.model import build_mvtn
    from mvtn_exp.tasks.robustness import turn_batch

    images = {}
    for canonical in ("pca", "none"):
        cfg = as_config(tiny_config(str(tmp_path), **{"selector.name": "spherical", "selector.canonical": canonical,
                                                        "views": 2, "image_size": 32}))
        ds = make_datasets(cfg)["test"]
        model = build_mvtn(cfg, len(ds.classes)).eval()
        batch = collate_shapes([ds[i] for i in range(3)])
        Q = _rotations(3, 5).float()
        with torch.no_grad():
            a, b = model(batch), model(turn_batch(batch, Q))
        images[canonical] = (a["images"] - b["images"]).abs().max()
        if canonical == "pca":
            def direction(o):
                az, el = torch.deg2rad(o["azim"]), torch.deg2rad(o["elev"])
                return torch.stack([torch.cos(el) * torch.sin(az), torch.sin(el), torch.cos(el) * torch.cos(az)], -1)
            torch.testing.assert_close(direction(b), torch.einsum("bij,bmj->bmi", Q, direction(a)), atol=1e-4, rtol=0)
    assert images["pca"] < 1e-3 < images["none"]


def test_canonical_is_validated():
    with pytest.raises(ValueError, match="selector.canonical"):
        as_config(tiny_config("/tmp/x", **{"selector.name": "circular", "selector.canonical": "icp"}))
