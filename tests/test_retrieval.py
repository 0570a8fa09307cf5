"""Retrieval: AP / mAP against sklearn and brute force, ranking ties, LFDA (scatter, eigenproblem,
separation vs PCA, degenerate inputs), SHREC'17 metrics on a hand-computed example, PR curve, PNG."""
from __future__ import annotations

import math

import numpy as np
import pytest
from sklearn.decomposition import PCA
from sklearn.metrics import average_precision_score

from mvtn_exp.tasks.retrieval import (
    LFDA,
    average_precision,
    lfda,
    local_scatter,
    mean_average_precision,
    pr_curve,
    pr_curve_png,
    rank,
    regularize,
    shrec17_gains,
    shrec17_metrics,
)


def _brute_ap(rel_sorted):
    hits, precs = 0, []
    for i, r in enumerate(rel_sorted):
        if r:
            hits += 1
            precs.append(hits / (i + 1))
    return sum(precs) / len(precs) if precs else 0.0


# ------------------------------------------------------------------------------------- AP / mAP

def test_ap_matches_sklearn_and_brute_force():
    rng = np.random.default_rng(0)
    q, db = rng.normal(size=(7, 5)), rng.normal(size=(40, 5))  # continuous: distinct distances
    ql, dl = rng.integers(0, 3, 7), rng.integers(0, 3, 40)
    dist = np.linalg.norm(q[:, None] - db[None], axis=-1)
    assert all(len(np.unique(row)) == row.size for row in dist)
    m, per = mean_average_precision(q, ql, db, dl)
    order = rank(q, db)
    for i in range(len(q)):
        relevant = dl == ql[i]
        assert np.array_equal(order[i], np.argsort(dist[i]))
        assert per[i] == pytest.approx(average_precision_score(relevant, -dist[i]), abs=1e-12)
        assert per[i] == pytest.approx(_brute_ap(relevant[order[i]]), abs=1e-12)
        assert average_precision(relevant[order[i]]) == pytest.approx(per[i])
    assert m == pytest.approx(per.mean())


def test_rank_covers_whole_database_and_breaks_ties_by_index():
    db = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]])
    q = np.zeros((2, 2))  # every database item at distance 1: pure tie
    order = rank(q, db)
    assert order.shape == (2, 5)
    assert order.tolist() == [[0, 1, 2, 3, 4]] * 2
    q2 = np.array([[1.0, 0.1]])  # items 0 and 2 tie (duplicates), then 1/4 tie, then 3
    assert rank(q2, db).tolist() == [[0, 2, 1, 4, 3]]
    rng = np.random.default_rng(1)
    big = rank(rng.normal(size=(3, 4)), rng.normal(size=(600, 4)))  # more than one block of queries
    assert all(sorted(row) == list(range(600)) for row in big.tolist())


def test_ap_no_relevant_is_zero_and_map_ranks_everything():
    assert average_precision(np.zeros(5, dtype=bool)) == 0.0
    assert average_precision([False, True, False, True]) == pytest.approx((1 / 2 + 2 / 4) / 2)
    db = np.arange(6, dtype=float)[:, None]
    dl = np.array([0, 0, 0, 1, 1, 1])
    q = np.array([[0.0], [5.0]])
    m, per = mean_average_precision(q, [2, 1], db, dl)  # class 2 is absent from the database
    assert per[0] == 0.0 and per[1] == pytest.approx(1.0)
    assert m == pytest.approx(0.5)
    # far relevant item is still counted: the whole database is ranked, not a top-k prefix
    _, per2 = mean_average_precision([[0.0]], [1], db, np.array([1, 0, 0, 0, 0, 1]))
    assert per2[0] == pytest.approx((1 + 2 / 6) / 2)


# ------------------------------------------------------------------------------------------ LFDA

