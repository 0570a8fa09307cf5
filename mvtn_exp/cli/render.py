"""``mvtn-render``: render a mesh or point cloud file from M views into a PNG grid and a .npy tensor.

Example: ``mvtn-render input=PATH views=12 layout=spherical image_size=128``. The last printed
lines are the paths of the files written into the Hydra run directory.

Before anything is written, ``check_size`` estimates the render's peak memory and the size of
``images.npy``: a large one (``images.npy`` over ``WARN_OUTPUT_BYTES``, or a peak over
``WARN_MEMORY_SHARE`` of the available memory) gets one warning line on stderr; one that needs
more memory than is available is refused in one line, exit code 2, unless ``allow_large=true``.
"""
from __future__ import annotations

import io
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf
from tqdm.auto import tqdm

from ..data import mesh_io
from ..data.shapes import Meshes, PointClouds, ShapeError
from ..render import budget, layouts
from ..render.config import RendererConfig
from ..render.renderer import MultiViewRenderer
from ..viz.images import view_grid, write_png
from ..config.compose import check_overrides

log = logging.getLogger("mvtn-render")
LAYOUTS = ("circular", "spherical", "fibonacci", "explicit")
WARN_OUTPUT_BYTES = 10**9  # images.npy above this: a warning line before rendering
WARN_MEMORY_SHARE = 0.5  # an expected peak above this share of the available memory: a warning line
IMAGE_BYTES = 12  # per output pixel: 3 float32 channels, as images.npy holds them
# per output pixel, what the command holds beside the renderer while views.png is made: the images,
# view_grid's float32 copies and uint8 grid, the PNG's raw rows (measured: 66 at 2048 px, rounded up)
HELD_BYTES = 72


@dataclass
class RenderAppConfig:
    """``mvtn-render`` settings. ``input`` is a file path or ``builtin:NAME`` (sphere, torus, box, capsule).
    ``progress``: a bar over the views on a terminal (false: none); ``allow_large``: render even
    when the expected peak memory exceeds the memory available (``check_size``)."""

    input: str = "???"
    views: int = 12
    layout: str = "spherical"
    azim: list[float] | None = None
    elev: list[float] | None = None
    distance: float = 2.2
    elevation: float = 30.0
    image_size: int = 128
    zup: bool = False
    as_points: bool = False
    num_points: int = 2048
    seed: int = 0
    device: str = "auto"
    progress: bool = True
    allow_large: bool = False
    renderer: RendererConfig = field(default_factory=RendererConfig)

    def validate(self) -> "RenderAppConfig":
        from ..config.schema import check_device, resolve_device

        check_device("device", self.device)
        if self.renderer.compile:
            from ..render.accel import require

            require(resolve_device(self.device))
        return self


ConfigStore.instance().store(name="render_schema", node=RenderAppConfig)


def builtin_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    makers = {
        "sphere": lambda: trimesh.creation.icosphere(subdivisions=4),
        "torus": lambda: trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=64, minor_sections=32),
        "box": lambda: trimesh.creation.box(extents=(1.6, 1.0, 0.6)),
        "capsule": lambda: trimesh.creation.capsule(height=1.2, radius=0.4),
    }
    if name not in makers:
        raise mesh_io.ShapeFileError(f"input=builtin:{name}: unknown built-in shape; expected one of {sorted(makers)}")
    m = makers[name]()
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def load_shape(cfg: RenderAppConfig, device: torch.device):
    """Read ``cfg.input``, orient (Y-up), centre and scale into the unit sphere -> Meshes or PointClouds."""
    name = cfg.input
    if name.startswith("builtin:"):
        verts, faces = builtin_mesh(name.split(":", 1)[1])
    elif mesh_io.is_point_file(name):
        verts, faces = mesh_io.read_points(name), None
    else:
        verts, faces = mesh_io.read_mesh(name)
    if cfg.zup:
        verts = mesh_io.zup_to_yup(verts)
    verts = mesh_io.normalize_unit_sphere(verts)
    if faces is not None and cfg.as_points:
        import trimesh

        rng = np.random.default_rng(cfg.seed)
        pts, _ = trimesh.sample.sample_surface(trimesh.Trimesh(verts, faces, process=False), cfg.num_points, seed=rng)
        verts, faces = np.asarray(pts), None
    v = torch.as_tensor(verts, dtype=torch.float32, device=device)
    if faces is None:
        return PointClouds.from_list([v], names=[name])
    return Meshes.from_list([v], [torch.as_tensor(faces, device=device)], names=[name])


