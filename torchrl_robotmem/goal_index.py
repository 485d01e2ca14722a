"""Exact nearest-goal recall over the transitions of a TorchRL storage.

:class:`GoalIndex` answers "which stored transitions achieved the goals
closest to this one?" (top-k, with success / env / run filters) on the live
columns of a :class:`~torchrl.data.replay_buffers.storages.TensorStorage`
(``LazyTensorStorage``, ``LazyMemmapStorage``, ``ZarrStorage``), and
:func:`recall` returns those transitions with their full context as a
TensorDict.

How it stays exact and fast
---------------------------
* A snapshot of the columns the index depends on (the goals, and the filter
  columns in use) is compared bitwise with the live columns whenever the
  storage's ``_mutation_revision`` moved. This finds appended rows and rows
  overwritten in place (ring buffer, ``rb[idx] = ...``, ``loads``) at about
  1 ms per million 3-D goals, whatever wrote them.
* Each filter combination (none, ``success_only``, an env subset, a run
  subset, ...) gets a *view*: rows are held by up to three segments, a large
  ``main`` one, a ``mid`` one (< ``rebuild_fraction`` of main) and a small
  ``live`` one (<= ``tail_size`` rows, rebuilt at each change). A changed row
  is dropped from the segment that held it (its stale entry is skipped at query
  time) and re-enters through ``live``; ``live`` overflows into ``mid``; when
  ``mid`` plus the stale rows of ``main`` outgrow ``rebuild_fraction`` of
  ``main``, the view is rebuilt from scratch. Views are built lazily, kept in
  an LRU cache, and only re-synchronised when queried.
* A segment is searched with scipy's ``cKDTree`` over a Euclidean embedding of
  the goals whose distances never exceed the metric (the identity for
  ``"euclidean"``; position + scaled quaternion, queried with both signs, for
  ``"pose"``), or by brute force (float32 matrix products with a rounding-error
  margin). Either way candidates are re-scored with the exact metric in float64
  and the candidate count grows until the lower bound on every row not returned
  reaches the current k-th distance, so results equal a brute-force search
  (ties aside). With ``backend="auto"`` the KD-tree is used for embeddings of
  dimension <= 4 and for small segments; otherwise both are timed on a few
  probe queries when a view is (re)built and the faster one is kept.
"""
from __future__ import annotations

import math
import time
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data.replay_buffers.storages import Storage, TensorStorage

from torchrl_robotmem.metrics import GoalMetric, get_metric
from torchrl_robotmem.storage.columns import has_rows, read_column

__all__ = ["GoalIndex", "recall"]

_LEVEL_MAIN, _LEVEL_MID, _LEVEL_LIVE = 1, 2, 3
_PROBE_MIN_ROWS = 50_000
_F32_EPS = 2.0**-24


def _as_storage(storage_or_rb: Any) -> TensorStorage:
    storage = getattr(storage_or_rb, "storage", storage_or_rb)
    if not isinstance(storage, Storage):
        raise TypeError(
            f"expected a TorchRL Storage or ReplayBuffer, got {type(storage_or_rb).__name__}."
        )
    if not isinstance(storage, TensorStorage):
        raise TypeError(
            f"{type(storage).__name__} is not a TensorStorage; GoalIndex reads the columns "
            "of LazyTensorStorage, LazyMemmapStorage, ZarrStorage (or any TensorStorage)."
        )
    if storage.ndim != 1:
        raise ValueError(f"GoalIndex needs a storage with ndim=1, got ndim={storage.ndim}.")
    return storage


def _revision(storage: Storage) -> int | None:
    try:
        return int(storage._mutation_revision)
    except AttributeError:  # older torchrl: resynchronise on every query
        return None


def _key_str(key: NestedKey) -> str:
    return repr(key) if isinstance(key, tuple) else repr(str(key))


def _bits(a: np.ndarray) -> np.ndarray:
    """Flat integer view of a contiguous array, for bitwise comparison (NaN == NaN)."""
    flat = a.reshape(-1)
    return flat.view(np.dtype(f"i{flat.dtype.itemsize}")) if flat.dtype.kind != "b" else flat


