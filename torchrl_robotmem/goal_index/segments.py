"""Segment search: the exact k nearest rows of one frozen set of rows.

A :class:`Segment` holds storage rows frozen when it was built. It is searched
with scipy's ``cKDTree`` over a Euclidean embedding of the goals whose
distances never exceed the metric (:class:`TreeSegment`; the identity for
``"euclidean"``, position + scaled quaternion queried with both signs for
``"pose"``), or by brute force (:class:`BruteSegment`: float32 matrix products
with a proven rounding-error margin, or float64 ``pairwise`` for a metric
without an embedding). :func:`search_segment` re-scores candidates with the
exact metric in float64 and fetches more until the lower bound on every row
not returned reaches the current k-th distance, so its result equals a
brute-force search (ties aside).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree

from torchrl_robotmem.goal_index.metrics import GoalMetric

__all__ = ["BruteSegment", "Segment", "TreeSegment", "build_segment", "row_dtype", "search_segment"]

LEVEL_MAIN, LEVEL_MID, LEVEL_LIVE = 1, 2, 3
_F32_EPS = 2.0**-24


NODE_BYTES = 72
"""Bytes of one ``cKDTree`` node (scipy's ``ckdtreenode``: nine 8-byte fields)."""

LEAFSIZE = 16


def row_dtype(rows: np.ndarray) -> type:
    """int32 when every row of ``rows`` fits (storages below 2**31 rows), else int64."""
    return np.int32 if rows.size == 0 or int(rows.max()) < 2**31 - 1 else np.int64


class Segment:
    """Storage rows frozen at build time, searchable for their k nearest.

    ``rows`` is an array of storage rows, or an int ``n`` for rows ``0..n-1``
    (the main segment of a view every row passes: no array is held).
    Row ids are kept once, as int32 where they fit, with a trailing ``-1``
    (a KD-tree's "not found", ``loc == size``, maps to it).
    """

    def __init__(self, level: int, rows: np.ndarray | int):
        self.level = level
        self.n_stale = 0
        if isinstance(rows, (int, np.integer)):
            self.size = int(rows)
            self._rows_ext = None
        else:
            self.size = int(rows.size)
            self._rows_ext = np.empty(self.size + 1, dtype=row_dtype(rows))
            self._rows_ext[:-1] = rows
            self._rows_ext[-1] = -1

    @property
    def rows(self) -> np.ndarray:
        """The storage rows of the segment (made on the fly for a ``0..n-1`` segment)."""
        return np.arange(self.size) if self._rows_ext is None else self._rows_ext[:-1]

    def _pos(self, loc: np.ndarray) -> np.ndarray:
        """Storage rows (int64) of segment positions; ``loc == size`` -> ``-1``."""
        if self._rows_ext is None:
            return np.where(loc < self.size, loc, -1).astype(np.int64, copy=False)
        return self._rows_ext[loc].astype(np.int64, copy=False)

    def nbytes(self) -> int:
        """Bytes this segment holds (row ids and search structure)."""
        return 0 if self._rows_ext is None else int(self._rows_ext.nbytes)


class TreeSegment(Segment):
    """A ``cKDTree`` over the metric's embedding of the rows.

    The tree keeps ``emb`` as its data (``copy_data=False``). For the
    Euclidean metric over rows ``0..n-1`` that is the tracker's float64 goal
    snapshot itself (``shares_data``): rows changed later are overwritten in
    it, but they are stale here (their owner moved) and skipped, and an
    unchanged row is where the tree put it, so the search of the live rows
    stays exact; the tree only needs the split planes it was built with.
    """

    def __init__(self, level, rows, emb: np.ndarray, exact: bool, shares_data: bool = False):
        super().__init__(level, rows)
        self.exact = exact
        self.shares_data = shares_data
        self.tree = cKDTree(emb, leafsize=LEAFSIZE, compact_nodes=False, balanced_tree=False, copy_data=False)

    def nbytes(self) -> int:
        t = self.tree
        data = 0 if self.shares_data else t.n * t.m * 8  # float64 data, unless it is the snapshot
        return super().nbytes() + data + t.n * np.dtype(np.intp).itemsize + t.size * NODE_BYTES

    def query(self, qvars, kk, upper):
        kk = min(kk, self.size)
        ub = np.inf if upper == np.inf else upper * (1 + 1e-9) + 1e-12
        pos, dist, bound = [], [], None
        for v in qvars:
            d, loc = self.tree.query(v, k=kk, distance_upper_bound=ub, workers=1)
            if kk == 1:
                d, loc = d[:, None], loc[:, None]
            b = d[:, -1] if kk < self.size else np.full(d.shape[0], np.inf)
            bound = b if bound is None else np.minimum(bound, b)
            pos.append(self._pos(loc))
            dist.append(d)
        if len(qvars) > 1:
            pos, dist = np.concatenate(pos, 1), np.concatenate(dist, 1)
        else:
            pos, dist = pos[0], dist[0]
        return pos, (dist if self.exact else None), bound


class BruteSegment(Segment):
    """Float32 matrix-product search in the embedding, or float64 ``pairwise`` for custom metrics."""

    def __init__(self, level, rows, emb: np.ndarray | None, goals64: np.ndarray | None, metric):
        super().__init__(level, rows)
        self.metric = metric
        if emb is not None:
            # Centred, so that the float32 rounding margin scales with the spread of the goals
            # rather than with their distance to the origin.
            self.center = emb.mean(0) if self.size else np.zeros(emb.shape[1])
            self.X = torch.from_numpy(np.ascontiguousarray(emb - self.center, dtype=np.float32))
            self.norms = self.X.pow(2).sum(1)
            self.maxnorm = float(self.norms.max().sqrt()) if self.size else 0.0
            self.exact = False
        else:
            self.X = torch.from_numpy(np.ascontiguousarray(goals64, dtype=np.float64))
            self.norms = None
            self.exact = True

    def nbytes(self) -> int:
        extra = 0 if self.norms is None else self.norms.nbytes
        return super().nbytes() + self.X.nbytes + extra

    def _topk(self, score_fn, Q, kk):
        chunk = max(8192, (1 << 22) // max(Q, 1))
        best_v = best_i = None
        for c0 in range(0, self.size, chunk):
            s = score_fn(c0, c0 + chunk)
            v, i = torch.topk(s, min(kk, s.shape[1]), dim=1, largest=False, sorted=False)
            i += c0
            if best_v is not None:
                v = torch.cat([best_v, v], 1)
                v, j = torch.topk(v, min(kk, v.shape[1]), dim=1, largest=False, sorted=False)
                i = torch.cat([best_i, i], 1).gather(1, j)
            best_v, best_i = v, i
        best_v, j = torch.sort(best_v, dim=1)
        return best_v, best_i.gather(1, j)

    def query(self, qvars, kk, upper):
        kk = min(kk, self.size)
        if self.exact:
            q = torch.from_numpy(qvars[0])
            X, pw = self.X, self.metric.pairwise
            d, loc = self._topk(lambda a, b: pw(q, X[a:b]), q.shape[0], kk)
            d, loc = d.numpy(), loc.numpy()
            bound = d[:, -1].copy() if kk < self.size else np.full(d.shape[0], np.inf)
            return self._pos(loc), d, bound
        pos, bound = [], None
        e = self.X.shape[1]
        for v in qvars:
            v = v - self.center
            q = torch.from_numpy(v).float()
            X, norms = self.X, self.norms
            a, loc = self._topk(
                lambda c0, c1, q=q, X=X, norms=norms: torch.addmm(norms[c0:c1].unsqueeze(0), q, X[c0:c1].T, alpha=-2),
                q.shape[0],
                kk,
            )
            if kk < self.size:
                qn = (v * v).sum(1)
                # |fl(a) - true d^2| <= (e + 3) u (|x| + |q|)^2 up to second order; x4 margin.
                delta = 4 * (e + 3) * _F32_EPS * (self.maxnorm + np.sqrt(qn)) ** 2
                b = np.sqrt(np.maximum(a[:, -1].double().numpy() + qn - delta, 0.0))
            else:
                b = np.full(q.shape[0], np.inf)
            bound = b if bound is None else np.minimum(bound, b)
            pos.append(self._pos(loc.numpy()))
        return np.concatenate(pos, 1) if len(pos) > 1 else pos[0], None, bound


def build_segment(level: int, rows: np.ndarray | int, goals: np.ndarray, backend: str,
                  metric: GoalMetric) -> Segment:
    """A segment of ``backend`` (``"kdtree"`` / ``"brute"``) over ``rows`` whose goals are ``goals [len(rows), d]``.

    ``rows`` is an array of storage rows, or an int ``n`` for rows
    ``0..n-1``, whose ``goals`` are then a view of the tracker's snapshot: a
    KD-tree over the Euclidean metric's embedding (float64 goals as they
    are) searches that view in place.
    """
    size = rows if isinstance(rows, (int, np.integer)) else rows.size
    if backend == "kdtree":
        emb = metric.embed(goals)
        exact = metric.embedding_exact and len(metric.embed_queries(emb[:0])) == 1
        if size == 0:
            return BruteSegment(level, rows, emb, None, metric)
        shares = isinstance(rows, (int, np.integer)) and np.may_share_memory(emb, goals)
        return TreeSegment(level, rows, emb, exact, shares)
    if metric.embeddable:
        return BruteSegment(level, rows, metric.embed(goals), None, metric)
    return BruteSegment(level, rows, None, goals.astype(np.float64), metric)


def search_segment(seg: Segment, owner: np.ndarray, q: np.ndarray, qvars: list[np.ndarray], k: int,
                   max_d: float, rescore: Callable[[np.ndarray, np.ndarray], np.ndarray]):
    """Exact top-k ``(distance [Q, k], row [Q, k])`` of one segment; grows the candidate count as needed.

    ``owner[row]`` is the level of the segment holding ``row`` now (rows
    whose owner is another level are stale here and skipped); ``rescore(q,
    rows)`` gives exact float64 distances when the segment's are bounds.
    """
    Q = q.shape[0]
    if seg.n_stale == 0 and seg.exact and len(qvars) == 1:
        pos, dist, _ = seg.query(qvars, k, max_d)
        if pos.shape[1] < k:
            pad = k - pos.shape[1]
            dist = np.pad(dist, ((0, 0), (0, pad)), constant_values=np.inf)
            pos = np.pad(pos, ((0, 0), (0, pad)), constant_values=-1)
        return np.where(pos >= 0, dist, np.inf), pos
    out_d = np.full((Q, k), np.inf)
    out_p = np.full((Q, k), -1, dtype=np.int64)
    todo = np.arange(Q)
    if seg.exact:
        kk = k + math.ceil(3 * k * seg.n_stale / max(seg.size, 1)) + 4
    else:
        kk = 2 * k + 8
    while todo.size:
        sub_q = q[todo]
        pos, dist, bound = seg.query([v[todo] for v in qvars], kk, max_d)
        valid = pos >= 0
        if seg.n_stale:
            valid &= owner[np.maximum(pos, 0)] == seg.level
        if dist is not None and len(qvars) == 1 and todo.size == Q and dist.shape[1] >= k and valid[:, :k].all():
            # sorted exact results whose first k rows are all live: nothing to re-rank
            return dist[:, :k], pos[:, :k]
        if dist is None:
            dist = rescore(sub_q, pos)
        dist = np.where(valid, dist, np.inf)
        if len(qvars) > 1:  # the same row can come back once per query variant
            order = np.lexsort((pos, dist), axis=1)
            dist = np.take_along_axis(dist, order, 1)
            pos = np.take_along_axis(pos, order, 1)
            dup = np.zeros_like(valid)
            dup[:, 1:] = (pos[:, 1:] == pos[:, :-1]) & (pos[:, 1:] >= 0)
            dist = np.where(dup, np.inf, dist)
        width = dist.shape[1]
        if width < k:
            dist = np.pad(dist, ((0, 0), (0, k - width)), constant_values=np.inf)
            pos = np.pad(pos, ((0, 0), (0, k - width)), constant_values=-1)
        order = np.argsort(dist, axis=1, kind="stable")[:, :k]
        top_d = np.take_along_axis(dist, order, 1)
        top_p = np.where(np.isfinite(top_d), np.take_along_axis(pos, order, 1), -1)
        kth = top_d[:, -1]
        done = (bound >= kth) | (bound > max_d) | (kk >= seg.size)
        out_d[todo[done]] = top_d[done]
        out_p[todo[done]] = top_p[done]
        todo = todo[~done]
        kk = min(4 * kk, seg.size)
    return out_d, out_p
