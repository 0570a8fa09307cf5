"""MultiViewRenderer R: a batch of B shapes and views ``[B, M]`` -> images ``[B, M, 3, H, W]``.

Differentiable with respect to azimuth, elevation, distance and vertex / point positions.
Only what the settings need is computed: no normals or lights for silhouettes, no K > 1 search
without blur, no barycentrics for flat shading, nothing for pixels no primitive reaches.
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint

from ..data.shapes import Meshes, PointClouds, host_counts, subset
from . import accel, budget, lod, mesh_raster, nearest, picking, point_raster, shading, soft_search
from .cameras import Cameras, camera_to_ndc, to_camera_packed
from .compose import Compose
from .config import RendererConfig
from .ops import take, weighted3
from .precision import LOW_PRECISION, deterministic_algorithms, full_precision
from .topology import edge_neighbours


def seen_face_views(fv: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat shading's work list: the face-views (indices ``< n``) that some pixel slot ``fv`` shows,
    each once, and each slot's position in that list; found with a mark per face-view (linear, no
    sort), so shading costs never more than the face-views or the pixels."""
    seen = torch.zeros(n, dtype=torch.bool, device=fv.device)
    seen[fv.reshape(-1)] = True
    which = torch.nonzero(seen).squeeze(1)
    slot = torch.empty(n, dtype=torch.long, device=fv.device)
    slot[which] = torch.arange(len(which), device=fv.device)
    return which, take(slot, fv)


@dataclass
class RenderOutput:
    """images ``[B, M, 3, H, W]`` in [0, 1]; alpha ``[B, M, 1, H, W]`` coverage; stats: counters."""

    images: torch.Tensor
    alpha: torch.Tensor
    stats: dict


