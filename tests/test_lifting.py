"""Labels lifted from the views to the points: exact on a constructed case (the true label images
fed as predictions recover every seen point's label, unseen points take their nearest seen
point's), the two fusions, and the renderer's per-pixel primitive index behind it."""
from __future__ import annotations

import math

import pytest
import torch

from conftest import icosphere
from mvtn_exp.data.shapes import Meshes, PointClouds
from mvtn_exp.render.renderer import MultiViewRenderer
from mvtn_exp.tasks import lifting

AZIM = torch.tensor([[0.0, 90.0, 180.0, 270.0]])
ELEV = torch.tensor([[30.0, 30.0, 30.0, 30.0]])
PARTS = 8


def _octant(p: torch.Tensor) -> torch.Tensor:
    """The part of a point: its octant, ``[..., 3]`` -> ``[...]`` in 0..7."""
    return (p[..., 0] > 0).long() + 2 * (p[..., 1] > 0).long() + 4 * (p[..., 2] > 0).long()


def _one_hot_images(labels: torch.Tensor) -> torch.Tensor:
    """Label images ``[B, M, H, W]`` -> the 'predictions' a perfect 2D network gives ``[B, M, C, H, W]``."""
    logits = torch.nn.functional.one_hot(labels.clamp(min=0), PARTS).permute(0, 1, 4, 2, 3).float()
    return logits * (labels >= 0)[:, :, None]


def _sphere_on_faces(n: int):
    """An icosphere with parts by octant of each face's centre, and ``n`` points sampled on its
    faces (each point's face known)."""
    mesh = icosphere(3)
    faces = mesh.faces
    tri = mesh.verts[faces]
    face_parts = _octant(tri.mean(1))
    g = torch.Generator().manual_seed(0)
    face = torch.randint(len(faces), (n,), generator=g)
    u, v = torch.rand(n, generator=g), torch.rand(n, generator=g)
    flip = u + v > 1
    u, v = torch.where(flip, 1 - u, u), torch.where(flip, 1 - v, v)
    t = tri[face]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return mesh, face_parts, face, points


@pytest.mark.parametrize("fuse", lifting.FUSIONS)
def test_true_label_images_lift_back_to_every_seen_face_point(fuse):
    mesh, face_parts, face, points = _sphere_on_faces(3000)
    r = MultiViewRenderer(image_size=96)
    index = r.primitive_index(mesh, AZIM, ELEV)
    labels = lifting.pixel_labels(index, face_parts[None])
    scores, seen = lifting.lift(_one_hot_images(labels), index, len(mesh.faces), face[None], fuse=fuse)
    truth = face_parts[face]
    assert 0.5 < seen.float().mean() < 1.0  # the elevation-30 ring misses the bottom
    assert torch.equal(scores[0, seen[0]].argmax(-1), truth[seen[0]])  # 100% of the seen points
    filled = lifting.fill_unseen(points[None], scores, seen)[0].argmax(-1)
    hit = seen[0].nonzero().squeeze(1)
    for i in (~seen[0]).nonzero().squeeze(1).tolist():  # brute force: the nearest seen point's label
        j = hit[((points[hit] - points[i]) ** 2).sum(1).argmin()]
        assert filled[i] == truth[j]
    assert lifting.coverage(seen)[0] == pytest.approx(seen.float().mean().item())


def test_true_label_images_lift_back_to_every_seen_cloud_point():
    n = 2500
    k = torch.arange(n, dtype=torch.float64) + 0.5  # a Fibonacci sphere
    phi, theta = torch.acos(1 - 2 * k / n), math.pi * (1 + 5 ** 0.5) * k
    points = torch.stack([phi.sin() * theta.cos(), phi.cos(), phi.sin() * theta.sin()], 1).float()
    parts = _octant(points)
    clouds = PointClouds.from_list([points])
    r = MultiViewRenderer(image_size=96)
    index = r.primitive_index(clouds, AZIM, ELEV)
    assert index.max() < n and (index >= 0).any()
    scores, seen = lifting.lift(_one_hot_images(lifting.pixel_labels(index, parts[None])), index, n)
    assert seen.float().mean() > 0.3
    assert torch.equal(scores[0, seen[0]].argmax(-1), parts[seen[0]])


