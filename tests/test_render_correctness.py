"""Renderer behaviour against analytic answers and finite differences."""
import contextlib
import math

import pytest
import torch

from conftest import box_mesh, icosphere, random_triangles
from mvtn_exp.data.shapes import Meshes, PointClouds
from mvtn_exp.render import tiles
from mvtn_exp.render.renderer import MultiViewRenderer


def _analytic_sphere_mask(H, dist, fov):
    """Pixel centres inside the perspective projection of the unit sphere seen from ``dist``."""
    rho = math.tan(math.asin(1.0 / dist)) / math.tan(math.radians(fov) / 2)
    j, i = torch.meshgrid(torch.arange(H), torch.arange(H), indexing="xy")
    x = (2 * j + 1) / H - 1
    y = 1 - (2 * i + 1) / H
    return (x * x + y * y) <= rho * rho, rho


@pytest.mark.parametrize("azim,elev", [(0.0, 0.0), (37.0, 90.0), (200.0, -64.0)])
def test_sphere_silhouette_matches_analytic_projection(azim, elev):
    mesh = icosphere(5)
    r = MultiViewRenderer(image_size=128, shading="silhouette")
    out = r(mesh, torch.tensor([[azim]]), torch.tensor([[elev]]), 2.5)
    pred = out.alpha[0, 0, 0] > 0.5
    truth, _ = _analytic_sphere_mask(128, 2.5, 60.0)
    iou = (pred & truth).sum() / (pred | truth).sum()
    assert iou >= 0.99


def test_orthographic_sphere_radius():
    mesh = icosphere(5)
    r = MultiViewRenderer(image_size=128, shading="silhouette", orthographic=True, ortho_scale=1.25)
    out = r(mesh, torch.tensor([[10.0]]), torch.tensor([[20.0]]), 3.0)
    j, i = torch.meshgrid(torch.arange(128), torch.arange(128), indexing="xy")
    x, y = (2 * j + 1) / 128 - 1, 1 - (2 * i + 1) / 128
    truth = (x * x + y * y) <= (1 / 1.25) ** 2
    pred = out.alpha[0, 0, 0] > 0.5
    assert (pred & truth).sum() / (pred | truth).sum() >= 0.99


def test_soft_silhouette_of_closed_mesh_has_no_wireframe():
    # trap from DESIGN.md: per-face soft edges turn the interior of a closed mesh into a wireframe
    for mesh in (icosphere(3), icosphere(5)):
        r = MultiViewRenderer(image_size=128, mode="soft", shading="silhouette", sigma=1e-4)
        out = r(mesh, torch.tensor([[15.0, 100.0]]), torch.tensor([[20.0, -50.0]]), 2.5)
        truth, rho = _analytic_sphere_mask(128, 2.5, 60.0)
        # interior: 3 px inside the analytic rim (the polyhedron is slightly smaller than the sphere)
        j, i = torch.meshgrid(torch.arange(128), torch.arange(128), indexing="xy")
        x, y = (2 * j + 1) / 128 - 1, 1 - (2 * i + 1) / 128
        interior = (x * x + y * y).sqrt() <= rho - 3 * 2 / 128
        a = out.alpha[0, :, 0][:, interior]
        assert a.min() >= 0.99, f"min interior alpha {a.min():.4f}"


def _fd_check(fn, x, eps, rtol, atol):
    x = x.detach().clone().requires_grad_(True)
    (g,) = torch.autograd.grad(fn(x), x)
    num = torch.zeros_like(x)
    flat = x.detach().reshape(-1)
    for k in range(flat.numel()):
        xp, xm = flat.clone(), flat.clone()
        xp[k] += eps
        xm[k] -= eps
        num.reshape(-1)[k] = (fn(xp.reshape(x.shape)) - fn(xm.reshape(x.shape))) / (2 * eps)
    assert torch.isfinite(g).all()
    assert g.abs().max() > 0
    torch.testing.assert_close(g, num, rtol=rtol, atol=atol)