def view_angles(cfg: RenderAppConfig, device):
    if cfg.layout not in LAYOUTS:
        raise ValueError(f"layout={cfg.layout!r}: expected one of {list(LAYOUTS)}")
    if cfg.azim is not None or cfg.elev is not None or cfg.layout == "explicit":
        if cfg.azim is None or cfg.elev is None or len(cfg.azim) != len(cfg.elev) or not cfg.azim:
            raise ValueError("azim/elev: explicit views need two non-empty lists of equal length, e.g. azim=[0,90] elev=[30,30]")
        a = torch.tensor([list(cfg.azim)], dtype=torch.float32, device=device)
        e = torch.tensor([list(cfg.elev)], dtype=torch.float32, device=device)
        return a, e, torch.full_like(a, cfg.distance)
    if cfg.layout == "circular":
        return layouts.circular(cfg.views, elevation=cfg.elevation, distance=cfg.distance, device=device)
    sphere = "fibonacci" if cfg.layout == "fibonacci" else "equal_area"  # spherical: the paper's rings
    return layouts.spherical(cfg.views, distance=cfg.distance, device=device, sphere=sphere)


@dataclass
class SizeEstimate:
    """A render's cost, known before it starts: ``output_bytes``, the size of images.npy (exact);
    ``extra_bytes``, the memory the render adds to what the process holds; ``peak_bytes``, the
    process's expected resident peak; ``available_bytes``, the machine's memory left (None: unknown)."""

    output_bytes: int
    extra_bytes: int
    peak_bytes: int
    available_bytes: int | None


def view_count(cfg: RenderAppConfig) -> int:
    """M: the explicit angles' count, else ``views`` (every layout renders exactly ``views``)."""
    return len(cfg.azim) if cfg.azim else cfg.views


def estimate(cfg: RenderAppConfig) -> SizeEstimate:
    """What rendering ``cfg`` takes, from its settings alone: M x 3 x image_size^2 float32 images
    (``IMAGE_BYTES``), the command's copies of them while views.png is made (``HELD_BYTES``), and
    the renderer's own state for the one view it renders at a time (``budget.render_bytes``, or
    ``renderer.memory_budget_mb`` when set; on the host only when it renders on the CPU)."""
    from ..config.schema import resolve_device

    M, H = view_count(cfg), cfg.image_size
    pixels = M * H * H
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": (M, 3, H, H)})
    points = cfg.as_points or Path(cfg.input).suffix.lower() in mesh_io.POINT_SUFFIXES
    kind = "points" if points else ("soft" if cfg.renderer.mode == "soft" else "hard")
    one_view = (budget.render_bytes(kind, 1, H, max_candidates=cfg.renderer.max_candidates)
                if cfg.renderer.memory_budget_mb is None else int(cfg.renderer.memory_budget_mb * budget.MiB))
    if resolve_device(cfg.device) != "cpu":
        one_view = 0  # (the renderer's state is on the GPU; the images come to the host view by view)
    extra = max(pixels * IMAGE_BYTES + one_view, pixels * HELD_BYTES)
    return SizeEstimate(header.tell() + pixels * IMAGE_BYTES, extra, resident_bytes() + extra, available_memory())


