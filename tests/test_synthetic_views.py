"""The view-dependent synthetic dataset: classes, determinism, cache, geometry, uniform poses, the
detail as the only class difference, the visibility criterion (against ray casting and renders),
points, Hydra."""
import warnings

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf
from test_synthetic import on_surface_distance

from mvtn_exp.data import synthetic_views as sv

from mvtn_exp.data import view_detail as vd
from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.datasets import build_dataset
from mvtn_exp.data.synthetic import CacheWarning, random_rotation
from mvtn_exp.data.synthetic_views import CLASSES, SPLITS, SyntheticViews
from mvtn_exp.config.store import register_configs

COUNTS = (3, 1, 4)
NPTS = 128
ARRAYS = ("verts", "faces", "points", "labels", "rotations", "detail_anchor", "detail_axis", "detail_size")


def make(root, split="test", **kw):
    kw = {"num_per_class": COUNTS, "num_points": NPTS, "progress": False, **kw}
    return SyntheticViews(root, split, **kw)


@pytest.fixture(scope="module")
def splits(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic_views")
    return {s: make(root, s) for s in SPLITS}


def same(a, b):
    return all(np.array_equal(a._a[k], b._a[k]) for k in ARRAYS)


def canonical(ds, i):
    """Shape i's verts and detail frame back in the canonical pose (verts = canonical @ R^T)."""
    R = ds._a["rotations"][i].astype(np.float64)
    it = ds[i]
    return (it["verts"].double().numpy() @ R, ds._a["detail_anchor"][i] @ R, ds._a["detail_axis"][i] @ R)


# ------------------------------------------------------------------------------- classes, settings
def test_classes_counts_and_names(splits):
    assert CLASSES == sorted(set(CLASSES)) and len(CLASSES) == 8 and "empty" in CLASSES
    names = []
    for s, n in zip(SPLITS, COUNTS):
        ds = splits[s]
        assert ds.classes == CLASSES and len(ds) == n * len(CLASSES)
        assert np.bincount(ds.labels, minlength=len(CLASSES)).tolist() == [n] * len(CLASSES)
        for i in range(len(ds)):
            assert ds.names[i].rsplit("_", 2)[:2] == [CLASSES[ds.labels[i]], s]
        names += ds.names
    assert len(set(names)) == len(names)


def test_settings_are_validated(tmp_path):
    for kw, match in [({"split": "dev"}, "split"), ({"rotate": "z"}, "rotate"), ({"num_per_class": (1, 2)}, "num_per_class"),
                      ({"num_points": 0}, "num_points")]:
        with pytest.raises(ValueError, match=f"synthetic_views: .*{match}"):
            make(tmp_path, **kw)
    with pytest.raises(KeyError, match="unknown class"):
        sv.make_shape("knob", 0, np.eye(3))


# ------------------------------------------------------------------------------- determinism, cache
def test_same_seed_same_data_other_seed_differs(tmp_path, splits):
    a, b = make(tmp_path / "a"), make(tmp_path / "b")
    assert same(a, b) and same(a, splits["test"])
    c = make(tmp_path / "c", seed=1)
    assert a.names == c.names
    for k in ("points", "rotations", "detail_axis", "detail_size"):
        assert not np.isclose(a._a[k], c._a[k]).all(axis=tuple(range(1, a._a[k].ndim))).any(), k  # every shape differs


def test_second_construction_loads_from_cache(tmp_path, monkeypatch):
    first = make(tmp_path)

    def boom(*a, **k):
        raise AssertionError("generate_split called although the cache is valid")

    monkeypatch.setattr(sv, "generate_split", boom)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = make(tmp_path)
    assert same(first, second) and first.cache_path.name.startswith("synthetic_views_test_")
    assert [p.name for p in tmp_path.iterdir()] == [first.cache_path.name]


def test_other_settings_use_other_cache_files_and_corrupt_ones_are_rebuilt(tmp_path):
    base = make(tmp_path)
    paths = {base.cache_path} | {make(tmp_path, **kw).cache_path for kw in ({"rotate": "none"}, {"seed": 2}, {"num_points": 32})}
    assert len(paths) == 4
    assert make(tmp_path, num_per_class=(9, 9, COUNTS[2])).cache_path == base.cache_path  # other splits' counts
    base.cache_path.write_bytes(base.cache_path.read_bytes()[:500])
    with pytest.warns(CacheWarning, match="rebuilding"):
        assert same(base, make(tmp_path))


# ------------------------------------------------------------------------------- geometry
def test_shapes_are_clean_centred_in_the_unit_sphere_and_carry_their_detail_frame(splits):
    ds = splits["test"]
    for i in range(len(ds)):
        it, name = ds[i], ds.names[i]
        v, f, p = it["verts"].double(), it["faces"], it["points"].double()
        assert torch.isfinite(v).all() and abs(v.norm(dim=1).max().item() - 1) < 1e-5, name
        assert f.min() >= 0 and f.max() < len(v) and len(f) <= 2000, name
        R = it["rotation"].double()
        assert torch.allclose(R @ R.T, torch.eye(3, dtype=R.dtype), atol=1e-5) and torch.det(R) > 0.99, name
        cv, anchor, axis = canonical(ds, i)
        assert np.abs((cv.max(0) + cv.min(0)) / 2).max() < 1e-5, name  # bounding box centred
        # the frame: the cup axis is canonical +Z, the floor centre on it, the rim at the top of the box
        r_in, h, rd = ds._a["detail_size"][i]
        assert np.allclose(axis, [0, 0, 1], atol=1e-5) and np.allclose(anchor[:2], 0, atol=1e-5), name
        assert abs(anchor[2] + h - cv[:, 2].max()) < 1e-5 and 0 < rd < r_in and h > 0, name
        assert p.shape == (NPTS, 3) and on_surface_distance(p[::4].numpy(), v.numpy(), f.numpy()).max() < 1e-5, name


def test_detail_axis_is_spread_over_the_sphere(splits, tmp_path):
    axes = np.concatenate([splits[s]._a["detail_axis"] for s in SPLITS])  # 64 shapes
    assert np.allclose(np.linalg.norm(axes, axis=1), 1, atol=1e-5)
    assert np.linalg.norm(axes.mean(0)) < 0.3  # |mean| of n uniform unit vectors: about sqrt(1 / n) = 0.125
    octants = {tuple(x) for x in (axes > 0).astype(int)}
    assert len(octants) == 8
    for c in range(3):  # each coordinate of a uniform direction is uniform on [-1, 1]
        assert 0.3 < (np.abs(axes[:, c]) < 0.5).mean() < 0.7, c
    fixed = make(tmp_path, "val", rotate="none")._a["detail_axis"]  # and the test can fail: unrotated, all +Z
    assert np.allclose(fixed, [0, 0, 1], atol=1e-6)


def test_the_detail_is_the_only_class_difference(splits):
    # one generator gives every class the same body, cup and normalisation: the shapes agree on
    # every vertex and face of the body and cup, and differ only in the parts added after them
    R = random_rotation("so3", np.random.default_rng(5))
    base_v, base_f, *base_frame = sv.make_shape("empty", 11, R)
    extra = []
    for cls in CLASSES:
        v, f, *frame = sv.make_shape(cls, 11, R)
        assert np.array_equal(v[: len(base_v)], base_v) and np.array_equal(f[: len(base_f)], base_f), cls
        assert all(np.array_equal(a, b) for a, b in zip(frame, base_frame)), cls
        extra.append(len(f) - len(base_f))
    assert extra[CLASSES.index("empty")] == 0 and sorted(extra)[1] > 0
    # over the dataset, the body and cup proportions of every class overlap those of every other
    feats = {c: [] for c in CLASSES}
    for ds in splits.values():
        for i in range(len(ds)):
            cv, anchor, _ = canonical(ds, i)
            feats[CLASSES[ds.labels[i]]].append([*np.sort(np.ptp(cv, 0)), *ds._a["detail_size"][i][:2], anchor[2]])
    lo = np.array([np.min(feats[c], 0) for c in CLASSES])
    hi = np.array([np.max(feats[c], 0) for c in CLASSES])
    assert (lo.max(0) < hi.min(0)).all(), (lo, hi)


# ------------------------------------------------------------------------------- visibility
def hits(origins, targets, verts, faces, eps=1e-9):
    """``[R]`` bool: the segment origin -> target crosses a triangle (Moeller-Trumbore, float64)."""
    t = verts.astype(np.float64)[faces]
    a, e1, e2 = t[:, 0], t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    d = (targets - origins)[:, None]  # [R, 1, 3]
    p = np.cross(d, e2[None])
    det = (p * e1[None]).sum(-1)
    ok = np.abs(det) > eps
    det = np.where(ok, det, 1.0)
    s = origins[:, None] - a[None]
    u = (s * p).sum(-1) / det
    q = np.cross(s, e1[None])
    w = (d * q).sum(-1) / det
    tt = (q * e2[None]).sum(-1) / det
    return (ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (tt > 1e-7) & (tt < 1)).any(1)


@pytest.mark.parametrize("family", ["cup", "slab"])
def test_sees_detail_agrees_with_ray_casting_against_the_cup(family):
    """The criterion against ray casting on the empty twin's mesh; on the slab, a line that clears
    the detail cup's own rim must also clear the slab and the other three cups."""
    rng = np.random.default_rng(0)
    cams = rng.normal(size=(400, 3))
    cams = 2.2 * cams / np.linalg.norm(cams, axis=1, keepdims=True)
    checked = seen = 0
    for k in range(4):
        R = random_rotation("so3", rng)
        v, f, anchor, axis, size = sv.make_shape("empty", 100 + k, R, family=family)  # no detail over the floor centre
        vis = vd.sees_detail(anchor[None], axis[None], size[None], cams)[0]
        blocked = hits(np.repeat(anchor[None] + 1e-6 * axis, len(cams), 0), cams, v, f)
        # leave out the lines that pass within the 24-gon's rim band (inscribed circle .. corners)
        d = cams - anchor
        up = d @ axis
        drift = size[1] * np.linalg.norm(d - up[:, None] * axis, axis=1) / np.maximum(up, 1e-9)
        clear = (up <= size[1]) | (drift < size[0] * 0.999) | (drift > size[0] / np.cos(np.pi / 24) * 1.001)
        assert np.array_equal(vis[clear], ~blocked[clear]), k
        checked, seen = checked + clear.sum(), seen + vis.sum()
    assert checked > 1500 and 0.1 < seen / (4 * len(cams)) < 0.4


def test_one_fixed_view_sees_the_detail_at_most_half_the_time(splits):
    rows = {(r["layout"], r["M"]): r for r in vd.visibility_table(splits["test"], poses=50)}
    for layout in ("circular", "spherical"):
        one = rows[(layout, 1)]
        assert 0.05 < one["seen"] <= 0.5 and 0.1 < one["seen_mc"] <= 0.4, one
        assert one["seen_full"] <= one["seen"]
        assert rows[(layout, 1)]["seen_mc"] <= rows[(layout, 4)]["seen_mc"] <= rows[(layout, 12)]["seen_mc"]
    assert rows[("spherical", 12)]["seen_mc"] > 0.95  # 12 spread views: some view always finds it
    assert rows[("circular", 12)]["seen_mc"] < 0.9  # a ring at 30 deg misses cups pointing up or down


def test_renders_show_the_detail_exactly_when_the_criterion_says(splits):
    ds = splits["test"]
    axis = ds._a["detail_axis"].astype(np.float64)
    # a camera on the cup axis, one 80 deg away from it, and the default fixed view
    side = np.cross(axis, [[0.0, 1.0, 0.0]])
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    off = np.cos(np.radians(80)) * axis + np.sin(np.radians(80)) * side
    (a0, e0), (a1, e1) = vd.view_angles(axis), vd.view_angles(off)
    azim = np.stack([a0, a1, np.zeros(len(ds))], 1)
    elev = np.stack([e0, e1, np.full(len(ds), 30.0)], 1)
    traces = vd.rendered_traces(ds, azim, elev)
    expect = vd.sees_detail(ds._a["detail_anchor"], axis, ds._a["detail_size"], vd.camera_positions(azim, elev))
    detail = ds.labels != CLASSES.index("empty")
    assert expect[:, 0].all() and not expect[:, 1].any()
    assert (traces[detail, 0] >= 5).all(), traces[:, 0]  # seen down the axis, every detail shows
    assert (traces[:, 1] == 0).all() and (traces[~detail] == 0).all(), traces  # hidden behind the rim
    assert (traces[detail & expect[:, 2], 2] >= 3).all(), traces[:, 2]  # the fixed view, where it sees


# ------------------------------------------------------------------------------- points, Hydra
def test_points_mode_and_collate(tmp_path, splits):
    ds = make(tmp_path, "val", as_points=True)
    it = ds[0]
    assert "verts" not in it and it["points"].shape == (NPTS, 3) and it["detail_axis"].shape == (3,)
    assert torch.equal(it["points"], splits["val"][0]["points"])
    batch = collate_shapes([ds[i] for i in range(3)])
    assert batch["meshes"] is None and batch["points"].shape == (3, NPTS, 3) and batch["rotations"].shape == (3, 3, 3)
    meshes = collate_shapes([splits["val"][i] for i in range(3)])["meshes"]
    assert len(meshes) == 3


def _compose(overrides):
    register_configs()
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = compose("train", overrides=overrides)
    return OmegaConf.to_object(cfg).validate()


def test_composes_through_hydra_and_builds(tmp_path):
    cfg = _compose(["dataset=synthetic_views", f"dataset.root={tmp_path}", "dataset.num_per_class=[1,1,2]",
                    "dataset.num_points=64"])
    assert cfg.dataset.name == "synthetic_views" and cfg.dataset.rotate == "so3" and cfg.dataset.shape == "mesh"
    ds = build_dataset(cfg.dataset, "test", progress=False)
    assert isinstance(ds, SyntheticViews) and len(ds) == 2 * len(CLASSES) and ds.settings["rotate"] == "so3"
    assert ds.cache_path.parent == tmp_path
    pts = _compose(["dataset=synthetic_views_points"]).dataset
    assert pts.shape == "points" and pts.rotate == "so3" and pts.root.endswith("cache/synthetic_views")
    assert _compose(["dataset=synthetic_views", "dataset.rotate=y"]).dataset.rotate == "y"  # honoured
    with pytest.raises(ValueError, match="dataset.rotate"):
        _compose(["dataset=synthetic_views", "dataset.rotate=sideways"])


def test_trains_through_the_one_trainer(tmp_path):
    from mvtn_exp.engine import train

    cfg = {"views": 2, "image_size": 32, "epochs": 1, "batch_size": 4, "selector": {"name": "mvtn_spherical"},
           "dataset": {"name": "synthetic_views", "root": str(tmp_path / "cache"), "rotate": "so3",
                       "num_per_class": [1, 1, 1], "num_points": 64},
           "logger": {"progress": False, "tensorboard": False}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        m = train(cfg, tmp_path / "run")
    assert m["classes"] == CLASSES and m["test_size"] == len(CLASSES) and 0 <= m["test_acc"] <= 1


def test_detail_angles_png(tmp_path):
    from mvtn_exp.viz.views import detail_angles_png

    angles = np.random.default_rng(0).uniform(0, 180, (20, 3))
    assert detail_angles_png(angles, tmp_path / "a.png").stat().st_size > 1000
    with pytest.raises(ValueError, match=r"expected angles \[N, M\]"):
        detail_angles_png(np.zeros((0, 2)), tmp_path / "b.png")


# ------------------------------------------------------------------------------- the decoys family
@pytest.fixture(scope="module")
def decoys(tmp_path_factory):
    return make(tmp_path_factory.mktemp("decoys"), "test", family="decoys", num_per_class=(2, 1, 6))


def test_decoys_hide_the_detail_in_one_of_six_identical_cups(decoys):
    from mvtn_exp.data.config import VIEW_FAMILIES

    assert VIEW_FAMILIES == sv.FAMILIES
    faces = set()
    for i in range(len(decoys)):
        cv, anchor, axis = canonical(decoys, i)
        k = int(np.argmax(np.abs(axis)))
        assert np.isclose(abs(axis[k]), 1, atol=1e-5) and np.allclose(np.delete(anchor, k), 0, atol=1e-5)
        r_in, h, _ = decoys._a["detail_size"][i]
        assert abs(anchor[k] * np.sign(axis[k]) + h - np.abs(cv[:, k]).max()) < 1e-5  # its rim: the body's extent
        faces.add((k, np.sign(axis[k])))
    assert len(faces) == 6  # every face holds the detail for some shape
    # the body is the same whichever face holds the detail: the empty class's mesh ignores the face draw
    R = random_rotation("so3", np.random.default_rng(1))
    seeds = [s for s in range(40) if int(sv.draw_family("decoys", np.random.default_rng(s))[1].R[2, 2]) != 1][:2]
    assert len(seeds) == 2
    v0, f0, *_ = sv.make_shape("empty", seeds[0], R, family="decoys")
    assert len(f0) > 6 * 2 * sv.CUP_SECTIONS  # six cups
    for cls in ("cone", "ring"):  # the detail is the only difference to the empty twin
        v, f, *frame = sv.make_shape(cls, seeds[0], R, family="decoys")
        assert np.array_equal(v[: len(v0)], v0) and len(f) > len(f0)


def test_no_principal_axis_points_at_the_decoys_detail(decoys, splits):
    from mvtn_exp.selectors.canonical import pca_frames

    def aligned(ds):
        R = pca_frames(torch.tensor(ds._a["points"].reshape(len(ds), -1, 3), dtype=torch.float64)).numpy()
        cos = np.abs(np.einsum("bki,bi->bk", R, ds._a["detail_axis"].astype(np.float64)))
        return (cos > 0.95).mean(0)  # per canonical axis: shapes whose detail lies along it

    assert aligned(splits["test"])[1] > 0.9  # the cup family: the least-spread axis is the cup's
    assert (aligned(decoys) < 0.5).all()


def test_family_is_checked_and_keys_its_own_cache(tmp_path):
    cup = make(tmp_path, "val")
    assert make(tmp_path, "val", family="decoys").cache_path != cup.cache_path
    with pytest.raises(ValueError, match="dataset.family='cups'"):
        make(tmp_path, "val", family="cups")


# ------------------------------------------------------------------------------- the slab family
@pytest.fixture(scope="module")
def slab(tmp_path_factory):
    return make(tmp_path_factory.mktemp("slab"), "test", family="slab", num_per_class=(2, 1, 6))


def test_slab_hides_the_detail_in_one_of_four_cups_on_its_two_faces(slab):
    cups = set()
    for i in range(len(slab)):
        cv, anchor, axis = canonical(slab, i)
        assert np.isclose(abs(axis[2]), 1, atol=1e-5) and abs(anchor[1]) < 1e-5 and abs(anchor[0]) > 0.1
        r_in, h, _ = slab._a["detail_size"][i]
        assert abs(anchor[2] * np.sign(axis[2]) + h - np.abs(cv[:, 2]).max()) < 1e-5  # its rim: the slab's extent
        # nothing but the detail's own cup rises above its floor plane beyond the rim's height
        up = (cv - anchor) @ axis
        assert up.max() < h + 1e-5
        cups.add((np.sign(anchor[0]), np.sign(axis[2])))
    assert len(cups) == 4  # every cup holds the detail for some shape
    R = random_rotation("so3", np.random.default_rng(1))
    v0, f0, *_ = sv.make_shape("empty", 3, R, family="slab")
    assert len(f0) > 4 * 2 * sv.CUP_SECTIONS  # four cups
    for cls in ("cone", "ring"):  # the body is the same wherever the detail is: it is the only difference
        v, f, *frame = sv.make_shape(cls, 3, R, family="slab")
        assert np.array_equal(v[: len(v0)], v0) and len(f) > len(f0)


def test_slab_one_view_down_the_normal_sees_one_face_only(slab):
    """The principal frame finds the slab's normal, not the face: a canonical view along it sees
    the detail for about half the shapes, the view from the other side for the rest."""
    from mvtn_exp.selectors.canonical import pca_frames

    R = pca_frames(torch.tensor(slab._a["points"].reshape(len(slab), -1, 3), dtype=torch.float64)).numpy()
    axis = slab._a["detail_axis"].astype(np.float64)
    cos = np.einsum("bki,bi->bk", R, axis)
    k = int(np.argmax(np.abs(cos).mean(0)))
    assert (np.abs(cos[:, k]) > 0.95).mean() > 0.9  # one principal axis is the normal
    normal = R[:, k]
    seen = [vd.sees_detail(slab._a["detail_anchor"], axis, slab._a["detail_size"], (s * 2.2 * normal)[:, None]).mean()
            for s in (1, -1)]
    assert 0.2 < seen[0] < 0.8 and abs(seen[0] + seen[1] - 1) < 1e-9, seen


@pytest.mark.parametrize("family", ["decoys", "slab"])
def test_other_families_render_the_detail_exactly_when_the_criterion_says(family, request):
    """A camera on the detail's cup axis shows the detail in every shape, one 80 degrees off it
    shows nothing of it (the rim, the other cups and the body hide it)."""
    ds = request.getfixturevalue(family)
    axis = ds._a["detail_axis"].astype(np.float64)
    side = np.cross(axis, [[0.0, 1.0, 0.0]])
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    off = np.cos(np.radians(80)) * axis + np.sin(np.radians(80)) * side
    (a0, e0), (a1, e1) = vd.view_angles(axis), vd.view_angles(off)
    traces = vd.rendered_traces(ds, np.stack([a0, a1], 1), np.stack([e0, e1], 1))
    detail = ds.labels != CLASSES.index("empty")
    assert (traces[detail, 0] >= 5).all() and (traces[:, 1] == 0).all() and (traces[~detail] == 0).all()