@pytest.mark.parametrize("shading", ["flat", "smooth", "silhouette"])
def test_soft_mesh_gradients_match_finite_differences(shading):
    mesh = box_mesh(torch.float64)
    # blur covers the screen so the set of faces near a pixel never changes under the perturbation
    r = MultiViewRenderer(image_size=16, mode="soft", shading=shading, sigma=3e-3, gamma=3e-2,
                          blur_radius=3.0, faces_per_pixel=12, specular=0.3)
    g = torch.Generator().manual_seed(0)
    w = torch.rand(1, 2, 3, 16, 16, generator=g, dtype=torch.float64)
    azim = torch.tensor([[20.0, 130.0]], dtype=torch.float64)
    elev = torch.tensor([[25.0, -40.0]], dtype=torch.float64)
    dist = torch.tensor([[2.4, 2.8]], dtype=torch.float64)

    def loss(a=azim, e=elev, d=dist, v=mesh.verts):
        return (r(mesh.with_verts(v), a, e, d).images * w).sum()

    _fd_check(lambda a: loss(a=a), azim, 1e-4, 1e-4, 1e-6)
    _fd_check(lambda e: loss(e=e), elev, 1e-4, 1e-4, 1e-6)
    _fd_check(lambda d: loss(d=d), dist, 1e-6, 1e-4, 1e-6)
    verts = mesh.verts.clone()

    def vloss(v3):
        vv = torch.cat([v3, verts[3:]])
        return loss(v=vv)

    _fd_check(vloss, verts[:3], 1e-6, 1e-4, 1e-6)


def test_point_gradients_match_finite_differences():
    g = torch.Generator().manual_seed(1)
    pts = (torch.rand(60, 3, generator=g, dtype=torch.float64) * 2 - 1) * 0.8
    clouds = PointClouds.from_list([pts])
    w = torch.rand(1, 2, 3, 16, 16, generator=g, dtype=torch.float64)
    for comp in ("alpha", "norm"):
        r = MultiViewRenderer(image_size=16, compositor=comp, point_radius=0.12, points_per_pixel=60)
        azim = torch.tensor([[20.0, 130.0]], dtype=torch.float64)
        elev = torch.tensor([[25.0, -40.0]], dtype=torch.float64)
        _fd_check(lambda a: (r(clouds, a, elev, 2.5).images * w).sum(), azim, 1e-5, 1e-4, 1e-6)
        _fd_check(lambda e: (r(clouds, azim, e, 2.5).images * w).sum(), elev, 1e-5, 1e-4, 1e-6)


TRAINING_SETTINGS = {
    "mesh_hard_camera_light": dict(mode="hard", light="camera"),
    "mesh_soft": dict(mode="soft"),
    "mesh_soft_silhouette": dict(mode="soft", shading="silhouette"),
    "points_alpha": dict(compositor="alpha"),
    "points_norm": dict(compositor="norm"),
}


@pytest.mark.parametrize("name", sorted(TRAINING_SETTINGS))
def test_training_settings_give_nonzero_bounded_camera_gradients(name):
    settings = TRAINING_SETTINGS[name]
    if name.startswith("points"):
        g = torch.Generator().manual_seed(2)
        shape = PointClouds.from_list([(torch.rand(2048, 3, generator=g) * 2 - 1) * torch.tensor([0.9, 0.5, 0.3])])
    else:
        shape = box_mesh()
    r = MultiViewRenderer(image_size=64, **settings)
    azim = torch.tensor([[30.0, 75.0, 160.0, 250.0]], requires_grad=True)
    elev = torch.tensor([[20.0, -30.0, 60.0, 5.0]], requires_grad=True)
    img = r(shape, azim, elev, 2.2).images
    # a fixed random "network": the loss is a random projection of the images
    w = torch.rand(img.shape, generator=torch.Generator().manual_seed(3))
    ga, ge = torch.autograd.grad((img * w).sum() / (64 * 64), [azim, elev])
    for g in (ga, ge):
        assert torch.isfinite(g).all()
        assert (g.abs() > 1e-8).all(), f"{name}: zero camera gradient {g}"
        assert g.abs().max() < 10.0, f"{name}: camera gradient spikes {g}"


@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_tile_overflow_warns_and_drops_nothing(monkeypatch, mode):
    """Hard mode (K = 1) chunks runs of faces and combines their winners; soft mode bins by tile:
    a budget far under one face's box gives the images of one chunk, with one warning."""
    monkeypatch.setattr(tiles, "_warned_tile_budget", False)
    mesh = random_triangles(30, seed=9)
    full = MultiViewRenderer(image_size=32, mode=mode, shading="silhouette")
    tight = MultiViewRenderer(image_size=32, mode=mode, shading="silhouette", tile_size=16, max_candidates=10)
    a, e = torch.tensor([[0.0, 70.0]]), torch.tensor([[0.0, 20.0]])
    with pytest.warns(RuntimeWarning, match="budget grown, nothing dropped"):
        out = tight(mesh, a, e, 3.0).images
    assert torch.equal(out, full(mesh, a, e, 3.0).images)


