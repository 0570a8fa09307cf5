"""mvtn-bench: the quick benchmark end to end, the dense reference against search_faces, PeakMemory."""
import json
import math
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from conftest import random_triangles
from mvtn_exp.bench.dense import dense_pairs, dense_search, estimate_pairs
from mvtn_exp.runtime.memory import PeakMemory
from mvtn_exp.bench.scenes import torus
from mvtn_exp.render import layouts, mesh_raster
from mvtn_exp.render.renderer import MultiViewRenderer


def _table(md: str, heading: str) -> list[list[str]]:
    """Rows (cells) of the Markdown table under the ``## heading...`` line."""
    block = md.split("## " + heading, 1)[1].split("\n## ", 1)[0]
    lines = [l for l in block.splitlines() if l.startswith("|")]
    assert len(lines) >= 2 and set(lines[1].replace("|", "")) == {"-"}, block
    return [[c.strip() for c in l.strip("|").split("|")] for l in lines[2:]]


def _positive_finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


@pytest.mark.slow  # 22 s: the renderer rows are tested in-process; make test-all runs it
def test_quick_benchmark_cli(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "mvtn_exp.cli.bench", "quick=true", "repeats=2", "progress=false", f"hydra.run.dir={tmp_path}"],
        capture_output=True, text=True, check=True, timeout=300,
    )
    lines = out.stdout.strip().splitlines()
    md_path = Path(lines[-1])
    assert md_path == (tmp_path / "bench.md").resolve() and md_path.is_file()
    md = md_path.read_text()
    assert md.strip() in out.stdout  # the printed tables are the file's
    assert "MALLOC_MMAP_THRESHOLD_=65536" in md  # the CLI re-executed itself with the pinned threshold

    grid = _table(md, "Renderer grid")
    # (2k mesh, 2048 points) x 64 px x M in {1, 4} x K in {1, 8}, soft mesh rows in flat and smooth
    assert len(grid) == 10
    assert sorted(r[5] for r in grid if r[0] == "torus-2k" and r[4] == "8") == ["flat", "flat", "smooth", "smooth"]
    for row in grid:
        fwd, fb, peak = float(row[6]), float(row[7]), float(row[8])
        assert fwd > 0 and fb > 0 and math.isfinite(fwd) and math.isfinite(fb)
        assert peak >= 0 and math.isfinite(peak)
    assert {r[0] for r in grid} == {"torus-2k", "points-2048"}
    resnet = _table(md, "ResNet-18 reference")
    assert len(resnet) == 2 and all(float(r[2]) > 0 for r in resnet)
    dense = _table(md, "Dense reference")
    assert len(dense) == 2 and all(r[-1] == "yes" and float(r[5]) > 0 and float(r[6]) > 0 for r in dense)
    targets = _table(md, "Targets")
    edges = _table(md, "Soft edges")
    assert len(edges) == 3 and all(int(r[3]) > 0 and 0 <= float(r[4].rstrip("%")) <= 100 for r in edges)
    # hard, soft (2 shadings), compiled soft (2), points, LOD (2), batch of 8 (2)
    assert len(targets) == 10 and all(re.match(r"PASS|MISS|n/a", r[-1]) for r in targets)
    modules = _table(md, "Modules")
    assert len(modules) == 14  # R: 3 kinds x M in {1, 4}; G: 3 + the regressor alone; C: 2 backbones x 2 M
    params = {(r[0], r[1]): int(r[2].replace(",", "")) for r in modules}
    from mvtn_exp.models.multiview import build_multiview

    n_resnet = sum(p.numel() for p in build_multiview("mvcnn", "resnet18", 40).parameters())
    assert params[("C MVCNN, ResNet-18", "M=4, 64 px")] == n_resnet
    assert 0 < params[("G regressor alone (features given)", "M=4")] < params[
        ("G mvtn_spherical (PointNet + regressor)", "M=4, 256 points")]
    for r in modules:
        assert float(r[4]) > 0 and float(r[5]) > 0  # times only exist; no timed comparisons in tests
        assert (r[3] == "n/a (not FLOPs)") == r[0].startswith("R ")
    c1, c4 = (float(r[3]) for r in modules if r[0] == "C MVCNN, ResNet-18")
    assert math.isclose(c4, 4 * c1, rel_tol=0.01)  # FLOPs per shape grow with the views (3 digits printed)
    assert len(_table(md, "The paper's Table 12")) == 6 and len(_table(md, "The paper's Table 13")) == 5
    scaling = _table(md, "Scaling curves")
    assert {(r[0], r[1]) for r in scaling} == {(c, m) for c in ("faces", "pixels", "views", "batch")
                                                for m in ("hard", "soft smooth")}
    for r in scaling:
        ms = [float(x) for x in r[3].split(" / ")]
        assert len(ms) == 3 and all(t > 0 for t in ms) and math.isfinite(float(r[5])) and math.isfinite(float(r[6]))
    assert (tmp_path / "scaling.png").stat().st_size > 10_000

    data = json.loads((tmp_path / "bench.json").read_text())
    assert data["meta"]["options"]["quick"] is True
    assert len(data["grid"]) == 10
    for row in data["grid"]:
        assert all(_positive_finite(t) for t in row["fwd_s"] + row["fwd_bwd_s"]) and row["fwd_s"] and row["fwd_bwd_s"]
        assert row["peak_mib"] is not None and row["peak_mib"] >= 0
    assert all(_positive_finite(t) for r in data["resnet"] for t in r["fwd_bwd_s"])
    assert _positive_finite(data["meta"]["elapsed_s"])


