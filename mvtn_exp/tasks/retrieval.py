"""Retrieval: LFDA metric learning, Euclidean ranking, AP / mAP, SHREC'17-style metrics
(P@N, R@N, F1@N, mAP, NDCG; micro and macro averages) and precision-recall curves.

Numpy / scipy only (matplotlib is imported lazily by ``pr_curve_png``). Features are ``[n, D]``
arrays (anything ``np.asarray`` accepts, e.g. CPU tensors); labels are ``[n]`` integer / hashable
arrays. Distances are Euclidean; every query ranks the WHOLE database (nothing is dropped, so a
query that is also in the database retrieves itself first: pass disjoint sets to avoid that).
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np
import scipy.linalg
from scipy.spatial.distance import cdist

METRICS = ("P@N", "R@N", "F1@N", "mAP", "NDCG")
_CHUNK = 512  # queries per distance block: [chunk, m] float64 at a time


# ----------------------------------------------------------------------------------------- LFDA

def _kth_neighbour_distance(X: np.ndarray, k: int) -> np.ndarray:
    """Distance of each row of ``X`` to its ``k``-th nearest other row (``k`` clamped to ``n - 1``;
    0 when ``n == 1``). Blocked so that memory is ``O(chunk * n)``."""
    n = X.shape[0]
    k = min(max(int(k), 1), n - 1)
    if k <= 0:
        return np.zeros(n)
    out = np.empty(n)
    for s in range(0, n, _CHUNK):
        d2 = cdist(X[s:s + _CHUNK], X, "sqeuclidean")
        # column 0 of the sorted row is the point itself (distance 0), so index k is the k-th neighbour
        out[s:s + _CHUNK] = np.sqrt(np.partition(d2, k, axis=1)[:, k])
    return out


def _laplacian_quadratic(Xc: np.ndarray, W: np.ndarray) -> np.ndarray:
    """``Xc^T (diag(W 1) - W) Xc`` = ``1/2 sum_ij W_ij (x_i - x_j)(x_i - x_j)^T`` for symmetric ``W``."""
    deg = W.sum(1)
    return (Xc * deg[:, None]).T @ Xc - Xc.T @ (W @ Xc)


SCALINGS = ("class", "all")


def local_scaling(X: np.ndarray, y: np.ndarray, k: int = 7, scaling: str = "class") -> np.ndarray:
    """``sigma [n]``: distance from ``x_i`` to its ``k``-th nearest neighbour among the samples of
    its own class (``scaling="class"``, Sugiyama 2007: the affinity is computed class by class; ``k``
    clamped to ``n_c - 1``, 0 for a one-sample class) or among all samples (``"all"``, the
    former default; ``k`` clamped to ``n - 1``); floored at ``1e-6 * mean(positive
    sigmas)`` (1.0 if every sigma is 0) so duplicates never divide by 0."""
    if scaling not in SCALINGS:
        raise ValueError(f"lfda: scaling must be one of {SCALINGS}, got {scaling!r}")
    if scaling == "all":
        sigma = _kth_neighbour_distance(X, k)
    else:
        sigma = np.zeros(X.shape[0])
        for c in np.unique(y):
            idx = np.flatnonzero(y == c)
            sigma[idx] = _kth_neighbour_distance(X[idx], k)
    positive = sigma[sigma > 0]
    return np.maximum(sigma, 1e-6 * positive.mean() if positive.size else 1.0)


def local_scatter(X, y, k: int = 7, scaling: str = "class") -> tuple[np.ndarray, np.ndarray]:
    """Local within-class and between-class scatter matrices ``(S_w, S_b)``, each ``[d, d]``, of
    LFDA (Sugiyama 2007).

    Local scaling ``sigma_i``: ``local_scaling(X, y, k, scaling)`` (class-wise by default, as
    Sugiyama defines it); affinity ``A_ij = exp(-|x_i - x_j|^2 / (sigma_i sigma_j))``.
    ``W_w_ij = A_ij / n_c`` (same class c, else 0); ``W_b_ij = A_ij (1/n - 1/n_c)`` (same class, else
    ``1/n``); ``S = 1/2 sum_ij W_ij (x_i - x_j)(x_i - x_j)^T``. Computed class block by class block
    (``S_b = S_m - S_w`` with the mixture weights ``A_ij / n`` same class, ``1/n`` otherwise), so
    memory is ``O(n * chunk + max n_c^2)``, never ``n x n``.
    """
    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y)
    if X.ndim != 2 or y.shape != (X.shape[0],):
        raise ValueError(f"local_scatter: X {X.shape} and y {y.shape} must be [n, d] and [n]")
    n, d = X.shape
    Xc = X - X.mean(0)  # scatter is translation invariant; centring helps the round-off
    sigma = local_scaling(Xc, y, k, scaling)
    S_w = np.zeros((d, d))
    S_m = Xc.T @ Xc  # the all-pairs 1/n part of the mixture weights: (1/n) Laplacian of 1 1^T
    for c in np.unique(y):
        idx = np.flatnonzero(y == c)
        if idx.size < 2:
            continue  # a one-sample class has no within-class pair
        Xk = Xc[idx]
        A = np.exp(-cdist(Xk, Xk, "sqeuclidean") / np.outer(sigma[idx], sigma[idx]))
        S_w += _laplacian_quadratic(Xk, A / idx.size)
        S_m += _laplacian_quadratic(Xk, (A - 1.0) / n)
    S_w = 0.5 * (S_w + S_w.T)
    S_b = S_m - S_w
    return S_w, 0.5 * (S_b + S_b.T)


def regularize(S_w: np.ndarray, eps: float = 1e-4, S_b: np.ndarray | None = None) -> np.ndarray:
    """``S_w + r I`` with ``r = eps * trace(S_w) / d``, falling back to ``eps * trace(S_b) / d`` (then
    1.0) when ``S_w`` is 0, plus an absolute floor ``1e-12``: positive definite even when ``S_w`` is
    singular (``d > n``, one-sample classes)."""
    d = S_w.shape[0]
    r = eps * float(np.trace(S_w)) / d
    if not r > 1e-300 and S_b is not None:
        r = eps * float(np.trace(S_b)) / d
    if not r > 1e-300:
        r = 1.0
    return S_w + (r + 1e-12) * np.eye(d)


def _lfda_eig(X, y, dim: int, k: int, eps: float, scaling: str = "class"):
    X = np.asarray(X, dtype=np.float64)
    d = X.shape[1]
    dim = min(max(int(dim), 1), d)
    S_w, S_b = local_scatter(X, y, k, scaling)
    vals, vecs = scipy.linalg.eigh(S_b, regularize(S_w, eps, S_b), subset_by_index=[d - dim, d - 1])
    vals, vecs = vals[::-1], vecs[:, ::-1]  # descending
    flip = np.sign(vecs[np.abs(vecs).argmax(0), np.arange(dim)])  # deterministic sign
    return vals, vecs * np.where(flip == 0, 1.0, flip)


_LFDA_METRICS = ("weighted", "orthonormalized", "plain")


def _check_metric(metric: str) -> None:
    if metric not in _LFDA_METRICS:
        raise ValueError(f"lfda: metric must be one of {_LFDA_METRICS}, got {metric!r}")


def _embed(vals: np.ndarray, vecs: np.ndarray, metric: str) -> np.ndarray:
    _check_metric(metric)
    if metric == "weighted":
        return vecs * np.sqrt(np.clip(vals, 0.0, None))
    if metric == "orthonormalized":
        return np.linalg.qr(vecs)[0]
    return vecs  # "plain"


def lfda(X, y, dim: int, k: int = 7, metric: str = "weighted", eps: float = 1e-4, scaling: str = "class") -> np.ndarray:
    """Local Fisher Discriminant Analysis -> transformation ``T [d, dim]`` (embed with ``X @ T``).

    Solves ``S_b v = lambda S_w_reg v`` (``scipy.linalg.eigh``, ``S_w_reg = regularize(S_w, eps)``)
    and keeps the ``dim`` largest eigenvalues. ``metric``: ``"weighted"`` = eigenvectors scaled by
    ``sqrt(max(lambda, 0))``, ``"orthonormalized"`` = Q of their QR, ``"plain"`` = the eigenvectors
    (``S_w_reg``-orthonormal). ``dim > d`` is clamped to ``d`` (so ``T`` has ``min(dim, d)`` columns).
    """
    _check_metric(metric)  # before the expensive part
    vals, vecs = _lfda_eig(X, y, dim, k, eps, scaling)
    return _embed(vals, vecs, metric)


class LFDA:
    """``fit(X, y)`` / ``transform(X) = (X - mean_train) @ T``; ``eigvals_`` (descending), ``T_``, ``mean_``."""

    def __init__(self, dim: int, k: int = 7, metric: str = "weighted", eps: float = 1e-4, scaling: str = "class"):
        self.dim, self.k, self.metric, self.eps, self.scaling = dim, k, metric, eps, scaling

    def fit(self, X, y) -> LFDA:
        X = np.asarray(X, dtype=np.float64)
        self.mean_ = X.mean(0)
        _check_metric(self.metric)
        self.eigvals_, vecs = _lfda_eig(X, y, self.dim, self.k, self.eps, self.scaling)
        self.T_ = _embed(self.eigvals_, vecs, self.metric)
        return self

    def transform(self, X) -> np.ndarray:
        if not hasattr(self, "T_"):
            raise RuntimeError("LFDA.transform before fit")
        return (np.asarray(X, dtype=np.float64) - self.mean_) @ self.T_

    def fit_transform(self, X, y) -> np.ndarray:
        return self.fit(X, y).transform(X)


# ------------------------------------------------------------------------------ ranking and mAP

def _as_2d(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"{name} must be [n, D], got shape {a.shape}")
    return a


def _rank_blocks(query, database) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Yields ``(start, order [b, m], sorted squared distances [b, m])`` per block of queries."""
    q, db = _as_2d(query, "query"), _as_2d(database, "database")
    if q.shape[1] != db.shape[1]:
        raise ValueError(f"query dim {q.shape[1]} != database dim {db.shape[1]}")
    for s in range(0, q.shape[0], _CHUNK):
        # cdist computes each pair on its own: identical database rows get bit-identical distances
        d2 = cdist(q[s:s + _CHUNK], db, "sqeuclidean")
        order = np.argsort(d2, axis=1, kind="stable")  # ties -> lower database index first
        yield s, order, np.take_along_axis(d2, order, 1)