@pytest.mark.parametrize("kind", ["hard K=2", "soft", "points"])
def test_chunks_of_several_tiles_give_the_images_and_gradients_of_one_pass(kind, monkeypatch):
    """A chunk budget of a fraction of the scene's candidates: tiles of several images are gathered
    into chunks (their counts read once for all chunks); every pixel's candidates stay in one
    chunk, so images and camera gradients equal those of a single pass."""
    torch.manual_seed(3)
    if kind == "points":
        shapes = PointClouds.from_list([torch.randn(300, 3) * 0.5, torch.rand(200, 3) - 0.5])
        opts = dict(points_per_pixel=4)
    else:
        ico = icosphere(2)
        shapes = Meshes.from_list([ico.verts, ico.verts * 0.7 + 0.1], [ico.faces, ico.faces])
        opts = dict(mode="hard", faces_per_pixel=2) if kind == "hard K=2" else dict(mode="soft", faces_per_pixel=4)
    B = len(shapes)
    base = torch.tensor([[0.0, 100.0, 220.0]]).repeat(B, 1) + 17 * torch.arange(B)[:, None]
    outs, chunks = [], []
    enumerate_ = tiles._enumerate
    monkeypatch.setattr(tiles, "_enumerate", lambda *a, **k: chunks.append(1) or enumerate_(*a, **k))
    for chunk in (None, 300 if kind == "points" else 3000):
        a, e = base.clone().requires_grad_(True), torch.full((B, 3), 25.0, requires_grad=True)
        r = MultiViewRenderer(image_size=48, tile_size=16, **opts, **({} if chunk is None else dict(max_candidates=chunk)))
        o = r(shapes, a, e, 2.5)
        (o.images * torch.linspace(0, 1, 48)).sum().backward()
        outs.append((o.images.detach(), a.grad, e.grad))
        chunks.append(0)
    assert chunks.index(0) < chunks[chunks.index(0) + 1:].count(1)  # more chunks under the budget
    (i0, a0, e0), (i1, a1, e1) = outs
    assert torch.allclose(i0, i1, atol=1e-6) and torch.allclose(a0, a1, atol=1e-5) and torch.allclose(e0, e1, atol=1e-5)
    assert a0.abs().sum() > 0


def test_where_true_without_a_host_read_gives_nonzeros_indices():
    torch.manual_seed(0)
    for mask in (torch.rand(1000) < 0.3, torch.zeros(7, dtype=torch.bool), torch.ones(5, dtype=torch.bool),
                 torch.zeros(0, dtype=torch.bool)):
        with tiles.gpu_path():
            got = tiles.where_true(mask, int(mask.sum()))
        assert torch.equal(got, torch.nonzero(mask).squeeze(1)) and torch.equal(tiles.where_true(mask, int(mask.sum())), got)


@pytest.mark.parametrize("kind", ["hard K=2", "soft", "points"])
def test_the_searchs_cuda_form_renders_what_its_cpu_form_does(kind):
    """``tiles.gpu_path``: index lists without host reads (what CUDA runs); same images, alpha and
    camera gradients, bit for bit, chunked into tiles or not."""
    torch.manual_seed(4)
    if kind == "points":
        shapes, opts = PointClouds.from_list([torch.randn(300, 3) * 0.5, torch.rand(200, 3) - 0.5]), dict(points_per_pixel=4)
    else:
        ico = icosphere(2)
        shapes = Meshes.from_list([ico.verts, ico.verts * 0.7 + 0.1], [ico.faces, ico.faces])
        opts = dict(mode="hard", faces_per_pixel=2) if kind == "hard K=2" else dict(mode="soft", faces_per_pixel=4)
    for chunk in (None, 300 if kind == "points" else 3000):
        outs = []
        for form in (contextlib.nullcontext, tiles.gpu_path):
            a, e = torch.tensor([[10.0, 130.0, 250.0]] * 2, requires_grad=True), torch.full((2, 3), 30.0, requires_grad=True)
            r = MultiViewRenderer(image_size=48, tile_size=16, **opts, **({} if chunk is None else dict(max_candidates=chunk)))
            with form():
                o = r(shapes, a, e, 2.5)
                (o.images * torch.linspace(0, 1, 48)).sum().backward()
            outs.append((o.images.detach(), o.alpha.detach(), a.grad, e.grad))
        assert all(torch.equal(x, y) for x, y in zip(*outs))


