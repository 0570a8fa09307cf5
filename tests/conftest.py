import os
import sys
from pathlib import Path

if os.environ.get("PYTEST_XDIST_WORKER"):  # `make test` runs one worker per core: one thread each,
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # for this process and the CLIs it starts
        os.environ[_var] = "1"

# tests never touch the network: published weights (``backbone.weights=imagenet``) come from an
# empty mirror folder and a fresh hub cache, so a test that forgets its fixture fails at once, offline
_NO_NET = Path(os.environ.get("TMPDIR", "/tmp")) / f"mvtn-tests-{os.getpid()}"
os.environ.setdefault("MVTN_WEIGHTS_MIRROR", f"file://{_NO_NET}/no-weights-here")
os.environ.setdefault("TORCH_HOME", str(_NO_NET / "torch"))

import pytest  # noqa: E402
import torch  # noqa: E402

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)

sys.path.insert(0, str(Path(__file__).parent))

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real_samples"


@pytest.fixture
def real_samples() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"real samples not found at {SHARED} (../shared/data/real_samples beside the repo)")
    return SHARED


@pytest.fixture()
def tmpfs(tmp_path):
    """``tmpfs("600k")``: a tmpfs of that size under ``tmp_path`` (a full disk on demand), unmounted
    after the test; the test is skipped where this machine does not let us mount one."""
    import subprocess

    mounted = []

    def mount(size: str) -> Path:
        mnt = tmp_path / f"disk{len(mounted)}"
        mnt.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)], capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({(r.stderr or r.stdout).strip() or 'not permitted'})")
        mounted.append(mnt)
        return mnt

    try:
        yield mount
    finally:
        for mnt in mounted:
            subprocess.run(["umount", str(mnt)], capture_output=True)


def icosphere(subdivisions: int, dtype=torch.float32):
    import trimesh

    from mvtn_exp.data.shapes import Meshes

    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    return Meshes.from_list([torch.tensor(s.vertices, dtype=dtype)], [torch.tensor(s.faces)])


def box_mesh(dtype=torch.float32, extents=(1.2, 0.8, 0.5)):
    import trimesh

    from mvtn_exp.data.shapes import Meshes

    b = trimesh.creation.box(extents=extents)
    v = torch.tensor(b.vertices, dtype=dtype)
    return Meshes.from_list([v], [torch.tensor(b.faces)])


def random_triangles(n: int, seed: int, scale: float = 1.0, size: float = 0.5, dtype=torch.float64):
    """n independent random triangles (overlapping, crossing tiles) around the origin."""
    from mvtn_exp.data.shapes import Meshes

    g = torch.Generator().manual_seed(seed)
    centres = (torch.rand(n, 1, 3, generator=g, dtype=dtype) * 2 - 1) * scale
    verts = (centres + (torch.rand(n, 3, 3, generator=g, dtype=dtype) * 2 - 1) * size).reshape(-1, 3)
    faces = torch.arange(3 * n).reshape(n, 3)
    return Meshes.from_list([verts], [faces])


def tiny_config(cache, **kw) -> dict:
    """A tiny config as a nested dict; ``kw`` keys may be dotted (``selector.lr``)."""
    cfg = {"views": 2, "image_size": 32, "epochs": 2, "batch_size": 8, "seed": 0,
           "dataset": {"root": cache, "num_per_class": [4, 2, 2]}, "backbone": {"name": "small_cnn"},
           "logger": {"progress": False, "tensorboard": False}}
    for key, value in kw.items():
        node = cfg
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return cfg


def injected(tmp_path: Path, code: str) -> dict:
    """The environment for a CLI subprocess that runs ``code`` at start-up (a ``sitecustomize``
    module in its own folder first on ``PYTHONPATH``): how the fault tests inject a failure."""
    folder = tmp_path / "inject"
    folder.mkdir(exist_ok=True)
    (folder / "sitecustomize.py").write_text(code)
    return {"PYTHONPATH": os.pathsep.join([str(folder), os.environ.get("PYTHONPATH", "")])}


def run_in_processes(target, args_per_process: list[tuple], timeout: float = 120) -> None:
    """Start ``target(*args)`` in one spawned process per entry, side by side; each must exit 0."""
    import multiprocessing as mp

    procs = [mp.get_context("spawn").Process(target=target, args=args) for args in args_per_process]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout)
        assert p.exitcode == 0