class _StrongRef:
    """``weakref.ref``-like holder that keeps its object alive (and pickles)."""

    __slots__ = ("obj",)

    def __init__(self, obj):
        self.obj = obj

    def __call__(self):
        return self.obj


# -- segments -----------------------------------------------------------------
class _Segment:
    """Storage rows frozen at build time, searchable for their k nearest."""

    def __init__(self, level: int, rows: np.ndarray):
        self.level = level
        self.rows = rows
        self.size = int(rows.size)
        self.n_stale = 0
        self._rows_ext = np.append(rows, -1)  # KD-tree "not found" (loc == size) -> -1

    def _pos(self, loc: np.ndarray) -> np.ndarray:
        return self._rows_ext[loc]


class _TreeSegment(_Segment):
    """A ``cKDTree`` over the metric's embedding of the rows."""

    def __init__(self, level, rows, emb: np.ndarray, exact: bool):
        super().__init__(level, rows)
        self.exact = exact
        self.tree = cKDTree(emb, leafsize=16, compact_nodes=False, balanced_tree=False, copy_data=False)

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


class _BruteSegment(_Segment):
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
            self.exact = True

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


class _View:
    """Segments answering one filter combination."""

    def __init__(self, key):
        self.key = key
        self.seen = -1
        self.main = self.mid = self.live = None
        self.owner = np.zeros(0, dtype=np.int8)
        self.backend = None
        self.members = None

    @property
    def segments(self):
        return [s for s in (self.main, self.mid, self.live) if s is not None and s.size]


_DERIVED_STATE = ("_rev", "_n", "_epoch", "_snap", "_log", "_log_rows", "_log_floor", "_views", "_goal_shape")


