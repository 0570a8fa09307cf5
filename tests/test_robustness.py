"""Robustness transforms: rotation about Y and directional occlusion crops (mvtn_exp.tasks.robustness)."""
import itertools
import math

import pytest
import torch

from mvtn_exp.data.shapes import Meshes
from mvtn_exp.render.cameras import Cameras
from mvtn_exp.tasks import robustness

AXIS = {"x": 0, "y": 1, "z": 2}


class _Extent:
    """``robustness`` with the crop functions in the ``extent`` frame: most crop tests below check
    that frame's geometry (the plane from each shape's own extent); the ``unit_sphere`` frame, the
    default, has its own tests at the end."""

    def __getattr__(self, name):
        fn = getattr(robustness, name)
        if name in ("crop_plane", "crop_indices", "crop_points", "crop_mesh", "crop_batch"):
            return lambda *a, **kw: fn(*a, **{"frame": "extent", **kw})
        return fn


rb = _Extent()


def signed(xyz, d):
    return xyz[..., AXIS[d[1]]] * (1.0 if d[0] == "+" else -1.0)


def grid_cube(n: int = 4, half: float = 0.5, dtype=torch.float64):
    """Closed surface of the cube [-half, half]^3, each side an n x n grid of quads (2 triangles),
    outward-facing (counter-clockwise seen from outside)."""
    verts, faces = [], []
    g = torch.linspace(-half, half, n + 1, dtype=dtype)
    for axis in range(3):
        for sign in (-1.0, 1.0):
            a1, a2 = [k for k in range(3) if k != axis]
            base = sum(len(v) for v in verts)
            uu, vv = torch.meshgrid(g, g, indexing="ij")
            p = torch.zeros((n + 1) * (n + 1), 3, dtype=dtype)
            p[:, axis] = sign * half
            p[:, a1] = uu.reshape(-1)
            p[:, a2] = vv.reshape(-1)
            verts.append(p)
            for i, j in itertools.product(range(n), range(n)):
                a, b = base + i * (n + 1) + j, base + (i + 1) * (n + 1) + j
                c, d = b + 1, a + 1
                for tri in ([a, b, c], [a, c, d]):
                    faces.append(tri)
    v = torch.cat(verts)
    f = torch.tensor(faces)
    # weld the copies along the cube's edges: a closed, watertight surface
    v, inv = torch.unique(v, dim=0, return_inverse=True)
    f = inv[f]
    # orient every face outward
    n_ = torch.linalg.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = (n_ * v[f].mean(1)).sum(-1) < 0
    f[flip] = f[flip][:, [0, 2, 1]]
    return v, f


def octahedron(scale: float = 0.8, dtype=torch.float64):
    v = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=dtype) * scale
    f = []
    for sx, sy, sz in itertools.product((0, 1), (2, 3), (4, 5)):
        f.append([sx, sy, sz])
    f = torch.tensor(f)
    n_ = torch.linalg.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = (n_ * v[f].mean(1)).sum(-1) < 0
    f[flip] = f[flip][:, [0, 2, 1]]
    return v, f


def areas(v, f):
    return 0.5 * torch.linalg.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]).norm(dim=-1)


def sample_surface(v, f, n, gen):
    a = areas(v, f)
    idx = torch.multinomial(a / a.sum(), n, replacement=True, generator=gen)
    r1, r2 = torch.rand(n, generator=gen, dtype=v.dtype), torch.rand(n, generator=gen, dtype=v.dtype)
    s = r1.sqrt()
    w = torch.stack([1 - s, s * (1 - r2), s * r2], -1)
    return (v[f[idx]] * w[..., None]).sum(1)


# ------------------------------------------------------------------------------------------------
# rotation
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("theta", [10.0, 90.0, 180.0])
def test_sample_angles_range_and_spread(theta):
    a = rb.sample_angles(1000, theta, torch.Generator().manual_seed(3))
    assert a.shape == (1000,)
    assert float(a.min()) >= -theta and float(a.max()) <= theta
    assert float(a.min()) < -0.8 * theta and float(a.max()) > 0.8 * theta
    if theta == 90.0:
        assert not bool((a.abs() > 90.0).any())
    b = rb.sample_angles(1000, theta, torch.Generator().manual_seed(3))
    assert torch.equal(a, b)
    assert not torch.equal(a, rb.sample_angles(1000, theta, torch.Generator().manual_seed(4)))


def test_sample_angles_theta_180_covers_circle():
    a = rb.sample_angles(1000, 180.0, torch.Generator().manual_seed(0))
    assert float(a.min()) < -170 and float(a.max()) > 170
    with pytest.raises(ValueError):
        rb.sample_angles(10, 200.0)


