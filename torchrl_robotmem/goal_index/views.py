"""Filtered views: the segments answering one filter, kept in step with the tracked columns.

Each filter combination of an index (none, ``success_only``, an env subset, a
run subset, ...) gets a :class:`FilterView` whose rows are held by up to three
segments: a large ``main`` one, a ``mid`` one (< ``rebuild_fraction`` of main)
and a small ``live`` one (<= ``tail_size`` rows, rebuilt at each change). A
changed row (from the :class:`~torchrl_robotmem.goal_index.tracking.ColumnTracker`
log) is dropped from the segment that held it (its stale entry is skipped at
query time) and re-enters through ``live``; ``live`` overflows into ``mid``;
when ``mid`` plus the stale rows of ``main`` outgrow ``rebuild_fraction`` of
``main``, the view is rebuilt from scratch. With ``backend="auto"`` the
KD-tree is used for embeddings of dimension <= 4 and for small views;
otherwise both backends are timed on a few probe queries at each rebuild and
the faster one is kept.
"""
from __future__ import annotations

import time

import numpy as np
import torch
from tensordict.utils import NestedKey

from torchrl_robotmem.goal_index.filters import FilterKey
from torchrl_robotmem.goal_index.metrics import GoalMetric
from torchrl_robotmem.goal_index.segments import (
    LEVEL_LIVE,
    LEVEL_MAIN,
    LEVEL_MID,
    Segment,
    build_segment,
    row_dtype,
    search_segment,
)
from torchrl_robotmem.goal_index.tracking import ColumnTracker

__all__ = ["FilterView"]

_PROBE_MIN_ROWS = 50_000