def test_the_papers_time_and_memory_tables_beside_ours():
    """The paper's Tables 12 and 13 (L728-L790) as rows: our parameters and FLOPs of the same
    networks (exact where the architecture is the paper's), the paper's numbers beside them."""
    from mvtn_exp.bench.paper_modules import PAPER_T12, SEG, markdown, paper_module_rows
    from mvtn_exp.models.point_encoders import PaperPointNet

    res = paper_module_rows(True, "cpu", repeats=1, budget_s=0.01)
    t12 = {r["module"]: r for r in res["t12"]}
    assert set(t12) == set(PAPER_T12)
    assert t12["PointNet"]["params"] == sum(p.numel() for p in PaperPointNet(40).parameters()) == 3_471_473
    # G's regressor (the official one at M = 12, b = 40) is the paper's 9.09 K; G whole within 1% of
    # the paper's PointNet plus that regressor
    assert t12["MVTN* (regressor)"]["params"] == 9_092  # the paper: 9.09 K
    assert abs(t12["MVTN° (PointNet + regressor)"]["params"] - (3.47e6 + 9.09e3)) / 3.48e6 < 0.01
    assert abs(t12["PointNet"]["flops"] / PAPER_T12["PointNet"][0] - 1) < 0.03  # 2,048 points: the paper's FLOPs
    assert t12["MVTN° (PointNet + regressor)"]["flops"] > t12["PointNet"]["flops"] > 1e3 * t12["MVTN* (regressor)"]["flops"]
    t13 = {(r["module"], r["M"]): r for r in res["t13"]}
    assert {m for m, _ in t13} == {"R points", "R meshes", "MVCNN ResNet-18", "G PointNet", "G DGCNN", SEG}
    # MVPartSeg's C: torchvision's DeepLabV3-ResNet101 with its auxiliary head (60,996,202 with 21
    # outputs) with 51 outputs (each 1x1 classifier: 30 more outputs of 256 weights and a bias)
    assert t13[(SEG, 4)]["params"] == 60_996_202 + 2 * 30 * 257 and t13[(SEG, 4)]["paper"][1] == 61.0e6
    # C's FLOPs grow with the views: 4 of 12 at the same image size
    assert t13[("MVCNN ResNet-18", 4)]["flops"] == pytest.approx(t12["MVCNN"]["flops"] / 3, rel=1e-4)  # (+ one head)
    assert t13[("R points", 4)]["flops"] is None and all(r["ms"] > 0 for r in res["t12"] + res["t13"])
    md = markdown(res, "cpu")
    assert "| PointNet | 2048 points | 3.47 / 3.49 |" in md and "| MVTN* (regressor) | point features given | 0.00909 / 0.00909 |" in md


def _compare(mesh, size, views):
    r = MultiViewRenderer(image_size=size)
    azim, elev, dist = layouts.spherical(views)
    pf = r.project_faces(mesh, azim, elev, dist)[0]
    ref = mesh_raster.search_faces(pf, H=size, W=size, K=1, blur_radius=0.0, tile_size=r.cfg.tile_size,
                                   max_candidates=r.cfg.max_candidates)
    got = dense_search(pf, H=size, W=size, chunk_pairs=5000)  # small chunks: several per image
    assert len(ref.pix) > 0
    assert torch.equal(got.pix, ref.pix)
    assert torch.equal(got.prim, ref.prim)
    return pf


