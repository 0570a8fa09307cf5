"""renderer.memory_budget_mb: shapes rendered in groups and candidates searched in chunks that fit
the budget, with the same images and gradients as one pass; a budget that cannot hold one shape
or one tile is refused in one line naming the smallest that can."""
from __future__ import annotations

import pytest
import torch

from mvtn_exp.data.shapes import Meshes, PointClouds, subset
from mvtn_exp.render import budget
from mvtn_exp.render.renderer import MultiViewRenderer


def _meshes(n=4):
    import trimesh

    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=24, minor_sections=12)
    v = torch.tensor(t.vertices, dtype=torch.float32)
    f = torch.tensor(t.faces)
    # shapes of different sizes (so group offsets into the packed tensors matter)
    parts = [(v * (1 - 0.1 * k), f) if k % 2 == 0 else (v[:200] * 0.9, f[(f < 200).all(1)]) for k in range(n)]
    return Meshes.from_list([p[0] for p in parts], [p[1] for p in parts])


def _points(n=4):
    g = torch.Generator().manual_seed(1)
    return PointClouds.from_list([torch.randn(150 + 40 * k, 3, generator=g) * 0.4 for k in range(n)])


def _views(n=4, m=3):
    g = torch.Generator().manual_seed(2)
    return torch.rand(n, m, generator=g) * 360, torch.rand(n, m, generator=g) * 160 - 80


MODES = {"hard": dict(mode="hard", shading="smooth"), "soft": dict(mode="soft", shading="smooth", sigma=3e-4),
         "points": dict(points_per_pixel=4, point_radius=0.05)}


def _run(settings, shapes, azim, elev, train=False):
    torch.manual_seed(5)
    r = MultiViewRenderer(image_size=48, **settings).train(train)
    a, e = azim.clone().requires_grad_(True), elev.clone().requires_grad_(True)
    out = r(shapes, a, e, 2.2)
    (out.images * torch.linspace(0, 1, 48)).sum().add(out.alpha.sum()).backward()
    return out, a.grad, e.grad


def _smallest_budget(settings, shapes, azim, elev) -> float:
    """The smallest budget the renderer accepts for this batch (read from its refusal)."""
    with pytest.raises(budget.BudgetTooSmall) as err:
        MultiViewRenderer(image_size=48, memory_budget_mb=1e-3, **settings)(shapes, azim, elev)
    return float(str(err.value).split(">= ")[1].split(" ")[0])


@pytest.mark.parametrize("mode", list(MODES))
def test_groups_render_what_one_pass_renders(mode):
    shapes = _points() if mode == "points" else _meshes()
    azim, elev = _views()
    one, ga, ge = _run(MODES[mode], shapes, azim, elev, train=True)
    small = _smallest_budget(MODES[mode], shapes, azim, elev)  # about one shape per group
    many, ga2, ge2 = _run({**MODES[mode], "memory_budget_mb": small}, shapes, azim, elev, train=True)
    assert one.stats["groups"] == 1 and not one.stats["recomputed"] and many.stats["groups"] >= 2
    if mode == "soft":  # float rounding of the per-pixel sums may differ between chunkings
        assert torch.allclose(many.images, one.images, atol=1e-5) and torch.allclose(many.alpha, one.alpha, atol=1e-5)
        assert torch.allclose(ga2, ga, rtol=1e-4, atol=1e-4) and torch.allclose(ge2, ge, rtol=1e-4, atol=1e-4)
    else:
        assert torch.equal(many.images, one.images) and torch.equal(many.alpha, one.alpha)
        assert torch.equal(ga2, ga) and torch.equal(ge2, ge)
    assert int(many.stats["active_pixels"]) == int(one.stats["active_pixels"])


@pytest.mark.parametrize("mode", list(MODES))
def test_recomputed_groups_give_the_gradients_of_kept_ones(mode, monkeypatch):
    """When what the backward pass keeps of every group would not fit, each group's differentiable
    part runs again in the backward pass: the same images and camera gradients."""
    shapes = _points() if mode == "points" else _meshes()
    azim, elev = _views()
    one, ga, ge = _run(MODES[mode], shapes, azim, elev, train=True)
    # what the backward pass keeps of the batch, 2.8 GB, over half the 2 GiB share of 4 GiB: recompute
    monkeypatch.setitem(budget.SAVED_BYTES, mode, 10 ** 5)
    again, ga2, ge2 = _run({**MODES[mode], "memory_budget_mb": 4096}, shapes, azim, elev, train=True)
    assert again.stats["recomputed"] and again.stats["groups"] >= 1
    assert torch.equal(again.images, one.images) and torch.equal(again.alpha, one.alpha)
    assert torch.allclose(ga2, ga, rtol=1e-5, atol=1e-6) and torch.allclose(ge2, ge, rtol=1e-5, atol=1e-6)
    # vertex gradients reach the vertices through the recomputed part as well
    if mode != "points":
        v = shapes.verts.clone().requires_grad_(True)
        r = MultiViewRenderer(image_size=48, memory_budget_mb=4096, **MODES[mode])
        r(shapes.with_verts(v), azim, elev).images.sum().backward()
        assert v.grad is not None and v.grad.abs().sum() > 0