def test_train_mode_randomises_light_and_colour_eval_is_fixed():
    mesh = box_mesh()
    r = MultiViewRenderer(image_size=32)
    a, e = torch.tensor([[30.0]]), torch.tensor([[20.0]])
    ev1, ev2 = r(mesh, a, e).images, r(mesh, a, e).images
    assert torch.equal(ev1, ev2)
    r.train()
    torch.manual_seed(0)
    t1 = r(mesh, a, e).images
    t2 = r(mesh, a, e).images
    torch.manual_seed(0)
    t1_again = r(mesh, a, e).images
    assert not torch.equal(t1, t2)
    assert torch.equal(t1, t1_again)
    # white object at test time: the brightest pixel is grey-level (r = g = b)
    px = ev1[0, 0].reshape(3, -1)
    assert torch.allclose(px[0], px[1]) and torch.allclose(px[1], px[2])


@pytest.mark.parametrize("specular", [0.0, 0.4])
def test_flat_shading_of_the_seen_face_views_equals_shading_every_face_view(monkeypatch, specular):
    """Flat colours shaded once per seen face-view, or (the reference, defined here) for every
    face-view of the mesh: the same images and the same camera gradients."""
    from mvtn_exp.render import renderer as renderer_module

    def every_face_view(fv, n):
        return torch.arange(n, device=fv.device), fv

    mesh = icosphere(2)
    r = MultiViewRenderer(image_size=40, mode="hard", specular=specular, light="camera")
    out = {}
    for how in ("seen", "all"):
        a, e = torch.tensor([[10.0, 200.0]], requires_grad=True), torch.tensor([[30.0, -70.0]], requires_grad=True)
        if how == "all":
            monkeypatch.setattr(renderer_module, "seen_face_views", every_face_view)
        images = r(mesh, a, e).images
        (images * torch.linspace(0, 1, images.numel()).view_as(images)).sum().backward()
        out[how] = (images.detach(), a.grad, e.grad)
    assert out["seen"][0].max() > 0.3 and out["seen"][1].abs().sum() > 0
    assert torch.equal(out["all"][0], out["seen"][0])
    assert torch.allclose(out["all"][1], out["seen"][1], rtol=1e-4, atol=1e-6)
    assert torch.allclose(out["all"][2], out["seen"][2], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("comp", ["alpha", "norm"])
def test_coloured_points_keep_their_colour(comp):
    g = torch.Generator().manual_seed(5)
    pts = (torch.rand(800, 3, generator=g) * 2 - 1) * 0.5
    colors = torch.zeros(800, 3)
    colors[:400, 0] = 1.0  # red half, green half
    colors[400:, 1] = 1.0
    clouds = PointClouds(pts, torch.tensor([800]), colors)
    img = MultiViewRenderer(image_size=48, compositor=comp)(clouds, torch.tensor([[30.0]]), torch.tensor([[10.0]])).images[0, 0]
    assert img[0].max() > 0.5 and img[1].max() > 0.5
    assert img[2].abs().max() < 1e-6  # no blue anywhere: colours never leak from elsewhere


def test_soft_colour_edges_fade_into_background():
    """Soft mode composites the depth-blended surface over the background by soft coverage, so a
    partly covered edge pixel is darker than the surface on a black background (with SoftRas's
    background slot it kept the full surface colour at small gamma)."""
    r = MultiViewRenderer(image_size=48, mode="soft", shading="flat", sigma=1e-4, gamma=1e-4).eval()
    sphere = icosphere(2)
    out = r(sphere.with_verts(sphere.verts * 0.6), torch.tensor([[20.0]]),
            torch.tensor([[10.0]]), torch.tensor([[2.2]]))
    alpha = out.alpha.reshape(-1)
    rgb = out.images[0, 0].permute(1, 2, 0).reshape(-1, 3)
    rim = (alpha > 0.05) & (alpha < 0.95)
    assert int(rim.sum()) > 20
    assert bool((rgb[rim].amax(1) <= alpha[rim] + 1e-5).all())


@pytest.mark.parametrize("shading, min_cos", [("silhouette", 0.9), ("smooth", 0.5)])
def test_soft_camera_gradient_follows_finite_differences(shading, min_cos):
    """d(sum W * images)/d(azim, elev) against central differences (h = 0.5 deg) on an off-centre
    sphere; hard rasterisation is not held to this (its images are piecewise constant in the camera)."""
    sphere = icosphere(3, dtype=torch.float64)
    meshes = sphere.with_verts(sphere.verts * 0.5 + torch.tensor([0.3, 0.1, 0.0], dtype=torch.float64))
    r = MultiViewRenderer(image_size=48, mode="soft", shading=shading, sigma=1e-4, gamma=1e-4).eval()
    azim = torch.tensor([[0.0, 60.0, 150.0, 250.0]], dtype=torch.float64)
    elev = torch.tensor([[10.0, -20.0, 35.0, 5.0]], dtype=torch.float64)
    dist = torch.full_like(azim, 2.2)
    w = torch.rand(1, 4, 3, 48, 48, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def per_view(a, e):
        return (r(meshes, a, e, dist).images * w).flatten(2).sum(2)[0]  # [M]

    a, e = azim.clone().requires_grad_(True), elev.clone().requires_grad_(True)
    ga, ge = torch.autograd.grad(per_view(a, e).sum(), [a, e])
    h = 0.5
    with torch.no_grad():
        fa = (per_view(azim + h, elev) - per_view(azim - h, elev)) / (2 * h)
        fe = (per_view(azim, elev + h) - per_view(azim, elev - h)) / (2 * h)
    auto, fd = torch.cat([ga[0], ge[0]]), torch.cat([fa, fe])
    cos = float(torch.dot(auto, fd) / (auto.norm() * fd.norm()))
    assert cos > min_cos, (cos, auto, fd)
    assert 0.3 < float(auto.norm() / fd.norm()) < 3.0


def _signed_sqdist_autograd(xy, corners, px, py, interior):
    """Reference: the signed distance written plainly, differentiated by autograd."""
    x, y = xy[corners][..., 0], xy[corners][..., 1]  # [N, 3]

    def seg(a, b):
        ex, ey = x[:, b] - x[:, a], y[:, b] - y[:, a]
        t = (((px - x[:, a]) * ex + (py - y[:, a]) * ey) / (ex * ex + ey * ey)).clamp(0, 1)
        return (px - x[:, a] - t * ex) ** 2 + (py - y[:, a] - t * ey) ** 2

    def side(a, b):
        return (x[:, b] - x[:, a]) * (py - y[:, a]) - (y[:, b] - y[:, a]) * (px - x[:, a])

    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (y[:, 1] - y[:, 0]) * (x[:, 2] - x[:, 0])
    d = torch.stack([seg(1, 2), seg(2, 0), seg(0, 1)], 1)
    lam = torch.stack([side(1, 2), side(2, 0), side(0, 1)], 1) / area[:, None]
    inside = (lam >= 0).all(1)
    d_in = torch.where(interior, torch.full_like(d, 1e4), d).min(1).values
    return torch.where(inside, -d_in, d.min(1).values)


def test_signed_sqdist_matches_autograd_reference_in_value_and_gradient():
    from mvtn_exp.render.edge_distance import FAR_SQ, signed_sqdist

    g = torch.Generator().manual_seed(3)
    V, N = 40, 400
    xy = torch.randn(V, 2, dtype=torch.float64, generator=g)
    corners = torch.stack([torch.randperm(V, generator=g)[:3] for _ in range(N)])
    # half the points inside their triangle (a random convex combination), half anywhere
    w = torch.rand(N, 3, dtype=torch.float64, generator=g)
    w = w / w.sum(1, keepdim=True)
    inner = (w[:, :, None] * xy[corners]).sum(1)
    far = torch.randn(N, 2, dtype=torch.float64, generator=g)
    p = torch.where((torch.arange(N) % 2 == 0)[:, None], inner, far)
    interior = torch.rand(N, 3, generator=g) < 0.3
    interior[:4] = True  # some inside points with every edge interior: -FAR_SQ, no gradient
    a = xy.clone().requires_grad_(True)
    b = xy.clone().requires_grad_(True)
    got = signed_sqdist(a, corners, p[:, 0], p[:, 1], interior)
    ref = _signed_sqdist_autograd(b, corners, p[:, 0], p[:, 1], interior)
    assert (got < 0).sum() >= N // 3 and (got > 0).sum() >= N // 3  # both sides are exercised
    assert (got[:4] == -FAR_SQ).any()
    torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-12)
    weights = torch.randn(N, dtype=torch.float64, generator=g)
    (got * weights).sum().backward()
    (ref * weights).sum().backward()
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-8, atol=1e-10)
    valid = torch.arange(N) % 5 != 0
    masked = signed_sqdist(xy, corners, p[:, 0], p[:, 1], interior, valid)
    assert torch.all(masked[~valid] == FAR_SQ) and torch.equal(masked[valid], got.detach()[valid])
    assert torch.autograd.gradcheck(lambda v: signed_sqdist(v, corners[:60], p[:60, 0], p[:60, 1], interior[:60]),
                                    (xy.clone().requires_grad_(True),))