# -- the index ----------------------------------------------------------------
class GoalIndex:
    """Exact k-nearest-goal search over the transitions of a TorchRL storage.

    The index reads the storage's own columns and follows every change to them
    (appends, ring-buffer overwrites, ``loads``): results always equal a
    brute-force search over the rows currently stored (ties aside). See the
    module docstring for the data structures.

    Args:
        storage (Storage or ReplayBuffer): a ``TensorStorage`` with ``ndim=1``
            (``LazyTensorStorage``, ``LazyMemmapStorage``, ``ZarrStorage``), or
            a replay buffer holding one.

    Keyword Args:
        goal_key (NestedKey): column of goals to search. Defaults to
            ``("next", "achieved_goal")``, the goal reached by each transition.
        success_key (NestedKey): column read by ``success_only`` (a row counts
            as a success when its value is ``> 0.5``). Defaults to
            ``("next", "is_success")``.
        metric (str, GoalMetric or callable): ``"euclidean"`` (default) or
            ``"pose"`` / ``"hand"``, see :mod:`torchrl_robotmem.metrics`.
        metric_kwargs (dict, optional): keyword arguments of a named metric
            (e.g. ``{"rotation_weight": 0.5}``).
        env_names (sequence of str, optional): names of the integer codes of
            the env column (code ``i`` is ``env_names[i]``). Defaults to the
            storage's ``env_names`` attribute when it has one.
        env_key (NestedKey): column of env codes. Defaults to ``"env"``.
        run_key (NestedKey): column of run ids. Defaults to ``"run"``.
        backend (str): ``"auto"`` (default), ``"kdtree"`` or ``"brute"``.
        tail_size (int): size of the small segment rebuilt at every change.
            Defaults to 4096.
        rebuild_fraction (float): changed rows, as a fraction of the main
            segment, above which a view is rebuilt from scratch. Defaults to 0.05.
        max_cached_filters (int): filter combinations kept (LRU). Defaults to 8.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_robotmem.goal_index import GoalIndex
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000))
        >>> _ = rb.extend(TensorDict({
        ...     "observation": torch.randn(100, 25),
        ...     "action": torch.randn(100, 4),
        ...     ("next", "achieved_goal"): torch.rand(100, 3),
        ...     ("next", "is_success"): (torch.rand(100) < 0.3).float(),
        ... }, batch_size=[100]))
        >>> index = GoalIndex(rb)
        >>> out = index.recall(torch.tensor([0.5, 0.5, 0.5]), k=5, success_only=True)
        >>> out.batch_size, out["action"].shape, out["distance"].dtype
        (torch.Size([5]), torch.Size([5, 4]), torch.float32)
        >>> distance, index_, mask = index.search(torch.rand(8, 3), k=3)
        >>> distance.shape
        torch.Size([8, 3])
    """

    def __init__(
        self,
        storage,
        *,
        goal_key: NestedKey = ("next", "achieved_goal"),
        success_key: NestedKey = ("next", "is_success"),
        metric: str | GoalMetric | Any = "euclidean",
        metric_kwargs: dict | None = None,
        env_names: Sequence[str] | None = None,
        env_key: NestedKey = "env",
        run_key: NestedKey = "run",
        backend: str = "auto",
        tail_size: int = 4096,
        rebuild_fraction: float = 0.05,
        max_cached_filters: int = 8,
    ):
        self._storage_ref = _StrongRef(_as_storage(storage))
        self.goal_key = goal_key
        self.success_key = success_key
        self.env_key = env_key
        self.run_key = run_key
        self.metric = get_metric(metric, **(metric_kwargs or {}))
        self._env_names = tuple(env_names) if env_names is not None else None
        if backend not in ("auto", "kdtree", "brute"):
            raise ValueError(f"backend must be 'auto', 'kdtree' or 'brute', got {backend!r}.")
        if backend == "kdtree" and not self.metric._embeddable:
            raise ValueError(f"metric {self.metric!r} has no tree embedding; use backend='brute'.")
        self.backend = backend
        if int(tail_size) < 1:
            raise ValueError(f"tail_size must be >= 1, got {tail_size}.")
        self.tail_size = int(tail_size)
        if not 0 < float(rebuild_fraction) <= 1:
            raise ValueError(f"rebuild_fraction must be in (0, 1], got {rebuild_fraction}.")
        self.rebuild_fraction = float(rebuild_fraction)
        if int(max_cached_filters) < 1:
            raise ValueError(f"max_cached_filters must be >= 1, got {max_cached_filters}.")
        self.max_cached_filters = int(max_cached_filters)
        self._reset_state()

    def _reset_state(self):
        self._rev = None
        self._n = 0
        self._epoch = 0
        self._snap: dict[NestedKey, np.ndarray] = {}
        self._log: list[tuple[int, np.ndarray]] = []
        self._log_rows = 0
        self._log_floor = 0
        self._views: OrderedDict = OrderedDict()
        self._goal_shape = None

    # -- public ---------------------------------------------------------------
    @property
    def storage(self) -> TensorStorage:
        """The indexed storage."""
        st = self._storage_ref()
        if st is None:
            raise RuntimeError("the storage of this GoalIndex was garbage-collected.")
        return st

    @property
    def env_names(self) -> tuple[str, ...] | None:
        """Names of the env codes (``env_names=`` or the storage's ``env_names``)."""
        if self._env_names is not None:
            return self._env_names
        names = getattr(self.storage, "env_names", None)
        return tuple(names) if names is not None else None

    @property
    def goal_dim(self) -> int | None:
        """Dimension of the stored goals (``None`` until the storage has data)."""
        self._sync()
        return None if self._goal_shape is None else int(np.prod(self._goal_shape))

    @property
    def backend_in_use(self) -> str | None:
        """``"kdtree"`` or ``"brute"``: the search backend of the unfiltered view (once built)."""
        view = self._views.get((False, None, None))
        return None if view is None else view.backend

    def refresh(self, *, success_only: bool = False, env=None, run=None) -> GoalIndex:
        """Brings the view of these filters up to date now (search does it lazily)."""
        key = self._filter_key(success_only, env, run)
        self._sync()
        if self._goal_shape is not None:
            self._sync_view(self._get_view(key))
        return self

    def _member_rows(self, *, success_only: bool = False, env=None, run=None) -> torch.Tensor:
        """Storage rows passing these filters (int64), cached until the storage changes."""
        key = self._filter_key(success_only, env, run)
        self._sync()
        if self._goal_shape is None or self._n == 0:
            return torch.zeros(0, dtype=torch.int64)
        view = self._get_view(key)
        self._sync_view(view)
        if view.members is None or view.members[0] != self._epoch:
            view.members = (self._epoch, torch.from_numpy(np.flatnonzero(view.owner[: self._n])))
        return view.members[1]

    def search(
        self,
        goal,
        k: int = 5,
        *,
        success_only: bool = False,
        env: str | int | Sequence[str | int] | None = None,
        run: int | Sequence[int] | None = None,
        max_distance: float | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The k nearest stored goals: ``(distance, index, mask)``.

        Args:
            goal: ``[goal_dim]`` or ``[B, goal_dim]`` (tensor, array or list).
            k (int): number of neighbours (>= 1).

        Keyword Args:
            success_only (bool): only rows whose ``success_key`` is ``> 0.5``.
            env: env name(s) or integer code(s) to keep.
            run: run id(s) to keep.
            max_distance (float, optional): drop matches farther than this.

        Returns:
            ``distance`` (float32), ``index`` (int64 storage row) and ``mask``
            (bool), each ``[k]`` or ``[B, k]``, nearest first. Missing matches
            have ``mask=False``, ``distance=inf`` and ``index=-1``.
        """
        k = self._check_k(k)
        max_d = self._check_max_distance(max_distance)
        key = self._filter_key(success_only, env, run)
        self._sync()
        q, batched = self._parse_goal(goal)
        Q = q.shape[0]
        if self._goal_shape is None or self._n == 0 or Q == 0:
            d = np.full((Q, k), np.inf)
            p = np.full((Q, k), -1, dtype=np.int64)
        else:
            view = self._get_view(key)
            self._sync_view(view)
            d, p = self._search_view(view, q, k, max_d)
        if not batched:
            d, p = d[0], p[0]
        return torch.from_numpy(d.astype(np.float32)), torch.from_numpy(p), torch.from_numpy(p >= 0)

    def recall(
        self,
        goal,
        k: int = 5,
        *,
        success_only: bool = False,
        env: str | int | Sequence[str | int] | None = None,
        run: int | Sequence[int] | None = None,
        max_distance: float | None = None,
    ) -> TensorDictBase:
        """The k stored transitions whose goals are nearest to ``goal``, with their context.

        Same arguments as :meth:`search`. Returns a TensorDict of batch ``[k]``
        (or ``[B, k]``) with every stored key of those rows (observation,
        action, goals, ``"next"`` entries, tags...) plus ``distance``
        (float32), ``mask`` (bool) and ``index`` (int64 storage row). Masked
        entries hold zeros.
        """
        dist, index, mask = self.search(
            goal, k, success_only=success_only, env=env, run=run, max_distance=max_distance
        )
        st = self.storage
        if not st.initialized or st._storage is None:
            out = TensorDict({}, batch_size=index.shape)
        else:
            data = st._storage
            out = data[index.clamp_min(0).to(getattr(data, "device", None) or "cpu")]
            if not bool(mask.all()):
                out = out.masked_fill(~mask.to(out.device) if out.device else ~mask, 0)
        out.set("distance", dist)
        out.set("mask", mask)
        out.set("index", index)
        return out

    def __getstate__(self):
        # Trees and snapshots are derived data: rebuilt lazily after unpickling.
        state = {k: v for k, v in self.__dict__.items() if k not in _DERIVED_STATE}
        state["_storage_ref"] = _StrongRef(self.storage)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._reset_state()

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(goal_key={self.goal_key}, metric={self.metric!r}, "
            f"rows={self._n}, views={len(self._views)}, backend={self.backend_in_use})"
        )

    # -- input checks ---------------------------------------------------------
    @staticmethod
    def _check_k(k) -> int:
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
            raise ValueError(f"k must be a positive integer, got {k!r}.")
        return int(k)

    @staticmethod
    def _check_max_distance(max_distance) -> float:
        if max_distance is None:
            return np.inf
        max_distance = float(max_distance)
        if math.isnan(max_distance) or max_distance < 0:
            raise ValueError(f"max_distance must be >= 0, got {max_distance}.")
        return max_distance

    def _parse_goal(self, goal) -> tuple[np.ndarray, bool]:
        if isinstance(goal, torch.Tensor):
            q = goal.detach()
            q = (q if q.device.type == "cpu" else q.cpu()).double().numpy()
        else:
            try:
                q = np.asarray(goal, dtype=np.float64)
            except (TypeError, ValueError) as err:
                raise ValueError(f"goal must be numeric, got {type(goal).__name__}: {err}") from None
        if q.ndim not in (1, 2):
            raise ValueError(
                f"goal must have shape [goal_dim] or [B, goal_dim], got {tuple(q.shape)}."
            )
        batched = q.ndim == 2
        q = np.ascontiguousarray(q.reshape(-1, q.shape[-1]))
        if self._goal_shape is not None:
            dim = int(np.prod(self._goal_shape))
            if q.shape[1] != dim:
                raise ValueError(
                    f"goal has dimension {q.shape[1]} but the stored goals "
                    f"{_key_str(self.goal_key)} have dimension {dim}."
                )
        if not np.isfinite(q).all():
            raise ValueError("goal contains NaN or infinite values.")
        return q, batched

    def _filter_key(self, success_only, env, run):
        if not isinstance(success_only, (bool, np.bool_)):
            raise ValueError(f"success_only must be a bool, got {success_only!r}.")
        envs = None
        if env is not None:
            items = [env] if isinstance(env, (str, int, np.integer)) else list(env)
            codes = set()
            for item in items:
                if isinstance(item, str):
                    names = self.env_names
                    if names is None:
                        raise ValueError(
                            f"cannot filter on env {item!r}: no env names are known; pass "
                            "env_names= to GoalIndex (or use a storage with env_names)."
                        )
                    if item not in names:
                        raise ValueError(f"unknown env {item!r}; known envs: {list(names)}.")
                    codes.add(names.index(item))
                elif isinstance(item, (int, np.integer)) and not isinstance(item, bool):
                    codes.add(int(item))
                else:
                    raise ValueError(f"env must be a name, a code or a list of them, got {item!r}.")
            envs = tuple(sorted(codes))
        runs = None
        if run is not None:
            items = [run] if isinstance(run, (int, np.integer)) else list(run)
            if any(isinstance(r, bool) or not isinstance(r, (int, np.integer)) for r in items):
                raise ValueError(f"run must be an int or a list of ints, got {run!r}.")
            runs = tuple(sorted({int(r) for r in items}))
        return (bool(success_only), envs, runs)

    # -- storage synchronisation ----------------------------------------------
    def _column(self, st, key: NestedKey, n: int) -> np.ndarray:
        col = read_column(st, key, n)
        if col.device.type != "cpu":
            col = col.cpu()
        return torch.Tensor.numpy(col.as_subclass(torch.Tensor) if type(col) is not torch.Tensor else col)

    def _sync(self) -> None:
        st = self.storage
        rev = _revision(st)
        if rev is not None and rev == self._rev:
            return
        initialized = has_rows(st)
        n = len(st) if initialized else 0
        if not initialized:
            if self._n or self._goal_shape is not None:
                self._reset_state()
            self._rev = rev
            return
        cols = {key: self._column(st, key, n) for key in [self.goal_key, *self._snap_keys()]}
        goals = cols[self.goal_key]
        if goals.ndim < 2 or goals.dtype.kind not in "fiu":
            raise ValueError(
                f"goal column {_key_str(self.goal_key)} must be numeric with shape [N, goal_dim], "
                f"got dtype {goals.dtype} and shape {tuple(goals.shape)}."
            )
        shapes_changed = any(
            key in self._snap and (cols[key].shape[1:] != self._snap[key].shape[1:]
                                   or cols[key].dtype != self._snap[key].dtype)
            for key in cols
        )
        if self._goal_shape is None or n < self._n or shapes_changed:
            tracked = [key for key in self._snap if key != self.goal_key]
            self.metric.check_goal_dim(int(np.prod(goals.shape[1:])))
            self._reset_state()
            self._goal_shape = goals.shape[1:]
            for key in [self.goal_key, *tracked]:
                self._snap[key] = self._grow(None, cols[key], n)
            self._n = n
            self._epoch = 1
            self._rev = rev
            return
        m = self._n
        changed = np.zeros(m, dtype=bool)
        for key, live in cols.items():
            snap = self._snap[key]
            width = int(np.prod(live.shape[1:], dtype=np.int64)) or 1
            diff = np.flatnonzero(_bits(live[:m]) != _bits(snap[:m]))
            if diff.size:
                changed[diff // width] = True
        rows = np.flatnonzero(changed)
        for key, live in cols.items():
            snap = self._snap[key] = self._grow(self._snap[key], live, n)
            if rows.size:
                snap[rows] = live[rows]
            if n > m:
                snap[m:n] = live[m:n]
        if n > m:
            rows = np.concatenate([rows, np.arange(m, n)])
        if rows.size:
            self._epoch += 1
            self._log.append((self._epoch, rows))
            self._log_rows += rows.size
            limit = 2 * max(self.tail_size, int(self.rebuild_fraction * n)) + rows.size
            while self._log_rows > limit and len(self._log) > 1:
                epoch, old = self._log.pop(0)
                self._log_rows -= old.size
                self._log_floor = epoch
        self._n = n
        self._rev = rev

    def _snap_keys(self):
        return [key for key in self._snap if key != self.goal_key]

    @staticmethod
    def _grow(snap: np.ndarray | None, live: np.ndarray, n: int) -> np.ndarray:
        """Snapshot buffer with room for ``n`` rows (capacity doubles); new rows left for the caller."""
        if snap is None:
            out = np.empty((max(n, 1), *live.shape[1:]), dtype=live.dtype)
            out[:n] = live[:n]
            return out
        if snap.shape[0] >= n:
            return snap
        out = np.empty((max(n, 2 * snap.shape[0]), *snap.shape[1:]), dtype=snap.dtype)
        out[: snap.shape[0]] = snap
        return out

    def _track(self, key: NestedKey, what: str) -> None:
        if key in self._snap:
            return
        st = self.storage
        try:
            col = self._column(st, key, self._n)
        except KeyError as err:
            raise KeyError(f"{what} needs the column {_key_str(key)}: {err.args[0]}") from None
        if int(np.prod(col.shape[1:], dtype=np.int64)) != 1:
            raise ValueError(
                f"{what} needs one value per row in {_key_str(key)}, got shape {tuple(col.shape)}."
            )
        self._snap[key] = self._grow(None, col, self._n)

    # -- filtered views -------------------------------------------------------
    def _get_view(self, key) -> _View:
        view = self._views.get(key)
        if view is not None:
            self._views.move_to_end(key)
            return view
        success_only, envs, runs = key
        if success_only:
            self._track(self.success_key, "success_only")
        if envs is not None:
            self._track(self.env_key, "the env filter")
        if runs is not None:
            self._track(self.run_key, "the run filter")
        view = self._views[key] = _View(key)
        while len(self._views) > self.max_cached_filters:
            self._views.popitem(last=False)
        return view

    def _members(self, key, rows: np.ndarray | None) -> np.ndarray:
        n = self._n
        sel = slice(0, n) if rows is None else rows

        def col(k):
            c = self._snap[k][sel]
            return c.reshape(c.shape[0], int(np.prod(c.shape[1:], dtype=np.int64)))

        g = col(self.goal_key)
        mask = np.isfinite(g).all(1) if g.dtype.kind == "f" else np.ones(g.shape[0], dtype=bool)
        success_only, envs, runs = key
        if success_only:
            mask &= col(self.success_key)[:, 0] > 0.5
        if envs is not None:
            mask &= np.isin(col(self.env_key)[:, 0], envs)
        if runs is not None:
            mask &= np.isin(col(self.run_key)[:, 0], runs)
        return mask

    def _sync_view(self, view: _View) -> None:
        if view.seen == self._epoch:
            return
        n = self._n
        if view.owner.size < n:
            owner = np.zeros(max(n, 2 * view.owner.size), dtype=np.int8)
            owner[: view.owner.size] = view.owner
            view.owner = owner
        if view.main is None or view.seen < self._log_floor:
            self._rebuild_view(view)
            return
        logged = [rows for epoch, rows in self._log if epoch > view.seen]
        if not logged:
            view.seen = self._epoch
            return
        rows = logged[0] if len(logged) == 1 else np.unique(np.concatenate(logged))
        owner = view.owner
        counts = np.bincount(owner[rows], minlength=4)
        view.main.n_stale += int(counts[_LEVEL_MAIN])
        if view.mid is not None:
            view.mid.n_stale += int(counts[_LEVEL_MID])
        owner[rows] = 0
        fresh = rows[self._members(view.key, rows)]
        live_rows = fresh
        if view.live is not None:
            kept = view.live.rows[owner[view.live.rows] == _LEVEL_LIVE]
            live_rows = np.concatenate([kept, fresh]) if fresh.size else kept
        mid_size = view.mid.size if view.mid is not None else 0
        budget = max(self.tail_size, self.rebuild_fraction * view.main.size)
        if view.main.n_stale + mid_size + live_rows.size > budget:
            self._rebuild_view(view)
            return
        if live_rows.size > self.tail_size:
            if view.mid is not None:
                live_rows = np.concatenate([view.mid.rows[owner[view.mid.rows] == _LEVEL_MID], live_rows])
            view.mid = self._build_segment(_LEVEL_MID, live_rows, view.backend)
            owner[live_rows] = _LEVEL_MID
            view.live = None
        elif fresh.size or counts[_LEVEL_LIVE]:
            view.live = (
                self._build_segment(_LEVEL_LIVE, live_rows, view.backend) if live_rows.size else None
            )
            owner[live_rows] = _LEVEL_LIVE
        view.seen = self._epoch

    def _rebuild_view(self, view: _View) -> None:
        rows = np.flatnonzero(self._members(view.key, None))
        view.owner[:] = 0
        view.owner[rows] = _LEVEL_MAIN
        view.mid = view.live = None
        view.backend, main = self._choose_backend(rows)
        view.main = main if main is not None else self._build_segment(_LEVEL_MAIN, rows, view.backend)
        view.seen = self._epoch

    def _build_segment(self, level, rows, backend) -> _Segment:
        goals = self._snap[self.goal_key][rows]
        goals = goals.reshape(goals.shape[0], int(np.prod(self._goal_shape)))
        if backend == "kdtree":
            emb = self.metric._embed(goals)
            exact = self.metric._embedding_exact and len(self.metric._embed_queries(emb[:0])) == 1
            if rows.size == 0:
                return _BruteSegment(level, rows, emb, None, self.metric)
            return _TreeSegment(level, rows, emb, exact)
        if self.metric._embeddable:
            return _BruteSegment(level, rows, self.metric._embed(goals), None, self.metric)
        return _BruteSegment(level, rows, None, goals.astype(np.float64), self.metric)

    def _choose_backend(self, rows: np.ndarray) -> tuple[str, _Segment | None]:
        """The backend for a view's segments, and its main segment when the probe built it."""
        if self.backend != "auto":
            return self.backend, None
        if not self.metric._embeddable:
            return "brute", None
        goal_dim = int(np.prod(self._goal_shape))
        emb_dim = self.metric._embed(np.zeros((1, goal_dim))).shape[1]
        if emb_dim <= 4 or rows.size < _PROBE_MIN_ROWS:
            return "kdtree", None
        # Time both backends on a few queries near stored goals and keep the faster.
        tree = self._build_segment(_LEVEL_MAIN, rows, "kdtree")
        brute = self._build_segment(_LEVEL_MAIN, rows, "brute")
        rng = np.random.default_rng(0)
        goals = self._snap[self.goal_key][rng.choice(rows, 16)].reshape(16, -1).astype(np.float64)
        goals += rng.normal(size=goals.shape) * 0.01 * (goals.std(0, keepdims=True) + 1e-6)
        qvars = self.metric._embed_queries(goals)
        owner = np.full(1, _LEVEL_MAIN, dtype=np.int8)
        times = {}
        for name, seg in (("kdtree", tree), ("brute", brute)):
            t0 = time.perf_counter()
            self._search_segment(seg, owner, goals, qvars, 5, np.inf)
            times[name] = time.perf_counter() - t0
        choice = min(times, key=times.get)
        return choice, (tree if choice == "kdtree" else brute)

    # -- search ---------------------------------------------------------------
    def _search_view(self, view: _View, q: np.ndarray, k: int, max_d: float):
        segments = view.segments
        Q = q.shape[0]
        if not segments:
            return np.full((Q, k), np.inf), np.full((Q, k), -1, dtype=np.int64)
        qvars = self.metric._embed_queries(q) if self.metric._embeddable else [q]
        parts = [self._search_segment(seg, view.owner, q, qvars, k, max_d) for seg in segments]
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

    def _exact(self, q: np.ndarray, pos: np.ndarray) -> np.ndarray:
        g = self._snap[self.goal_key][np.maximum(pos, 0)]
        g = torch.from_numpy(g.reshape(*pos.shape, int(np.prod(self._goal_shape))).astype(np.float64))
        return self.metric.distance(torch.from_numpy(q)[:, None, :], g).numpy()

    def _search_segment(self, seg, owner, q, qvars, k, max_d):
        """Top-k (distance, row) of one segment, exact: grows the candidate count as needed."""
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
                dist = self._exact(sub_q, pos)
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


# -- module-level entry point -------------------------------------------------
_INDEX_CACHE: dict[int, dict] = {}


def _metric_cache_key(metric, metric_kwargs):
    if isinstance(metric, str):
        return (metric.lower(), tuple(sorted((metric_kwargs or {}).items())))
    return (metric, tuple(sorted((metric_kwargs or {}).items())))


def _shared_index(
    storage_or_rb,
    *,
    goal_key: NestedKey = ("next", "achieved_goal"),
    success_key: NestedKey = ("next", "is_success"),
    metric="euclidean",
    metric_kwargs: dict | None = None,
    env_names: Sequence[str] | None = None,
) -> GoalIndex:
    """The GoalIndex cached for this storage and configuration (weakly held by the storage)."""
    st = _as_storage(storage_or_rb)
    sid = id(st)
    entry = _INDEX_CACHE.get(sid)
    if entry is None or entry["ref"]() is not st:
        entry = _INDEX_CACHE[sid] = {"ref": weakref.ref(st), "indexes": {}}
        weakref.finalize(st, _INDEX_CACHE.pop, sid, None)
    key = (goal_key, success_key, _metric_cache_key(metric, metric_kwargs),
           tuple(env_names) if env_names is not None else None)
    index = entry["indexes"].get(key)
    if index is None:
        index = GoalIndex(st, goal_key=goal_key, success_key=success_key, metric=metric,
                          metric_kwargs=metric_kwargs, env_names=env_names)
        index._storage_ref = weakref.ref(st)  # the cache must not keep the storage alive
        entry["indexes"][key] = index
    return index


def recall(
    storage_or_rb,
    goal,
    k: int = 5,
    *,
    goal_key: NestedKey = ("next", "achieved_goal"),
    success_key: NestedKey = ("next", "is_success"),
    metric="euclidean",
    metric_kwargs: dict | None = None,
    env_names: Sequence[str] | None = None,
    success_only: bool = False,
    env: str | int | Sequence[str | int] | None = None,
    run: int | Sequence[int] | None = None,
    max_distance: float | None = None,
) -> TensorDictBase:
    """Recalls the k stored transitions whose goals are nearest to ``goal``.

    A :class:`GoalIndex` is built on first use and cached per storage (and per
    ``goal_key``/``success_key``/``metric``/``env_names``); it is dropped with
    the storage. Arguments and output are those of :meth:`GoalIndex.recall`.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_robotmem.goal_index import recall
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
        >>> _ = rb.extend(TensorDict({
        ...     "action": torch.randn(10, 4),
        ...     ("next", "achieved_goal"): torch.arange(30.0).view(10, 3),
        ...     ("next", "is_success"): torch.ones(10),
        ... }, batch_size=[10]))
        >>> out = recall(rb, [0.0, 1.0, 2.0], k=2)
        >>> out["index"], out["distance"]
        (tensor([0, 1]), tensor([0.0000, 5.1962]))
    """
    index = _shared_index(
        storage_or_rb, goal_key=goal_key, success_key=success_key, metric=metric,
        metric_kwargs=metric_kwargs, env_names=env_names,
    )
    return index.recall(
        goal, k, success_only=success_only, env=env, run=run, max_distance=max_distance
    )
