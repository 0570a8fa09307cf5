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