def rank(query, database) -> np.ndarray:
    """``query [q, D]``, ``database [m, D]`` -> ``indices [q, m]``: every database index per query,
    nearest (Euclidean) first, ties broken by database index."""
    blocks = [order for _, order, _ in _rank_blocks(query, database)]
    return np.concatenate(blocks) if blocks else np.zeros((0, np.asarray(database).shape[0]), dtype=np.int64)


def average_precision(relevant_sorted) -> float:
    """Mean of the precision at each relevant rank of a ranked relevance list; 0 if none is relevant."""
    rel = np.asarray(relevant_sorted, dtype=bool)
    hits = np.flatnonzero(rel)
    if hits.size == 0:
        return 0.0
    return float(np.mean(np.arange(1, hits.size + 1) / (hits + 1)))


def mean_average_precision(query_feats, query_labels, db_feats, db_labels) -> tuple[float, np.ndarray]:
    """``(mAP, per-query AP [q])``: each query ranks the whole database (relevant = same label)."""
    ql, dl = np.asarray(query_labels), np.asarray(db_labels)
    ap = np.zeros(len(ql))
    for s, order, _ in _rank_blocks(query_feats, db_feats):
        rel = dl[order] == ql[s:s + order.shape[0], None]
        for i, r in enumerate(rel):
            ap[s + i] = average_precision(r)
    return (float(ap.mean()) if ap.size else 0.0), ap


