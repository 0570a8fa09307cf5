"""Batching dataset items (dicts from ``SyntheticShapes`` and friends) into the packed containers."""
from __future__ import annotations

from typing import Sequence

import torch

from .shapes import Meshes

DETAIL_KEYS = ("detail_anchor", "detail_axis", "detail_size")


def collate_shapes(batch: Sequence[dict]) -> dict:
    """A ``DataLoader`` collate_fn: list of B items -> one batch.

    Items carry ``points [N, 3]``, ``label``, ``name`` and optionally ``verts [V_i, 3]`` /
    ``faces [F_i, 3]`` (local indices) and ``rotation [3, 3]``. Returns a dict with
    ``meshes``: packed ``Meshes`` of B shapes (``None`` when the items carry no mesh),
    ``points [B, N, 3]`` float, ``labels [B]`` long, ``names`` list[str] and, when every item has
    one, ``rotations [B, 3, 3]``, ``part_labels [B, N]`` long (part datasets: a part id per point), ``face_parts [sum F]``
    long (mesh part datasets: a part id per face, packed like ``meshes.faces``), ``point_faces [B, N]``
    long (the shape-local face each point lies on)
    and the ``synthetic_views`` detail frame (``detail_anchor``, ``detail_axis``, ``detail_size``,
    each ``[B, 3]``).
    """
    if not batch:
        raise ValueError("collate_shapes: empty batch")
    names = [str(b["name"]) for b in batch]
    sizes = {tuple(b["points"].shape) for b in batch}
    if len(sizes) != 1:
        raise ValueError(f"collate_shapes: point clouds of different sizes {sorted(sizes)} in one batch ({names})")
    out = {
        "points": torch.stack([torch.as_tensor(b["points"]) for b in batch]),
        "labels": torch.tensor([int(b["label"]) for b in batch], dtype=torch.long),
        "names": names,
        "meshes": None,
    }
    if all("verts" in b and "faces" in b for b in batch):
        out["meshes"] = Meshes.from_list([torch.as_tensor(b["verts"]) for b in batch],
                                         [torch.as_tensor(b["faces"], dtype=torch.long) for b in batch], names=names)
    if all("rotation" in b for b in batch):
        out["rotations"] = torch.stack([torch.as_tensor(b["rotation"]) for b in batch])
    if out["meshes"] is not None and all("face_parts" in b for b in batch):  # (packed as the meshes' faces)
        out["face_parts"] = torch.cat([torch.as_tensor(b["face_parts"], dtype=torch.long) for b in batch])
    if out["meshes"] is not None and all("point_faces" in b for b in batch):
        out["point_faces"] = torch.stack([torch.as_tensor(b["point_faces"], dtype=torch.long) for b in batch])
    if all("part_labels" in b for b in batch):
        out["part_labels"] = torch.stack([torch.as_tensor(b["part_labels"], dtype=torch.long) for b in batch])
    for key in DETAIL_KEYS:
        if all(key in b for b in batch):
            out[key] = torch.stack([torch.as_tensor(b[key]) for b in batch])
    return out
