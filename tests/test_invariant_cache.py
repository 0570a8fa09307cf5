"""The content-keyed cache of mvtn_poi's rotation-invariant descriptors (selectors/invariant_cache.py)."""
import pytest
import torch

from mvtn_exp.selectors import build_selector
from mvtn_exp.selectors.invariant_cache import InvariantCache
from mvtn_exp.selectors.poi import invariant_descriptors


def _rotation(seed):
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    return q.float()  # det +-1: turns and reflections alike


def _clouds(B, N=128, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(B, N, 3, generator=g) * torch.tensor([1.0, 0.6, 0.3])
    return p - p.mean(1, keepdim=True)


class _Counting:
    def __init__(self):
        self.calls, self.rows = 0, 0

    def __call__(self, p):
        self.calls += 1
        self.rows += len(p)
        return invariant_descriptors(p, (8, 16))


def test_turned_clouds_hit_and_match_a_fresh_computation():
    fn = _Counting()
    cache = InvariantCache(fn, capacity=16)
    pts = _clouds(4)
    first = cache(pts)
    assert (fn.calls, fn.rows, cache.misses, cache.hits) == (1, 4, 4, 0)
    assert torch.equal(first, invariant_descriptors(pts, (8, 16)))
    hits = 0
    for seed in range(5):
        turned = pts @ _rotation(seed).T
        out = cache(turned)
        fresh = invariant_descriptors(turned, (8, 16))
        assert torch.allclose(out, fresh, atol=1e-4, rtol=1e-4)
        hits = cache.hits
    assert hits >= 16  # at most a rare rounding miss over 20 lookups of turned copies
    assert len(cache) <= 16


def test_other_clouds_and_other_orders_miss():
    fn = _Counting()
    cache = InvariantCache(fn, capacity=16)
    pts = _clouds(2)
    cache(pts)
    other = _clouds(2, seed=1)
    cache(other)
    assert cache.misses == 4 and cache.hits == 0
    shuffled = pts[:, torch.randperm(pts.shape[1], generator=torch.Generator().manual_seed(0))]
    out = cache(shuffled)
    assert cache.misses == 6  # a permuted cloud is another key: its rows follow its own order
    assert torch.equal(out, invariant_descriptors(shuffled, (8, 16)))
    # a cloud one point of which moved a little (within the key's rounding) must not reuse the entry
    nudged = pts.clone()
    nudged[:, 0] *= 1.001
    cache(nudged)
    assert cache.misses == 8


def test_capacity_bounds_the_entries_and_drops_the_least_recent():
    fn = _Counting()
    cache = InvariantCache(fn, capacity=3)
    a, b, c, d = (_clouds(1, seed=s) for s in range(4))
    for x in (a, b, c):
        cache(x)
    cache(a)  # a is now the most recent
    cache(d)  # drops b
    assert len(cache) == 3 and cache.misses == 4 and cache.hits == 1
    cache(a), cache(c), cache(d)
    assert cache.hits == 4
    cache(b)
    assert cache.misses == 5


def test_capacity_zero_always_computes_and_negative_is_refused():
    fn = _Counting()
    cache = InvariantCache(fn, capacity=0)
    pts = _clouds(2)
    cache(pts), cache(pts)
    assert fn.calls == 2 and len(cache) == 0
    with pytest.raises(ValueError, match="capacity"):
        InvariantCache(fn, capacity=-1)


def test_poi_views_with_the_cache_equal_those_without():
    torch.manual_seed(0)
    plain = build_selector("mvtn_poi", 2, cache=0).eval()
    cached = build_selector("mvtn_poi", 2, cache=8).eval()
    cached.load_state_dict(plain.state_dict())
    for sel in (plain, cached):
        for p in sel.scorer[-1].parameters():
            torch.nn.init.normal_(p, std=1.0, generator=torch.Generator().manual_seed(1))
    pts = _clouds(3, N=96)
    for seed in range(3):
        turned = pts @ _rotation(seed).T
        for a, b in zip(plain(turned), cached(turned)):
            assert torch.allclose(a, b, atol=1e-3)
    assert cached.descriptors.hits >= 4 and len(cached.descriptors) <= 8