def test_rotate_y_keeps_y_and_norms_and_direction():
    g = torch.Generator().manual_seed(0)
    xyz = torch.randn(5, 100, 3, generator=g, dtype=torch.float64)
    ang = torch.tensor([0.0, 30.0, -75.0, 90.0, 180.0])
    out = rb.rotate_y(xyz, ang)
    assert torch.equal(out[..., 1], xyz[..., 1])
    torch.testing.assert_close(out.norm(dim=-1), xyz.norm(dim=-1))
    torch.testing.assert_close(out[0], xyz[0])
    # +90 degrees: +Z -> +X, +X -> -Z
    e = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(rb.rotate_y(e[2], 90.0), e[0], atol=1e-12, rtol=0)
    torch.testing.assert_close(rb.rotate_y(e[0], 90.0), -e[2], atol=1e-12, rtol=0)
    # composition and inverse
    torch.testing.assert_close(rb.rotate_y(rb.rotate_y(xyz, ang), -ang), xyz)
    torch.testing.assert_close(rb.rotate_y(xyz, ang), torch.einsum("bij,bnj->bni", rb.y_rotation_matrix(ang), xyz))


def test_rotation_matches_camera_azimuth():
    """A shape turned by a, seen from azimuth a, looks like the original seen from azimuth 0."""
    g = torch.Generator().manual_seed(1)
    p = torch.randn(50, 3, generator=g)
    for a in (90.0, 37.0, -120.0):
        R_a, C_a = Cameras(torch.tensor([[a]]), torch.zeros(1, 1), torch.full((1, 1), 2.5)).frames()
        R_0, C_0 = Cameras(torch.zeros(1, 1), torch.zeros(1, 1), torch.full((1, 1), 2.5)).frames()
        # the camera at azimuth a sits where +Z (azimuth 0) is turned to
        torch.testing.assert_close(C_a[0, 0], rb.rotate_y(C_0[0, 0], a), atol=1e-5, rtol=0)
        seen_a = (rb.rotate_y(p, a) - C_a[0, 0]) @ R_a[0, 0].T
        seen_0 = (p - C_0[0, 0]) @ R_0[0, 0].T
        torch.testing.assert_close(seen_a, seen_0, atol=1e-5, rtol=0)


def test_rotate_batch_points_and_meshes_consistent():
    g = torch.Generator().manual_seed(2)
    vs = [torch.randn(n, 3, generator=g) for n in (7, 12, 5)]
    fs = [torch.randint(0, len(v), (4, 3), generator=g) for v in vs]
    meshes = Meshes.from_list(vs, fs, names=["a", "b", "c"])
    batch = {"points": torch.randn(3, 64, 3, generator=g), "meshes": meshes, "labels": torch.tensor([0, 1, 2]),
             "names": ["a", "b", "c"], "rotations": torch.eye(3).expand(3, 3, 3).clone()}
    before = {k: batch[k].clone() for k in ("points", "rotations")}
    verts_before = meshes.verts.clone()
    angles = torch.tensor([20.0, -90.0, 135.0])
    out = rb.rotate_batch(batch, angles)
    assert out is not batch
    for b in range(3):
        torch.testing.assert_close(out["points"][b], rb.rotate_y(batch["points"][b], angles[b]))
        got = torch.split(out["meshes"].verts, out["meshes"].verts_per_shape.tolist())[b]
        torch.testing.assert_close(got, rb.rotate_y(vs[b], angles[b]))
        torch.testing.assert_close(out["rotations"][b], rb.y_rotation_matrix(angles[b]).float())
    assert torch.equal(out["meshes"].faces, meshes.faces)
    assert out["labels"] is batch["labels"] and out["names"] == batch["names"]
    # input untouched
    assert torch.equal(batch["points"], before["points"]) and torch.equal(batch["rotations"], before["rotations"])
    assert torch.equal(batch["meshes"].verts, verts_before)
    # points-only batch
    out2 = rb.rotate_batch({"points": batch["points"], "meshes": None, "labels": batch["labels"]}, angles)
    assert out2["meshes"] is None
    torch.testing.assert_close(out2["points"], out["points"])


