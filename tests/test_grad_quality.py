"""The camera-gradient quality benchmark on a tiny case: table structure and a gradient that must match FD."""
import json
import math
from pathlib import Path

import torch

from studies import study

_gq = study("grad_quality")
LOSSES, SETTINGS, MultiViewRenderer, Probe, Scene, main, random_views, synthetic_meshes = (
    _gq.LOSSES, _gq.SETTINGS, _gq.MultiViewRenderer, _gq.Probe, _gq.Scene, _gq.main, _gq.random_views, _gq.synthetic_meshes)


def _table(md: str, heading: str) -> list[list[str]]:
    block = md.split("## " + heading, 1)[1].split("\n## ", 1)[0]
    lines = [l for l in block.splitlines() if l.startswith("|")]
    assert len(lines) >= 2 and set(lines[1].replace("|", "")) == {"-"}, block
    return [[c.strip() for c in l.strip("|").split("|")] for l in lines[2:]]


def test_tiny_grad_quality(tmp_path, capsys):
    main(["--size", "24", "--shapes", "1", "--views", "2", "--no-big", "--pole-h", "0.1,1", "--repeats", "1",
          "--cache-dir", str(tmp_path / "cache"), "--out", str(tmp_path / "out"), "--quiet"])
    lines = capsys.readouterr().out.strip().splitlines()
    md_path, js_path = Path(lines[-2]), Path(lines[-1])
    assert md_path.parent == (tmp_path / "out").resolve() and md_path.suffix == ".md" and js_path.suffix == ".json"
    res = json.loads(js_path.read_text())
    md = md_path.read_text()

    rows = res["rows"]
    assert {(r["setting"], r["loss"], r["h"]) for r in rows} == {(m, l, h) for m in SETTINGS for l in LOSSES for h in (0.5, 0.1)}
    for r in rows:
        assert r["dtype"] == "float64"
        assert r["fwd_bwd_ms_f32"] > 0 and r["fwd_bwd_ms_measured"] > 0
    by = {(r["setting"], r["loss"], r["h"]): r for r in rows}
    sil = by["soft_silhouette", "images", 0.5]
    assert sil["cos_angles"] > 0.8 and sil["median_shape_cos"] > 0.8, sil
    assert 0.5 < sil["ratio_angles"] < 2.0, sil
    # hard coverage is a mask: autograd has nothing, FD does
    hard = by["hard_flat", "alpha", 0.5]
    assert hard["cos_angles"] is None and hard["ratio_angles"] == 0.0

    table = _table(md, "Gradient quality: synthetic 1x2 @ 24 px")
    assert len(table) == len(rows) and all(len(row) == 13 for row in table)
    assert {row[0] for row in table} == set(SETTINGS)

    pole = res["pole"]
    assert len(pole) == 2 * 5 * 2
    for r in pole:
        assert math.isfinite(r["auto_median"]) and math.isfinite(r["fd_median_0.1"]) and math.isfinite(r["fd_median_1"])
        assert 0 <= r["agree_0.1"] <= r["shapes"] == 1
    assert len(_table(md, "Near the pole")) == len(pole)
    # the analytic frame turns at one rate at every elevation, the poles included
    rates = {round(f["dR_delev"], 9) for f in res["frame"]} | {round(f["dR_dazim"], 9) for f in res["frame"]}
    assert rates == {round(math.radians(1) * math.sqrt(2), 9)}


def test_moving_every_view_at_once_equals_moving_one(tmp_path):
    """The batched central difference relies on each view depending on its own camera only."""
    meshes = synthetic_meshes(2, tmp_path)
    scene = Scene("t", meshes, *random_views(2, 2, 0, 2.2), 24)
    probe = Probe(MultiViewRenderer(image_size=24, mode="soft", shading="smooth").eval(), scene, torch.float64, 1, "uniform")
    a, e, d = probe.cams()
    with torch.no_grad():
        every = probe.losses(a + 0.5, e, d)["images"]
        one = a.clone()
        one[1, 0] += 0.5
        single = probe.losses(one, e, d)["images"]
    assert torch.equal(every[1, 0], single[1, 0])
