"""The soft search's row-level hidden test and the opt-in compiled renderer (``renderer.compile=true``).

The row test (``soft_search.RowMin``, ``_unhidden_rows``) must drop only candidates the
per-candidate hidden test drops anyway: the search's result is compared with the filter off.
The compiled renderer must give the eager images and camera gradients to float rounding, and must
really compile (dynamo's frame counter), or say in one line why it cannot.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from mvtn_exp.data.shapes import Meshes
from mvtn_exp.render import accel, mesh_raster, soft_search, tiles
from mvtn_exp.render.renderer import MultiViewRenderer


def _torus(sections: int = 24) -> Meshes:
    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=sections, minor_sections=sections)
    return Meshes.from_list([torch.tensor(np.asarray(t.vertices), dtype=torch.float32)],
                            [torch.tensor(np.asarray(t.faces), dtype=torch.long)])


VIEWS = (torch.tensor([[20.0, 200.0, 90.0]]), torch.tensor([[35.0, -60.0, 5.0]]))


@pytest.mark.parametrize("W,longest", [(1, None), (7, None), (16, None), (37, None), (37, 5), (64, 9)])
def test_row_min_is_the_minimum_over_each_range(W, longest):
    g = torch.Generator().manual_seed(W)
    H, images = 3, 2
    values = torch.randn(images * H * W, generator=g, dtype=torch.float64)
    values[::5] = float("-inf")
    rm = soft_search.RowMin(values, H, W, longest)
    rows = torch.randint(0, images * H, (400,), generator=g)
    j0 = torch.randint(-2, W + 1, (400,), generator=g)
    j1 = torch.randint(-2, W + 2, (400,), generator=g)
    if longest is not None:  # callers clip their ranges to at most ``longest`` columns
        j1 = torch.minimum(j1, j0.clamp(min=0) + longest - 1)
    got = rm.query(rows, j0, j1)
    assert got.dtype == values.dtype
    grid = values.view(-1, W)
    for r, a, b, v in zip(rows.tolist(), j0.tolist(), j1.tolist(), got.tolist()):
        a, b = max(a, 0), min(b, W - 1)
        want = float(grid[r, a:b + 1].min()) if b >= a else float("inf")
        assert v == want, (r, a, b)


def test_the_row_test_drops_only_hidden_candidates(monkeypatch):
    # a torus seen at an angle: its far side is hidden behind the near side in most rows
    meshes = _torus(32)
    r = MultiViewRenderer(image_size=48, mode="soft", faces_per_pixel=4, sigma=1e-3)
    enumerated = []
    real_rows = tiles._enumerate_rows

    def counting(*args):
        out = real_rows(*args)
        enumerated.append(len(out.prim))
        return out

    monkeypatch.setattr(tiles, "_enumerate_rows", counting)

    def search():
        enumerated.clear()
        with torch.no_grad():
            out = r(meshes, *VIEWS, 2.2)
        return out, sum(enumerated)

    with_rows, n_with = search()
    monkeypatch.setattr(soft_search, "_unhidden_rows", lambda span, *a: span)
    without, n_without = search()
    assert torch.equal(with_rows.images, without.images) and torch.equal(with_rows.alpha, without.alpha)
    assert n_with < 0.9 * n_without, (n_with, n_without)  # the test is not idle on this scene


def test_hidden_rows_are_emptied_and_visible_ones_kept():
    # one image row of 8 columns: hidden_below 5 everywhere but column 6 (-inf: a rim pixel)
    H, W = 1, 8
    hidden_below = torch.full((W,), 5.0)
    hidden_below[6] = float("-inf")
    faces = soft_search._Faces(fv=torch.arange(3), image=torch.zeros(3, dtype=torch.long), cols=None, table=None,
                               planes=None, zl_max=torch.tensor([4.0, 6.0, 4.0]))

    def span(p, yy):  # face 0: columns 0-3, face 1: 0-3, face 2: 4-7
        return torch.tensor([0, 0, 4]), torch.tensor([3, 3, 7])

    boxes = tiles.PixelBoxes(faces.image, torch.zeros(3, dtype=torch.long), torch.full((3,), W - 1), None, None)
    rows = soft_search._unhidden_rows(span, faces, boxes, soft_search.RowMin(hidden_below, H, W), H)
    j0, j1 = rows(torch.arange(3), torch.zeros(3))
    # face 0 is behind everywhere in its columns: emptied; face 1 is in front; face 2 reaches the rim
    assert (j1 < j0).tolist() == [True, False, False]


def _render_both(shading: str):
    meshes = _torus(24)
    out = {}
    for comp in (False, True):
        r = MultiViewRenderer(image_size=40, mode="soft", shading=shading, faces_per_pixel=4, sigma=5e-4, compile=comp)
        azim, elev = (v.clone().requires_grad_(True) for v in VIEWS)
        o = r(meshes, azim, elev, 2.2)
        (o.images * torch.linspace(0, 1, o.images.numel()).view_as(o.images)).sum().backward()
        out[comp] = (o.images.detach(), o.alpha.detach(), azim.grad, elev.grad)
    return out


@pytest.mark.skipif(accel.unavailable("cpu") is not None, reason=str(accel.unavailable("cpu")))
@pytest.mark.parametrize("shading", [pytest.param("smooth", marks=pytest.mark.slow), "flat"])  # (smooth: a minute to compile)
def test_compiled_renderer_matches_eager(shading):
    import torch._dynamo

    torch._dynamo.utils.counters.clear()
    out = _render_both(shading)
    assert sum(torch._dynamo.utils.counters["frames"].values()) > 0, "renderer.compile=true compiled nothing"
    eager, comp = out[False], out[True]
    assert eager[1].max() > 0.5 and ((eager[1] > 0.01) & (eager[1] < 0.99)).sum() > 50  # real soft edges
    assert (eager[0] - comp[0]).abs().max() <= 1e-5
    assert (eager[1] - comp[1]).abs().max() <= 1e-5
    for ge, gc in zip(eager[2:], comp[2:]):
        assert ge.abs().max() > 0
        torch.testing.assert_close(gc, ge, rtol=1e-3, atol=1e-3 * float(ge.abs().max()))


def test_compile_off_runs_nothing_compiled():
    import torch._dynamo

    torch._dynamo.utils.counters.clear()
    MultiViewRenderer(image_size=24, mode="soft", faces_per_pixel=2, sigma=1e-3)(_torus(12), *VIEWS, 2.2)
    assert sum(torch._dynamo.utils.counters["frames"].values()) == 0


def test_compile_without_a_compiler_is_refused_in_one_line(monkeypatch):
    from mvtn_exp.cli.train import validate_for_training
    from mvtn_exp.engine.trainer import as_config

    cfg = as_config({"renderer": {"compile": True}})  # a stored config is not checked against the machine
    monkeypatch.setattr(accel.shutil, "which", lambda name: None)
    assert "C++ compiler" in accel.unavailable("cpu")
    with pytest.raises(ValueError, match=r"renderer.compile=true needs a C\+\+ compiler"):
        validate_for_training(cfg)
    monkeypatch.undo()
    monkeypatch.setattr(accel.sysconfig if hasattr(accel, "sysconfig") else __import__("sysconfig"), "get_paths",
                        lambda: {"include": "/nonexistent-include"})
    assert "Python.h" in accel.unavailable("cpu")
    assert mesh_raster.barycentrics.eager is not None  # the eager definition stays reachable


def test_a_failing_compile_is_one_log_line_then_eager(monkeypatch, caplog):
    import torch._dynamo.exc as dynamo_exc

    def broken(fn, **kw):
        def call(*a, **k):
            raise dynamo_exc.BackendCompilerFailed(lambda: None, RuntimeError("InvalidCxxCompiler: no working compiler"), None)
        return call

    @accel.fused
    def double(x):
        return 2 * x

    monkeypatch.setattr(torch, "compile", broken)
    monkeypatch.setattr(accel, "_FAILED", [])
    assert torch.equal(double(torch.ones(2)), torch.full((2,), 2.0))  # eager outside compiled(True)
    with accel.compiled(True), caplog.at_level("WARNING"):
        assert torch.equal(double(torch.ones(2)), torch.full((2,), 2.0))  # failed to compile: eager
        assert torch.equal(double(torch.ones(3)), torch.full((3,), 2.0))  # and eager from then on, said once
        assert not accel.enabled()
    lines = [r.getMessage() for r in caplog.records if "torch.compile failed" in r.getMessage()]
    assert len(lines) == 1 and "InvalidCxxCompiler" in lines[0] and "eagerly" in lines[0] and "\n" not in lines[0]
    assert "InvalidCxxCompiler" in accel.failure()


@pytest.mark.slow  # two fresh processes, the first compiling from an empty cache (about a minute)
@pytest.mark.skipif(accel.unavailable("cpu") is not None, reason=str(accel.unavailable("cpu")))
def test_compile_time_study_separates_the_compile_from_the_render():
    from studies import study

    compile_time = study("compile_time")
    row = compile_time.in_fresh_process("warm", "flat", sections=8, size=24, views=2)
    assert row["shading"] == "flat" and row["faces"] == 128 and row["cache"] == "warm"
    # the first call traces and compiles (or loads its compile cache): far dearer than a render
    assert row["first_s"] > 5 * row["second_s"] > 0
    assert "| warm | flat | 128 |" in compile_time.to_markdown([row])


def test_compile_null_compiles_only_where_it_was_measured_faster(monkeypatch):
    """``renderer.compile=null`` (the default): compiled for soft renders of at least
    ``accel.AUTO_MIN_SIZE`` px with autograd recording on a CPU that can compile; eager for hard
    and point renders, small images, renders without autograd (``mvtn-render``, evaluation) and
    on CUDA; true and false are what they say."""
    import contextlib

    from mvtn_exp.render import renderer as renderer_mod

    asked = []

    @contextlib.contextmanager
    def record(on):
        asked.append(bool(on))
        yield

    monkeypatch.setattr(renderer_mod.accel, "compiled", record)
    monkeypatch.setattr(accel, "_unavailable_cached", lambda device_type: None)
    from conftest import icosphere

    mesh = icosphere(1)
    a, e = torch.tensor([[30.0]], requires_grad=True), torch.tensor([[10.0]])
    big, small = accel.AUTO_MIN_SIZE, accel.AUTO_MIN_SIZE // 2

    def compiles(grad=True, **kw):
        asked.clear()
        with torch.set_grad_enabled(grad):
            MultiViewRenderer(**kw)(mesh, a, e)
        return asked[0]

    assert compiles(image_size=big, mode="soft", shading="silhouette")
    assert not compiles(grad=False, image_size=big, mode="soft", shading="silhouette")
    assert not compiles(image_size=small, mode="soft", shading="silhouette")
    assert not compiles(image_size=big, mode="hard", shading="silhouette")
    assert not compiles(image_size=big, mode="soft", shading="silhouette", compile=False)
    assert compiles(image_size=small, mode="hard", shading="silhouette", compile=True)
    assert not accel.auto_compiles("cuda", True, big)
    monkeypatch.setattr(accel, "_unavailable_cached", lambda device_type: "no C++ compiler")
    assert not compiles(image_size=big, mode="soft", shading="silhouette")  # cannot compile here: eager, no error
