"""The GPU-cost counter: kernel ops (operators that compute, views excluded) and host syncs
(data-dependent sizes, reads to the host), counted on the CPU; and the paper-scale bench rows."""
from __future__ import annotations

import torch

from mvtn_exp.bench.kernel_ops import OpCounter, count_call


def test_counts_computing_ops_not_views_and_the_syncs_among_them():
    x = torch.arange(12.0)
    with OpCounter() as c:
        y = x.view(3, 4).t()[1:]  # views only
        z = y + 1  # one kernel
    assert c.ops == 1 and c.syncs == 0 and z.shape == (3, 3)
    with OpCounter() as c:
        torch.nonzero(x > 3)  # gt, nonzero (sync)
        x[x > 5]  # gt, index with a bool mask (sync)
        int(x.sum())  # sum, item (sync)
        x.tolist()  # a read to the host (sync, no operator on the CPU)
        torch.repeat_interleave(torch.arange(3), torch.tensor([1, 2, 3]))  # size from data (sync)
        torch.repeat_interleave(torch.arange(3), torch.tensor([1, 2, 3]), output_size=6)  # size given: none
        x.index_select(0, torch.tensor([1, 2]))  # no sync
    assert c.syncs == 5, c.sync_names
    assert set(c.sync_names) == {"nonzero", "index", "_local_scalar_dense", "tolist", "repeat_interleave"}
    assert c.ops >= 9


def test_count_call_counts_forward_and_backward_apart():
    w = torch.ones(4, requires_grad=True)
    row = count_call(lambda: (w * 2).exp(), lambda out: out.sum())
    assert row["fwd_ops"] == 2 and row["fwd_syncs"] == 0 and row["bwd_ops"] >= 2 and w.grad is not None


def test_paper_scale_call_counts_a_render_and_a_budget_groups_it():
    from mvtn_exp.bench import paper_scale

    dev = torch.device("cpu")
    one = paper_scale.call("points", 2, None, dev, count=True)
    assert one["groups"] == 1 and one["fwd_ops"] > 50 and one["bwd_ops"] > 10 and one["seconds"] > 0
    # no per-shape work: a larger batch costs the same number of operators
    four = paper_scale.call("points", 4, None, dev, count=True)
    assert four["fwd_ops"] == one["fwd_ops"] and four["fwd_syncs"] == one["fwd_syncs"]
    split = paper_scale.call("points", 4, 500.0, dev, count=True)  # room for about one shape per group
    assert split["groups"] >= 2 and split["fwd_ops"] > four["fwd_ops"]
    res = {"counts": [dict(four, batch=paper_scale.BATCH)], "budget": [], "resnet_ms": 1.0}
    text = paper_scale.markdown(res, on_gpu=False)
    assert "| points | 32 |" in text and "kernel ops per forward render" in text


def test_a_search_in_chunks_reads_their_sizes_once_not_per_chunk(monkeypatch):
    """Binning into tiles costs two host reads per search pass (the pair count, then every tile's
    counts at once), and each further chunk at most its three data-dependent sizes (row spans,
    hidden and kept candidates): a read per tile or a second read of a chunk's counts fails."""
    from conftest import icosphere
    from mvtn_exp.render import tiles
    from mvtn_exp.render.renderer import MultiViewRenderer

    mesh = icosphere(3)
    a, e = torch.tensor([[0.0, 90.0, 180.0, 270.0]]), torch.full((1, 4), 20.0)
    passes, chunks = [], []
    split, enumerate_ = tiles._split_box_by_tiles, tiles._enumerate
    monkeypatch.setattr(tiles, "_split_box_by_tiles", lambda *x, **k: passes.append(1) or split(*x, **k))
    monkeypatch.setattr(tiles, "_enumerate", lambda *x, **k: chunks.append(1) or enumerate_(*x, **k))
    rows = {}
    for name, chunk in (("one", None), ("tiled", 4000)):
        passes.clear(), chunks.clear()
        r = MultiViewRenderer(image_size=64, mode="soft", faces_per_pixel=4, tile_size=16,
                              **({} if chunk is None else dict(max_candidates=chunk)))
        with OpCounter() as c, tiles.gpu_path():  # (the search's CUDA form, as the benchmark counts it)
            r(mesh, a, e, 2.5)
        rows[name] = (c.syncs, len(passes), len(chunks))
    (one, _, n_one), (tiled, n_passes, n_chunks) = rows["one"], rows["tiled"]
    assert n_passes == 2 and n_chunks >= n_one + 4, rows  # both passes binned, several chunks each
    assert tiled <= one + 2 * n_passes + 3 * (n_chunks - n_one), rows
