"""The embedded synthetic dataset: classes, splits, determinism, cache, geometry, view-dependent details, collate."""
import hashlib
import shutil
import warnings

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from mvtn_exp.data import synthetic
from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.shapes import Meshes
from mvtn_exp.data.synthetic import CLASSES, SPLITS, CacheWarning, SyntheticShapes, build_shape
from mvtn_exp.render.renderer import MultiViewRenderer

COUNTS = (3, 1, 2)
NPTS = 256


def make(root, split="test", **kw):
    kw = {"num_per_class": COUNTS, "num_points": NPTS, "progress": False, **kw}
    return SyntheticShapes(root, split, **kw)


@pytest.fixture(scope="module")
def splits(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    return {s: make(root, s) for s in SPLITS}


def items(ds):
    return [ds[i] for i in range(len(ds))]


def digest(item):
    return hashlib.sha1(item["verts"].numpy().tobytes() + item["faces"].numpy().tobytes()).hexdigest()


def same(a, b):
    return all(torch.equal(x[k], y[k]) for x, y in zip(items(a), items(b)) for k in ("verts", "faces", "points"))


def on_surface_distance(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per point, the smallest plane distance to a triangle whose (slightly grown) interior holds
    its projection: ``[P]`` (inf when no triangle does). An upper bound on the distance to the mesh
    up to the 1e-4 barycentric tolerance."""
    p = points[:, None].astype(np.float64)
    t = verts.astype(np.float64)[faces][None]
    a, e1, e2 = t[..., 0, :], t[..., 1, :] - t[..., 0, :], t[..., 2, :] - t[..., 0, :]
    d = p - a
    d00, d01, d11 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    d20, d21 = (d * e1).sum(-1), (d * e2).sum(-1)
    den = d00 * d11 - d01 ** 2
    v, w = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    n = np.cross(e1, e2)
    plane = np.abs((d * n).sum(-1)) / np.linalg.norm(n, axis=-1)
    inside = (v >= -1e-4) & (w >= -1e-4) & (v + w <= 1 + 1e-4)
    return np.where(inside, plane, np.inf).min(1)


# ------------------------------------------------------------------------------- classes, splits
def test_classes_labels_counts_and_names(splits):
    assert len(CLASSES) >= 10 and CLASSES == sorted(set(CLASSES))
    all_names = []
    for s, n in zip(SPLITS, COUNTS):
        ds = splits[s]
        assert ds.classes == CLASSES and len(ds) == n * len(CLASSES)
        labels = np.array([it["label"] for it in items(ds)])
        assert labels.min() >= 0 and labels.max() < len(CLASSES)
        assert np.bincount(labels, minlength=len(CLASSES)).tolist() == [n] * len(CLASSES)
        for it in items(ds):
            assert it["name"].rsplit("_", 2)[0] == CLASSES[it["label"]]
        all_names += [it["name"] for it in items(ds)]
    assert len(set(all_names)) == len(all_names)


def test_splits_are_disjoint(splits):
    seen = {s: {digest(it) for it in items(splits[s])} for s in SPLITS}
    for s in SPLITS:
        assert len(seen[s]) == len(splits[s])  # no duplicate shape inside a split either
    assert not (seen["train"] & seen["val"]) and not (seen["train"] & seen["test"]) and not (seen["val"] & seen["test"])


def test_settings_are_validated(tmp_path):
    for kw, match in [({"split": "dev"}, "split"), ({"rotate": "z"}, "rotate"), ({"num_per_class": (1, 2)}, "num_per_class")]:
        with pytest.raises(ValueError, match=match):
            make(tmp_path, **kw)
    with pytest.raises(KeyError, match="unknown class"):
        build_shape("teapot", 0)
    with pytest.raises(ValueError, match="max_faces"):
        build_shape("mug", 0, max_faces=50)
    with pytest.raises(AssertionError, match="mug_test_0003"):
        synthetic._check("mug_test_0003", np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]), np.array([[0, 1, 2]]))
    with pytest.raises(AssertionError, match="box_val_0001.*degenerate"):
        synthetic._check("box_val_0001", np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.array([[0, 1, 2]]))


# ------------------------------------------------------------------------------- determinism, cache
def test_same_seed_same_data_other_seed_differs(tmp_path, splits):
    a, b = make(tmp_path / "a"), make(tmp_path / "b")
    assert same(a, b) and same(a, splits["test"])
    c = make(tmp_path / "c", seed=1)
    assert all(not torch.equal(x["verts"], y["verts"]) or not torch.equal(x["points"], y["points"])
               for x, y in zip(items(a), items(c)))
    assert [x["name"] for x in items(a)] == [y["name"] for y in items(c)]


def test_second_construction_loads_from_cache(tmp_path, monkeypatch):
    first = make(tmp_path)

    def boom(*a, **k):
        raise AssertionError("generate_split called although the cache is valid")

    monkeypatch.setattr(synthetic, "generate_split", boom)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = make(tmp_path)
    assert same(first, second)
    assert [p.name for p in tmp_path.iterdir()] == [first.cache_path.name]  # no temp files left


def test_other_settings_use_other_cache_files(tmp_path):
    base = make(tmp_path)
    paths = {base.cache_path}
    for kw in ({"rotate": "y"}, {"seed": 3}, {"max_faces": 600}, {"num_points": 64}, {"num_per_class": (3, 1, 1)}):
        paths.add(make(tmp_path, **kw).cache_path)
    assert len(paths) == 6 and all(p.exists() for p in paths)
    # other splits' counts do not change this split's content, so they share its cache
    assert make(tmp_path, num_per_class=(7, 5, 2)).cache_path == base.cache_path


def test_cache_with_other_settings_under_this_name_is_rebuilt(tmp_path):
    good = make(tmp_path / "a")
    other = make(tmp_path / "o", rotate="so3")
    shutil.copy(other.cache_path, good.cache_path)  # a stale file under this setting's name
    with pytest.warns(CacheWarning, match="other settings"):
        again = make(tmp_path / "a")
    assert same(good, again)


@pytest.mark.parametrize("damage", ["truncate", "garbage"])
def test_corrupt_cache_is_detected_and_rebuilt(tmp_path, damage):
    good = make(tmp_path)
    raw = good.cache_path.read_bytes()
    good.cache_path.write_bytes(raw[: len(raw) // 2] if damage == "truncate" else b"not a zip file" * 100)
    with pytest.warns(CacheWarning, match="rebuilding"):
        again = make(tmp_path)
    assert same(good, again)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the rebuilt file is whole again
        assert same(good, make(tmp_path))


def test_readable_but_inconsistent_cache_is_rebuilt(tmp_path):
    good = make(tmp_path)
    with np.load(good.cache_path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["faces"] = arrays["faces"] + 10_000  # indices past each shape's vertices
    with open(good.cache_path, "wb") as fh:
        np.savez(fh, **arrays)
    with pytest.warns(CacheWarning, match="inconsistent"):
        again = make(tmp_path)
    assert same(good, again)


# ------------------------------------------------------------------------------- geometry
@pytest.mark.parametrize("rotate", ["none", "so3"])
def test_geometry_is_clean_normalised_and_points_lie_on_the_surface(tmp_path, rotate):
    ds = make(tmp_path, rotate=rotate, max_faces=1200)
    for it in items(ds):
        v, f, p, R = it["verts"].double(), it["faces"], it["points"].double(), it["rotation"].double()
        name = it["name"]
        assert it["verts"].dtype == it["points"].dtype == torch.float32 and f.dtype == torch.int64
        assert torch.isfinite(v).all() and torch.isfinite(p).all(), name
        assert abs(v.norm(dim=1).max().item() - 1) < 1e-5, name
        canon = v @ R  # verts = canonical @ R^T; the canonical bounding box is centred
        assert ((canon.max(0).values + canon.min(0).values) / 2).abs().max() < 1e-5, name
        assert torch.allclose(R @ R.T, torch.eye(3, dtype=R.dtype), atol=1e-5) and torch.det(R) > 0
        assert f.min() >= 0 and f.max() < len(v) and len(f) <= 1200, name
        t = v[f]
        area = torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]).norm(dim=1) / 2
        assert (area > 0).all() and area.sum() > 0.1, name
        assert p.shape == (NPTS, 3) and (p.norm(dim=1) <= 1 + 1e-5).all(), name
        d = on_surface_distance(p[::4].numpy(), v.numpy(), f.numpy())
        assert d.max() < 1e-5, (name, d.max())
    # the distance check itself can fail: points pulled towards the centre leave the surface
    it = ds[0]
    assert on_surface_distance(0.8 * it["points"][:32].numpy(), it["verts"].numpy(), it["faces"].numpy()).max() > 1e-3


def test_rotate_y_keeps_the_height_profile_so3_changes_it(tmp_path):
    ds = {r: make(tmp_path, "val", rotate=r) for r in ("none", "y", "so3")}
    turned = 0
    for a, b, c in zip(items(ds["none"]), items(ds["y"]), items(ds["so3"])):
        ya, yb, yc = (torch.sort(x["verts"][:, 1]).values for x in (a, b, c))
        assert torch.allclose(ya, yb, atol=1e-5), a["name"]
        assert (ya - yc).abs().max() > 1e-2, a["name"]
        assert torch.equal(a["faces"], b["faces"])
        assert torch.allclose(b["verts"] @ b["rotation"], a["verts"], atol=1e-5)  # same shape, turned
        turned += int(not torch.allclose(a["verts"], b["verts"], atol=1e-3))
    assert turned == len(ds["y"])


# ------------------------------------------------------------------------------- view choice matters
def pair(cls_a, cls_b, seed):
    """Raw instances of two classes drawn from the same generator, normalised by one common transform."""
    (va, fa), (vb, fb) = build_shape(cls_a, seed), build_shape(cls_b, seed)
    both = np.concatenate([va, vb])
    centre = (both.max(0) + both.min(0)) / 2
    r = np.linalg.norm(both - centre, axis=1).max()
    return [torch.tensor((v - centre) / r, dtype=torch.float32) for v in (va, vb)], [torch.tensor(f) for f in (fa, fb)]


def render_pairs(cls_a, cls_b, azim, elev, **renderer):
    """Images of (a, b) for seeds 0..2: two tensors ``[3, M, 3 or 1, 32, 32]``."""
    verts, faces = zip(*(pair(cls_a, cls_b, s) for s in range(3)))
    meshes = Meshes.from_list([v for vs in verts for v in vs], [f for fs in faces for f in fs])
    B = len(meshes)
    r = MultiViewRenderer(image_size=32, **renderer)
    out = r(meshes, torch.tensor(azim, dtype=torch.float32).repeat(B, 1), torch.tensor(elev, dtype=torch.float32).repeat(B, 1))
    img = out.alpha if renderer.get("shading") == "silhouette" else out.images
    return img[0::2], img[1::2]


def differing_pixels(a, b, tol=1e-4):
    """``[S, M]`` count of pixels that differ between two image stacks ``[S, M, C, H, W]``."""
    return ((a - b).abs() > tol).any(2).flatten(2).sum(-1)


def test_cabinet_handle_shows_only_from_some_directions():
    # silhouettes: along Z (front, back) the handle lies inside the box outline; from the sides it
    # sticks out (from at least one side: perspective can hide it behind a wide box's near face)
    box, cab = render_pairs("box", "cabinet", [0, 180, 90, -90], [0, 0, 0, 0], shading="silhouette")
    n = differing_pixels(box, cab)
    assert (n[:, :2] == 0).all(), n
    assert (n[:, 2:].max(1).values >= 2).all(), n
    # shaded: seen from the front-right and above it shows; from the opposite direction it is hidden
    box, cab = render_pairs("box", "cabinet", [30, 210], [25, -25], shading="flat", specular=0.0)
    n = differing_pixels(box, cab)
    assert (n[:, 0] >= 4).all() and (n[:, 1] == 0).all(), n


def test_mug_handle_hidden_along_the_x_axis():
    can, mug = render_pairs("can", "mug", [0, 180, 90, -90], [0, 0, 0, 0], shading="silhouette")
    n = differing_pixels(can, mug)
    assert (n[:, :2] >= 5).all(), n  # the handle's ring beside the body
    assert (n[:, 2:] <= 1).all(), n  # behind / in front of the body (a polygon rim may flip a pixel)


def test_shelf_is_a_box_in_silhouette_but_open_at_the_front():
    # (no specular term in the shaded check: flat specular uses the face centroid, and the shelf
    # splits the box's outer planes into other triangles)
    box, shelf = render_pairs("box", "shelf", [0, 180, 90, 0], [0, 0, 0, 90], shading="silhouette")
    assert (differing_pixels(box, shelf) == 0).all()
    box, shelf = render_pairs("box", "shelf", [20, 200], [10, -10], shading="flat", specular=0.0)
    n = differing_pixels(box, shelf)
    assert (n[:, 0] >= 10).all() and (n[:, 1] == 0).all(), n


# ------------------------------------------------------------------------------- collate
@pytest.mark.parametrize("workers", [0, 2])
def test_collate_in_a_dataloader(splits, workers):
    ds = splits["train"]
    loader = DataLoader(ds, batch_size=4, shuffle=False, num_workers=workers, collate_fn=collate_shapes)
    batches = list(loader)
    assert len(batches) == (len(ds) + 3) // 4
    batch = batches[1]
    expect = [ds[i] for i in range(4, 8)]
    meshes = batch["meshes"]
    assert isinstance(meshes, Meshes) and len(meshes) == 4
    assert meshes.faces_per_shape.tolist() == [len(it["faces"]) for it in expect]
    assert meshes.verts_per_shape.tolist() == [len(it["verts"]) for it in expect]
    assert torch.equal(meshes.verts, torch.cat([it["verts"] for it in expect]))
    assert meshes.faces[: len(expect[0]["faces"])].equal(expect[0]["faces"])
    assert batch["points"].shape == (4, NPTS, 3) and batch["points"].dtype == torch.float32
    assert batch["labels"].shape == (4,) and batch["labels"].dtype == torch.long
    assert batch["labels"].tolist() == [it["label"] for it in expect]
    assert batch["names"] == meshes.names == [it["name"] for it in expect]
    assert batch["rotations"].shape == (4, 3, 3)


def test_collate_points_only(tmp_path):
    ds = make(tmp_path, "val", as_points=True)
    assert "verts" not in ds[0] and ds[0]["points"].shape == (NPTS, 3)
    batch = collate_shapes([ds[i] for i in range(3)])
    assert batch["meshes"] is None and batch["points"].shape == (3, NPTS, 3)


def test_a_root_holding_anything_but_caches_is_refused_untouched(tmp_path):
    """The synthetic root is a cache folder: a real dataset's folder passed by mistake is refused
    before anything is written there."""
    real = tmp_path / "ModelNet10"
    (real / "chair").mkdir(parents=True)
    with pytest.raises(ValueError, match="'chair', which is not a synthetic cache file"):
        make(real)
    assert [p.name for p in real.iterdir()] == ["chair"]
    ok = make(tmp_path / "cache")  # caches only (and their temp files): fine
    assert ok.cache_path.parent == tmp_path / "cache"
