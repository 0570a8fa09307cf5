"""Numerical safety at the extremes: no NaN/Inf in images or gradients."""
import pytest
import torch

from conftest import box_mesh, icosphere
from mvtn_exp.data.shapes import Meshes, PointClouds, ShapeError
from mvtn_exp.render.renderer import MultiViewRenderer

SETTINGS = {
    "mesh_hard": dict(mode="hard"),
    "mesh_soft": dict(mode="soft"),
    "mesh_soft_smooth": dict(mode="soft", shading="smooth"),
    "points_alpha": dict(compositor="alpha"),
    "points_norm": dict(compositor="norm"),
}


def _shape(name, dtype=torch.float32):
    if name.startswith("points"):
        g = torch.Generator().manual_seed(0)
        pts = (torch.rand(500, 3, generator=g, dtype=dtype) * 2 - 1) * 0.6
        pts[0] = 0.0  # a point on the optical axis: even a 1x1 image sees it
        return PointClouds.from_list([pts])
    return box_mesh(dtype)


def _render_and_grad(r, shape, azim, elev, dist, dtype=torch.float32):
    azim = torch.as_tensor(azim, dtype=dtype).reshape(1, -1).requires_grad_(True)
    elev = torch.as_tensor(elev, dtype=dtype).reshape(1, -1).requires_grad_(True)
    dist = torch.as_tensor(dist, dtype=dtype).expand_as(azim).clone().requires_grad_(True)
    verts = (shape.verts if isinstance(shape, Meshes) else shape.points).detach().clone().requires_grad_(True)
    shape = shape.with_verts(verts) if isinstance(shape, Meshes) else shape.with_points(verts)
    out = r(shape, azim, elev, dist)
    assert torch.isfinite(out.images).all() and torch.isfinite(out.alpha).all()
    assert out.images.min() >= 0 and out.images.max() <= 1
    w = torch.rand(out.images.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
    grads = torch.autograd.grad((out.images * w).sum(), [azim, elev, dist, verts], allow_unused=True)
    for g in grads:
        assert g is None or torch.isfinite(g).all()
    return out, grads


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_poles_and_beyond(name):
    r = MultiViewRenderer(image_size=48, **SETTINGS[name])
    out, _ = _render_and_grad(r, _shape(name), [0.0, 45.0, 10.0, 200.0, 300.0, 0.0, 77.0],
                              [90.0, -90.0, 89.9999, -89.9999, 120.0, -120.0, 90.0 + 1e-5], 2.2)
    assert (out.alpha.flatten(2).amax(-1) > 0).all(), "every view of a centred shape sees it"


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_pole_images_are_continuous(name):
    r = MultiViewRenderer(image_size=48, **SETTINGS[name])
    a = torch.tensor([[30.0, 30.0, 30.0]])
    e = torch.tensor([[89.9999, 90.0, 90.0001]])
    img = r(_shape(name), a, e, 2.2).images[0]
    assert (img[0] - img[1]).abs().mean() < 0.01 and (img[1] - img[2]).abs().mean() < 0.01


@pytest.mark.parametrize("name", sorted(SETTINGS))
@pytest.mark.parametrize("dist", [1.01, 100.0, 0.3])
def test_near_far_and_inside_camera(name, dist):
    r = MultiViewRenderer(image_size=32, **SETTINGS[name])
    _render_and_grad(r, _shape(name), [10.0, 200.0], [20.0, -60.0], dist)


@pytest.mark.parametrize("sigma", [1e-8, 1e3])
@pytest.mark.parametrize("gamma", [1e-8, 1e3])
@pytest.mark.parametrize("shading", ["flat", "silhouette"])
def test_extreme_sigma_gamma(sigma, gamma, shading):
    r = MultiViewRenderer(image_size=24, mode="soft", shading=shading, sigma=sigma, gamma=gamma)
    _render_and_grad(r, box_mesh(), [30.0, 120.0], [20.0, -45.0], 2.2)


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_everything_off_screen(name):
    shape = _shape(name)
    if isinstance(shape, Meshes):
        shape = shape.with_verts(shape.verts + torch.tensor([50.0, 0.0, 0.0]))
    else:
        shape = shape.with_points(shape.points + torch.tensor([50.0, 0.0, 0.0]))
    out, _ = _render_and_grad(MultiViewRenderer(image_size=32, **SETTINGS[name]), shape, [0.0], [0.0], 2.2)
    assert out.alpha.max() == 0


def test_empty_point_cloud():
    # (seeded: 10 points of radius 0.02 NDC miss every pixel centre of a 16 px image now and then)
    empty = PointClouds.from_list([torch.zeros(0, 3), torch.rand(200, 3, generator=torch.Generator().manual_seed(0)) - 0.5])
    for comp in ("alpha", "norm"):
        out = MultiViewRenderer(image_size=16, compositor=comp)(empty, torch.zeros(2, 3), torch.zeros(2, 3), 2.2)
        assert out.alpha[0].max() == 0 and out.alpha[1].max() > 0
        assert torch.isfinite(out.images).all()


@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_one_face_zero_area_and_duplicated_faces(mode):
    v = torch.tensor([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.0, 0.5, 0.0], [0.2, 0.2, 0.0]])
    one = Meshes.from_list([v[:3]], [torch.tensor([[0, 1, 2]])])
    r = MultiViewRenderer(image_size=32, mode=mode)
    out, _ = _render_and_grad(r, one, [0.0, 180.0], [0.0, 0.0], 2.0)
    assert (out.alpha.flatten(1).amax(1) > 0).all()
    # zero area (collinear and repeated vertices) plus a face duplicated three times
    degenerate = torch.tensor([[0, 1, 2], [0, 1, 1], [0, 0, 0], [0, 3, 3], [0, 1, 2], [0, 1, 2]])
    out2, _ = _render_and_grad(r, Meshes.from_list([v], [degenerate]), [0.0, 180.0], [0.0, 0.0], 2.0)
    if mode == "hard":
        assert torch.allclose(out2.images, out.images, atol=1e-6)
    else:  # soft coverage is a product over faces: the triplicated face thickens only the blurred rim
        a1, a2 = out.alpha.detach(), out2.alpha.detach()
        solid = (((a1 > 0.999) & (a2 > 0.999)) | ((a1 == 0) & (a2 == 0))).reshape(out.images.shape[:2] + out.images.shape[3:])
        assert solid.float().mean() > 0.5
        assert torch.allclose(out2.images.permute(0, 1, 3, 4, 2)[solid], out.images.permute(0, 1, 3, 4, 2)[solid],
                              atol=1e-3)
        assert bool((out2.alpha >= out.alpha - 1e-6).all()) and torch.isfinite(out2.images).all()


