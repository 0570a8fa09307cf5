"""The paper's two time-and-memory tables as ``mvtn-bench modules=true`` rows, beside the paper's numbers.

Table 12 (IJCV supplement, ``tbl:speed-supp``, L728-L748): per network, forward FLOPs, MACs,
parameters and the time one input sample takes through it: the PointNet and DGCNN classifiers
(2,048 points: the count that gives the paper's FLOPs, which it does not state), MVCNN and ViewGCN
on ResNet-18 at M = 12 views of 224 px, MVTN's regressor alone (MVTN*) and G whole (MVTN°: the
paper's PointNet and the regressor). Table 13 (the MVTorch table, L753-L790): the renderer at
M = 4..12 for points (2,048) and meshes (the benchmark's 2,048-face torus; the paper's meshes are
ModelNet40's), MVCNN ResNet-18, G with PointNet or DGCNN, and the segmentation pipeline's C
(MVPartSeg: DeepLabV3 on ResNet-101 with its auxiliary head, 51 outputs) at M = 4..12.

Ours: one sample (batch 1), forward in eval mode under ``no_grad`` on the benchmark's device;
FLOPs are ``torch.utils.flop_counter`` counts (matrix products and convolutions, 2 per
multiply-accumulate: MACs = FLOPs / 2), the renderer has none. The paper's times are its own GPU's
(unnamed), so the time columns compare a setting's share, not machines.
"""
from __future__ import annotations

import torch

from ..models.multiview import build_multiview
from ..models.point_encoders import PaperPointNetConfig, PointEncoderConfig, build_point_encoder
from ..config.options import OPTIONS
from ..selectors import build_selector
from .modules import RegressorAlone
from .render_report import md_table
from .scenes import Views, render_fns, renderer_for, torus, torus_points
from .timing import med_ms, time_runs

POINTS = 2048
NUM_CLASSES = 40
PARTS = 50  # ShapeNet Parts
G, M_, K_ = 1e9, 1e6, 1e3
# Table 12 (L737-L744): network -> (FLOPs, MACs, parameters, ms)
PAPER_T12 = {"PointNet": (1.78 * G, 0.89 * G, 3.49 * M_, 3.34), "DGCNN": (10.42 * G, 5.21 * G, 0.95 * M_, 16.35),
             "MVCNN": (43.72 * G, 21.86 * G, 11.20 * M_, 39.89), "ViewGCN": (44.19 * G, 22.09 * G, 23.56 * M_, 26.06),
             "MVTN* (regressor)": (18.52 * K_, 9.26 * K_, 9.09 * K_, 0.9),
             "MVTN° (PointNet + regressor)": (1.78 * G, 0.89 * G, 4.24 * M_, 3.50)}
SEG = "C DeepLabV3 ResNet-101"  # MVPartSeg's 2D network: 61 M parameters with the auxiliary head
# Table 13 (L768-L792): (module, M) -> (ms, parameters, FLOPs or None)
PAPER_T13 = {
    **{("R points", m): (t, 0.0, None) for m, t in zip((4, 6, 8, 10, 12), (10.74, 12.61, 15.42, 17.45, 20.16))},
    **{("R meshes", m): (t, 0.0, None) for m, t in zip((4, 6, 8, 10, 12), (19.15, 25.11, 28.83, 32.94, 37.55))},
    **{("MVCNN ResNet-18", m): (t, 11.20 * M_, f * G) for m, t, f in
       zip((4, 6, 8, 10, 12), (2.59, 2.75, 3.13, 3.50, 4.01), (14.57, 21.86, 29.15, 36.43, 43.72))},
    **{("G PointNet", m): (t, p * M_, 1.77 * G) for m, t, p in
       zip((4, 6, 8, 10, 12), (3.46, 3.44, 3.46, 3.44, 3.42), (3.47, 3.47, 3.47, 3.48, 3.48))},
    **{("G DGCNN", m): (t, p * M_, 10.42 * G) for m, t, p in
       zip((4, 6, 8, 10, 12), (4.09, 4.10, 4.10, 4.10, 4.10), (0.95, 0.96, 0.96, 0.96, 0.96))},
    **{(SEG, m): (t, 61.00 * M_, f * G) for m, t, f in   # MVPartSeg deeplab (L788-L792)
       zip((4, 6, 8, 10, 12), (54.00, 67.15, 91.04, 112.52, 121.49), (387.74, 581.61, 775.48, 969.35, 1163.21))},
}


def _measure(net, x, device, repeats: int, budget_s: float) -> dict:
    """Parameters, forward FLOPs and forward ms of ``net(*x)`` on one sample (eval, no_grad)."""
    from torch.utils.flop_counter import FlopCounterMode

    net = net.to(device).eval()

    def fwd():
        with torch.no_grad():
            net(*x)

    with torch.no_grad(), FlopCounterMode(display=False) as count:
        net(*x)
    fwd()  # warm-up
    return dict(params=sum(p.numel() for p in net.parameters()), flops=float(count.get_total_flops()),
                ms=med_ms(time_runs(fwd, device, repeats, budget_s)))


class _Head(torch.nn.Module):
    """A multi-view network called with its views (ViewGCN reads them)."""

    def __init__(self, net, M: int):
        super().__init__()
        self.net, self.M = net, M

    def forward(self, images):
        B = len(images)
        views = (torch.linspace(0, 330, self.M).expand(B, -1).to(images), torch.full((B, self.M), 30.0).to(images),
                 torch.full((B, self.M), 2.2).to(images))
        return self.net(images, views)


def _g(M: int, encoder: PointEncoderConfig):
    """The paper's G (the official regressor) for M learned spherical views on ``encoder``."""
    return build_selector("mvtn_spherical", M, point_encoder=encoder, regressor="official")