class MultiViewRenderer(nn.Module):
    """The renderer R of MVTN (no learnable parameters).

    ``forward(shapes, azim, elev, dist)``: shapes is a ``Meshes`` or ``PointClouds`` batch of B;
    azim, elev in degrees and dist in world units, each ``[B, M]`` (dist may be a float).
    In ``train()`` mode lights and colours follow ``train_light``/``train_color`` (random draws use
    torch's global generator, so they are seeded with the run), in ``eval()`` ``light``/``color``.
    """

    def __init__(self, cfg: RendererConfig | None = None, **overrides):
        super().__init__()
        cfg = cfg or RendererConfig()
        if overrides:
            cfg = RendererConfig(**{**cfg.__dict__, **overrides})
        self.cfg = cfg.validate()
        self.train(False)

    # ---------------------------------------------------------------- public API
    def forward(self, shapes, azim: torch.Tensor, elev: torch.Tensor, dist=2.2) -> RenderOutput:
        if not torch.is_tensor(dist):  # (in azim's type, or float32 for a low-precision azim)
            dist = torch.full(azim.shape, float(dist), device=azim.device,
                              dtype=torch.float32 if azim.dtype in LOW_PRECISION else azim.dtype)
        if azim.dim() != 2:
            raise ValueError(f"renderer: views must be [B, M], got azim {tuple(azim.shape)}")
        if len(shapes) != azim.shape[0]:
            raise ValueError(f"renderer: {len(shapes)} shapes but views for {azim.shape[0]} (azim {tuple(azim.shape)})")
        if not isinstance(shapes, (Meshes, PointClouds)):
            raise TypeError(f"renderer: expected Meshes or PointClouds, got {type(shapes).__name__}")
        # R computes in float32 whatever autocast surrounds it (C may run in bf16 / fp16: the search's
        # depth order, barycentrics and blend weights would round wrongly there); float64 stays float64
        compile_ = self.cfg.compile if self.cfg.compile is not None else accel.auto_compiles(
            azim.device.type, self.cfg.soft, self.cfg.image_size)
        with torch.autocast(azim.device.type, enabled=False), accel.compiled(compile_), \
                deterministic_algorithms(self.cfg.deterministic):
            shapes, azim, elev, dist = full_precision(shapes, azim, elev, dist)
            return self._render(shapes, azim, elev, dist)

    @torch.no_grad()
    def primitive_index(self, shapes, azim: torch.Tensor, elev: torch.Tensor, dist=2.2) -> torch.Tensor:
        """What each pixel shows: ``[B, M, H, W]`` long, the shape-local index of the front-most face
        covering the pixel centre (meshes: a hard search whatever the mode, on the full mesh: level
        of detail would renumber the faces) or of the front-most point whose splat covers it (point
        clouds), -1 on the background. Same cameras as ``forward``; no gradient (``render/picking.py``)."""
        if not torch.is_tensor(dist):
            dist = torch.full(azim.shape, float(dist), device=azim.device,
                              dtype=torch.float32 if azim.dtype in LOW_PRECISION else azim.dtype)
        with torch.autocast(azim.device.type, enabled=False):
            return picking.front_index(self, *full_precision(shapes, azim, elev, dist))

    def _render(self, shapes, azim, elev, dist) -> RenderOutput:
        """Shapes in groups within the memory budget (``render/budget.py``; one group when it fits),
        each group's active pixels computed whole, then the images composed once."""
        c = self.cfg
        H = W = c.image_size
        B, M = azim.shape
        mesh = isinstance(shapes, Meshes)
        stats = {}
        if mesh and c.lod:
            before = shapes.faces_per_shape.sum()
            shapes = lod.simplify_meshes(shapes, lod.face_budget(c.image_size, c.lod_faces_per_row, c.lod_faces_per_pixel),
                                         c.image_size, c.lod_min_iou)
            stats["lod_faces"] = (before, shapes.faces_per_shape.sum())
        ref = shapes.verts if mesh else shapes.points
        kind = ("soft" if c.soft else "hard") if mesh else "points"
        work = budget.plan(kind, shapes.faces_per_shape if mesh else shapes.points_per_shape, M, H, c.max_candidates,
                           c.memory_budget_mb, ref.device)
        overflow = None
        if work.strict:
            def overflow(n):
                raise budget.BudgetTooSmall(budget.tile_too_large(work.budget_mb, kind, n))
        draws = self._draws(B, ref) if mesh and c.shading != "silhouette" else None
        parts = []
        counts = host_counts(shapes) if len(work.groups) > 1 else None
        pixels = self._mesh_pixels if mesh else self._point_pixels
        for a, b in work.groups:
            group = (shapes, azim, elev, dist, draws) if (a, b) == (0, B) else (
                subset(shapes, a, b, counts), azim[a:b], elev[a:b], dist[a:b], None if draws is None else draws.part(a, b))
            pix, rgb, alpha, part_stats = pixels(*group, work.max_candidates, overflow, work.recompute)
            parts.append((pix + a * M * H * W if a else pix, rgb, alpha))
            add_stats(stats, part_stats)
        stats.update(groups=len(work.groups), recomputed=work.recompute)
        images, alpha = self._compose(parts, B * M, H * W, ref)
        return RenderOutput(images.view(B, M, 3, H, W), alpha.view(B, M, 1, H, W), stats)

    # ---------------------------------------------------------------- shared helpers
    def _cameras(self, azim, elev, dist) -> Cameras:
        c = self.cfg
        return Cameras(azim, elev, dist, fov=c.fov, orthographic=c.orthographic, ortho_scale=c.ortho_scale)

    def _project(self, pts: torch.Tensor, counts: torch.Tensor, cams: Cameras):
        """Packed ``[N, 3]`` world points -> per (point, view) NDC xy ``[N*M, 2]``, depth ``[N*M]``, image ``[N*M]``."""
        B, M = cams.azim.shape
        shape_of = torch.repeat_interleave(torch.arange(B, device=pts.device), counts, output_size=len(pts))
        image = (shape_of[:, None] * M + torch.arange(M, device=pts.device)).reshape(-1)
        R, C = cams.frames()
        xy, z = camera_to_ndc(to_camera_packed(pts, counts, R, C, shape_of), cams, self.cfg.znear)
        return xy, z, image

    def _background(self, ref: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.cfg.background, dtype=ref.dtype, device=ref.device)

    def _compose(self, parts: list, N: int, HW: int, ref) -> tuple[torch.Tensor, torch.Tensor]:
        """Scatter the groups' active-pixel ``(pix, rgb, alpha)`` into dense channel-first images ``[N, 3, HW]``
        and alpha ``[N * HW]`` (see ``compose.Compose``)."""
        if not parts:
            parts = [(ref.new_zeros(0, dtype=torch.long), ref.new_zeros(0, 3), ref.new_zeros(0))]
        return Compose.apply(self._background(ref), N, HW, *(t for part in parts for t in part))

    def _draws(self, B, ref) -> "Draws":
        """The batch's light directions (unit ``[B, 3]`` world, None: towards each camera) and albedos
        ``[B, 3]``, drawn once per call (random ones from torch's global generator, light first)."""
        mode = self.cfg.train_light if self.training else self.cfg.light
        light = None
        if mode == "fixed":
            d = torch.tensor(self.cfg.light_direction, dtype=ref.dtype, device=ref.device)
            light = torch.nn.functional.normalize(d, dim=0, eps=1e-12).expand(B, 3)
        elif mode == "random":
            light = torch.nn.functional.normalize(torch.randn(B, 3, dtype=ref.dtype).to(ref.device), dim=-1, eps=1e-12)
        mode = self.cfg.train_color if self.training else self.cfg.color
        if mode == "white":
            albedo = torch.ones(B, 3, dtype=ref.dtype, device=ref.device)
        elif mode == "fixed":
            albedo = torch.tensor(self.cfg.object_color, dtype=ref.dtype, device=ref.device).expand(B, 3)
        else:
            albedo = (0.25 + 0.75 * torch.rand(B, 3, dtype=ref.dtype)).to(ref.device)
        return Draws(light, albedo)

    # ---------------------------------------------------------------- meshes
    def _mesh_pixels(self, meshes: Meshes, azim, elev, dist, draws, max_candidates, overflow, recompute=False):
        """One group of meshes -> its active pixels: flat index ``[P]``, rgb ``[P, 3]``, alpha ``[P]``, stats.
        recompute: keep nothing of the differentiable part for the backward pass but the selection;
        it is computed again there (``torch.utils.checkpoint``; the budget asks for it)."""
        c = self.cfg
        H = W = c.image_size
        B, M = azim.shape
        verts = meshes.verts
        blur = c.effective_blur()
        K = c.effective_k()
        with torch.no_grad() if recompute else contextlib.nullcontext():
            pf, _, C = self.project_faces(meshes, azim, elev, dist)
        alive, facing = pf.alive, pf.facing
        interior = None
        if c.soft:
            interior = self._interior_edges(meshes.faces, facing, M, len(meshes.verts))
        ranking = self.soft_ranking(dist.to(verts.dtype), interior)
        sel = mesh_raster.search_faces(pf, H=H, W=W, K=K, blur_radius=blur, tile_size=c.tile_size, max_candidates=max_candidates,
                                       ranking=ranking, overflow=overflow)
        stats = dict(faces_alive=alive.sum(), face_views=len(alive), active_pixels=len(sel.pix), max_candidates=sel.most)
        if c.soft:
            stats.update(slots=(sel.prim >= 0).sum(), rest_faces=0 if sel.rest_pix is None else len(sel.rest_pix))
        if not recompute:
            rgb, alpha = self._mesh_shade(meshes, pf, C, sel, ranking, draws, M)
            return sel.pix, rgb, alpha, stats

        def shade(azim, elev, dist):  # run again in the backward pass: nothing of it is kept until then
            pf, _, C = self.project_faces(meshes, azim, elev, dist)
            return self._mesh_shade(meshes, pf, C, sel, self.soft_ranking(dist.to(verts.dtype), interior), draws, M)

        rgb, alpha = checkpoint(shade, azim, elev, dist, use_reentrant=False, preserve_rng_state=False)
        return sel.pix, rgb, alpha, stats

    def _mesh_shade(self, meshes: Meshes, pf, C, sel, ranking, draws, M) -> tuple[torch.Tensor, torch.Tensor]:
        """The differentiable part of a group of meshes: rgb ``[P, 3]`` and alpha ``[P]`` of the
        selected pixels ``sel`` from the projected faces ``pf`` and camera centres C ``[B*M, 3]``."""
        c = self.cfg
        H = W = c.image_size
        verts = meshes.verts
        if c.soft:
            return self._soft_pixels(meshes, pf, sel, ranking, draws, M, C)
        frag = mesh_raster.face_fragments(pf, sel, H=H, W=W, need_bary=c.shading == "smooth", need_dist=False, interior_edge=None)
        if c.shading == "silhouette":
            alpha = frag.valid[:, 0].to(verts.dtype)
            return alpha[:, None] + (1 - alpha[:, None]) * self._background(verts), alpha
        return shading.hard_blend(self._face_colors(meshes, frag, draws, M, C), frag.valid)

    def _soft_pixels(self, meshes: Meshes, pf, sel, ranking, draws, M, C) -> tuple[torch.Tensor, torch.Tensor]:
        """Soft mode on the active pixels ``sel.pix`` ``[P]`` -> rgb ``[P, 3]``, alpha ``[P]``.

        Only the used slots are shaded (packed, one per row); coverage adds every other face within
        the blur radius where the slots leave the pixel uncovered (``soft_search.rest_log_miss``).
        """
        c = self.cfg
        H = W = c.image_size
        bg = self._background(meshes.verts)
        slots, owner = soft_search.packed_slots(sel)
        frag = mesh_raster.face_fragments(pf, slots, H=H, W=W, need_bary=c.shading == "smooth", need_dist=True,
                                          interior_edge=ranking.interior)
        P = len(sel.pix)
        miss = shading.log_miss(frag.dist[:, 0], owner, P, c.sigma)
        miss = miss + soft_search.rest_log_miss(pf, sel, miss, ranking, H=H, W=W)
        alpha = shading.coverage(miss)
        if c.shading == "silhouette":
            return alpha[:, None] + (1 - alpha[:, None]) * bg, alpha
        colors = self._face_colors(meshes, frag, draws, M, C)[:, 0]
        image = take(torch.div(sel.pix, H * W, rounding_mode="floor"), owner)
        rgb = shading.softmax_blend(colors, frag.dist[:, 0], frag.zbuf[:, 0], owner, alpha, take(ranking.zfar, image),
                                    take(ranking.znear, image), bg, sigma=c.sigma, gamma=c.gamma)
        return rgb, alpha

    def soft_ranking(self, dist: torch.Tensor, interior: torch.Tensor | None = None) -> soft_search.SoftRanking | None:
        """How soft mode ranks faces for views at camera distances ``dist`` ``[B, M]`` (None in hard mode);
        interior: ``[F*M, 3]`` interior-edge flags (``_interior_edges``).

        The per-image depth range of a unit-sphere shape is [dist - 1, dist + 1] (near end clamped
        at ``znear``): the same range normalises depth in the search and in ``softmax_blend``.
        """
        c = self.cfg
        if not c.soft:
            return None
        d = dist.reshape(-1)
        return soft_search.SoftRanking(d + 1.0, (d - 1.0).clamp(min=c.znear), c.sigma, c.gamma, c.soft_slots == "depth",
                                       interior, c.coverage_tol, math.inf if c.depth_window is None else c.depth_window)

    def project_faces(self, meshes: Meshes, azim, elev, dist):
        """Project and cull all faces for all views -> (ProjectedFaces, Cameras, camera centres ``[B*M, 3]``)."""
        c = self.cfg
        B, M = azim.shape
        verts = meshes.verts
        if not torch.is_tensor(dist):
            dist = torch.full_like(azim, float(dist))
        cams = self._cameras(azim.to(verts.dtype), elev.to(verts.dtype), dist.to(verts.dtype))
        xy, z, _ = self._project(verts, meshes.verts_per_shape, cams)
        C = cams.frames()[1]
        with torch.no_grad():
            # gather whole rows of M views per corner, then one strided copy to corner-coordinate rows
            V = len(verts)
            xyz = torch.cat([xy.detach(), z.detach()[:, None]], 1).view(V, M * 3)
            cols = take(xyz, meshes.faces).view(-1, 3, M, 3).permute(1, 3, 0, 2).reshape(9, -1)  # [9, F*M]
            alive, facing = mesh_raster.cull(cols, znear=c.znear, cull_backfaces=c.cull_backfaces,
                                             H=c.image_size, W=c.image_size)
        pf = mesh_raster.ProjectedFaces(cols, alive, facing, xy, z, meshes.faces, meshes.shape_of_face(), M, B * M)
        return pf, cams, C.reshape(B * M, 3)

    def _interior_edges(self, faces, facing, M, num_verts: int | None = None) -> torch.Tensor:
        """``[F*M, 3]`` True where the neighbour across an edge is alive and faces the same way."""
        nb = edge_neighbours(faces, num_verts)  # [F, 3]
        nb_fv = (nb[:, None, :] * M + torch.arange(M, device=faces.device)[None, :, None]).reshape(-1, 3)
        own = facing.unsqueeze(1)
        other = facing[nb_fv.clamp(min=0)]
        return (nb_fv >= 0) & (own != 0) & (other == own)

    def _face_colors(self, meshes: Meshes, frag: mesh_raster.Fragments, draws: "Draws", M, C) -> torch.Tensor:
        """Phong colour of every (active pixel, slot): ``[P, K, 3]``; C: camera centres ``[B*M, 3]``."""
        c = self.cfg
        verts, faces = meshes.verts, meshes.faces
        fv = frag.fv.clamp(min=0)
        tri = take(verts, faces)  # [F, 3, 3]
        fn = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
        lights = (torch.nn.functional.normalize(C, dim=-1, eps=1e-12) if draws.light is None
                  else draws.light.repeat_interleave(M, 0))
        albedos = draws.albedo

        def shade(fv_idx, normals, points):
            f = torch.div(fv_idx, M, rounding_mode="floor")
            img = fv_idx - f * M + take(meshes.shape_of_face(), f) * M
            return shading.phong(normals, points, take(C, img), take(lights, img), take(albedos, torch.div(img, M, rounding_mode="floor")),
                                 ambient=c.ambient, diffuse=c.diffuse, specular=c.specular,
                                 shininess=c.shininess, two_sided=c.two_sided)

        if c.shading == "smooth":
            f = torch.div(fv, M, rounding_mode="floor")
            vn = torch.zeros_like(verts).index_add(0, faces.reshape(-1), fn.repeat_interleave(3, 0))
            normals = weighted3(frag.bary, take(vn, take(faces, f)))
            points = weighted3(frag.bary, take(tri, f))
            return shade(fv, normals, points)
        # flat: one colour per face and view, shaded once per seen face-view; each pixel takes its own
        which, slot_of = seen_face_views(fv, len(faces) * M)
        f = torch.div(which, M, rounding_mode="floor")
        return take(shade(which, take(fn, f), take(tri.mean(1), f)), slot_of)

    # ---------------------------------------------------------------- points
    def _point_pixels(self, clouds: PointClouds, azim, elev, dist, draws, max_candidates, overflow, recompute=False):
        """One group of point clouds -> its active pixels: flat index ``[P]``, rgb ``[P, 3]``, alpha ``[P]``, stats
        (``recompute``: as ``_mesh_pixels``)."""
        c = self.cfg
        H = W = c.image_size
        B, M = azim.shape
        pts = clouds.points
        cams = self._cameras(azim.to(pts.dtype), elev.to(pts.dtype), dist.to(pts.dtype))
        xy, z, image = self._project(pts, clouds.points_per_shape, cams)
        r = c.point_radius
        with torch.no_grad():
            alive = (z >= c.znear) & (xy.detach().abs() <= 1 + r).all(-1)
        sel = point_raster.search_points(xy, z, image, alive, H=H, W=W, K=c.points_per_pixel, radius=r, num_images=B * M,
                                         tile_size=c.tile_size, max_candidates=max_candidates, overflow=overflow)
        stats = {"points_alive": alive.sum(), "active_pixels": len(sel.pix)}
        with torch.no_grad():  # (a recomputed group keeps only these, in int32)
            packed = point_raster.PackedSlots.of(sel)
            kept = packed.compact(len(xy)) if recompute else packed
        del sel

        def shade(xy):
            p = kept.long()
            a = point_raster.point_alphas(xy, p, H=H, W=W, radius=r, opacity=c.point_opacity)
            colors = None if clouds.colors is None else take(clouds.colors, torch.div(p.point, M, rounding_mode="floor"))
            composite = shading.alpha_composite if c.compositor == "alpha" else shading.norm_weighted_composite
            return composite(p.slot, a, len(p.pix), p.K, colors, self._background(pts))

        rgb, alpha = checkpoint(shade, xy, use_reentrant=False, preserve_rng_state=False) if recompute else shade(xy)
        return packed.pix, rgb, alpha, stats


@dataclass
class Draws:
    """A call's light directions ``[B, 3]`` (None: towards each camera) and albedos ``[B, 3]``."""

    light: torch.Tensor | None
    albedo: torch.Tensor

    def part(self, a: int, b: int) -> "Draws":
        return Draws(None if self.light is None else self.light[a:b], self.albedo[a:b])


def add_stats(total: dict, part: dict) -> None:
    """Fold one group's counters into the call's: sums, and the largest ``max_candidates``."""
    for key, value in part.items():
        if key not in total:
            total[key] = value
        elif key == "max_candidates":
            total[key] = nearest.largest([total[key], value])
        else:
            total[key] = total[key] + value
