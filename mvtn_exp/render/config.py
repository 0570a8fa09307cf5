"""Renderer settings: one dataclass, used both at run time and as the Hydra schema (group ``renderer``)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

MESH_MODES = ("hard", "soft")
SHADINGS = ("flat", "smooth", "silhouette")
LIGHTS = ("camera", "fixed", "random")
COLORS = ("white", "fixed", "random")
COMPOSITORS = ("alpha", "norm")
SOFT_SLOTS = ("logit", "depth")


@dataclass
class RendererConfig:
    """Settings of the multi-view renderer R.

    Mesh: ``mode=hard`` renders the nearest face (K=1, no blur); ``mode=soft`` blends the
    ``faces_per_pixel`` nearest faces within ``blur_radius`` (NDC; derived from ``sigma`` when
    null) with SoftRas probabilities ``sigmoid(-d^2 / sigma)`` (d in NDC) and depth weights
    ``exp(zinv / gamma)``. Lighting is Phong; ``light``/``color`` apply at evaluation,
    ``train_light``/``train_color`` while training (the paper's recipe: random light and colour
    while training, camera-relative light and white at test).
    Points: white discs of ``point_radius`` (NDC) on ``background``, ``points_per_pixel`` nearest
    in depth, composited front-to-back (``alpha``) or with normalised weights (``norm``).
    """

    image_size: int = 224
    fov: float = 60.0
    orthographic: bool = False
    ortho_scale: float = 1.0
    znear: float = 0.01
    background: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # meshes
    mode: str = "hard"
    shading: str = "flat"
    faces_per_pixel: int = 8
    sigma: float = 1e-4
    gamma: float = 1e-4
    blur_radius: float | None = None
    # with blur_radius null: faces whose SoftRas probability at a pixel is below this are not searched
    # there (the blur radius is where sigmoid(-d^2/sigma) = prob_cutoff); a speed/accuracy knob
    prob_cutoff: float = 1e-4
    # which K faces hold a pixel's soft slots: "logit" (largest blend weights; coverage counts
    # every face within the blur radius) or "depth" (PyTorch3D's: the K nearest; coverage from them)
    soft_slots: str = "logit"
    # soft coverage closer to 1 than this counts as full: faces beyond the K slots are then neither
    # searched behind the surface nor counted (0: exact, only where coverage rounds to 1)
    coverage_tol: float = 1e-3
    # soft colour: faces whose blend logit trails a pixel's largest by more than this (weight below
    # exp(-depth_window) of it) get no slot, and hidden ones are not searched (null: no pruning)
    depth_window: float | None = 12.0
    cull_backfaces: bool = False
    light: str = "camera"
    train_light: str = "random"
    light_direction: list[float] = field(default_factory=lambda: [0.0, 1.0, 0.0])
    color: str = "white"
    train_color: str = "random"
    object_color: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])
    ambient: float = 0.3
    diffuse: float = 0.7
    specular: float = 0.2
    shininess: float = 32.0
    two_sided: bool = True
    # points
    point_radius: float = 0.02
    points_per_pixel: int = 8
    compositor: str = "alpha"
    point_opacity: float = 1.0
    # level of detail (render/lod.py): simplify meshes to lod_faces_per_row * image_size faces
    # (lod_faces_per_pixel * image_size^2 when set), keeping a simplification only if its
    # silhouettes at image_size match the mesh's to lod_min_iou (cached per mesh)
    lod: bool = False
    lod_faces_per_row: float = 32.0
    lod_faces_per_pixel: Optional[float] = None
    lod_min_iou: float = 0.99
    # search
    tile_size: int = 32
    # how much memory one render may hold at once (render/budget.py): shapes are rendered in groups
    # and candidates searched in chunks that fit; null: half the memory free to the process
    # on CUDA, and on CPU no grouping, chunks of max_candidates (a size that suits CPU caches)
    memory_budget_mb: Optional[float] = None
    max_candidates: int = 1 << 21
    # torch.compile the per-candidate maths (render/accel.py): faster soft renders after a one-time
    # compile per process (measured in docs/results/renderer-speed.md); results equal eager's to
    # float rounding. true needs a C++ compiler on CPU, Triton on CUDA; false: always eager;
    # null (automatic): compiled where measured faster (accel.auto_compiles: soft mode, at least
    # 192 px, with autograd recording, on a CPU that can compile), else eager
    compile: Optional[bool] = None
    # repeatable on CUDA: the renderer runs under torch's deterministic algorithms (its float
    # index_add / scatter sums then accumulate in a fixed order, e.g. the soft search's test of which
    # pixels are fully covered); no effect on CPU, where they are already repeatable
    deterministic: bool = False

    def validate(self) -> "RendererConfig":
        def one_of(key, allowed):
            if getattr(self, key) not in allowed:
                raise ValueError(f"renderer.{key}={getattr(self, key)!r}: expected one of {list(allowed)}")

        one_of("mode", MESH_MODES)
        one_of("shading", SHADINGS)
        one_of("light", LIGHTS)
        one_of("train_light", LIGHTS)
        one_of("color", COLORS)
        one_of("train_color", COLORS)
        one_of("compositor", COMPOSITORS)
        one_of("soft_slots", SOFT_SLOTS)
        checks = {
            "image_size": self.image_size >= 1,
            "faces_per_pixel": self.faces_per_pixel >= 1,
            "points_per_pixel": self.points_per_pixel >= 1,
            "sigma": self.sigma > 0,
            "gamma": self.gamma > 0,
            "point_radius": self.point_radius > 0,
            "znear": self.znear > 0,
            "tile_size": self.tile_size >= 1,
            "max_candidates": self.max_candidates >= 1,
            "lod_faces_per_row": self.lod_faces_per_row > 0,
            "lod_faces_per_pixel": self.lod_faces_per_pixel is None or self.lod_faces_per_pixel > 0,
            "lod_min_iou": 0 <= self.lod_min_iou <= 1,
            "point_opacity": 0 < self.point_opacity <= 1,
            "coverage_tol": 0 <= self.coverage_tol < 1,
            "prob_cutoff": 0 < self.prob_cutoff < 0.5,
        }
        for key, ok in checks.items():
            if not ok:
                raise ValueError(f"renderer.{key}={getattr(self, key)!r} is out of range")
        for key in ("background", "light_direction", "object_color"):
            if len(getattr(self, key)) != 3:
                raise ValueError(f"renderer.{key} must have 3 entries, got {getattr(self, key)}")
        if self.memory_budget_mb is not None and not self.memory_budget_mb > 0:
            raise ValueError(f"renderer.memory_budget_mb must be > 0 (MiB) or null (automatic), got {self.memory_budget_mb}")
        if self.depth_window is not None and not self.depth_window > 0:
            raise ValueError(f"renderer.depth_window must be > 0 or null, got {self.depth_window}")
        if self.blur_radius is not None and self.blur_radius < 0:
            raise ValueError(f"renderer.blur_radius must be >= 0 or null, got {self.blur_radius}")
        return self

    @property
    def soft(self) -> bool:
        return self.mode == "soft"

    def effective_blur(self) -> float:
        """Blur radius (NDC) of soft mode: ``blur_radius``, else where sigmoid(-d^2/sigma) falls to
        ``prob_cutoff`` (1e-4: 3.0 sqrt(sigma)); capped at the screen diagonal."""
        if not self.soft:
            return 0.0
        r = self.blur_radius if self.blur_radius is not None else math.sqrt(self.sigma * math.log(1.0 / self.prob_cutoff - 1.0))
        return min(r, 2 * math.sqrt(2.0))

    def camera_gradient_problem(self) -> str | None:
        """Why meshes rendered with these settings give a learned selector (almost) no camera
        gradient, naming the setting; None when they do."""
        if not self.soft:
            return ("renderer.mode=hard: images are piecewise constant in the camera, so a learned selector gets "
                    "almost no useful gradient (measured); use renderer=soft")
        pixels = self.effective_blur() * self.image_size / 2
        if pixels < 0.25:
            return (f"renderer.sigma={self.sigma:g} (blur_radius={self.blur_radius}) blurs edges over {pixels:.2g} px "
                    f"at image_size={self.image_size}, under a quarter pixel: only the few pixel centres that closely "
                    "hug an edge see it, so the silhouettes' camera gradient is spiky and does not follow the image "
                    "(measured on a box: cosine with finite differences 0.85 at 0.05 px, 0.99 at 0.2 px); raise sigma")
        return None

    def effective_k(self) -> int:
        """Faces per pixel actually searched: 1 when nothing is blurred (no K>1 work without blur)."""
        return self.faces_per_pixel if self.soft and self.effective_blur() > 0 else 1
