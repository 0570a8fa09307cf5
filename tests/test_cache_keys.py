"""What a dataset cache holds is decided by its key: a strict run is strict whatever ran before, a
file edited in place (size and modification time put back) rebuilds it, each skipped file is
reported once and counted once, a cache write on a full disk is one line naming the file and leaves
no lock or temp file behind, and a mesh file with vertices but no faces says how many it has."""
from __future__ import annotations

import errno
import json
import logging
import os
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest

from mvtn_exp.data import mesh_io, modelnet, packed
from mvtn_exp.data.mesh_io import ShapeFileError
from mvtn_exp.data.modelnet import ModelNetMeshes
from mvtn_exp.data.packed import CacheWarning

from test_modelnet import BOX_F, BOX_V, _off

ROOT = Path(__file__).resolve().parents[1]
NAN = "chair/train/chair_0101.off"
FLAT = "chair/train/chair_0102.off"  # one face, zero area
NO_FACES = "airplane/test/airplane_0103.off"  # 3 vertices, 0 faces


def _tree(root: Path) -> Path:
    """2 classes x (2 train, 2 test) boxes, and the three bad files: 2 in train, 1 in test."""
    for c, cls in enumerate(("chair", "airplane")):
        for split in ("train", "test"):
            d = root / cls / split
            d.mkdir(parents=True)
            for k in range(2):
                (d / f"{cls}_{k + 1:04d}.off").write_text(_off(BOX_V * (1 + k + c), BOX_F))
    nan = BOX_V.copy()
    nan[3, 1] = np.nan
    (root / NAN).write_text(_off(nan, BOX_F))
    (root / FLAT).write_text(_off(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), [[0, 1, 2]]))
    (root / NO_FACES).write_text("OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n")
    return root


@pytest.fixture()
def tree(tmp_path):
    return _tree(tmp_path / "ModelNet")


def _reasons(tree: Path) -> dict[str, str]:
    return {NAN: f"{tree / NAN}: 1 vertices are NaN or Inf",
            FLAT: f"{tree / FLAT}: all 1 faces have zero area",
            NO_FACES: f"{tree / NO_FACES}: 3 vertices and no faces; expected a triangle mesh (a point cloud? use a "
                      "point file)"}


def _load(tree, cache, split, **kw):
    """As ``dataset=modelnet40`` builds it (``<cache_dir>/modelnet``), 64 points a shape."""
    return ModelNetMeshes(tree, split, cache_dir=cache / "modelnet", num_points=64, progress=False, **kw)


def _leftovers(cache: Path) -> list[str]:
    return sorted(p.name for p in cache.rglob("*") if p.name.endswith((".lock", ".tmp", ".tmp.npz")))