# ------------------------------------------------------------------------------------------------
# occlusion: points
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("direction", rb.DIRECTIONS)
def test_crop_points_fraction_and_side(direction):
    g = torch.Generator().manual_seed(5)
    N = 4000
    pts = torch.rand(2, N, 3, generator=g) * 2 - 1
    pts[1] = pts[1] * torch.tensor([0.3, 0.9, 0.5]) + 0.1   # a different box
    for r in (0.1, 0.2, 0.3, 0.5, 0.75):
        idx, count = rb.crop_indices(pts, direction, r, torch.Generator().manual_seed(0))
        assert torch.allclose(count.double() / N, torch.full((2,), 1 - r, dtype=torch.float64), atol=0.03)
        out = rb.crop_points(pts, direction, r, torch.Generator().manual_seed(0))
        assert out.shape == pts.shape and torch.isfinite(out).all()
        u = signed(pts, direction)
        cut = u.max(1).values - r * (u.max(1).values - u.min(1).values)
        assert bool((signed(out, direction) <= cut[:, None] + 1e-6).all())
        # every survivor is kept, and nothing else
        for b in range(2):
            assert set(idx[b].tolist()) == set((u[b] <= cut[b]).nonzero().flatten().tolist())


def test_crop_points_refill_unbiased_and_seeded():
    g = torch.Generator().manual_seed(6)
    N = 20000
    pts = torch.rand(1, N, 3, generator=g) * 2 - 1
    idx, count = rb.crop_indices(pts, "+x", 0.5, torch.Generator().manual_seed(1))
    k = int(count[0])
    surv, refill = idx[0, :k], idx[0, k:]
    assert len(refill) == N - k > 5000
    # survivors first, each once, in order
    assert torch.equal(surv, (pts[0, :, 0] <= pts[0, :, 0].max() - 0.5 * (pts[0, :, 0].max() - pts[0, :, 0].min()))
                       .nonzero().flatten())
    surv_set = set(surv.tolist())
    assert set(refill.tolist()) <= surv_set
    # uniform over survivors: mean index and mean position match, draws spread over all of them
    assert abs(refill.double().mean() - surv.double().mean()) < 0.02 * N
    torch.testing.assert_close(pts[0, refill].mean(0), pts[0, surv].mean(0), atol=0.03, rtol=0)
    hist = torch.bincount(torch.searchsorted(surv, refill), minlength=k).double()
    quarters = hist.reshape(-1)[: k - k % 4].reshape(4, -1).sum(1) / len(refill)
    assert bool(((quarters - 0.25).abs() < 0.03).all())
    out1 = rb.crop_points(pts, "+x", 0.5, torch.Generator().manual_seed(1))
    out2 = rb.crop_points(pts, "+x", 0.5, torch.Generator().manual_seed(1))
    out3 = rb.crop_points(pts, "+x", 0.5, torch.Generator().manual_seed(2))
    assert torch.equal(out1, out2) and not torch.equal(out1, out3)


def test_crop_points_ratio_zero_identity_and_extremes():
    g = torch.Generator().manual_seed(7)
    N = 1000
    pts = torch.rand(3, N, 3, generator=g)
    assert rb.crop_points(pts, "-y", 0.0, g) is pts
    for d in rb.DIRECTIONS:
        out = rb.crop_points(pts, d, 0.999, torch.Generator().manual_seed(0))
        assert out.shape == pts.shape and torch.isfinite(out).all()
        idx, count = rb.crop_indices(pts, d, 0.999, torch.Generator().manual_seed(0))
        floor = max(1, math.ceil(rb.POINT_FLOOR * N))
        assert bool((count >= floor).all())
        # the floor keeps the points furthest into the kept side
        u = signed(pts, d)
        for b in range(3):
            kept = set(idx[b].tolist())
            assert kept == set(u[b].argsort()[: int(count[b])].tolist())
    # a plane beyond every point still leaves the floor
    idx, count = rb.crop_indices(pts, "+x", 0.5, None, planes=torch.full((3,), -5.0))
    assert bool((count == 10).all())
    with pytest.raises(ValueError):
        rb.crop_points(pts, "+w", 0.2)
    with pytest.raises(ValueError):
        rb.crop_points(pts, "+x", 1.0)