def test_hard_chunks_of_faces_keep_the_tie_rule(monkeypatch):
    """K = 1 over runs of faces: a face drawn twice (indices 0 and 25, the same depth everywhere)
    wins with its smaller index even when its copies land in different chunks."""
    from mvtn_exp.data.shapes import Meshes
    from mvtn_exp.render import mesh_raster

    monkeypatch.setattr(tiles, "_warned_tile_budget", True)  # (the warning is tested above)
    base = random_triangles(24, seed=3)
    verts = torch.cat([base.verts, base.verts[:3]])
    faces = torch.cat([base.faces, torch.arange(72, 75)[None]])  # face 24 copies face 0
    mesh = Meshes.from_list([verts], [faces])
    r = MultiViewRenderer(image_size=32, mode="hard", shading="silhouette")
    a, e = torch.tensor([[0.0, 90.0]]), torch.tensor([[0.0, 10.0]])
    with torch.no_grad():
        pf = r.project_faces(mesh, a, e, torch.full_like(a, 3.0))[0]
    runs = [mesh_raster.search_faces(pf, H=32, W=32, K=1, blur_radius=0.0, tile_size=16, max_candidates=m)
            for m in (1 << 21, 40, 1)]
    for s in runs[1:]:
        assert torch.equal(s.pix, runs[0].pix) and torch.equal(s.prim, runs[0].prim)
    won = runs[0].prim[:, 0] // 2  # face index (fv = face * M + view)
    assert (won == 0).any() and not (won == 24).any()