def test_dense_reference_matches_search_faces_torus():
    pf = _compare(torus("torus-2k", "cpu"), 32, 3)
    assert dense_pairs(pf, 32, 32) == 32 * 32 * int(pf.alive.sum()) <= estimate_pairs(2048, 3, 32, 32)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dense_reference_matches_search_faces_overlapping(dtype):
    _compare(random_triangles(200, seed=3, dtype=dtype), 40, 4)


def test_peak_memory_detects_200mib():
    n = 200 * (1 << 20) // 4
    with PeakMemory("cpu") as pm:
        x = torch.ones(n)  # touched: resident
        time.sleep(0.02)
        del x
    assert 140 <= pm.peak_mib <= 260, pm.peak_mib
    with PeakMemory("cpu") as small:
        y = torch.ones(1000)
        del y
    assert small.peak_mib < 50


def test_loader_bench_table():
    from mvtn_exp.bench.loader_bench import run

    rows = [ln for ln in run(shapes=8, faces=80, batch=4, views=2, size=32).splitlines() if ln.startswith("| ")]
    assert [r.split("|")[1].strip() for r in rows[1:]] == ["0", "2"]
    for r in rows[1:]:
        ms_batch, ms_step, share = (c.strip() for c in r.split("|")[2:5])
        assert float(ms_batch) > 0 and float(ms_step) > 0 and share.endswith("%")


def test_prob_cutoff_bench_measures_against_the_default():
    """The cut-off shortcut's table: the default row is the reference (no error, cosine 1); a larger
    cut-off shrinks the blur radius and moves some edge pixels (it is measured, not free)."""
    from studies import study

    prob_cutoff = study("prob_cutoff")
    from mvtn_exp.bench.edge_error import torus_mesh
    from mvtn_exp.render.config import RendererConfig

    rows = prob_cutoff.measure(torus_mesh(12), [prob_cutoff.DEFAULT, 0.05], size=32, views=2, repeats=1)
    ref, cut = rows
    assert ref["cov_off"] == ref["rgb_off"] == 0.0 and abs(ref["grad_cos"] - 1) < 1e-6 and ref["edge_pixels"] > 0
    assert cut["cov_max"] > 0 and cut["grad_cos"] < 1 - 1e-6
    small, big = (RendererConfig(mode="soft", prob_cutoff=p).effective_blur() for p in (0.05, 1e-4))
    assert small < big
    assert "| 0.05 |" in prob_cutoff.to_markdown(rows, "t")


def test_scaling_fit_and_bend_on_known_curves():
    from mvtn_exp.bench.scaling import bend, fit_exponent

    ns = [1, 2, 4, 8, 16]
    assert math.isclose(fit_exponent(ns, [3 * n ** 1.5 for n in ns]), 1.5)
    # flat (fixed cost) until 4, then linear: the bend is at n = 4, local exponent 0 -> 1
    ys = [10, 10, 10, 20, 40]
    assert bend(ns, ys) == "n=4: 0.00 -> 1.00"
    assert bend([1, 2], [1, 2]) == "-"


def test_step_ratio_bench_times_both_sides_with_the_trainers_step(tmp_path):
    """Fixed and learned views at the same M, stage split from the trainer's StepTimer."""
    from mvtn_exp.bench import step_ratio

    rows = step_ratio.measure([f"dataset.root={tmp_path}", "dataset.num_per_class=[4,2,2]", "image_size=32", "batch_size=4",
                               "logger=none"], views=(1, 2), rounds=1, batches=2)
    assert [r["views"] for r in rows] == [1, 2] and all(r["selector"] == "mvtn_spherical" for r in rows)
    for r in rows:
        assert r["steps_per_round"] == 2
        for side in step_ratio.SIDES:
            parts = sum(r[f"{side}_{k}"] for k in ("data", "selector", "render", "backbone", "optimizer"))
            assert r[f"{side}_total"] > 0 and abs(parts - r[f"{side}_total"]) < 1e-9
        assert r["learned_selector"] > 0 and 0 < r["render_share"] < 1 and r["ratio"] > 0
    table = step_ratio.to_markdown(rows, "t")
    assert table.count("\n| ") == 3 and "| 2 | " in table