# ------------------------------------------------------------------------------------------------
# occlusion: meshes
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("direction", rb.DIRECTIONS)
def test_crop_mesh_cube(direction):
    v, f = grid_cube(4)
    a0 = float(areas(v, f).sum())
    assert abs(a0 - 6.0) < 1e-9
    for r in (0.1, 0.25, 0.3, 0.5, 0.75, 0.999):   # 0.25 / 0.5 / 0.75 cut exactly through grid vertices
        cv, cf = rb.crop_mesh(v, f, direction, r)
        assert torch.isfinite(cv).all()
        assert cf.dtype == torch.long and cf.min() >= 0 and cf.max() < len(cv)
        assert len(torch.unique(cf)) == len(cv)            # no unreferenced vertices
        cut = 0.5 - r * 1.0
        u = signed(cv, direction)
        assert bool((u <= cut + 1e-6).all())
        assert abs(float(u.max()) - cut) < 1e-9             # the plane is reached exactly
        a = areas(cv, cf)
        assert bool((a > 0).all())
        # open cut: four side walls shortened to (1 - r) plus the untouched opposite side
        assert abs(float(a.sum()) - (4 * (1 - r) + 1)) < 1e-6
        # orientation preserved: normals still point outward
        n_ = torch.linalg.cross(cv[cf[:, 1]] - cv[cf[:, 0]], cv[cf[:, 2]] - cv[cf[:, 0]])
        assert bool(((n_ * cv[cf].mean(1)).sum(-1) > 0).all())
    assert rb.crop_mesh(v, f, direction, 0.0) == (v, f)
    cv, cf = rb.crop_mesh(v, f, direction, 0.0)
    assert cv is v and cf is f


def test_crop_mesh_shared_cut_vertices_and_float32():
    v, f = grid_cube(3, dtype=torch.float32)
    cv, cf = rb.crop_mesh(v, f, "+z", 0.4)
    assert cv.dtype == torch.float32
    # every cut edge gets one vertex shared by both neighbouring faces: 4 walls x (3 grid lines +
    # 3 diagonals) cut edges, and the only open edges of the (watertight) cube are on the rim
    on_plane = (cv[:, 2] - (0.5 - 0.4)).abs() < 1e-6
    assert int(on_plane.sum()) == 4 * (3 + 3)
    e = torch.cat([cf[:, [0, 1]], cf[:, [1, 2]], cf[:, [2, 0]]]).sort(1).values
    uniq, count = torch.unique(e, dim=0, return_counts=True)
    assert bool((count <= 2).all())
    open_edges = uniq[count == 1]
    assert len(open_edges) == 4 * (3 + 3) and bool(on_plane[open_edges].all())
    assert bool((areas(cv.double(), cf) > 0).all())


def test_crop_mesh_never_empty():
    v, f = grid_cube(2)
    cv, cf = rb.crop_mesh(v, f, "+y", 0.5, plane=-10.0)   # plane beyond the whole mesh
    assert len(cf) >= 1 and torch.isfinite(cv).all() and bool((areas(cv, cf) > 0).all())
    # kept faces are those reaching furthest into the kept side (the y = -0.5 side)
    assert torch.allclose(cv[:, 1].min(), torch.tensor(-0.5, dtype=v.dtype))
    vo, fo = octahedron()
    cv, cf = rb.crop_mesh(vo, fo, "-x", 0.999)
    assert len(cf) == 4 and bool((areas(cv, cf) > 0).all())
    assert abs(float(cv[:, 0].min()) - (-0.8 + 0.999 * 1.6)) < 1e-9


# ------------------------------------------------------------------------------------------------
# batch
# ------------------------------------------------------------------------------------------------
def _two_shape_batch(N=3000):
    g = torch.Generator().manual_seed(11)
    vc, fc = grid_cube(3)
    vc = vc * torch.tensor([1.0, 0.6, 0.8], dtype=vc.dtype) + 0.1
    vo, fo = octahedron(0.9)
    pts = torch.stack([sample_surface(vc, fc, N, g), sample_surface(vo, fo, N, g)]).float()
    meshes = Meshes.from_list([vc.float(), vo.float()], [fc, fo], names=["cube", "octa"])
    return {"points": pts, "meshes": meshes, "labels": torch.tensor([0, 1]), "names": ["cube", "octa"]}


@pytest.mark.parametrize("direction", ["+x", "-y", "+z"])
def test_crop_batch_consistent(direction):
    batch = _two_shape_batch()
    pts_before, verts_before = batch["points"].clone(), batch["meshes"].verts.clone()
    out = rb.crop_batch(batch, direction, 0.3, torch.Generator().manual_seed(0))
    assert torch.equal(batch["points"], pts_before) and torch.equal(batch["meshes"].verts, verts_before)
    m = out["meshes"]
    assert isinstance(m, Meshes) and len(m) == 2 and m.names == ["cube", "octa"]
    assert out["points"].shape == batch["points"].shape and out["labels"] is batch["labels"]
    in_v = torch.split(batch["meshes"].verts, batch["meshes"].verts_per_shape.tolist())
    out_v = torch.split(m.verts, m.verts_per_shape.tolist())
    out_f = torch.split(m.faces, m.faces_per_shape.tolist())
    for b in range(2):
        u_in = signed(in_v[b], direction)
        cut = u_in.max() - 0.3 * (u_in.max() - u_in.min())
        # the mesh reaches exactly the cut of its own extent ...
        assert abs(float(signed(out_v[b], direction).max() - cut)) < 1e-5
        off = int(m.vert_offsets()[b])
        assert bool((areas(out_v[b].double(), out_f[b] - off) > 0).all())
        # ... and the points were cut by the very same plane: kept = every original point below it
        u_pts = signed(batch["points"][b], direction)
        expected = batch["points"][b][u_pts <= cut]
        got = torch.unique(out["points"][b], dim=0)
        assert torch.equal(got, torch.unique(expected, dim=0))
        # the kept points are a sizeable part, not everything
        assert 0.3 * len(u_pts) < len(expected) < 0.95 * len(u_pts)
    # same per-shape result as cropping each shape alone
    alone = rb.crop_mesh(in_v[1], batch["meshes"].faces[batch["meshes"].faces_per_shape[0]:] - len(in_v[0]),
                         direction, 0.3)
    torch.testing.assert_close(out_v[1], alone[0])