class FilterView:
    """The rows passing one filter, as searchable segments.

    Args:
        key (FilterKey): the filter.
        tracker (ColumnTracker): the columns (the filter's columns must be tracked).
        metric (GoalMetric): the goal metric.
        columns (dict): ``{"success": key, "env": key, "run": key}``, the
            stored columns the filter reads.
        backend (str): ``"auto"``, ``"kdtree"`` or ``"brute"``.
        tail_size (int), rebuild_fraction (float): see :class:`~torchrl_robotmem.goal_index.GoalIndex`.
    """

    def __init__(self, key: FilterKey, tracker: ColumnTracker, metric: GoalMetric,
                 columns: dict[str, NestedKey], backend: str, tail_size: int, rebuild_fraction: float):
        self.key = key
        self.tracker = tracker
        self.metric = metric
        self.columns = columns
        self.backend_choice = backend
        self.tail_size = tail_size
        self.rebuild_fraction = rebuild_fraction
        self.seen = -1  # tracker revision the segments reflect
        self.main = self.mid = self.live = None
        self.owner = np.zeros(0, dtype=np.int8)  # row -> level of the segment holding it (0: none)
        self.backend = None
        self.builds = 0
        self._members = None  # (revision, int64 rows)

    @property
    def segments(self) -> list[Segment]:
        return [s for s in (self.main, self.mid, self.live) if s is not None and s.size]

    # -- membership -------------------------------------------------------------
    def _mask(self, rows: np.ndarray | None) -> np.ndarray:
        tr = self.tracker
        sel = slice(0, tr.n) if rows is None else rows
        return self.key.mask(lambda name: tr.flat(self.columns[name], sel)[:, 0], tr.flat(tr.goal_key, sel))

    def member_rows(self) -> torch.Tensor:
        """Rows passing the filter (int64, sorted), cached until the tracked columns change."""
        self.sync()
        rev = self.tracker.revision
        if self._members is None or self._members[0] != rev:
            self._members = (rev, torch.from_numpy(np.flatnonzero(self.owner[: self.tracker.n])))
        return self._members[1]

    def nbytes(self) -> int:
        """Bytes this view holds: the row owner map, its segments, the cached member rows."""
        members = 0 if self._members is None else self._members[1].nbytes
        return int(self.owner.nbytes) + sum(s.nbytes() for s in (self.main, self.mid, self.live)
                                            if s is not None) + int(members)

    @property
    def size(self) -> int:
        """Rows currently held (stale entries excluded)."""
        return sum(s.size - s.n_stale for s in self.segments)

    # -- keeping up with the tracker ---------------------------------------------------
    def sync(self) -> None:
        tr = self.tracker
        if self.seen == tr.revision:
            return
        n = tr.n
        if self.owner.size < n:
            # grows as the tracker's snapshots do, never past their capacity
            cap = max(n, min(2 * self.owner.size, tr.capacity))
            owner = np.zeros(cap, dtype=np.int8)
            owner[: self.owner.size] = self.owner
            self.owner = owner
        rows = tr.changed_since(self.seen) if self.main is not None else None
        if rows is None:
            self._rebuild()
            return
        if not rows.size:
            self.seen = tr.revision
            return
        owner = self.owner
        counts = np.bincount(owner[rows], minlength=4)
        self.main.n_stale += int(counts[LEVEL_MAIN])
        if self.mid is not None:
            self.mid.n_stale += int(counts[LEVEL_MID])
        owner[rows] = 0
        fresh = rows[self._mask(rows)]
        live_rows = fresh
        if self.live is not None:
            kept = self.live.rows[owner[self.live.rows] == LEVEL_LIVE]
            live_rows = np.concatenate([kept, fresh]) if fresh.size else kept
        mid_size = self.mid.size if self.mid is not None else 0
        budget = max(self.tail_size, self.rebuild_fraction * self.main.size)
        if self.main.n_stale + mid_size + live_rows.size > budget:
            self._rebuild()
            return
        if live_rows.size > self.tail_size:
            if self.mid is not None:
                live_rows = np.concatenate([self.mid.rows[owner[self.mid.rows] == LEVEL_MID], live_rows])
            self.mid = self._segment(LEVEL_MID, live_rows, self.backend)
            owner[live_rows] = LEVEL_MID
            self.live = None
        elif fresh.size or counts[LEVEL_LIVE]:
            self.live = self._segment(LEVEL_LIVE, live_rows, self.backend) if live_rows.size else None
            owner[live_rows] = LEVEL_LIVE
        self.seen = tr.revision

    def _rebuild(self) -> None:
        n = self.tracker.n
        mask = self._mask(None)
        self.owner[:] = 0
        if mask.all():  # every row passes: the main segment holds rows 0..n-1 without an array of them
            rows = n
            self.owner[:n] = LEVEL_MAIN
        else:
            rows = np.flatnonzero(mask)
            rows = rows.astype(row_dtype(rows), copy=False)
            self.owner[rows] = LEVEL_MAIN
        del mask
        self.main = None  # let the old segment go before the new one is built
        self.mid = self.live = None
        self.backend, main = self._choose_backend(rows)
        self.main = main if main is not None else self._segment(LEVEL_MAIN, rows, self.backend)
        self.seen = self.tracker.revision
        self.builds += 1

    def _segment(self, level: int, rows: np.ndarray | int, backend: str) -> Segment:
        sel = slice(0, rows) if isinstance(rows, int) else rows  # a slice: a view, not a copy of the goals
        return build_segment(level, rows, self.tracker.flat(self.tracker.goal_key, sel), backend, self.metric)

    def _choose_backend(self, rows: np.ndarray | int) -> tuple[str, Segment | None]:
        """The backend for the segments, and the main segment when the probe built it."""
        if self.backend_choice != "auto":
            return self.backend_choice, None
        if not self.metric.embeddable:
            return "brute", None
        emb_dim = self.metric.embed(np.zeros((1, self.tracker.goal_dim))).shape[1]
        count = rows if isinstance(rows, int) else rows.size
        if emb_dim <= 4 or count < _PROBE_MIN_ROWS:
            return "kdtree", None
        # Time both backends on a few queries near stored goals and keep the faster.
        tree = self._segment(LEVEL_MAIN, rows, "kdtree")
        brute = self._segment(LEVEL_MAIN, rows, "brute")
        rng = np.random.default_rng(0)
        goals = self.tracker.flat(self.tracker.goal_key, rng.choice(rows, 16)).astype(np.float64)
        goals += rng.normal(size=goals.shape) * 0.01 * (goals.std(0, keepdims=True) + 1e-6)
        qvars = self.metric.embed_queries(goals)
        owner = np.full(1, LEVEL_MAIN, dtype=np.int8)
        times = {}
        for name, seg in (("kdtree", tree), ("brute", brute)):
            t0 = time.perf_counter()
            search_segment(seg, owner, goals, qvars, 5, np.inf, self._rescore)
            times[name] = time.perf_counter() - t0
        choice = min(times, key=times.get)
        return choice, (tree if choice == "kdtree" else brute)

    # -- search ---------------------------------------------------------------------
    def _rescore(self, q: np.ndarray, pos: np.ndarray) -> np.ndarray:
        g = self.tracker.column(self.tracker.goal_key)[np.maximum(pos, 0)]
        g = torch.from_numpy(g.reshape(*pos.shape, self.tracker.goal_dim).astype(np.float64))
        return self.metric.distance(torch.from_numpy(q)[:, None, :], g).numpy()

    def search(self, q: np.ndarray, k: int, max_d: float) -> tuple[np.ndarray, np.ndarray]:
        """Exact top-k ``(distance [Q, k] float64, row [Q, k] int64)``; missing: ``inf`` / ``-1``."""
        self.sync()
        segments = self.segments
        Q = q.shape[0]
        if not segments:
            return np.full((Q, k), np.inf), np.full((Q, k), -1, dtype=np.int64)
        qvars = self.metric.embed_queries(q) if self.metric.embeddable else [q]
        parts = [search_segment(seg, self.owner, q, qvars, k, max_d, self._rescore) for seg in segments]
        if len(parts) == 1:
            d, p = parts[0]
        else:
            d = np.concatenate([x[0] for x in parts], 1)
            p = np.concatenate([x[1] for x in parts], 1)
            order = np.argsort(d, axis=1, kind="stable")[:, :k]
            d = np.take_along_axis(d, order, 1)
            p = np.take_along_axis(p, order, 1)
        far = ~(d <= max_d)
        if far.any():
            d = np.where(far, np.inf, d)
            p = np.where(far, -1, p)
        return d, p

    def search_episodes(self, q: np.ndarray, k: int, max_d: float,
                        episode_key: NestedKey) -> tuple[np.ndarray, np.ndarray]:
        """Exact top-k over episodes: the nearest row of each of the k nearest episodes.

        The top-m rows, searched exactly, hold the nearest row of every
        episode that has one among them, in order; once they hold k distinct
        episodes (or every row within reach), no other episode can come
        closer. m grows until that holds; it stays below the rows of the k
        largest episodes. ``episode_key`` must be tracked.
        """
        self.sync()
        episodes = self.tracker.column(episode_key).reshape(-1)
        size = self.size
        Q = q.shape[0]
        out_d = np.full((Q, k), np.inf)
        out_p = np.full((Q, k), -1, dtype=np.int64)
        todo = np.arange(Q)
        m = min(max(8 * k, 64), max(size, k))
        while todo.size:
            d, p = self.search(q[todo], m, max_d)
            valid = p >= 0
            ep = np.where(valid, episodes[np.maximum(p, 0)], 0)
            order = np.argsort(ep, axis=1, kind="stable")  # stable: the nearest row of an episode first
            sorted_ep = np.take_along_axis(ep, order, 1)
            first_sorted = np.ones_like(valid)
            first_sorted[:, 1:] = sorted_ep[:, 1:] != sorted_ep[:, :-1]
            first = np.empty_like(valid)
            np.put_along_axis(first, order, first_sorted, 1)
            first &= valid
            found = first.sum(1)
            done = (found >= k) | ~valid[:, -1] | (m >= size)
            if done.any():
                sel = first[done] & (np.cumsum(first[done], 1) <= k)
                pick = np.argsort(~sel, axis=1, kind="stable")[:, :k]
                keep = np.take_along_axis(sel, pick, 1)
                if pick.shape[1] < k:
                    pad = k - pick.shape[1]
                    pick = np.pad(pick, ((0, 0), (0, pad)))
                    keep = np.pad(keep, ((0, 0), (0, pad)))
                out_d[todo[done]] = np.where(keep, np.take_along_axis(d[done], pick, 1), np.inf)
                out_p[todo[done]] = np.where(keep, np.take_along_axis(p[done], pick, 1), -1)
            todo = todo[~done]
            m = min(4 * m, max(size, k))
        return out_d, out_p