def test_random_lights_and_colours_are_drawn_once_per_call():
    """Training draws a light and a colour per shape: the same ones whatever the grouping."""
    shapes = _meshes()
    azim, elev = _views()
    settings = dict(mode="hard", shading="flat", train_light="random", train_color="random")
    one, _, _ = _run(settings, shapes, azim, elev, train=True)
    many, _, _ = _run({**settings, "memory_budget_mb": _smallest_budget(settings, shapes, azim, elev)}, shapes,
                      azim, elev, train=True)
    assert many.stats["groups"] >= 2 and torch.equal(many.images, one.images)
    torch.manual_seed(5)
    MultiViewRenderer(image_size=48, **settings).train()(shapes, azim, elev)
    after_one = torch.rand(3)
    torch.manual_seed(5)
    MultiViewRenderer(image_size=48, memory_budget_mb=_smallest_budget(settings, shapes, azim, elev),
                      **settings).train()(shapes, azim, elev)
    assert torch.equal(torch.rand(3), after_one)


def test_subset_takes_whole_shapes():
    m = _meshes()
    part = subset(m, 1, 3)
    assert part.verts_per_shape.tolist() == m.verts_per_shape[1:3].tolist()
    assert int(part.faces.min()) == 0 and int(part.faces.max()) == len(part.verts) - 1
    nv = m.verts_per_shape.tolist()
    assert torch.equal(part.verts, m.verts[nv[0]:nv[0] + nv[1] + nv[2]])


def test_a_budget_too_small_for_one_shape_or_one_tile_names_the_smallest_that_works():
    shapes = _meshes(2)
    azim, elev = _views(2)
    r = MultiViewRenderer(image_size=48, mode="hard", memory_budget_mb=0.05)
    with pytest.raises(budget.BudgetTooSmall) as err:
        r(shapes, azim, elev)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("renderer.memory_budget_mb=0.05:")
    need = float(msg.split(">= ")[1].split(" ")[0])
    r2 = MultiViewRenderer(image_size=48, mode="hard", memory_budget_mb=need)
    r2(shapes, azim, elev)  # renders: the named budget holds one shape, and its chunk holds its tiles



def test_a_tile_over_an_explicit_budgets_chunk_is_refused(monkeypatch):
    """Never silently grown: with an explicit budget, one tile whose candidates exceed the chunk
    stops the render in one line naming the budget that would hold it (CPU without a budget: the
    chunk is max_candidates, and such a tile is processed alone)."""
    shapes = _meshes(2)
    azim, elev = _views(2)
    plan = budget.plan("soft", shapes.faces_per_shape, 3, 48, 1 << 21, None, torch.device("cpu"))
    assert plan.groups == [(0, 2)] and not plan.strict and plan.max_candidates == 1 << 21
    monkeypatch.setitem(budget.CANDIDATE_BYTES, "soft", 10 ** 5)  # a chunk of a few candidates
    r = MultiViewRenderer(image_size=48, mode="soft", shading="flat", tile_size=48, memory_budget_mb=20)
    with pytest.raises(budget.BudgetTooSmall, match=r"one screen tile holds \d+ candidate pairs.*>= \d+") as err:
        r(shapes, azim, elev)
    assert "\n" not in str(err.value)
    with pytest.warns(RuntimeWarning, match="processed alone"):
        import mvtn_exp.render.tiles as tiles

        monkeypatch.setattr(tiles, "_warned_tile_budget", False)
        MultiViewRenderer(image_size=48, mode="soft", shading="flat", tile_size=48, max_candidates=50)(shapes, azim, elev)


def test_budget_setting_is_validated_and_cuda_takes_a_share_of_free_memory(monkeypatch):
    with pytest.raises(ValueError, match="renderer.memory_budget_mb must be > 0"):
        MultiViewRenderer(memory_budget_mb=0)
    assert budget.budget_mb(None, torch.device("cpu")) is None and budget.budget_mb(512, torch.device("cpu")) == 512.0
    monkeypatch.setattr(budget, "available_mb", lambda device: 80_000.0)
    assert budget.budget_mb(None, torch.device("cuda")) == budget.CUDA_SHARE * 80_000.0
    p = budget.plan("hard", torch.tensor([20_000] * 32), 12, 224, 1 << 21, None, torch.device("cuda"))
    assert p.groups == [(0, 32)] and p.max_candidates > (1 << 21) and not p.strict
    p = budget.plan("soft", torch.tensor([20_000] * 32), 12, 224, 1 << 21, 6144, torch.device("cpu"))
    assert len(p.groups) > 1 and p.strict and p.recompute and all(b > a for a, b in p.groups) and p.groups[-1][1] == 32
    p = budget.plan("hard", torch.tensor([20_000] * 32), 12, 224, 1 << 21, 2048, torch.device("cpu"))
    assert p.groups[-1][1] == 32 and p.max_candidates <= (1 << 24)
