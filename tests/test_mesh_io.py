import numpy as np
import pytest
import torch

from mvtn_exp.data import mesh_io
from mvtn_exp.data.mesh_io import ShapeFileError
from mvtn_exp.data.shapes import Meshes
from mvtn_exp.render.renderer import MultiViewRenderer

QUAD = "0 0 0\n1 0 0\n1 1 0\n0 1 0\n"


def test_off_with_glued_header_comments_and_polygons(tmp_path):
    p = tmp_path / "glued.off"
    p.write_text("OFF4 2 0\n# a comment\n\n" + QUAD + "3 0 1 2\n4 0 1 2 3\n")
    v, f = mesh_io.read_off(p)
    assert v.shape == (4, 3) and f.tolist() == [[0, 1, 2], [0, 1, 2], [0, 2, 3]]


def test_off_standard_header(tmp_path):
    p = tmp_path / "std.off"
    p.write_text("OFF\n4 1 0\n" + QUAD + "4 0 1 2 3\n")
    v, f = mesh_io.read_mesh(p)
    assert len(f) == 2


@pytest.mark.parametrize("text,match", [
    ("", "empty file"),
    ("PLY\n", "expected an OFF header"),
    ("OFF\n4 1\n0 0 0\n", "vertex lines"),
    ("OFF\n4 1 0\n" + QUAD + "3 0 1\n", "face lines"),
    ("OFF\n4 1 0\n" + QUAD + "3 0 1 9\n", "out of range"),
    ("OFF\n4 1 0\n0 0 0\n1 0 0\nnan 1 0\n0 1 0\n3 0 1 2\n", "NaN or Inf"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n2 0 0\n3 0 1 2\n", "zero area"),
])
def test_broken_off_files_are_refused_with_the_path(tmp_path, text, match):
    p = tmp_path / "broken.off"
    p.write_text(text)
    with pytest.raises(ShapeFileError, match=match) as err:
        mesh_io.read_mesh(p)
    assert str(p) in str(err.value)


def test_obj_and_point_files(tmp_path):
    obj = tmp_path / "tri.obj"
    obj.write_text("mtllib missing.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl x\nf 1 2 3\n")
    v, f = mesh_io.read_mesh(obj)
    assert v.shape == (3, 3) and f.shape == (1, 3)
    pts = np.random.default_rng(0).normal(size=(50, 6))
    np.save(tmp_path / "p.npy", pts)
    np.savetxt(tmp_path / "p.txt", pts, delimiter=",")
    for name in ("p.npy", "p.txt"):
        assert mesh_io.is_point_file(tmp_path / name)
        assert np.allclose(mesh_io.read_points(tmp_path / name), pts[:, :3])
    with pytest.raises(ShapeFileError, match="no such file"):
        mesh_io.read_points(tmp_path / "missing.npy")


def test_zup_and_normalisation():
    xyz = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    yup = mesh_io.zup_to_yup(xyz)
    assert np.allclose(yup[0], [0.0, 2.0, 0.0])  # +Z becomes +Y
    n = mesh_io.normalize_unit_sphere(yup + 5)
    assert np.isclose(np.linalg.norm(n, axis=1).max(), 1.0)
    assert np.allclose((n.max(0) + n.min(0)) / 2, 0.0)


def test_real_modelnet_samples_render_with_non_empty_silhouettes(real_samples):
    files = sorted(real_samples.glob("ModelNet*/*/*/*.off"))
    assert len(files) >= 8
    r = MultiViewRenderer(image_size=64, shading="silhouette")
    for path in files:
        v, f = mesh_io.read_mesh(path)
        v = mesh_io.normalize_unit_sphere(mesh_io.zup_to_yup(v))
        m = Meshes.from_list([torch.tensor(v, dtype=torch.float32)], [torch.tensor(f)], names=[path.name])
        out = r(m, torch.tensor([[0.0, 90.0, 180.0, 45.0]]), torch.tensor([[30.0, 30.0, 90.0, -60.0]]), 2.2)
        cover = out.alpha.flatten(2).mean(-1)
        assert (cover > 0.01).all(), f"{path.name}: an empty view {cover.tolist()}"
