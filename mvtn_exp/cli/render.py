"""``mvtn-render``: render a mesh or point cloud file from M views into a PNG grid and a .npy tensor.

Example: ``mvtn-render input=PATH views=12 layout=spherical image_size=128``. The last printed
lines are the paths of the files written into the Hydra run directory.
"""
from __future__ import annotations

import logging
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
from ..render import layouts
from ..render.config import RendererConfig
from ..render.renderer import MultiViewRenderer
from ..viz.images import view_grid, write_png
from ..config.compose import check_overrides

log = logging.getLogger("mvtn-render")
LAYOUTS = ("circular", "spherical", "fibonacci", "explicit")


@dataclass
class RenderAppConfig:
    """``mvtn-render`` settings. ``input`` is a file path or ``builtin:NAME`` (sphere, torus, box, capsule)."""

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


def render_file(cfg: RenderAppConfig, out_dir: Path) -> list[Path]:
    from ..config.schema import resolve_device

    device = torch.device(resolve_device(cfg.device))
    torch.manual_seed(cfg.seed)
    rcfg = RendererConfig(**{**OmegaConf.to_container(OmegaConf.structured(cfg.renderer)), "image_size": cfg.image_size})
    shape = load_shape(cfg, device)
    azim, elev, dist = view_angles(cfg, device)
    renderer = MultiViewRenderer(rcfg).to(device)
    images, alpha = [], []
    with torch.no_grad():  # one view at a time, with a progress bar on a terminal (large images take minutes)
        for i in tqdm(range(azim.shape[1]), desc="render", unit="view", disable=None, leave=False):
            out = renderer(shape, azim[:, i:i + 1], elev[:, i:i + 1], dist[:, i:i + 1])
            images.append(out.images)
            alpha.append(out.alpha)
    images = torch.cat(images, 1)  # [1, M, 3, H, W]
    if float(torch.cat(alpha, 1).max()) == 0.0:
        log.warning("%s: every view is empty (shape outside all views?)", cfg.input)
    out_dir.mkdir(parents=True, exist_ok=True)
    png = write_png(out_dir / "views.png", view_grid(images[0]))
    npy = out_dir / "images.npy"
    np.save(npy, images[0].cpu().numpy())
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


def main() -> None:
    check_overrides("mvtn-render", "render", RenderAppConfig, sys.argv[1:], validate=RenderAppConfig.validate)
    _app()


if __name__ == "__main__":
    main()
