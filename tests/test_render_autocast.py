"""R computes in float32 whatever autocast surrounds it: a user who wraps the whole model (or the
renderer alone) in bf16 autocast gets the float32 images, alpha and camera gradients, in hard,
soft and point modes; inputs given in bfloat16 are computed in float32 too."""
from __future__ import annotations

import pytest
import torch

from conftest import tiny_config
from mvtn_exp.data.shapes import Meshes, PointClouds
from mvtn_exp.engine.trainer import as_config
from mvtn_exp.model import build_mvtn
from mvtn_exp.render.renderer import MultiViewRenderer


def _scene():
    import trimesh

    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=24, minor_sections=12)
    v = torch.tensor(t.vertices, dtype=torch.float32)
    mesh = Meshes.from_list([v, v * 0.8], [torch.tensor(t.faces)] * 2)
    g = torch.Generator().manual_seed(0)
    points = PointClouds.from_list([torch.randn(300, 3, generator=g) * 0.4] * 2)
    azim = torch.tensor([[10.0, 100.0, 233.0], [45.0, 170.0, 300.0]])
    elev = torch.tensor([[20.0, -35.0, 80.0], [0.0, 50.0, -89.0]])
    return mesh, points, azim, elev


SETTINGS = {"hard": dict(mode="hard", shading="smooth"), "soft": dict(mode="soft", shading="smooth", sigma=3e-4),
            "points": dict(points_per_pixel=4, point_radius=0.05)}


def _render(r, shapes, azim, elev, autocast: bool):
    a, e = azim.clone().requires_grad_(True), elev.clone().requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        out = r(shapes, a, e, 2.2)
        loss = (out.images * torch.linspace(0, 1, out.images.shape[-1])).sum() + out.alpha.sum()
    loss.backward()
    return out, a.grad, e.grad


@pytest.mark.parametrize("mode", list(SETTINGS))
def test_renderer_under_bf16_autocast_gives_the_float32_images_and_gradients(mode):
    mesh, points, azim, elev = _scene()
    shapes = points if mode == "points" else mesh
    r = MultiViewRenderer(image_size=48, **SETTINGS[mode]).eval()
    ref, ga, ge = _render(r, shapes, azim, elev, autocast=False)
    out, ga2, ge2 = _render(r, shapes, azim, elev, autocast=True)
    assert out.images.dtype == out.alpha.dtype == torch.float32
    assert torch.equal(out.images, ref.images) and torch.equal(out.alpha, ref.alpha)
    assert torch.equal(ga, ga2) and torch.equal(ge, ge2) and ga.abs().sum() > 0
    # bfloat16 inputs (a G that ran under autocast) are computed in float32: within bf16's rounding
    # of the inputs, not the images' rounding through a bf16 search
    low = shapes.to(dtype=torch.bfloat16)
    with torch.no_grad():
        got = r(low, azim.bfloat16(), elev.bfloat16(), 2.2)
        want = r(low.to(dtype=torch.float32), azim.bfloat16().float(), elev.bfloat16().float(), 2.2)
    assert got.images.dtype == torch.float32 and torch.equal(got.images, want.images)


def test_the_whole_model_under_bf16_autocast_renders_the_float32_images(tmp_path):
    """The trainer's own precision=bf16 autocasts C alone; a user who wraps the whole model gets
    the same images as without autocast (C's logits then differ only by C's bf16 rounding)."""
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.engine.trainer import make_datasets

    cfg = as_config(tiny_config(str(tmp_path), views=3, image_size=48, **{"renderer.mode": "hard"}))
    batch = collate_shapes([make_datasets(cfg)["train"][i] for i in range(4)])
    torch.manual_seed(0)
    model = build_mvtn(cfg, 4).eval()
    with torch.no_grad():
        ref = model(batch)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = model(batch)
    assert torch.equal(out["azim"].float(), ref["azim"]) or (out["azim"].float() - ref["azim"]).abs().max() < 1.0
    views = [ref[k] for k in ("azim", "elev", "dist")]
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        images = model.render(batch, *views)
    assert images.dtype == torch.float32 and torch.equal(images, ref["images"])
    assert torch.isfinite(out["logits"]).all()


def test_deterministic_settings_turn_torchs_deterministic_algorithms_on_and_back_off(tmp_path):
    """renderer.deterministic: the renderer's forward runs under torch's deterministic algorithms
    (the same images; the flag is restored after); deterministic=true: the whole run, the renderer
    included, and the previous settings come back when the run ends."""
    from mvtn_exp.runtime import seeding
    from mvtn_exp.engine import train

    mesh, _, azim, elev = _scene()
    seen = []
    r = MultiViewRenderer(image_size=32, mode="soft", deterministic=True)
    real = r._render
    r._render = lambda *a: seen.append(torch.are_deterministic_algorithms_enabled()) or real(*a)
    out = r(mesh, azim, elev)
    plain = MultiViewRenderer(image_size=32, mode="soft")(mesh, azim, elev)
    assert seen == [True] and not torch.are_deterministic_algorithms_enabled()
    assert torch.equal(out.images, plain.images)
    with seeding.deterministic(True):
        assert torch.are_deterministic_algorithms_enabled() and torch.is_deterministic_algorithms_warn_only_enabled()
    assert not torch.are_deterministic_algorithms_enabled()
    metrics = train(tiny_config(str(tmp_path / "cache"), epochs=1, deterministic=True), tmp_path / "run")
    assert metrics["config"]["deterministic"] and metrics["config"]["renderer"]["deterministic"]
    assert not torch.are_deterministic_algorithms_enabled()