def test_the_index_covers_exactly_what_a_hard_render_covers():
    mesh = icosphere(2)
    r = MultiViewRenderer(image_size=64, mode="hard")
    index = r.primitive_index(mesh, AZIM, ELEV)
    alpha = r(mesh, AZIM, ELEV).alpha[:, :, 0]
    assert torch.equal(index >= 0, alpha > 0.5) and index.max() < len(mesh.faces)
    two = Meshes.from_list([mesh.verts, mesh.verts * 0.5], [mesh.faces, mesh.faces])  # shape-local indices
    both = r.primitive_index(two, AZIM.expand(2, -1), ELEV.expand(2, -1))
    assert torch.equal(both[0], index[0]) and both[1].max() < len(mesh.faces)


def test_mean_and_mode_differ_as_their_rules_say():
    """One primitive, three views: two prefer part 1 by a little, one prefers part 2 by a lot."""
    index = torch.zeros(1, 3, 1, 1, dtype=torch.long)
    logits = torch.tensor([[0.0, 1.0, 0.9], [0.0, 1.0, 0.9], [0.0, 0.0, 9.0]]).view(1, 3, 3, 1, 1)
    mean, _ = lifting.lift(logits, index, 1, fuse="mean")
    mode, _ = lifting.lift(logits, index, 1, fuse="mode")
    assert mean[0, 0].argmax() == 2 and mode[0, 0].argmax() == 1
    assert torch.allclose(mean[0, 0], logits[0, :, :, 0, 0].mean(0))
    assert mode[0, 0].floor().tolist() == [0.0, 2.0, 1.0]  # the votes (the tie-break stays below one)


def test_pixels_of_one_primitive_are_averaged_within_a_view_before_the_views():
    """View 0 shows the primitive in three pixels, view 1 in one: each view weighs the same."""
    index = torch.tensor([[[[0, 0, 0]], [[0, -1, -1]]]])  # [1, 2, 1, 3]
    logits = torch.zeros(1, 2, 2, 1, 3)
    logits[0, 0, 1] = 3.0  # view 0: part 1 in all three pixels
    logits[0, 1, 0, 0, 0] = 1.0  # view 1: part 0
    mean, seen = lifting.lift(logits, index, 1)
    assert seen.all() and torch.allclose(mean[0, 0], torch.tensor([0.5, 1.5]))


def test_the_mean_lift_passes_gradients_to_the_pixels_it_used():
    index = torch.tensor([[[[0, 1], [-1, 1]]]])  # [1, 1, 2, 2]
    logits = torch.randn(1, 1, 3, 2, 2, requires_grad=True)
    scores, _ = lifting.lift(logits, index, 2)
    scores.sum().backward()
    used = (index >= 0)[:, :, None].expand_as(logits)
    assert (logits.grad[used] != 0).all() and (logits.grad[~used] == 0).all()


def test_an_unknown_fusion_is_refused():
    with pytest.raises(ValueError, match="fuse='vote'"):
        lifting.lift(torch.zeros(1, 1, 2, 1, 1), torch.zeros(1, 1, 1, 1, dtype=torch.long), 1, fuse="vote")


def test_the_embedded_part_meshes_lift_exactly_through_the_faces_their_points_lie_on(tmp_path):
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.data.synthetic_parts import SyntheticParts

    ds = SyntheticParts(tmp_path, "test", num_per_class=(1, 1, 1), num_points=512, progress=False)
    batch = collate_shapes([ds[i] for i in range(len(ds))])
    meshes = batch["meshes"]
    B = len(batch["points"])
    face_parts = lifting.per_shape(batch["face_parts"], meshes.faces_per_shape)
    assert face_parts.shape == (B, int(meshes.faces_per_shape.max()))
    r = MultiViewRenderer(image_size=96)
    index = r.primitive_index(meshes, AZIM.expand(B, -1), ELEV.expand(B, -1))
    labels = lifting.pixel_labels(index, face_parts)
    logits = torch.nn.functional.one_hot(labels.clamp(min=0), ds.num_parts).permute(0, 1, 4, 2, 3).float()
    scores, seen = lifting.lift(logits * (labels >= 0)[:, :, None], index, face_parts.shape[1], batch["point_faces"])
    assert 0.5 < seen.float().mean() < 1.0
    assert torch.equal(scores[seen].argmax(-1), batch["part_labels"][seen])  # every seen point, exactly
