import numpy as np
import pytest
import torch
import trimesh

from mvtn_exp.data import mesh_io
from mvtn_exp.data.shapes import Meshes
from mvtn_exp.render import lod
from mvtn_exp.render.renderer import MultiViewRenderer


def _sphere():
    s = trimesh.creation.icosphere(subdivisions=5)
    return np.asarray(s.vertices), np.asarray(s.faces)


def test_simplify_reaches_budget_and_is_cached():
    v, f = _sphere()
    res = lod.simplify(v, f, 2000)
    assert res.faces_in == len(f) and res.faces_out <= 2200
    assert res.faces.max() < len(res.verts) and np.isfinite(res.verts).all()
    assert lod.simplify(v, f, 2000) is res  # cache hit
    assert lod.simplify(v, f[:1000], 5000).faces_out == 1000  # under budget: untouched


def test_budget_is_a_request_on_real_meshes(real_samples):
    v, f = mesh_io.read_mesh(real_samples / "ModelNet40" / "desk" / "train" / "desk_0001.off")
    res = lod.simplify(v, f, max(16, len(f) // 10))
    # may not reach the budget (open, non-manifold mesh) but never corrupts or loses the shape
    assert 0 < res.faces_out <= len(f)
    assert res.faces.max() < len(res.verts) and np.isfinite(res.verts).all()


def test_lod_render_is_close_and_refuses_vertex_gradients():
    v, f = _sphere()
    m = Meshes.from_list([torch.tensor(v, dtype=torch.float32)], [torch.tensor(f)])
    a, e = torch.tensor([[10.0, 120.0]]), torch.tensor([[20.0, -40.0]])
    full = MultiViewRenderer(image_size=64, shading="silhouette")(m, a, e)
    low = MultiViewRenderer(image_size=64, shading="silhouette", lod=True, lod_faces_per_pixel=0.5)
    out = low(m, a, e)
    assert out.stats["lod_faces"][1] <= 0.55 * 64 * 64 + 200 < len(f)
    p, q = full.alpha > 0.5, out.alpha > 0.5
    assert (p & q).sum() / (p | q).sum() > 0.98
    with pytest.raises(ValueError, match="lod"):
        low(m.with_verts(m.verts.clone().requires_grad_(True)), a, e)


def test_budget_follows_the_image_side_unless_faces_per_pixel_is_set():
    assert lod.face_budget(64) == 2048 and lod.face_budget(224) == 7168  # 32 faces per pixel row
    assert lod.face_budget(224, 16.0) == 3584
    assert lod.face_budget(64, 32.0, 0.5) == 2048 and lod.face_budget(224, 32.0, 0.5) == 25088  # the former rule
    assert lod.face_budget(2, 1.0) == 16  # never fewer than 16


def test_a_simplification_the_silhouettes_reject_is_retried_larger(monkeypatch):
    """IoU under lod_min_iou: the next budget up (x 2) is tried; none passing keeps the mesh."""
    v, f = _sphere()
    calls = []

    def fake_iou(va, fa, vb, fb, size):
        calls.append(len(fb))
        return 0.5 if len(calls) == 1 else 1.0

    monkeypatch.setattr(lod, "silhouette_iou", fake_iou)
    res = lod.simplify(v, f, 1000, image_size=64, min_iou=0.99)
    assert len(calls) == 2 and calls[0] <= 1100 < calls[1] <= 2200 and res.faces_out == calls[1]
    monkeypatch.setattr(lod, "silhouette_iou", lambda *a: 0.0)
    kept = lod.simplify(v, f, 999, image_size=64, min_iou=0.99)
    assert kept.faces_out == len(f) and kept.verts is v


def test_lod_keeps_a_real_tables_legs(real_samples):
    """A real ModelNet table (8,652 faces): simplified to 2,048 faces its legs go (silhouette IoU
    0.66 at 64 px); the silhouette check keeps what the image shows."""
    v, f = mesh_io.read_mesh(real_samples / "ModelNet10" / "table" / "train" / "table_0001.off")
    v = (v - (v.max(0) + v.min(0)) / 2) / np.linalg.norm(v - (v.max(0) + v.min(0)) / 2, axis=1).max()
    m = Meshes.from_list([torch.tensor(v, dtype=torch.float32)], [torch.tensor(f, dtype=torch.long)])
    a, e = torch.tensor([[0.0, 90.0, 45.0]]), torch.tensor([[0.0, 30.0, -20.0]])
    full = MultiViewRenderer(image_size=64, mode="hard", shading="silhouette")(m, a, e).alpha > 0.5
    unchecked = lod.simplify(v, f, lod.face_budget(64), 64, min_iou=0.0)
    assert unchecked.faces_out <= 2100  # the budget alone would be reached
    out = MultiViewRenderer(image_size=64, mode="hard", shading="silhouette", lod=True)(m, a, e)
    low = out.alpha > 0.5
    assert float((full & low).sum() / (full | low).sum()) >= 0.99
    bare = Meshes.from_list([torch.tensor(unchecked.verts, dtype=torch.float32)], [torch.tensor(unchecked.faces)])
    cut = MultiViewRenderer(image_size=64, mode="hard", shading="silhouette")(bare, a, e).alpha > 0.5
    assert float((full & cut).sum() / (full | cut).sum()) < 0.9  # what the check prevents


def test_the_lod_study_reports_what_lod_keeps():
    """``scripts/studies/lod_check.py`` on a small sphere: a row per size, the budget of the
    renderer's rule, a silhouette IoU that meets the check, and the Markdown table."""
    from studies import study

    lc = study("lod_check")
    v, f = _sphere()
    table = lc.rows({"sphere": lc.unit_mesh(v, f)}, [16, 32], 0.99, views=2)
    assert [r["size"] for r in table] == [16, 32] and [r["budget"] for r in table] == [512, 1024]
    assert all(r["kept"] <= r["faces"] == len(f) for r in table) and all(r["iou"] >= 0.95 for r in table)
    assert "| sphere | 20480 | 32 | 1024 |" in lc.to_markdown(table, 0.99)


def test_the_lod_accuracy_study_evaluates_one_checkpoint_per_budget(tmp_path):
    """``scripts/studies/lod_accuracy.py`` on a one-epoch tiny run: one row per setting, the same
    weights (without LOD the study's accuracy is the run's own test accuracy)."""
    from conftest import tiny_config as tiny
    from mvtn_exp.engine import train
    from studies import study

    m = train(tiny(str(tmp_path / "cache"), epochs=1, **{"renderer.mode": "hard"}), tmp_path / "run")
    la = study("lod_accuracy")
    table = la.rows(tmp_path / "run" / "best.pt", "test", (None, {"lod_faces_per_pixel": 0.01, "lod_min_iou": 0.0}))
    assert [r["lod"] for r in table] == ["false", "true"] and table[1]["budget"] == 16
    assert abs(table[0]["acc"] - m["test_acc"]) < 1e-9 and table[0]["n"] == m["test_size"]
    assert "| true | 0.01 per pixel, unchecked | 16 |" in la.to_markdown(table)


def test_simplify_meshes_cache_hit_skips_the_host_and_a_moved_mesh_misses(monkeypatch):
    """A shape seen before (same vertices, faces and settings) comes from the device cache: neither
    simplified nor hashed again; moving one vertex, or the same mesh in another batch position, is
    keyed by its own content."""
    v, f = _sphere()
    lod._DEVICE_CACHE.clear()
    calls = []
    real = lod.simplify
    monkeypatch.setattr(lod, "simplify", lambda *a, **k: calls.append(1) or real(*a, **k))
    vt = torch.tensor(v, dtype=torch.float32)
    small = torch.tensor(f[:300])
    m = Meshes.from_list([vt, vt], [torch.tensor(f), small])
    first = lod.simplify_meshes(m, 2000)
    assert len(calls) == 2 and first.faces_per_shape.tolist()[1] == 300
    again = lod.simplify_meshes(Meshes.from_list([vt, vt], [torch.tensor(f), small]), 2000)
    assert len(calls) == 2  # both from the cache
    assert torch.equal(first.verts, again.verts) and torch.equal(first.faces, again.faces)
    moved = vt.clone()
    moved[5, 0] += 1e-3
    lod.simplify_meshes(Meshes.from_list([moved], [torch.tensor(f)]), 2000)
    assert len(calls) == 3
    keys = lod.fingerprints(Meshes.from_list([vt, moved, vt], [torch.tensor(f)] * 3))
    assert keys[0] == keys[2] != keys[1]
    # the same vertices with another face order (a different mesh): another key
    assert lod.fingerprints(Meshes.from_list([vt], [torch.tensor(f[::-1].copy())]))[0] != keys[0]