def table12(device, size: int, repeats: int, budget_s: float, seed: int = 0) -> list[dict]:
    gen = torch.Generator().manual_seed(seed)
    pts = torch.randn(1, POINTS, 3, generator=gen).to(device)
    imgs = torch.rand(1, 12, 3, size, size, generator=gen).to(device)
    torch.manual_seed(seed)
    g = _g(12, PaperPointNetConfig())
    dgcnn = OPTIONS["point_encoder"].schema("dgcnn")().validate()
    nets = {"PointNet": (build_point_encoder("pointnet_paper", NUM_CLASSES), (pts,)),
            "DGCNN": (build_point_encoder("dgcnn", NUM_CLASSES, **dgcnn.kwargs()), (pts,)),
            "MVCNN": (_Head(build_multiview("mvcnn", "resnet18", NUM_CLASSES), 12), (imgs,)),
            "ViewGCN": (_Head(build_multiview("viewgcn", "resnet18", NUM_CLASSES), 12), (imgs,)),
            "MVTN* (regressor)": (RegressorAlone(g), (torch.randn(1, g.regressor[0].in_features, generator=gen).to(device),)),
            "MVTN° (PointNet + regressor)": (g, (pts,))}
    rows = []
    for name, (net, x) in nets.items():
        ours = _measure(net, x, device, repeats, budget_s)
        rows.append(dict(module=name, setting=_t12_setting(name, size), **ours, paper=PAPER_T12[name]))
    return rows


def _t12_setting(name: str, size: int) -> str:
    if name in ("MVCNN", "ViewGCN"):
        return f"ResNet-18, M = 12, {size} px"
    return f"{POINTS} points" if "regressor)" not in name or "PointNet" in name else "point features given"


def table13(device, size: int, views, repeats: int, budget_s: float, seed: int = 0) -> list[dict]:
    gen = torch.Generator().manual_seed(seed)
    pts = torch.randn(1, POINTS, 3, generator=gen).to(device)
    mesh, cloud = torus("torus-2k", device), torus_points(POINTS, seed, device)
    dgcnn = OPTIONS["point_encoder"].schema("dgcnn")().validate()
    rows = []
    for M in views:
        for label, shape, K in (("R points", cloud, 8), ("R meshes", mesh, 1)):
            fwd, _, _ = render_fns(renderer_for(shape, size, K), shape, Views(M, 1, device))
            fwd()
            rows.append(dict(module=label, M=M, params=0, flops=None, ms=med_ms(time_runs(fwd, device, repeats, budget_s)),
                             paper=PAPER_T13.get((label, M))))
        torch.manual_seed(seed)
        imgs = torch.rand(1, M, 3, size, size, generator=gen).to(device)
        nets = (("MVCNN ResNet-18", build_multiview("mvcnn", "resnet18", NUM_CLASSES), imgs),
                ("G PointNet", _g(M, PaperPointNetConfig()), pts), ("G DGCNN", _g(M, dgcnn), pts),
                (SEG, _segmenter(), imgs))
        for label, net, x in nets:
            rows.append(dict(module=label, M=M, **_measure(net, (x,), device, repeats, budget_s),
                             paper=PAPER_T13.get((label, M))))
    return rows


def _segmenter():
    """MVPartSeg's C: DeepLabV3 on ResNet-101 with the auxiliary head (torchvision's 61.0 M
    parameters with 21 outputs; here the 50 parts of ShapeNet Parts and the background)."""
    return OPTIONS["segnet"].schema("deeplabv3")(aux=True).validate().build_c(PARTS + 1, "resnet101")


def paper_module_rows(quick: bool, device, repeats: int, budget_s: float, seed: int = 0) -> dict:
    """``{"t12": rows, "t13": rows, "size": px}``: quick runs 64 px and M = 4 only (the tables' shapes)."""
    device = torch.device(device)
    size, views = (64, (4,)) if quick else (224, (4, 6, 8, 10, 12))
    return {"t12": table12(device, size, repeats, budget_s, seed), "t13": table13(device, size, views, repeats, budget_s, seed),
            "size": size}


def _num(v, scale: float, fmt: str = "{:.3g}") -> str:
    return "-" if v is None else fmt.format(v / scale)


def _pair(ours, paper, scale) -> str:
    return f"{_num(ours, scale)} / {_num(paper, scale)}"


def markdown(res: dict, device: str) -> str:
    t12 = [[r["module"], r["setting"], _pair(r["params"], r["paper"][2], M_), _pair(r["flops"], r["paper"][0], G),
            _pair(r["flops"] / 2, r["paper"][1], G), f"{r['ms']:.2f} / {r['paper'][3]:g}"] for r in res["t12"]]
    t13 = [[r["module"], r["M"], _pair(r["params"], None if r["paper"] is None else r["paper"][1], M_),
            _pair(r["flops"], None if r["paper"] is None else r["paper"][2], G),
            f"{r['ms']:.2f} / " + ("-" if r["paper"] is None else f"{r['paper'][0]:g}")] for r in res["t13"]]
    head = (f"one sample, forward, eval mode; ours on {device} / the paper's (its GPU, unnamed); "
            f"{res['size']} px; MACs = FLOPs / 2")
    return (f"## The paper's Table 12, time and memory (L728-L748): {head}\n\n"
            + md_table(["network", "setting", "params M (ours / paper)", "GFLOPs (ours / paper)", "GMACs (ours / paper)",
                        "ms (ours / paper)"], t12)
            + f"\n\n## The paper's Table 13, MVTorch modules (L753-L790): {head}; R: the 2,048-face torus (meshes, hard) "
            f"and 2,048 points (8 per pixel)\n\n"
            + md_table(["module", "M", "params M (ours / paper)", "GFLOPs (ours / paper)", "ms (ours / paper)"], t13))