def _brute_scatter(X, y, k, scaling="class"):
    """Sugiyama (2007) written out pair by pair; sigma_i: the k-th nearest neighbour of x_i within
    its class ("class", k clamped to n_c - 1; a lone sample's sigma does not matter) or among all."""
    n = len(X)
    D = np.linalg.norm(X[:, None] - X[None], axis=-1)
    if scaling == "all":
        sigma = np.sort(D, axis=1)[:, k]
    else:
        sigma = np.ones(n)
        for i in range(n):
            same = np.sort(D[i, y == y[i]])  # itself first
            if len(same) > 1:
                sigma[i] = same[min(k, len(same) - 1)]
    A = np.exp(-D ** 2 / np.outer(sigma, sigma))
    counts = {c: int((y == c).sum()) for c in np.unique(y)}
    S_w, S_b = np.zeros((X.shape[1],) * 2), np.zeros((X.shape[1],) * 2)
    for i in range(n):
        for j in range(n):
            diff = np.outer(X[i] - X[j], X[i] - X[j])
            if y[i] == y[j]:
                nc = counts[y[i]]
                S_w += 0.5 * A[i, j] / nc * diff
                S_b += 0.5 * A[i, j] * (1 / n - 1 / nc) * diff
            else:
                S_b += 0.5 / n * diff
    return S_w, S_b


@pytest.mark.parametrize("scaling", ["class", "all"])
def test_local_scatter_matches_pairwise_definition(scaling):
    rng = np.random.default_rng(2)
    X = rng.normal(size=(13, 3)) + 5.0
    y = np.array([0] * 5 + [1] * 4 + [2] * 3 + [3])
    S_w, S_b = local_scatter(X, y, k=3, scaling=scaling)
    ref_w, ref_b = _brute_scatter(X, y, 3, scaling)
    assert np.allclose(S_w, ref_w, atol=1e-10) and np.allclose(S_b, ref_b, atol=1e-10)


def test_class_wise_local_scaling_is_the_default_and_differs():
    """Sugiyama's LFDA scales by the k-th neighbour within the class; the all-samples variant gives
    another S_w (interleaved classes: a sample's neighbours are mostly of other classes)."""
    rng = np.random.default_rng(5)
    X = rng.normal(size=(60, 4))
    y = np.arange(60) % 3
    default, _ = local_scatter(X, y, k=7)
    cls, _ = local_scatter(X, y, k=7, scaling="class")
    every, _ = local_scatter(X, y, k=7, scaling="all")
    assert np.array_equal(default, cls)
    assert np.linalg.norm(every - cls) / np.linalg.norm(cls) > 0.05
    with pytest.raises(ValueError, match="scaling"):
        local_scatter(X, y, scaling="global")


def _loo_1nn(Z, y):
    D = np.linalg.norm(Z[:, None] - Z[None], axis=-1)
    np.fill_diagonal(D, np.inf)
    return float((y[D.argmin(1)] == y).mean())


def _hidden_subspace_data(seed=3, per_class=40, d=10):
    rng = np.random.default_rng(seed)
    means = np.array([[0.0, 0.0], [3.0, 0.0], [1.5, 2.6]])
    y = np.repeat(np.arange(3), per_class)
    signal = means[y] + 0.4 * rng.normal(size=(len(y), 2))
    noise = 8.0 * rng.normal(size=(len(y), d - 2))  # high variance, no class information
    Q = np.linalg.qr(rng.normal(size=(d, d)))[0]  # hide the subspace by a random rotation
    return np.hstack([signal, noise]) @ Q, y


def test_lfda_separates_better_than_pca():
    X, y = _hidden_subspace_data()
    Z_lfda = LFDA(dim=2, k=7).fit_transform(X, y)
    Z_pca = PCA(n_components=2).fit_transform(X)
    acc_lfda, acc_pca = _loo_1nn(Z_lfda, y), _loo_1nn(Z_pca, y)
    assert acc_lfda > 0.95
    assert acc_lfda > acc_pca + 0.3