def resident_bytes() -> int:
    """This process's resident memory now (/proc/self/statm; 0 where it cannot be read)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return 0


def available_memory() -> int | None:
    """Bytes the machine can still give this process: ``MemAvailable`` of /proc/meminfo (else
    ``os.sysconf``'s free pages), at most the room left under a cgroup v2 memory limit (containers,
    batch jobs); None when none of them can be read."""
    found = []
    try:
        with open("/proc/meminfo") as f:
            found += [int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable:")]
    except (OSError, ValueError, IndexError):
        pass
    if not found:
        try:
            found.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (OSError, ValueError, AttributeError):
            pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            found.append(int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text()))
    except (OSError, ValueError):
        pass
    return max(0, min(found)) if found else None


def _size(n: int | None) -> str:
    if n is None:
        return "unknown"
    return f"{n / 1e9:.1f} GB" if n >= 10**9 else f"{n / 1e6:.0f} MB"


def check_size(cfg: RenderAppConfig) -> None:
    """Before the run folder is made: a render whose images.npy exceeds ``WARN_OUTPUT_BYTES`` or
    whose expected peak exceeds ``WARN_MEMORY_SHARE`` of the available memory gets one warning line
    on stderr; one that needs more than the available memory is refused in one line, exit code 2,
    nothing written (``allow_large=true``: rendered anyway, with the warning)."""
    est = estimate(cfg)
    what = f"image_size={cfg.image_size} views={view_count(cfg)}"
    sizes = f"expected peak memory ~{_size(est.peak_bytes)}, images.npy ~{_size(est.output_bytes)}"
    avail = est.available_bytes
    if avail is not None and est.extra_bytes > avail and not cfg.allow_large:
        print(f"mvtn-render: error: {what}: {sizes}; that needs more than the {_size(avail)} of memory available "
              "(expected a smaller image_size or fewer views; allow_large=true renders anyway)", file=sys.stderr)
        sys.exit(2)
    if est.output_bytes > WARN_OUTPUT_BYTES or (avail is not None and est.extra_bytes > WARN_MEMORY_SHARE * avail):
        print(f"mvtn-render: warning: {what}: {sizes} ({_size(avail)} of memory available)", file=sys.stderr)


def render_file(cfg: RenderAppConfig, out_dir: Path) -> list[Path]:
    from ..config.schema import resolve_device

    device = torch.device(resolve_device(cfg.device))
    torch.manual_seed(cfg.seed)
    rcfg = RendererConfig(**{**OmegaConf.to_container(OmegaConf.structured(cfg.renderer)), "image_size": cfg.image_size})
    shape = load_shape(cfg, device)
    azim, elev, dist = view_angles(cfg, device)
    renderer = MultiViewRenderer(rcfg).to(device)
    M, H = azim.shape[1], cfg.image_size
    images = torch.empty(M, 3, H, H, dtype=torch.float32)  # [M, 3, H, W] on the host, filled view by view
    seen = 0.0
    with torch.no_grad():  # one view at a time, with a progress bar on a terminal (large images take minutes)
        for i in tqdm(range(M), desc="render", unit="view", disable=None if cfg.progress else True, leave=False):
            out = renderer(shape, azim[:, i:i + 1], elev[:, i:i + 1], dist[:, i:i + 1])
            images[i] = out.images[0, 0].cpu()
            seen = max(seen, float(out.alpha.max()))
            del out
    if seen == 0.0:
        log.warning("%s: every view is empty (shape outside all views?)", cfg.input)
    out_dir.mkdir(parents=True, exist_ok=True)
    png = write_png(out_dir / "views.png", view_grid(images))
    npy = out_dir / "images.npy"
    np.save(npy, images.numpy())
    angles = out_dir / "views.csv"
    rows = ["view,azim_deg,elev_deg,dist"] + [f"{i},{a:.4f},{e:.4f},{d:.4f}" for i, (a, e, d) in
                                               enumerate(zip(azim[0].tolist(), elev[0].tolist(), dist[0].tolist()))]
    angles.write_text("\n".join(rows) + "\n")
    return [png, npy, angles]


@hydra.main(version_base="1.3", config_path="../conf", config_name="render")
def _app(cfg) -> None:
    try:
        obj: RenderAppConfig = OmegaConf.to_object(cfg)
        paths = render_file(obj, Path(HydraConfig.get().runtime.output_dir))
    except (mesh_io.ShapeFileError, ShapeError, ValueError) as exc:
        # bad input: one clear line, no traceback
        print(f"mvtn-render: error: {exc}", file=sys.stderr)
        sys.exit(2)
    for p in paths:
        print(p)


def before_run(cfg: RenderAppConfig) -> RenderAppConfig:
    """The settings' own checks, then ``check_size`` (a warning line, or a refusal: exit code 2)."""
    cfg.validate()
    check_size(cfg)
    return cfg


def main() -> None:
    check_overrides("mvtn-render", "render", RenderAppConfig, sys.argv[1:], validate=before_run)
    _app()


if __name__ == "__main__":
    main()