# ------------------------------------------------------------------------------ SHREC'17 metrics

def _dcg(gains: np.ndarray) -> float:
    """The SHREC'17 evaluator's DCG: ``g_1 + sum_{r >= 2} g_r / log2(r)`` (ranks 1 and 2 weigh 1)."""
    if gains.size == 0:
        return 0.0
    return float(gains[0] + np.sum(gains[1:] / np.log2(np.arange(2, gains.size + 1))))


def shrec17_gains(same: np.ndarray, query_sub, db_subs) -> np.ndarray:
    """Graded relevance ``[m]`` of every database item to one query, as the SHREC'17 evaluator
    grades it (``resultsToScores``). The evaluator reads the split CSV, where a model labelled only
    at its synset carries the synset as its sub-synset id; here such a model has ``None``. So, in
    the query's synset (``same``): 3 when the two sub-synset ids are equal (two synset-only models
    included), 2 when the item is synset-only and the query is not, 1 otherwise (a sibling
    sub-synset, or a synset-only query and an item with a sub-synset); 0 in another synset."""
    gains = np.zeros(same.shape[0])
    if db_subs is None:
        gains[same] = 1.0
        return gains
    db_none = np.array([d is None for d in db_subs], dtype=bool)
    exact = np.array([d == query_sub for d in db_subs], dtype=bool)  # None == None: both synset-only
    gains[same] = 1.0
    gains[same & db_none] = 2.0
    gains[same & exact] = 3.0
    return gains


