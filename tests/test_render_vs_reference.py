"""The tile kernels against the dense reference: identical ids (hard), images within 1e-5 (soft)."""
import math

import pytest
import torch

import reference
from conftest import random_triangles
from mvtn_exp.data.shapes import Meshes, PointClouds
from mvtn_exp.render import mesh_raster, point_raster, tiles
from mvtn_exp.render.renderer import MultiViewRenderer

VIEWS = (torch.tensor([[0.0, 70.0, 200.0]]), torch.tensor([[10.0, -35.0, 89.0]]))


def _search_both(r: MultiViewRenderer, meshes, dist):
    c = r.cfg
    azim, elev = VIEWS
    pf, _, _ = r.project_faces(meshes, azim, elev, dist)
    H = c.image_size
    ranking = r.soft_ranking(torch.full_like(azim, dist))
    if ranking is not None:  # no depth-window pruning: the slots must then be exactly the reference's
        ranking.depth_window = math.inf
    sel = mesh_raster.search_faces(pf, H=H, W=H, K=c.effective_k(), blur_radius=c.effective_blur(),
                                   tile_size=c.tile_size, max_candidates=c.max_candidates, ranking=ranking)
    ref = reference.dense_face_search(
        pf.xy, pf.z, pf.image, H=H, W=H, K=c.effective_k(), blur=c.effective_blur(), znear=c.znear,
        cull_backfaces=c.cull_backfaces, area_eps=mesh_raster.area_eps(pf.xy.dtype, H, H), num_images=azim.numel(),
        ranking=ranking)
    return sel, ref


def _assert_same(sel, ref):
    assert len(ref.pix) > 0
    assert torch.equal(sel.pix, ref.pix)
    assert torch.equal(sel.prim, ref.prim)
    if sel.rest_pix is not None:
        # the candidates beyond the K slots: a subset of the reference's (the search leaves out
        # faces of fully covered pixels, which cannot change coverage); the ones test_soft_edges_*
        # needs are checked there through the images
        got = set(zip(sel.rest_pix.tolist(), sel.rest_prim.tolist()))
        assert got <= set(zip(ref.rest_pix.tolist(), ref.rest_prim.tolist()))
        assert sel.most <= ref.most


@pytest.mark.parametrize("tile_size,max_candidates", [(8, 1 << 24), (8, 64), (5, 200), (32, 1)])
@pytest.mark.parametrize("cull_backfaces", [False, True])
def test_hard_ids_match_dense(tile_size, max_candidates, cull_backfaces):
    # 40 overlapping random triangles, many larger than an 8 px tile, crossing tile borders;
    # some vertices lie behind the camera at distance 2 (scale 1.6 + size 0.7 > 2)
    meshes = random_triangles(40, seed=1, scale=1.6, size=0.7)
    r = MultiViewRenderer(image_size=24, mode="hard", tile_size=tile_size, max_candidates=max_candidates, cull_backfaces=cull_backfaces)
    sel, ref = _search_both(r, meshes, 2.0)
    pf, _, _ = r.project_faces(meshes, *VIEWS, 2.0)
    assert bool((pf.z < r.cfg.znear).any(1).any()), "scene must contain faces partly behind the camera"
    _assert_same(sel, ref)


@pytest.mark.parametrize("K", [1, 5])
@pytest.mark.parametrize("tile_size,max_candidates", [(8, 1 << 24), (4, 300)])
def test_soft_k_nearest_ids_match_dense(tile_size, max_candidates, K):
    meshes = random_triangles(30, seed=2, scale=1.0, size=0.5)
    r = MultiViewRenderer(image_size=20, mode="soft", faces_per_pixel=K, sigma=2e-3, tile_size=tile_size, max_candidates=max_candidates)
    sel, ref = _search_both(r, meshes, 2.5)
    _assert_same(sel, ref)