@pytest.mark.parametrize("colored", [False, True])
def test_packed_point_compositing_equals_the_dense_formulas(colored):
    """Rank-by-rank compositing of the occupied slots gives the dense [P, K] formulas (front to
    back, and normalised with the background as a sample), values and gradients, with alphas of
    exactly 0 and 1 among them."""
    from mvtn_exp.render import shading

    g = torch.Generator().manual_seed(2)
    P, K = 7, 4
    used = torch.tensor([4, 1, 0, 3, 2, 4, 1])  # slots per pixel, filled from rank 0
    slot = torch.cat([p * K + torch.arange(n) for p, n in enumerate(used.tolist())])
    alpha = torch.rand(len(slot), generator=g, dtype=torch.float64)
    alpha[0], alpha[3] = 1.0, 0.0
    alpha.requires_grad_(True)
    colors = torch.rand(len(slot), 3, generator=g, dtype=torch.float64) if colored else None
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    dense_a = alpha.new_zeros(P * K).index_copy(0, slot, alpha).view(P, K)
    dense_c = None if colors is None else colors.new_zeros(P * K, 3).index_copy(0, slot, colors).view(P, K, 3)
    c = torch.ones(P, K, 1, dtype=torch.float64) if dense_c is None else dense_c
    T = torch.cumprod(1 - dense_a, 1)
    w = dense_a * torch.cat([torch.ones_like(T[:, :1]), T[:, :-1]], 1)
    want_alpha = ((w[..., None] * c).sum(1) + T[:, -1:] * bg, 1 - T[:, -1])
    Tn = torch.prod(1 - dense_a, 1, keepdim=True)
    want_norm = (((dense_a[..., None] * c).sum(1) + Tn * bg) / (dense_a.sum(1, keepdim=True) + Tn), 1 - Tn[:, 0])
    for fn, want in ((shading.alpha_composite, want_alpha), (shading.norm_weighted_composite, want_norm)):
        rgb, cov = fn(slot, alpha, P, K, colors, bg)
        assert torch.allclose(rgb, want[0]) and torch.allclose(cov, want[1])
        weights = torch.linspace(0.1, 1.0, rgb.numel(), dtype=torch.float64).view_as(rgb)
        got = torch.autograd.grad((rgb * weights).sum() + cov.sum(), alpha)[0]
        ref = torch.autograd.grad((want[0] * weights).sum() + want[1].sum(), alpha, retain_graph=True)[0]
        assert torch.allclose(got, ref)
    assert torch.equal(shading.alpha_composite(slot, alpha, P, K, colors, bg)[1][2], torch.tensor(0.0, dtype=torch.float64))