def _no_preprocessing(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("preprocessed again: the cache was not used")

    monkeypatch.setattr(modelnet, "preprocess", refuse)


def _prepare(args, cwd=ROOT, code: str | None = None):
    """``mvtn-prepare ARGS`` in a fresh process (``code``: Python run first, e.g. a monkeypatch)."""
    entry = ["-m", "mvtn_exp.cli.prepare"] if code is None else [
        "-c", code + "\nimport sys\nsys.argv = ['mvtn-prepare', *sys.argv[1:]]\n"
                     "from mvtn_exp.cli.prepare import main\nmain()"]
    return subprocess.run([sys.executable, *entry, *args], cwd=cwd, capture_output=True, text=True, timeout=120)


# ---------------------------------------------------------------- strict is strict, warm or cold
def test_strict_after_a_lenient_run_refuses_with_the_cold_line(tree, tmp_path, monkeypatch):
    with pytest.raises(ShapeFileError) as cold:
        _load(tree, tmp_path / "cold", "train", strict=True)
    assert str(cold.value) == _reasons(tree)[NAN]  # the first bad file, in file order
    assert not _leftovers(tmp_path / "cold")  # no lock file left by the refused build
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        lenient = _load(tree, tmp_path / "cache", "train")
        test = _load(tree, tmp_path / "cache", "test")
    assert lenient.skipped == [_reasons(tree)[NAN], _reasons(tree)[FLAT]]
    assert test.skipped == [_reasons(tree)[NO_FACES]]
    _no_preprocessing(monkeypatch)  # what follows is decided by the cache alone
    for split in ("train", "val"):
        with pytest.raises(ShapeFileError) as warm:
            _load(tree, tmp_path / "cache", split, strict=True)
        assert str(warm.value) == str(cold.value)
    with pytest.raises(ShapeFileError, match="3 vertices and no faces"):
        _load(tree, tmp_path / "cache", "test", strict=True)


def test_a_cache_that_skipped_nothing_serves_strict_runs(tree, tmp_path, monkeypatch):
    for bad in (NAN, FLAT, NO_FACES):
        (tree / bad).unlink()
    built = _load(tree, tmp_path / "cache", "test")
    _no_preprocessing(monkeypatch)
    again = _load(tree, tmp_path / "cache", "test", strict=True)
    assert again.cache_path == built.cache_path and again.names == built.names and not again.skipped


def test_cli_strict_after_lenient_exits_2_with_the_one_line(tree, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        _load(tree, tmp_path / "cache", "train")  # the lenient run, as mvtn-prepare would have built it
    r = _prepare(["dataset=modelnet40", f"dataset.root={tree}", f"dataset.cache_dir={tmp_path / 'cache'}",
                  "dataset.num_points=64", "dataset.strict=true", "logger.progress=false",
                  f"hydra.run.dir={tmp_path / 'run'}"])
    assert r.returncode == 2, r.stderr[-2000:]
    assert r.stderr.strip().splitlines() == [f"mvtn-prepare: error: {_reasons(tree)[NAN]}"]
    assert "Traceback" not in r.stdout + r.stderr and not _leftovers(tmp_path / "cache")


# ---------------------------------------------------------------- each skipped file once, counted once
def test_each_skipped_file_is_one_log_line_and_no_warning(tree, tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="mvtn_exp.data")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a warning (with its source line) would fail here
        warnings.simplefilter("ignore", modelnet.CountWarning)
        for split in ("train", "val", "test"):
            _load(tree, tmp_path / "cache", split)
    lines = [r.getMessage() for r in caplog.records]
    for bad, reason in _reasons(tree).items():
        assert [line for line in lines if bad.rsplit("/", 1)[1] in line] == [f"skipping {reason}"], lines
    assert sum("skipped 2 of 6 shapes" in line for line in lines) == 1
    assert sum("skipped 1 of 5 shapes" in line for line in lines) == 1


def test_prepare_counts_three_bad_files_as_three(tree, tmp_path, capsys):
    from mvtn_exp.cli.prepare import prepare
    from mvtn_exp.config.schema import as_config

    cfg = as_config({"dataset": {"name": "modelnet40", "root": str(tree), "cache_dir": str(tmp_path / "cache"),
                                 "num_points": 64}, "logger": {"progress": False}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", modelnet.CountWarning)
        summary = prepare(cfg)
    out = capsys.readouterr().out.splitlines()
    assert [line.split(", ")[-1] for line in out[:3]] == ["2 skipped", "0 skipped", "1 skipped"]
    assert out[3] == "3 skipped in all"
    assert sorted(summary["skipped"]) == sorted(_reasons(tree).values())
    assert sum(len(s["skipped"]) for s in summary["splits"].values()) == 3


def test_prepare_cli_reports_each_bad_file_once(tree, tmp_path):
    r = _prepare(["dataset=modelnet40", f"dataset.root={tree}", f"dataset.cache_dir={tmp_path / 'cache'}",
                  "dataset.num_points=64", "logger.progress=false", f"hydra.run.dir={tmp_path / 'run'}"])
    assert r.returncode == 0, r.stderr[-2000:]
    text = r.stdout + r.stderr
    assert "Warning" not in text and "warnings.warn" not in text
    for bad in (NAN, FLAT, NO_FACES):
        assert text.count(str(tree / bad)) == 1, (bad, text)
    assert "3 skipped in all" in r.stdout.splitlines()
    assert len(json.loads((tmp_path / "run" / "prepare.json").read_text())["skipped"]) == 3


def test_train_and_val_of_one_h5_file_report_a_bad_row_once(tmp_path, caplog):
    from mvtn_exp.data.scanobjectnn import ScanObjectNN
    from test_scanobjectnn import _clouds, _write

    data = _clouds(30, 0)
    data[3, 0, 0] = np.nan
    root = tmp_path / "ScanObjectNN"
    _write(root / "main_split" / "training_objectdataset.h5", 30, 0, data=data)
    caplog.set_level(logging.WARNING, logger="mvtn_exp.data")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", modelnet.CountWarning)
        train = ScanObjectNN(root, "train", variant="obj_bg")
        val = ScanObjectNN(root, "val", variant="obj_bg")
    assert train.skipped == val.skipped and len(train.skipped) == 1
    assert [r.getMessage() for r in caplog.records if "row 3" in r.getMessage()] == [f"skipping {train.skipped[0]}"]


# ---------------------------------------------------------------- the key holds the files' bytes
def _edit_in_place(path: Path, old: str, new: str) -> None:
    """Replace ``old`` by ``new`` (same length) in ``path``, then put its modification time back."""
    assert len(old) == len(new)
    st = path.stat()
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    after = path.stat()
    assert (after.st_size, after.st_mtime_ns) == (st.st_size, st.st_mtime_ns)


def test_a_file_edited_in_place_with_size_and_mtime_kept_rebuilds(tree, tmp_path, monkeypatch):
    one = tree / "chair" / "test" / "chair_0001.off"  # BOX_V as is: z spans 0 .. 2
    before = _load(tree, tmp_path / "cache", "test")
    _edit_in_place(one, "2.000000", "7.000000")  # the box 3.5 times as tall, same bytes count
    calls = []
    real = modelnet.preprocess
    monkeypatch.setattr(modelnet, "preprocess", lambda path, *a, **k: calls.append(path.name) or real(path, *a, **k))
    after = _load(tree, tmp_path / "cache", "test")
    assert after.cache_path != before.cache_path and calls  # rebuilt
    i = after.names.index("chair_0001")
    height = lambda ds: float(np.ptp(ds[i]["verts"].numpy()[:, 1]) / np.ptp(ds[i]["verts"].numpy()[:, 0]))
    assert height(after) == pytest.approx(3.5 * height(before), rel=1e-4)  # the new content (file Z is our Y)


def test_the_digest_memo_reads_only_changed_files(tree, tmp_path, monkeypatch):
    monkeypatch.setattr(packed, "RACY_NS", 0)  # (the tree is seconds old: trust its change times at once)
    files = sorted(tree.rglob("*.off"))
    read = []
    real = packed.file_digest
    monkeypatch.setattr(packed, "file_digest", lambda p: read.append(Path(p).name) or real(p))
    first = packed.files_fingerprint(files, tree, tmp_path / "cache")
    assert len(read) == len(files)
    read.clear()
    assert packed.files_fingerprint(files, tree, tmp_path / "cache") == first and read == []  # a warm start
    one = tree / "chair" / "test" / "chair_0001.off"
    _edit_in_place(one, "2.000000", "7.000000")  # size and modification time put back: the change time moved
    edited = packed.files_fingerprint(files, tree, tmp_path / "cache")
    assert read == [one.name] and edited != first
    assert edited == packed.files_fingerprint(files, tree)  # the same key as reading every file


def test_a_file_changed_within_the_clock_tick_is_read_again(tree, tmp_path, monkeypatch):
    files = sorted(tree.rglob("*.off"))  # just written: each is racy
    packed.files_fingerprint(files, tree, tmp_path / "cache")
    read = []
    real = packed.file_digest
    monkeypatch.setattr(packed, "file_digest", lambda p: read.append(Path(p).name) or real(p))
    packed.files_fingerprint(files, tree, tmp_path / "cache")
    assert len(read) == len(files)


def test_a_touched_file_keeps_its_cache(tree, tmp_path, monkeypatch):
    before = _load(tree, tmp_path / "cache", "test")
    one = tree / "chair" / "test" / "chair_0001.off"
    st = one.stat()
    os.utime(one, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # same bytes, a new time
    _no_preprocessing(monkeypatch)
    assert _load(tree, tmp_path / "cache", "test").cache_path == before.cache_path


def test_a_cache_of_the_old_key_scheme_is_rebuilt_not_misread(tree, tmp_path):
    built = _load(tree, tmp_path / "cache", "test")
    with np.load(built.cache_path) as z:
        arrays = {k: z[k] for k in z.files if k != "settings"}
        settings = json.loads(str(z["settings"]))
    settings.update(version="1", files="0" * 40)  # as the previous code keyed it (sizes and times)
    packed.save_npz_atomic(built.cache_path, arrays, settings)
    with pytest.warns(CacheWarning, match="other settings"):
        again = _load(tree, tmp_path / "cache", "test")
    with np.load(again.cache_path) as z:
        assert json.loads(str(z["settings"]))["version"] == modelnet.PREP_VERSION


# ---------------------------------------------------------------- a full disk
def _enospc(*a, **k):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_on_the_cache_write_names_it_and_leaves_no_lock(tree, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setattr(np, "savez_compressed", _enospc)
    with pytest.raises(OSError) as err:
        _load(tree, cache, "test")
    assert err.value.errno == errno.ENOSPC and err.value.filename.endswith(".npz")
    target = Path(err.value.filename)
    assert target.parent == cache / "modelnet" and target.with_suffix(".parts").is_dir()  # finished shapes kept
    assert not _leftovers(cache) and not target.exists()
    monkeypatch.undo()
    done = []
    real = modelnet.preprocess
    monkeypatch.setattr(modelnet, "preprocess", lambda path, *a, **k: done.append(path.name) or real(path, *a, **k))
    ds = _load(tree, cache, "test")
    assert ds.cache_path == target and len(ds) == 4 and done == [Path(NO_FACES).name]  # resumed: only the skip redone


def test_a_full_disk_on_a_part_names_it_and_leaves_no_temp_file(tree, tmp_path, monkeypatch):
    monkeypatch.setattr(np, "savez", _enospc)
    with pytest.raises(OSError) as err:
        _load(tree, tmp_path / "cache", "test")
    assert err.value.errno == errno.ENOSPC and Path(err.value.filename).parent.suffix == ".parts"
    assert not _leftovers(tmp_path / "cache")


def test_cli_full_disk_is_one_line_naming_the_cache(tree, tmp_path):
    patch = "import errno, os, numpy as np\n" \
            "def full(*a, **k):\n    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))\n" \
            "np.savez_compressed = full"
    r = _prepare(["dataset=modelnet40", f"dataset.root={tree}", f"dataset.cache_dir={tmp_path / 'cache'}",
                  "dataset.num_points=64", "logger.progress=false", f"hydra.run.dir={tmp_path / 'run'}"], code=patch)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(err) == 1, r.stderr[-2000:]
    cache = next((tmp_path / "cache" / "modelnet").glob("*.parts")).with_suffix(".npz")
    assert err[0].startswith(f"mvtn-prepare: error: no space left on the device (writing {cache})")
    assert not _leftovers(tmp_path / "cache")


@pytest.fixture()
def small_disk(tmpfs):
    """A 12 KiB tmpfs: room for a few shapes' parts, not for a split's cache."""
    return tmpfs("12k")


def test_a_real_full_disk_names_the_file_and_leaves_no_lock(tree, small_disk):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        with pytest.raises(OSError) as err:
            _load(tree, small_disk, "train")
    assert err.value.errno == errno.ENOSPC and str(small_disk) in err.value.filename
    assert not _leftovers(small_disk)


def test_a_waiter_whose_lock_file_went_locks_the_new_one(tmp_path):
    path = tmp_path / "c.npz"
    held, order = threading.Event(), []

    def first():
        with packed.cache_lock(path):
            held.set()
            order.append("first in")
            threading.Event().wait(0.3)  # the second waits on this lock file meanwhile
            order.append("first out")

    t = threading.Thread(target=first)
    t.start()
    held.wait(10)
    with packed.cache_lock(path):  # its lock file is removed by the first: it locks a new one
        order.append("second in")
    t.join(10)
    assert order == ["first in", "first out", "second in"]
    assert not path.with_name("c.npz.lock").exists()


def test_shapenet_strict_after_lenient_refuses_with_the_cold_line(tmp_path, monkeypatch):
    from mvtn_exp.data import shapenet
    from test_shapenet import _load as load_shapenet
    from test_shapenet import _tree as shapenet_tree

    tree = shapenet_tree(tmp_path / "ShapeNetCore.v2")
    bare = tree / "02747177" / "0c9d8e7f" / "models" / "model_normalized.obj"
    bare.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")  # a test-split OBJ with 3 vertices, no faces
    reason = f"{bare}: 3 vertices and no faces; expected a triangle mesh (a point cloud? use a point file)"
    with pytest.raises(ShapeFileError) as cold:
        load_shapenet(tree, tmp_path / "cold", "test", strict=True)
    assert str(cold.value) == reason
    assert load_shapenet(tree, tmp_path, "test").skipped == [reason]
    monkeypatch.setattr(shapenet, "preprocess", lambda *a, **k: pytest.fail("preprocessed again"))
    with pytest.raises(ShapeFileError) as warm:
        load_shapenet(tree, tmp_path, "test", strict=True)
    assert str(warm.value) == reason


# ---------------------------------------------------------------- no faces: the real vertex count
@pytest.mark.parametrize("name,text", [("bare.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
                                       ("bare.off", "OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n")])
def test_a_mesh_file_without_faces_says_how_many_vertices_it_has(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(ShapeFileError) as err:
        mesh_io.read_mesh(p)
    assert str(err.value) == f"{p}: 3 vertices and no faces; expected a triangle mesh (a point cloud? use a point file)"


def test_a_lock_file_released_while_the_cache_root_is_checked_is_no_stranger(tmp_path, monkeypatch):
    """Two runs starting at once on a cold cache: one lists the root while the other's
    ``.npz.lock`` is there and checks it once it is gone; the check passes over it."""
    from pathlib import Path

    from mvtn_exp.data.synthetic_cache import check_cache_root

    (tmp_path / "synthetic_train_0123.npz").write_bytes(b"")
    gone = tmp_path / "synthetic_val_0123.npz.lock"  # listed, then released (removed) by the other run
    listing = Path.iterdir
    monkeypatch.setattr(Path, "iterdir", lambda self: iter([*listing(self), gone]))
    check_cache_root(tmp_path, "synthetic")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match="holds 'notes.txt', which is not a synthetic cache file"):
        check_cache_root(tmp_path, "synthetic")