@pytest.mark.parametrize("shading", ["flat", "smooth", "silhouette"])
def test_soft_images_match_dense(monkeypatch, shading):
    meshes = random_triangles(25, seed=3, scale=0.9, size=0.6)
    r = MultiViewRenderer(image_size=20, mode="soft", shading=shading, faces_per_pixel=4, sigma=1e-3, gamma=1e-2, tile_size=6,
                          coverage_tol=0.0)
    out = r(meshes, *VIEWS, 2.5)

    def dense(pf, *, H, W, K, blur_radius, tile_size, max_candidates, ranking, overflow=None):
        return reference.dense_face_search(pf.xy, pf.z, pf.image, H=H, W=W, K=K, blur=blur_radius, znear=r.cfg.znear,
                                           cull_backfaces=False, area_eps=mesh_raster.area_eps(pf.xy.dtype, H, W), num_images=3,
                                           ranking=ranking)

    monkeypatch.setattr(mesh_raster, "search_faces", dense)
    ref = r(meshes, *VIEWS, 2.5)
    assert ref.alpha.max() > 0.5
    assert (out.images - ref.images).abs().max() <= 1e-5
    assert (out.alpha - ref.alpha).abs().max() <= 1e-5


@pytest.mark.parametrize("max_candidates", [1 << 24, 50])
def test_point_ids_match_dense(max_candidates):
    g = torch.Generator().manual_seed(4)
    pts = (torch.rand(300, 3, generator=g, dtype=torch.float64) * 2 - 1) * 1.5
    clouds = PointClouds.from_list([pts])
    r = MultiViewRenderer(image_size=24, points_per_pixel=4, point_radius=0.15, tile_size=8, max_candidates=max_candidates)
    azim, elev = VIEWS
    cams = r._cameras(azim.double(), elev.double(), torch.full_like(azim, 2.0).double())
    xy, z, image = r._project(pts, clouds.points_per_shape, cams)
    rad = r.cfg.point_radius
    alive = (z >= r.cfg.znear) & (xy.abs() <= 1 + rad).all(-1)
    sel = point_raster.search_points(xy, z, image, alive, H=24, W=24, K=4, radius=rad, num_images=3, tile_size=8, max_candidates=max_candidates)
    ref = reference.dense_point_search(xy, z, image, H=24, W=24, K=4, radius=rad, znear=r.cfg.znear, num_images=3)
    _assert_same(sel, ref)


def test_batch_of_ragged_meshes_equals_one_by_one():
    a = random_triangles(10, seed=5)
    b = random_triangles(23, seed=6)
    both = Meshes.from_list([a.verts, b.verts], [a.faces, b.faces])
    r = MultiViewRenderer(image_size=16, mode="soft", sigma=1e-3)
    azim = torch.tensor([[0.0, 90.0], [45.0, 180.0]])
    elev = torch.tensor([[10.0, 20.0], [-30.0, 60.0]])
    out = r(both, azim, elev, 2.5).images
    for i, m in enumerate((a, b)):
        single = r(m, azim[i:i + 1], elev[i:i + 1], 2.5).images
        assert torch.allclose(out[i:i + 1], single, atol=1e-6)


def _torus(sections: int, open_half: bool):
    import numpy as np
    import trimesh

    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=sections, minor_sections=sections)
    v, f = np.asarray(t.vertices), np.asarray(t.faces)
    if open_half:  # an open mesh: its boundary is a silhouette from every direction
        f = f[v[f][:, :, 2].mean(1) >= 0]
    return Meshes.from_list([torch.tensor(v, dtype=torch.float32)], [torch.tensor(f, dtype=torch.long)])