def test_lfda_generalised_eigenproblem_residual():
    X, y = _hidden_subspace_data(seed=4, per_class=15, d=6)
    eps = 1e-4
    V = lfda(X, y, dim=3, k=5, metric="plain", eps=eps)
    S_w, S_b = local_scatter(X, y, k=5)
    S_reg = regularize(S_w, eps, S_b)
    lam = np.einsum("di,de,ei->i", V, S_b, V) / np.einsum("di,de,ei->i", V, S_reg, V)
    resid = np.linalg.norm(S_b @ V - S_reg @ V * lam, axis=0) / np.linalg.norm(S_b @ V, axis=0)
    assert resid.max() < 1e-8
    assert np.all(np.diff(lam) <= 1e-9)  # descending
    model = LFDA(dim=3, k=5, eps=eps).fit(X, y)
    assert np.allclose(model.eigvals_, lam, rtol=1e-8)
    # the weighted embedding scales the same vectors by sqrt(lambda)
    assert np.allclose(lfda(X, y, 3, 5, "weighted", eps), V * np.sqrt(np.clip(lam, 0, None)))
    T = lfda(X, y, 3, 5, "orthonormalized", eps)
    assert np.allclose(T.T @ T, np.eye(3), atol=1e-10)


def test_lfda_degenerate_inputs_shapes_and_clamp():
    rng = np.random.default_rng(5)
    X = rng.normal(size=(8, 30))  # d > n: S_w singular
    y = np.array([0, 0, 0, 1, 1, 1, 2, 3])  # classes 2 and 3 have one sample
    for metric in ("weighted", "orthonormalized", "plain"):
        T = lfda(X, y, dim=4, metric=metric)
        assert T.shape == (30, 4) and np.all(np.isfinite(T))
    X[1] = X[0]  # duplicate point: sigma may hit the floor
    model = LFDA(dim=2, k=1).fit(X, y)
    Z = model.transform(rng.normal(size=(5, 30)))
    assert Z.shape == (5, 2) and np.all(np.isfinite(Z))
    assert np.allclose(model.transform(model.mean_[None]), 0.0)
    assert lfda(rng.normal(size=(20, 5)), np.arange(20) % 2, dim=50).shape == (5, 5)  # dim clamped to d
    assert np.all(np.isfinite(lfda(np.ones((4, 3)), [0, 0, 1, 1], dim=2)))  # all points identical
    with pytest.raises(ValueError):
        lfda(X, y, dim=2, metric="nope")


# -------------------------------------------------------------------------------- SHREC metrics

# database: 1-D points 0, 1, 2, 3 with labels 0, 1, 0, 1.
# query A (label 0, x=1.4): order 1, 2, 0, 3 -> relevance 0 1 1 0
# query C (label 0, x=-.5): order 0, 1, 2, 3 -> relevance 1 0 1 0
# query D (label 1, x=-.5): order 0, 1, 2, 3 -> relevance 0 1 0 1
_DB, _DL = np.arange(4.0)[:, None], np.array([0, 1, 0, 1])
_Q, _QL = np.array([[1.4], [-0.5], [-0.5]]), np.array([0, 0, 1])


def test_shrec_metrics_hand_computed():
    """The SHREC'17 evaluator's definitions on a hand-worked case: AP divided by the relevant
    models of the ground truth, DCG with ranks 1 and 2 both weighing 1."""
    out = shrec17_metrics(_Q, _QL, _DB, _DL, n=3)
    assert out["N"] == 3
    g = 1 / math.log2(3)
    # A: rel 0 1 1 -> DCG 0 + 1 + g, ideal 1 + 1; C: 1 0 1 -> 1 + 0 + g; D: 0 1 0 -> 1; R = 2 for every query
    per = {"P@N": [2 / 3, 2 / 3, 1 / 3], "R@N": [1, 1, 0.5], "F1@N": [0.8, 0.8, 0.4],
           "mAP": [(1 / 2 + 2 / 3) / 2, (1 + 2 / 3) / 2, (1 / 2) / 2],
           "NDCG": [(1 + g) / 2, (1 + g) / 2, 1 / 2]}
    for key, vals in per.items():
        assert out["per_query"][key] == pytest.approx(vals), key
        assert out["micro"][key] == pytest.approx(np.mean(vals)), key
        assert out["macro"][key] == pytest.approx(((vals[0] + vals[1]) / 2 + vals[2]) / 2), key
    assert out["micro"]["P@N"] == pytest.approx(5 / 9) and out["macro"]["P@N"] == pytest.approx(0.5)
    assert out["macro"]["mAP"] == pytest.approx(23 / 48)


