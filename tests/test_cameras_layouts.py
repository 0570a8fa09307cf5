import math

import pytest
import torch

from mvtn_exp.render import layouts
from mvtn_exp.render.cameras import Cameras


def _cams(azim, elev, dist=2.0, dtype=torch.float64):
    a = torch.as_tensor(azim, dtype=dtype).reshape(1, -1)
    e = torch.as_tensor(elev, dtype=dtype).reshape(1, -1)
    return Cameras(a, e, torch.full_like(a, dist))


def test_position_convention_y_up():
    R, C = _cams([0.0, 90.0, 0.0], [0.0, 0.0, 90.0]).frames()
    torch.testing.assert_close(C[0, 0], torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64))  # azim 0: +Z
    torch.testing.assert_close(C[0, 1], torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64))  # azim 90: +X
    torch.testing.assert_close(C[0, 2], torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64), atol=1e-12, rtol=0)  # elev 90: +Y
    # the camera looks at the origin: forward (third row) is -C/|C|
    torch.testing.assert_close(R[0, :, 2], -C[0] / 2.0)
    # at azim 0, elev 0 the image's right is +X and up is +Y
    torch.testing.assert_close(R[0, 0, 0], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(R[0, 0, 1], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


def test_frames_orthonormal_everywhere_including_poles():
    elev = torch.tensor([-180.0, -120.0, -90.0, -89.9999, -45.0, 0.0, 45.0, 89.9999, 90.0, 90.0001, 120.0, 270.0])
    azim = torch.linspace(-400, 400, len(elev))
    R, _ = _cams(azim, elev).frames()
    eye = torch.eye(3, dtype=torch.float64).expand_as(R[0])
    torch.testing.assert_close(R[0] @ R[0].transpose(-1, -2), eye, atol=1e-12, rtol=0)
    # rows (right, up, forward): x right, y up, z depth -- a left-handed screen frame, det = -1 everywhere
    torch.testing.assert_close(torch.linalg.det(R[0]), -torch.ones(len(elev), dtype=torch.float64))


def test_frame_is_smooth_across_the_pole():
    e = torch.tensor([89.999, 90.0, 90.001], dtype=torch.float64)
    R, _ = _cams([33.0, 33.0, 33.0], e).frames()
    # |dR/de| stays O(1) per radian (a look-at with a fixed up vector blows up to ~1e3 here)
    step = math.radians(0.001)
    assert ((R[0, 1] - R[0, 0]).abs().max() / step) < 1.5
    assert ((R[0, 2] - R[0, 1]).abs().max() / step) < 1.5


def test_camera_gradients_finite_at_poles():
    a = torch.tensor([[10.0, 10.0]], dtype=torch.float64, requires_grad=True)
    e = torch.tensor([[90.0, -90.0]], dtype=torch.float64, requires_grad=True)
    R, C = Cameras(a, e, torch.full_like(a, 2.0)).frames()
    ga, ge = torch.autograd.grad((R.sum() + C.sum()), [a, e])
    assert torch.isfinite(ga).all() and torch.isfinite(ge).all()


def test_bad_camera_arguments():
    with pytest.raises(ValueError, match=r"\[B, M\]"):
        Cameras(torch.zeros(2, 3), torch.zeros(2, 4), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="fov"):
        Cameras(torch.zeros(1, 1), torch.zeros(1, 1), torch.ones(1, 1), fov=180.0)


def test_circular_layout():
    a, e, d = layouts.circular(8, batch=3, distance=2.5)
    assert a.shape == e.shape == d.shape == (3, 8)
    torch.testing.assert_close(a[0], torch.arange(8.0) * 45.0)
    assert (e == 30.0).all() and (d == 2.5).all()


@pytest.mark.parametrize("M", list(range(1, 41)) + [64, 100, 1000])
def test_spherical_layout_has_exactly_m_distinct_views(M):
    a, e, _ = layouts.spherical(M, batch=2)
    assert a.shape == (2, M)
    assert (e.abs() < 90).all()
    if M > 1:
        a, e = torch.deg2rad(a[0].double()), torch.deg2rad(e[0].double())
        p = torch.stack([e.cos() * a.sin(), e.sin(), e.cos() * a.cos()], 1)
        d = torch.cdist(p, p) + 10 * torch.eye(M, dtype=torch.float64)
        # near-uniform: nearest-neighbour spacing within a constant of the ideal sqrt(4 pi / M)
        assert d.min() > 0.5 * math.sqrt(4 * math.pi / M)


def test_spherical_layout_covers_the_sphere():
    a, e, _ = layouts.spherical(200)
    y = torch.sin(torch.deg2rad(e[0]))
    # equal-area: as many views above as below the equator, mean height ~0
    assert abs(float(y.mean())) < 1e-6
    assert (y > 0.9).any() and (y < -0.9).any()


@pytest.mark.parametrize("bad", [0, -3, 2.5])
def test_layouts_reject_bad_m(bad):
    with pytest.raises(ValueError, match="views"):
        layouts.spherical(bad)
    with pytest.raises(ValueError, match="views"):
        layouts.circular(bad)