def test_crop_batch_ratio_zero_and_points_only():
    batch = _two_shape_batch(500)
    out = rb.crop_batch(batch, "+y", 0.0, torch.Generator().manual_seed(0))
    assert out["points"] is batch["points"] and out["meshes"] is batch["meshes"]
    pts_only = {"points": batch["points"], "meshes": None, "labels": batch["labels"], "names": batch["names"]}
    out = rb.crop_batch(pts_only, "-z", 0.5, torch.Generator().manual_seed(0))
    assert out["meshes"] is None
    torch.testing.assert_close(out["points"], rb.crop_points(batch["points"], "-z", 0.5,
                                                              torch.Generator().manual_seed(0)))
    u = signed(batch["points"], "-z")
    cut = u.max(1).values - 0.5 * (u.max(1).values - u.min(1).values)
    assert bool((signed(out["points"], "-z") <= cut[:, None]).all())


# ------------------------------------------------------------------------- the unit-sphere frame
def test_unit_sphere_frame_is_the_official_rule():
    """The official code keeps ``sign * x > 2|r| - 1``: a fixed plane in the unit sphere's frame
    whatever the shape's extent (brute force on random points, all six directions)."""
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(4, 2000, 3, generator=g, dtype=torch.float64) * 1.2 - 0.6  # inside [-0.6, 0.6]^3
    for d, r in itertools.product(robustness.DIRECTIONS, (0.1, 0.3, 0.5, 0.75)):
        idx, count = robustness.crop_indices(pts, d, r, torch.Generator().manual_seed(0))
        axis, sign = AXIS[d[1]], (1.0 if d[0] == "+" else -1.0)
        # the official rule names the side it keeps: keeping -sign * x > 2r - 1 removes the cap on the +sign side
        official = -sign * pts[..., axis] > 2 * r - 1
        for b in range(4):
            n_kept = int(official[b].sum())
            if n_kept >= math.ceil(0.01 * 2000):
                assert int(count[b]) == n_kept
                assert torch.equal(torch.sort(idx[b, :n_kept]).values, torch.nonzero(official[b]).flatten())
    assert float(robustness.crop_plane(pts, "+x", 0.25)[0]) == 0.5


def test_unit_sphere_frame_floors_shapes_wholly_cut_and_says_so():
    v, f = grid_cube(3, half=0.3)  # the cube lies in [-0.3, 0.3]: at r = 0.75 the plane u = -0.5 is below it
    pts = v[None].float().repeat(2, 1, 1)
    pts[1] = pts[1] * 3.0  # this one reaches u = -0.9 and keeps its lower part
    batch = {"points": pts, "meshes": None, "labels": torch.tensor([0, 1]), "names": ["small", "large"]}
    out = robustness.crop_batch(batch, "+y", 0.75, torch.Generator().manual_seed(0))
    assert out["occlusion_floored"].tolist() == [True, False]
    assert bool((out["points"][1][:, 1] <= -0.5).all())
    cv, cf = robustness.crop_mesh(v, f, "+y", 0.75)  # the mesh: the floor of faces nearest the kept side
    assert len(cf) == max(1, math.ceil(0.01 * len(f))) and float(cv[:, 1].min()) == -0.3
    small = robustness.crop_batch(batch, "+y", 0.1, torch.Generator().manual_seed(0))  # plane 0.8: nothing cut
    assert not bool(small["occlusion_floored"].any()) and torch.equal(small["points"][0], pts[0])
    with pytest.raises(ValueError, match="frame"):
        robustness.crop_batch(batch, "+y", 0.1, frame="box")