def test_shrec_map_counts_the_relevant_models_of_the_ground_truth():
    """A list too short to hold every relevant model scores less: 3 of 10 relevant, all at the top,
    give AP 3/10 (the per-list average precision would say 1)."""
    db = np.arange(11.0)[:, None]
    labels = np.array([0] * 10 + [1])
    out = shrec17_metrics([[0.0]], [0], db, labels, n=3)
    assert out["per_query"]["mAP"][0] == pytest.approx(0.3)
    assert average_precision([True, True, True]) == 1.0
    assert out["per_query"]["P@N"][0] == 1.0 and out["per_query"]["R@N"][0] == pytest.approx(0.3)


def test_shrec_n_capped_and_graded_ndcg():
    out = shrec17_metrics(_Q, _QL, _DB, _DL)  # default n=1000 > 4 database items
    assert out["N"] == 4
    assert out["micro"]["R@N"] == pytest.approx(1.0) and out["micro"]["P@N"] == pytest.approx(0.5)
    g = 1 / math.log2(3)
    # graded, query A (sub 'a'): order 1, 2, 0, 3; item 0 same sub-synset (3), item 2 labelled only
    # at the synset (2) -> gains 0 2 3: DCG 0 + 2 + 3 g, ideal 3 + 2
    subs = ["a", "x", None, "y"]
    graded = shrec17_metrics(_Q[:1], _QL[:1], _DB, _DL, n=3, query_sublabels=["a"], db_sublabels=subs)
    assert graded["per_query"]["NDCG"][0] == pytest.approx((2 + 3 * g) / 5)
    assert graded["micro"]["P@N"] == pytest.approx(2 / 3)  # P/R use binary relevance
    # a query labelled only at its synset: item 0 (a sub-synset) 1, item 2 (synset only too: the
    # evaluator's sub-synset ids are equal, both the synset's) 3
    assert shrec17_gains(_DL == 0, None, subs).tolist() == [1.0, 0.0, 3.0, 0.0]
    assert shrec17_gains(_DL == 0, "b", subs).tolist() == [1.0, 0.0, 2.0, 0.0]  # a sibling sub-synset: 1
    none_rel = shrec17_metrics([[0.0]], [7], _DB, _DL, n=2)  # no relevant item anywhere
    assert all(v == 0.0 for v in none_rel["micro"].values())
    with pytest.raises(ValueError):
        shrec17_metrics(_Q, _QL, _DB, _DL, query_sublabels=["a"] * 3)


def test_shrec_synset_only_models_grade_as_the_evaluator_does():
    """The toy case: one synset, the query and two database models labelled only at the synset,
    two with a sub-synset. The evaluator gives synset-only pairs 3 (equal sub-synset ids in the
    CSV); grading them 2 (the former reading) gives another NDCG."""
    db = np.arange(5.0)[:, None]
    labels = np.zeros(5, dtype=int)
    subs = [None, "a", "b", None, None]  # item 0 is the query itself
    out = shrec17_metrics([[0.0]], [0], db, labels, n=5, query_sublabels=[None], db_sublabels=subs)
    g = [3, 1, 1, 3, 3]  # ranked by distance: items 0..4
    dcg = lambda gs: gs[0] + sum(v / math.log2(r) for r, v in enumerate(gs[1:], start=2))
    assert out["per_query"]["NDCG"][0] == pytest.approx(dcg(g) / dcg(sorted(g, reverse=True)))
    former = [2, 1, 1, 2, 2]
    assert abs(dcg(former) / dcg(sorted(former, reverse=True)) - out["per_query"]["NDCG"][0]) > 0.01