def shrec17_metrics(query_feats, query_labels, db_feats, db_labels, n: int = 1000,
                    query_sublabels=None, db_sublabels=None) -> dict:
    """SHREC'17 (ShapeNetCore55) retrieval metrics as the challenge's evaluator computes them, over
    the retrieved list: the top ``N = min(n, m)`` of each query's ranking (``rank``); relevant =
    same label (synset). In the challenge the database is the query's own split, the query
    included (``mvtn-eval`` does so); ``R`` = relevant items of the database.

    - ``P@N`` = relevant retrieved / N; ``R@N`` = relevant retrieved / R (0 when R = 0);
      ``F1@N`` = per-query ``2PR / (P + R)`` (0 when P + R = 0).
    - ``mAP``: per query ``sum over relevant retrieved ranks r of P@r``, divided by R (the relevant
      models of the ground truth, not the relevant retrieved: a list too short to hold them all
      scores less).
    - ``NDCG`` = DCG / ideal DCG (``_dcg``: ranks 1 and 2 weigh 1, then ``1 / log2 r``) with the
      graded relevance of ``shrec17_gains`` when ``query_sublabels`` / ``db_sublabels`` are given
      (sub-synsets; ``None`` for a model labelled only at its synset), else 1 for the same label;
      the ideal list is the database's N best gains (0 if none).

    Returns ``{"N": N, "micro": {metric: mean over queries}, "macro": {metric: mean over the query
    classes of the per-class mean}, "per_query": {metric: array [q]}}``.
    """
    ql, dl = np.asarray(query_labels), np.asarray(db_labels)
    m = dl.shape[0]
    if (query_sublabels is None) != (db_sublabels is None):
        raise ValueError("shrec17_metrics: give both query_sublabels and db_sublabels, or neither")
    qs = list(query_sublabels) if query_sublabels is not None else None
    ds = list(db_sublabels) if db_sublabels is not None else None
    if qs is not None and (len(qs) != len(ql) or len(ds) != m):
        raise ValueError(f"shrec17_metrics: {len(qs)} / {len(ds)} sub-labels for {len(ql)} queries / {m} items")
    N = min(int(n), m)
    if N < 1:
        raise ValueError(f"shrec17_metrics: need n >= 1 and a non-empty database (n={n}, m={m})")
    per = {k: np.zeros(len(ql)) for k in METRICS}
    ranks = np.arange(1, N + 1)
    for s, order, _ in _rank_blocks(query_feats, db_feats):
        for i, row in enumerate(order):
            j = s + i
            same = dl == ql[j]
            n_rel = int(same.sum())
            top = row[:N]
            rel = same[top]
            hits = int(rel.sum())
            p = hits / N
            r = hits / n_rel if n_rel else 0.0
            per["P@N"][j], per["R@N"][j] = p, r
            per["F1@N"][j] = 2 * p * r / (p + r) if p + r > 0 else 0.0
            per["mAP"][j] = float(np.sum((np.cumsum(rel) / ranks)[rel]) / n_rel) if n_rel else 0.0
            gains = shrec17_gains(same, qs[j] if qs is not None else None, ds)
            ideal = _dcg(np.sort(gains)[::-1][:N])
            per["NDCG"][j] = _dcg(gains[top]) / ideal if ideal > 0 else 0.0
    classes = np.unique(ql)
    micro = {k: float(v.mean()) if v.size else 0.0 for k, v in per.items()}
    macro = {k: float(np.mean([v[ql == c].mean() for c in classes])) if classes.size else 0.0
             for k, v in per.items()}
    return {"N": N, "micro": micro, "macro": macro, "per_query": per}