def test_only_zero_area_faces_render_empty_without_nan():
    v = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [1.0, 0.0, 0.0]])
    out, _ = _render_and_grad(MultiViewRenderer(image_size=16, mode="soft"), Meshes.from_list([v], [torch.tensor([[0, 1, 2]])]), [0.0], [0.0], 2.0)
    assert torch.isfinite(out.images).all()


@pytest.mark.parametrize("size,name", [pytest.param(s, n, marks=pytest.mark.slow) if (s, n) == (1024, "mesh_soft") else (s, n)
                                       for n in ("mesh_hard", "mesh_soft", "points_alpha") for s in (1, 1024)])
def test_tiny_and_huge_images(size, name):  # (1024 px soft: ~9 s on 2 cores, make test-all)
    r = MultiViewRenderer(image_size=size, **SETTINGS[name])
    out, _ = _render_and_grad(r, _shape(name), [30.0], [20.0], 2.2)
    assert out.images.shape == (1, 1, 3, size, size)
    assert out.alpha.max() > 0


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_float64(name):
    r = MultiViewRenderer(image_size=24, **SETTINGS[name])
    out, _ = _render_and_grad(r, _shape(name, torch.float64), [30.0], [20.0], 2.2, dtype=torch.float64)
    assert out.images.dtype == torch.float64


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_vertex_names_the_shape(bad):
    v = torch.rand(4, 3)
    v[2, 1] = bad
    with pytest.raises(ShapeError, match="chair_0042"):
        Meshes.from_list([torch.rand(3, 3), v], [torch.tensor([[0, 1, 2]]), torch.tensor([[0, 1, 2]])], names=["ok", "chair_0042"])
    with pytest.raises(ShapeError, match="cloud_7"):
        PointClouds.from_list([v], names=["cloud_7"])


def test_face_index_out_of_range_names_the_shape():
    with pytest.raises(ShapeError, match="desk_1"):
        Meshes.from_list([torch.rand(3, 3)], [torch.tensor([[0, 1, 3]])], names=["desk_1"])


def test_sphere_fills_screen_when_camera_is_inside_it():
    # camera at distance 0.5 inside the unit sphere: the inside of the sphere is seen everywhere
    r = MultiViewRenderer(image_size=32, mode="hard", shading="silhouette")
    out = r(icosphere(3), torch.tensor([[0.0]]), torch.tensor([[0.0]]), 0.5)
    assert out.alpha.mean() > 0.95


@pytest.mark.parametrize("settings,problem", [
    (dict(mode="hard"), "renderer.mode=hard"),
    (dict(mode="hard", shading="smooth"), "renderer.mode=hard"),
    (dict(mode="soft", sigma=1e-8, image_size=224), "renderer.sigma=1e-08"),
    (dict(mode="soft", sigma=1e-4, image_size=8), "renderer.sigma=0.0001"),
    (dict(mode="soft", sigma=1e-4, image_size=64), None),
    (dict(mode="soft", sigma=1e-8, blur_radius=0.05, image_size=64), None),
])
def test_settings_without_camera_gradient_are_named(settings, problem):
    from mvtn_exp.render.config import RendererConfig

    got = RendererConfig(**settings).validate().camera_gradient_problem()
    assert (got is None) if problem is None else got.startswith(problem)


@pytest.mark.parametrize("sigma,size,flagged", [(1e-8, 224, True), (1e-4, 64, False)])
def test_sub_pixel_blur_gives_no_usable_camera_gradient(sigma, size, flagged):
    # silhouettes of a box from 8 azimuths: the camera gradient of the image sums against central
    # differences. A blur far below a pixel (flagged by camera_gradient_problem) does not follow them.
    box = box_mesh()
    r = MultiViewRenderer(mode="soft", shading="silhouette", sigma=sigma, image_size=size)
    azim = torch.tensor([[10.0, 30.0, 50.0, 70.0, 100.0, 130.0, 160.0, 200.0]], requires_grad=True)
    elev = torch.full((1, 8), 20.0)
    r(box, azim, elev, 2.5).images.sum().backward()
    with torch.no_grad():
        fd = (r(box, azim + 0.5, elev, 2.5).images - r(box, azim - 0.5, elev, 2.5).images).sum(dim=(2, 3, 4))[0]
    g = azim.grad[0]
    cos = float(torch.nn.functional.cosine_similarity(g, fd, 0))
    ratio = float(g.norm() / fd.norm())
    assert (r.cfg.camera_gradient_problem() is not None) == flagged
    if flagged:
        assert cos < 0.9 or not 0.67 < ratio < 1.5
    else:
        assert cos > 0.99 and 0.9 < ratio < 1.1