@pytest.mark.parametrize("shading,open_half,slots", [
    ("silhouette", False, "logit"), ("flat", False, "logit"), ("smooth", False, "logit"),
    ("silhouette", True, "logit"), ("smooth", True, "logit"), ("smooth", False, "depth"),
])
def test_soft_edges_match_unlimited_k(monkeypatch, shading, open_half, slots):
    # a 32 x 32 torus (2k faces) at 48 px with a blur of about two pixels: rim pixels have more
    # faces within the blur radius than K = 3 slots. Against the dense reference that keeps every
    # face (K unlimited): coverage must not depend on K at all, and colour may miss only the
    # smallest softmax weights. PyTorch3D's choice (soft_slots=depth) fails this.
    meshes = _torus(32, open_half)
    azim, elev = torch.tensor([[20.0, 200.0]]), torch.tensor([[35.0, -60.0]])
    r = MultiViewRenderer(image_size=48, mode="soft", shading=shading, faces_per_pixel=3, sigma=1e-3, soft_slots=slots)
    out = r(meshes, azim, elev, 2.2)
    assert out.stats["max_candidates"] > 3 * 3, "the scene must have rims with many more faces than slots"

    def dense(pf, *, H, W, K, blur_radius, tile_size, max_candidates, ranking, overflow=None):
        return reference.dense_face_search(pf.xy, pf.z, pf.image, H=H, W=W, K=None, blur=blur_radius, znear=r.cfg.znear,
                                           cull_backfaces=False, area_eps=mesh_raster.area_eps(pf.xy.dtype, H, W),
                                           num_images=2, ranking=ranking)

    monkeypatch.setattr(mesh_raster, "search_faces", dense)
    ref = r(meshes, azim, elev, 2.2)
    edge = (ref.alpha > 1e-3) & (ref.alpha < 1 - 1e-3)
    assert int(edge.sum()) > 100
    cov_off = ((out.alpha - ref.alpha).abs() > 0.02)[edge].float().mean()
    rgb_off = ((out.images - ref.images).abs().amax(2, keepdim=True) > 0.02)[edge].float().mean()
    if slots == "depth":
        assert cov_off > 0.05
        return
    assert (out.alpha - ref.alpha).abs().max() < 1e-5
    assert cov_off == 0 and rgb_off < 0.01


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ring_enumeration_skips_only_pixels_inside_the_triangle(dtype):
    """The soft search's near pass enumerates a ring (``row_spans(hole=...)``): against the whole
    dilated triangle it may drop only pixels whose centre is inside the face."""
    g = torch.Generator().manual_seed(5)
    n, H = 300, 64
    c = (torch.rand(n, 1, 2, generator=g, dtype=dtype) * 2 - 1) * 0.8
    xy = c + (torch.rand(n, 3, 2, generator=g, dtype=dtype) * 2 - 1) * 0.4  # many faces of 5-25 px
    xy[:20, 1, 1] = xy[:20, 0, 1] + 1e-4  # near-horizontal edges
    xy[20:40, 2, 1] = xy[20:40, 0, 1]  # exactly horizontal edges
    z = torch.ones(n, 3, dtype=dtype)
    cols = torch.stack([xy[:, 0, 0], xy[:, 0, 1], z[:, 0], xy[:, 1, 0], xy[:, 1, 1], z[:, 1],
                        xy[:, 2, 0], xy[:, 2, 1], z[:, 2]])
    table = mesh_raster.face_table(cols)
    radius = 1.5 * 2 / H
    boxes = mesh_raster.face_boxes(cols, torch.zeros(n, dtype=torch.long), radius, H, H)
    planes = mesh_raster.table_planes(table)
    ys = table[mesh_raster.TABLE_CORNERS + 1:mesh_raster.TABLE_CORNERS + 6:2]

    def pairs(hole):
        span = mesh_raster.row_spans(planes, boxes, radius, tiles.SMALL_BOX, H, hole=hole)
        out = [tiles.concat(p) for p in tiles.candidate_chunks(boxes, H, H, 32, 1 << 22, dtype, span)]
        cand = out[0]
        return cand, set(zip(cand.prim.tolist(), cand.pix.tolist()))

    whole, all_pairs = pairs(None)
    _, ring = pairs((ys.amin(0), ys.amax(0)))
    assert ring <= all_pairs
    dropped = all_pairs - ring
    assert len(dropped) > len(all_pairs) // 10  # the faces' insides are a real share of the work
    prim = torch.tensor([p for p, _ in dropped])
    x, y = tiles.pixel_centres(torch.tensor([q for _, q in dropped]), H, H, dtype)
    lam = mesh_raster.barycentrics(table, prim, x, y)
    assert bool(((lam[0] >= 0) & (lam[1] >= 0) & (lam[2] >= 0)).all())
