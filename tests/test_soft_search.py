"""The soft search's row spans with the interior left out (pass 2 wants only pixels outside a face)."""
import torch

from mvtn_exp.render import mesh_raster, tiles


def _candidates(tris: torch.Tensor, H: int, radius: float, skip_inside: bool) -> set:
    """(face, pixel) pairs the row spans enumerate for triangles ``[N, 3, 2]`` (NDC) in one image."""
    x, y = tris[..., 0], tris[..., 1]
    z = torch.full_like(x[:, 0], 2.0)
    cols = torch.stack([x[:, 0], y[:, 0], z, x[:, 1], y[:, 1], z, x[:, 2], y[:, 2], z])
    image = torch.zeros(len(tris), dtype=torch.long)
    boxes = mesh_raster.face_boxes(cols, image, radius, H, H)
    planes = mesh_raster.face_planes(x[:, 0], y[:, 0], x[:, 1], y[:, 1], x[:, 2], y[:, 2])
    span = mesh_raster.row_spans(planes, boxes, radius, 0, H, skip_inside=skip_inside)
    out = set()
    for parts in tiles.candidate_chunks(boxes, H, H, 8, 1 << 30, torch.float32, span, 0):
        c = tiles.concat(parts)
        out |= set(zip(c.prim.tolist(), c.pix.tolist()))
    return out


def _strictly_inside(tris: torch.Tensor, face: int, pix: int, H: int) -> bool:
    t = tris[face].double()
    px, py = tiles.pixel_centres(torch.tensor([pix]), H, H, torch.float64)
    (ax, ay), (bx, by), (cx, cy) = t.tolist()
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    lams = [((q[0] - p[0]) * (float(py) - p[1]) - (q[1] - p[1]) * (float(px) - p[0])) / area
            for p, q in (((bx, by), (cx, cy)), ((cx, cy), (ax, ay)), ((ax, ay), (bx, by)))]
    return min(lams) > 0


def test_skipped_pixels_are_strictly_inside_and_nothing_outside_is_lost():
    g = torch.Generator().manual_seed(0)
    tris = [torch.rand(40, 3, 2, generator=g) * 1.6 - 0.8]  # random, many large
    tris.append(torch.tensor([[[-0.7, 0.5], [0.7, 0.5], [0.0, -0.6]],  # horizontal top edge
                              [[-0.7, -0.5], [0.0, 0.6], [0.7, -0.5 + 1e-6]],  # almost horizontal bottom edge
                              [[-0.9, -0.9], [0.9, 0.9], [0.9, 0.91]],  # a sliver
                              [[0.2, 0.2], [0.2, 0.2 + 1e-7], [0.8, -0.3]]]))  # two corners almost together
    tris = torch.cat(tris)
    H, radius = 48, 0.06
    every = _candidates(tris, H, radius, skip_inside=False)
    outside = _candidates(tris, H, radius, skip_inside=True)
    assert outside <= every
    skipped = every - outside
    assert len(skipped) > 0.3 * len(every)  # large faces: most of a dilated box is the interior
    assert all(_strictly_inside(tris, f, p, H) for f, p in skipped)
    # the hole above a horizontal edge: rows in the dilated margin above y = 0.5 keep all their pixels
    above = {(f, p) for f, p in every if f == 40 and float(tiles.pixel_centres(torch.tensor([p]), H, H, torch.float32)[1]) > 0.5}
    assert above and above <= outside