# ---------------------------------------------------------------------------- precision-recall

def pr_curve(query_feats, query_labels, db_feats, db_labels, points: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """Interpolated precision-recall curve averaged over queries -> ``(recall [points], precision
    [points])``.

    Recall levels are ``linspace(0, 1, points)`` (default 11: the classic 11-point curve). For each
    query (over its full ranking of the database), the interpolated precision at level ``r`` is the
    maximum precision at any rank whose recall is ``>= r``; these are averaged over the queries that
    have at least one relevant database item (zeros if none has).
    """
    if points < 2:
        raise ValueError("pr_curve: points must be >= 2")
    ql, dl = np.asarray(query_labels), np.asarray(db_labels)
    levels = np.linspace(0.0, 1.0, points)
    total, count = np.zeros(points), 0
    for s, order, _ in _rank_blocks(query_feats, db_feats):
        rel = dl[order] == ql[s:s + order.shape[0], None]
        for r in rel:
            n_rel = int(r.sum())
            if n_rel == 0:
                continue
            cum = np.cumsum(r)
            prec = cum / np.arange(1, r.size + 1)
            rec = cum / n_rel
            # max precision at recall >= level: suffix maximum, looked up at the first rank reaching level
            suffix_max = np.maximum.accumulate(prec[::-1])[::-1]
            first = np.searchsorted(rec, levels - 1e-12, side="left")
            total += suffix_max[np.minimum(first, r.size - 1)]
            count += 1
    return levels, (total / count if count else total)


def pr_curve_png(curves: Mapping[str, tuple[Sequence[float], Sequence[float]]], path, title: str = "") -> Path:
    """``{label: (recall, precision)}`` -> one line per label on ``[0, 1]^2`` -> ``path`` (PNG)."""
    from ..viz.plots import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 4.5), dpi=100)
    for label, (recall, precision) in curves.items():
        recall, precision = np.asarray(recall, dtype=float), np.asarray(precision, dtype=float)
        if recall.shape != precision.shape:
            plt.close(fig)
            raise ValueError(f"pr_curve_png: {label!r}: recall {recall.shape} != precision {precision.shape}")
        ax.plot(recall, precision, marker=".", label=str(label))
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.grid(alpha=0.3)
    if curves:
        ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)