def test_shrec_against_a_brute_force_evaluator():
    """Random features, 4 synsets with sub-synsets: every metric equals a direct re-implementation
    written from the definitions (the query's own split as database, itself included)."""
    rng = np.random.default_rng(0)
    n, N = 40, 7
    X = rng.normal(size=(n, 5))
    y = rng.integers(0, 4, n)
    sub = [None if rng.random() < 0.4 else f"{c}-{rng.integers(0, 2)}" for c in y]
    out = shrec17_metrics(X, y, X, y, n=N, query_sublabels=sub, db_sublabels=sub)
    for q in range(n):
        d = ((X - X[q]) ** 2).sum(1)
        top = sorted(range(n), key=lambda j: (d[j], j))[:N]
        assert top[0] == q  # the query retrieves itself first
        relevant = [j for j in range(n) if y[j] == y[q]]
        hits = [j in relevant for j in top]

        csv_sub = [s_ if s_ is not None else f"synset-{c}" for s_, c in zip(sub, y)]  # the split CSV's column

        def grade(j):  # the evaluator's resultsToScores, on the CSV's sub-synset ids
            if y[j] != y[q]:
                return 0
            if csv_sub[j] == csv_sub[q]:
                return 3
            return 2 if csv_sub[j] == f"synset-{y[q]}" else 1

        ap = sum(sum(hits[:r + 1]) / (r + 1) for r in range(N) if hits[r]) / len(relevant)
        dcg = lambda gs: sum(g_ if r == 0 else g_ / math.log2(r + 1) for r, g_ in enumerate(gs))
        ideal = dcg(sorted((grade(j) for j in range(n)), reverse=True)[:N])
        p, r_ = sum(hits) / N, sum(hits) / len(relevant)
        expected = {"P@N": p, "R@N": r_, "F1@N": 2 * p * r_ / (p + r_), "mAP": ap, "NDCG": dcg([grade(j) for j in top]) / ideal}
        for key, val in expected.items():
            assert out["per_query"][key][q] == pytest.approx(val), (q, key)


# --------------------------------------------------------------------------------- PR curve, PNG

def test_pr_curve_eleven_point():
    recall, precision = pr_curve(_Q[1:2], _QL[1:2], _DB, _DL)  # relevance 1 0 1 0
    assert np.allclose(recall, np.linspace(0, 1, 11))
    assert np.allclose(precision, [1.0] * 6 + [2 / 3] * 5)
    _, p = pr_curve(_Q, _QL, _DB, _DL, points=3)  # levels 0, .5, 1 averaged over the 3 queries
    assert np.allclose(p, [(2 / 3 + 1 + 1 / 2) / 3, (2 / 3 + 1 + 1 / 2) / 3, (2 / 3 + 2 / 3 + 1 / 2) / 3])
    db, dl = np.array([[0.0], [1.0], [10.0], [11.0]]), np.array([0, 0, 1, 1])
    assert np.allclose(pr_curve(db + 0.1, dl, db, dl)[1], 1.0)  # perfect rankings


def test_pr_curve_png_magic(tmp_path):
    curves = {"raw": pr_curve(_Q, _QL, _DB, _DL), "lfda": (np.linspace(0, 1, 5), np.linspace(1, 0.5, 5))}
    path = pr_curve_png(curves, tmp_path / "sub" / "pr.png", title="PR")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError):
        pr_curve_png({"bad": ([0, 1], [1])}, tmp_path / "bad.png")