def test_step_ratio_overrides_of_the_learned_side_leave_the_fixed_side_alone(tmp_path):
    """``learned`` overrides reach the learned side only (a key the fixed selector lacks is fine)."""
    from mvtn_exp.bench import step_ratio

    common = [f"dataset.root={tmp_path}", "dataset.num_per_class=[4,2,2]", "image_size=32", "batch_size=4", "logger=none"]
    learned = ["selector=mvtn_poi", "selector.gain=16"]
    fixed = step_ratio._side(common, 1, True, 1, 0, learned)["cfg"]
    mine = step_ratio._side(common, 1, False, 1, 0, learned)["cfg"]
    assert fixed.selector.name == "spherical" and not hasattr(fixed.selector, "gain")
    assert mine.selector.name == "mvtn_poi" and mine.selector.gain == 16
    rows = step_ratio.measure(common, views=(1,), rounds=1, batches=1, learned=learned)
    assert rows[0]["selector"] == "mvtn_poi"


def test_paired_times_alternate_which_side_goes_first():
    from mvtn_exp.bench.timing import paired_times

    calls = []
    ta, tb = paired_times(lambda: calls.append("a"), lambda: calls.append("b"), torch.device("cpu"), repeats=5,
                          budget_s=10.0)
    assert len(ta) == len(tb) == 5
    # warm-ups, round 1 (a first), then b first, a first, ...
    assert "".join(calls) == "ab" + "ab" + "ba" + "ab" + "ba" + "ab"
    ta, tb = paired_times(lambda: time.sleep(0.02), lambda: None, torch.device("cpu"), repeats=50, budget_s=0.01)
    assert len(ta) == len(tb) == 5  # at least 5 rounds, whatever the budget


def test_paired_ratio_is_the_median_of_the_rounds_ratios():
    """A load that changes between rounds cancels in each round's ratio; the ratio of the medians
    would pair one side's loaded rounds with the other's quiet ones (the bench's rounds at a758e68)."""
    from mvtn_exp.bench.timing import paired_ratio

    a, b = [103.5, 98.8, 83.4, 69.8, 64.2], [56.3, 56.8, 36.8, 36.3, 36.6]
    assert paired_ratio((a, b)) == pytest.approx(103.5 / 56.3)  # rounds' ratios 1.84 1.74 2.27 1.92 1.75
    assert sorted(a)[2] / sorted(b)[2] == pytest.approx(2.266, abs=1e-3)  # what the medians' ratio said
    assert paired_ratio(([2.0, 4.0], [1.0, 2.0])) == pytest.approx(2.0)
    assert paired_ratio(([3.0], [1.0, 2.0, 1.5])) == pytest.approx(2.0)  # unpaired: medians divided


def test_targets_take_their_ratios_from_the_paired_times():
    """With paired times the Targets rows use them (not the grid's own rows, timed at another moment)."""
    from mvtn_exp.bench.render_bench import Bench, BenchOptions
    from mvtn_exp.bench.render_report import targets

    b = Bench(BenchOptions())
    S, M = b.grid.target_size, b.grid.target_views
    b.res.resnet.append(dict(images=M, size=S, fwd_bwd_s=[1.0]))
    for name, K, sh, t in (("torus-20k", 1, "flat", 0.5), ("torus-2k", 1, "flat", 0.1), ("torus-100k", 1, "flat", 0.9)):
        b.res.grid.append(dict(shape=name, size=S, views=M, K=K, shading=sh, fwd_bwd_s=[t]))
    rows = {r["target"].split(":")[0]: r for r in targets(b)}
    hard = rows[f"20k-face mesh, {M} views, {S} px, K=1"]
    assert hard["status"] == "MISS" and hard["measured"] == pytest.approx(0.5)  # from the grid rows
    b.res.paired.update(hard=([0.1, 0.11, 0.095], [1.0, 1.1, 0.95]), **{"100k": ([0.15] * 3, [0.1] * 3)})
    rows = {r["target"]: r for r in targets(b)}
    hard = next(r for t, r in rows.items() if t.startswith(f"20k-face mesh, {M} views, {S} px, K=1"))
    assert hard["status"] == "PASS" and hard["measured"] == pytest.approx(0.1) and "100.0 ms vs ResNet-18 1000.0 ms: 0.100 x" in hard["value"]
    big = next(r for t, r in rows.items() if "without LOD" in t)
    assert big["status"] == "PASS" and big["measured"] == pytest.approx(1.5)
    assert next(r for t, r in rows.items() if "with LOD" in t)["status"].startswith("n/a")
