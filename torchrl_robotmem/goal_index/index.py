"""The index facade: :class:`GoalIndex`, the shared index of a storage, and :func:`recall`.

:class:`GoalIndex` answers "which stored transitions achieved the goals
closest to this one?" (top-k, with success / env / run filters, optionally
one match per episode) on the live columns of a
:class:`~torchrl.data.replay_buffers.storages.TensorStorage`
(``LazyTensorStorage``, ``LazyMemmapStorage``, ``ZarrStorage``), exactly.
:meth:`GoalIndex.for_storage` returns *the* index of a storage, the one that
:func:`recall`, :class:`~torchrl_robotmem.GoalSimilaritySampler`,
:class:`~torchrl_robotmem.RecallTransform` and
:class:`~torchrl_robotmem.RobotMemory` share. The work is done by
:mod:`.tracking` (following the storage), :mod:`.views` (one set of segments
per filter) and :mod:`.segments` (exact search).
"""
from __future__ import annotations

import math
import threading
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data.replay_buffers.storages import TensorStorage

from torchrl_robotmem.recall.filters import FilterKey, RowFilter
from torchrl_robotmem.recall.metrics import GoalMetric, get_metric
from torchrl_robotmem.recall.tracking import ColumnTracker, as_tensor_storage, stored_rows
from torchrl_robotmem.recall.views import FilterView

__all__ = ["GoalIndex", "recall"]

GOAL_KEY: NestedKey = ("next", "achieved_goal")
SUCCESS_KEY: NestedKey = ("next", "is_success")

_ALL_ROWS = FilterKey(False, None, None)
_SUCCESS_ONLY = FilterKey(True, None, None)

EnvSpec = str | int | Sequence[str | int] | None
RunSpec = int | Sequence[int] | None


def _key_str(key: NestedKey) -> str:
    return repr(key) if isinstance(key, tuple) else repr(str(key))


class GoalIndex:
    """Exact k-nearest-goal search over the transitions of a TorchRL storage.

    The index reads the storage's own columns and follows every change to them
    (appends, ring-buffer overwrites, ``loads``): results always equal a
    brute-force search over the rows currently stored (ties aside). Nothing
    is built until the first query. Use :meth:`for_storage` to get the index
    a storage shares with :func:`recall`, the sampler, the transform and
    :class:`~torchrl_robotmem.RobotMemory`; the constructor makes a private one.

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
            ``"pose"`` / ``"hand"``, see :mod:`torchrl_robotmem.recall.metrics`.
        metric_kwargs (dict, optional): keyword arguments of a named metric
            (e.g. ``{"rotation_weight": 0.5}``).
        env_names (sequence of str, optional): names of the integer codes of
            the env column (code ``i`` is ``env_names[i]``). Defaults to the
            storage's ``env_names`` attribute when it has one.
        env_key (NestedKey): column of env codes. Defaults to ``"env"``.
        run_key (NestedKey): column of run ids. Defaults to ``"run"``.
        episode_key (NestedKey): column of episode ids, read by
            ``one_per_episode``. Defaults to ``"episode"``.
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
        >>> from torchrl_robotmem.recall import GoalIndex
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000))
        >>> _ = rb.extend(TensorDict({
        ...     "observation": torch.randn(100, 25),
        ...     "action": torch.randn(100, 4),
        ...     ("next", "achieved_goal"): torch.rand(100, 3),
        ...     ("next", "is_success"): (torch.rand(100) < 0.3).float(),
        ...     "episode": torch.arange(100) // 10,
        ... }, batch_size=[100]))
        >>> index = GoalIndex.for_storage(rb)
        >>> index is GoalIndex.for_storage(rb.storage)  # one shared index per storage
        True
        >>> out = index.recall(torch.tensor([0.5, 0.5, 0.5]), k=5, success_only=True)
        >>> out.batch_size, out["action"].shape, out["distance"].dtype
        (torch.Size([5]), torch.Size([5, 4]), torch.float32)
        >>> distance, row, mask = index.search(torch.rand(8, 3), k=3, one_per_episode=True)
        >>> distance.shape, bool((row // 10).unique(dim=1).shape[1] == 3)
        (torch.Size([8, 3]), True)
    """

    def __init__(
        self,
        storage,
        *,
        goal_key: NestedKey = GOAL_KEY,
        success_key: NestedKey = SUCCESS_KEY,
        metric: str | GoalMetric | Any = "euclidean",
        metric_kwargs: dict | None = None,
        env_names: Sequence[str] | None = None,
        env_key: NestedKey = "env",
        run_key: NestedKey = "run",
        episode_key: NestedKey = "episode",
        backend: str = "auto",
        tail_size: int = 4096,
        rebuild_fraction: float = 0.05,
        max_cached_filters: int = 8,
    ):
        self._init(as_tensor_storage(storage), False, goal_key=goal_key, success_key=success_key,
                   metric=metric, metric_kwargs=metric_kwargs, env_names=env_names, env_key=env_key,
                   run_key=run_key, episode_key=episode_key, backend=backend, tail_size=tail_size,
                   rebuild_fraction=rebuild_fraction, max_cached_filters=max_cached_filters)

    def _init(self, storage, weak, *, goal_key, success_key, metric, metric_kwargs, env_names, env_key,
              run_key, episode_key, backend, tail_size, rebuild_fraction, max_cached_filters):
        self.goal_key = goal_key
        self.success_key = success_key
        self.env_key = env_key
        self.run_key = run_key
        self.episode_key = episode_key
        self.metric = get_metric(metric, **(metric_kwargs or {}))
        self._env_names = tuple(env_names) if env_names is not None else None
        if backend not in ("auto", "kdtree", "brute"):
            raise ValueError(f"backend must be 'auto', 'kdtree' or 'brute', got {backend!r}.")
        if backend == "kdtree" and not self.metric.embeddable:
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
        self._tracker = ColumnTracker(storage, goal_key, weak=weak, tail_size=self.tail_size,
                                      rebuild_fraction=self.rebuild_fraction)
        self._views: OrderedDict[FilterKey, FilterView] = OrderedDict()
        self._dropped_builds = 0
        # A shared index may serve a collector thread's transform and the trainer's sampler at once.
        self._lock = threading.RLock()

    # -- the shared index -----------------------------------------------------
    @classmethod
    def for_storage(
        cls,
        storage_or_rb,
        *,
        goal_key: NestedKey = GOAL_KEY,
        success_key: NestedKey = SUCCESS_KEY,
        metric: str | GoalMetric | Any = "euclidean",
        metric_kwargs: dict | None = None,
        env_names: Sequence[str] | None = None,
    ) -> GoalIndex:
        """THE index of this storage for these keys and metric, shared by every caller.

        :func:`recall`, :class:`~torchrl_robotmem.GoalSimilaritySampler`,
        :class:`~torchrl_robotmem.RecallTransform` and
        :class:`~torchrl_robotmem.RobotMemory` all use it, so a storage is
        indexed once however many of them read it. One index is kept per
        storage object and per (``goal_key``, ``success_key``, metric,
        ``env_names``); metrics are compared by what they compute
        (``"l2"`` and ``EuclideanMetric()`` share). The shared index holds its
        storage weakly and is dropped with it: keep the storage (or the
        buffer, memory, transform...) alive while you use the index.
        """
        st = as_tensor_storage(storage_or_rb)
        metric_obj = get_metric(metric, **(metric_kwargs or {}))
        sid = id(st)
        entry = _SHARED.get(sid)
        if entry is None or entry[0]() is not st:
            entry = _SHARED[sid] = (weakref.ref(st), {})
            weakref.finalize(st, _drop_shared, sid, entry[0])
        key = (goal_key, success_key, metric_obj.key, tuple(env_names) if env_names is not None else None)
        index = entry[1].get(key)
        if index is None:
            index = cls.__new__(cls)
            index._init(st, True, goal_key=goal_key, success_key=success_key, metric=metric_obj,
                        metric_kwargs=None, env_names=env_names, env_key="env", run_key="run",
                        episode_key="episode", backend="auto", tail_size=4096, rebuild_fraction=0.05,
                        max_cached_filters=8)
            entry[1][key] = index
        return index

    # -- properties -----------------------------------------------------------
    @property
    def storage(self) -> TensorStorage:
        """The indexed storage."""
        return self._tracker.storage

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
        with self._lock:
            self._sync()
            return self._tracker.goal_dim

    @property
    def revision(self) -> int:
        """A counter that moves whenever the indexed columns change (brought up to date first).

        Equal revisions mean equal goals and filter columns, so anything derived
        from search results (a sampler's candidates) can be cached under it.
        """
        with self._lock:
            self._sync()
            return self._tracker.revision

    @property
    def backend_in_use(self) -> str | None:
        """``"kdtree"`` or ``"brute"``: the search backend of the unfiltered view (once built)."""
        view = self._views.get(_ALL_ROWS)
        return None if view is None else view.backend

    def stats(self) -> dict[str, int]:
        """Rows indexed, revision, filter views held and view (re)builds since the index was made."""
        return {
            "rows": self._tracker.n,
            "revision": self._tracker.revision,
            "views": len(self._views),
            "view_builds": self._dropped_builds + sum(v.builds for v in self._views.values()),
        }

    # -- queries ----------------------------------------------------------------
    def refresh(self, filter: RowFilter | None = None, *, success_only: bool = False, env: EnvSpec = None,
                run: RunSpec = None) -> GoalIndex:
        """Brings the view of this filter up to date now (queries do it lazily)."""
        key = self._resolve(filter, success_only, env, run)
        with self._lock:
            self._sync()
            if self._tracker.goal_shape is not None:
                self._view(key).sync()
        return self

    def member_rows(self, filter: RowFilter | None = None, *, success_only: bool = False, env: EnvSpec = None,
                    run: RunSpec = None) -> torch.Tensor:
        """Storage rows passing the filter (int64, sorted; non-finite goals excluded), cached until they change."""
        key = self._resolve(filter, success_only, env, run)
        with self._lock:
            self._sync()
            if self._tracker.goal_shape is None or self._tracker.n == 0:
                return torch.zeros(0, dtype=torch.int64)
            return self._view(key).member_rows()

    def search(
        self,
        goal,
        k: int = 5,
        *,
        filter: RowFilter | None = None,
        success_only: bool = False,
        env: EnvSpec = None,
        run: RunSpec = None,
        max_distance: float | None = None,
        one_per_episode: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The k nearest stored goals: ``(distance, index, mask)``.

        Args:
            goal: ``[goal_dim]`` or ``[B, goal_dim]`` (tensor, array or list).
            k (int): number of neighbours (>= 1). Clamped to the storage's
                capacity (``max_size``: no query can match more rows), and the
                search itself to the rows that pass the filter.

        Keyword Args:
            filter (RowFilter, optional): the filters as one value (instead of
                ``success_only`` / ``env`` / ``run``).
            success_only (bool): only rows whose ``success_key`` is ``> 0.5``.
            env: env name(s) or integer code(s) to keep.
            run: run id(s) to keep.
            max_distance (float, optional): drop matches farther than this.
            one_per_episode (bool): the k results come from k different
                episodes (the ``episode_key`` column): the nearest row of each
                of the k nearest episodes. Defaults to ``False``.

        Returns:
            ``distance`` (float32), ``index`` (int64 storage row) and ``mask``
            (bool), each ``[w]`` or ``[B, w]`` with ``w = min(k, max_size)``
            (``k`` for any ``k`` the storage could ever answer: the shape does
            not depend on how many rows are stored), nearest first. Missing
            matches (fewer rows stored, passing the filter or within
            ``max_distance``) have ``mask=False``, ``distance=inf`` and
            ``index=-1``; nothing is searched or allocated beyond ``w`` and the
            rows that pass the filter.
        """
        k = _check_k(k)
        max_d = _check_max_distance(max_distance)
        key = self._resolve(filter, success_only, env, run)
        if not isinstance(one_per_episode, (bool, np.bool_)):
            raise ValueError(f"one_per_episode must be a bool, got {one_per_episode!r}.")
        with self._lock:
            self._sync()
            q, batched = self._parse_goal(goal)
            Q = q.shape[0]
            # k is clamped to the rows that can exist (the width of the result, fixed for a
            # given k and storage: callers size specs on it) and to the rows passing the
            # filter (the search): a k far above them allocates nothing for it
            width = min(k, int(self.storage.max_size))
            kk = 0
            if width and Q and self._tracker.goal_shape is not None and self._tracker.n:
                if one_per_episode:
                    self._tracker.track(self.episode_key, "one_per_episode")
                view = self._view(key)
                view.sync()
                kk = min(width, view.size)
            if kk:
                d, p = self._search_episodes(view, q, kk, max_d) if one_per_episode else view.search(q, kk, max_d)
                if kk < width:
                    d = np.pad(d, ((0, 0), (0, width - kk)), constant_values=np.inf)
                    p = np.pad(p, ((0, 0), (0, width - kk)), constant_values=-1)
            else:
                d = np.full((Q, width), np.inf)
                p = np.full((Q, width), -1, dtype=np.int64)
        if not batched:
            d, p = d[0], p[0]
        return torch.from_numpy(d.astype(np.float32)), torch.from_numpy(p), torch.from_numpy(p >= 0)

    def recall(
        self,
        goal,
        k: int = 5,
        *,
        filter: RowFilter | None = None,
        success_only: bool = False,
        env: EnvSpec = None,
        run: RunSpec = None,
        max_distance: float | None = None,
        one_per_episode: bool = False,
    ) -> TensorDictBase:
        """The k stored transitions whose goals are nearest to ``goal``, with their context.

        Same arguments as :meth:`search`. Returns a TensorDict of batch ``[w]``
        (or ``[B, w]``), ``w = min(k, max_size)``, with every stored key of
        those rows (observation, action, goals, ``"next"`` entries, tags...)
        plus ``distance`` (float32), ``mask`` (bool) and ``index`` (int64
        storage row). Masked entries hold zeros.
        """
        dist, index, mask = self.search(goal, k, filter=filter, success_only=success_only, env=env, run=run,
                                        max_distance=max_distance, one_per_episode=one_per_episode)
        out = stored_rows(self.storage, index)
        if out is None:
            out = TensorDict({}, batch_size=index.shape)
        elif not bool(mask.all()):
            out = out.masked_fill(~mask.to(out.device) if out.device else ~mask, 0)
        out.set("distance", dist)
        out.set("mask", mask)
        out.set("index", index)
        return out

    # -- pickling ---------------------------------------------------------------
    def __getstate__(self):
        # Views and snapshots are derived data: rebuilt lazily after unpickling.
        state = dict(self.__dict__)
        state["_views"] = OrderedDict()
        state["_dropped_builds"] = 0
        del state["_lock"]
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.RLock()

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(goal_key={self.goal_key}, metric={self.metric!r}, "
            f"rows={self._tracker.n}, views={len(self._views)}, backend={self.backend_in_use})"
        )

    # -- internals --------------------------------------------------------------
    def _sync(self) -> None:
        self._tracker.sync(self.metric.check_goal_dim)

    def _resolve(self, filter, success_only, env, run) -> FilterKey:
        if filter is None and env is None and run is None and type(success_only) is bool:
            return _SUCCESS_ONLY if success_only else _ALL_ROWS  # the common case, without a RowFilter
        flt = RowFilter.of(filter, success_only=success_only, env=env, run=run)
        return flt.resolve(self.env_names if flt.env is not None else None)

    def _view(self, key: FilterKey) -> FilterView:
        view = self._views.get(key)
        if view is not None:
            self._views.move_to_end(key)
            return view
        tracker = self._tracker
        if key.success_only:
            tracker.track(self.success_key, "success_only")
        if key.envs is not None:
            tracker.track(self.env_key, "the env filter")
        if key.runs is not None:
            tracker.track(self.run_key, "the run filter")
        columns = {"success": self.success_key, "env": self.env_key, "run": self.run_key}
        view = self._views[key] = FilterView(key, tracker, self.metric, columns, self.backend, self.tail_size,
                                             self.rebuild_fraction)
        while len(self._views) > self.max_cached_filters:
            self._dropped_builds += self._views.popitem(last=False)[1].builds
        return view

    def _search_episodes(self, view: FilterView, q: np.ndarray, k: int, max_d: float):
        """Exact top-k over episodes: the nearest row of each of the k nearest episodes.

        The top-m rows, searched exactly, hold the nearest row of every
        episode that has one among them, in order; once they hold k distinct
        episodes (or every row within reach), no other episode can come
        closer. m grows until that holds; it stays below the rows of the k
        largest episodes.
        """
        view.sync()
        episodes = self._tracker.column(self.episode_key).reshape(-1)
        size = view.size
        Q = q.shape[0]
        out_d = np.full((Q, k), np.inf)
        out_p = np.full((Q, k), -1, dtype=np.int64)
        todo = np.arange(Q)
        m = min(max(8 * k, 64), max(size, k))
        while todo.size:
            d, p = view.search(q[todo], m, max_d)
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
        dim = self._tracker.goal_dim
        if dim is not None and q.shape[1] != dim:
            raise ValueError(
                f"goal has dimension {q.shape[1]} but the stored goals "
                f"{_key_str(self.goal_key)} have dimension {dim}."
            )
        if not np.isfinite(q).all():
            raise ValueError("goal contains NaN or infinite values.")
        return q, batched


def _check_k(k) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k must be a positive integer, got {k!r}.")
    return int(k)


def _check_max_distance(max_distance) -> float:
    if max_distance is None:
        return np.inf
    max_distance = float(max_distance)
    if math.isnan(max_distance) or max_distance < 0:
        raise ValueError(f"max_distance must be >= 0, got {max_distance}.")
    return max_distance


# storage id -> (weak ref to the storage, {(goal_key, success_key, metric key, env_names): GoalIndex})
_SHARED: dict[int, tuple[weakref.ref, dict]] = {}


def _drop_shared(sid: int, ref: weakref.ref) -> None:
    entry = _SHARED.get(sid)
    if entry is not None and entry[0] is ref:
        del _SHARED[sid]


def recall(
    storage_or_rb,
    goal,
    k: int = 5,
    *,
    goal_key: NestedKey = GOAL_KEY,
    success_key: NestedKey = SUCCESS_KEY,
    metric: str | GoalMetric | Any = "euclidean",
    metric_kwargs: dict | None = None,
    env_names: Sequence[str] | None = None,
    filter: RowFilter | None = None,
    success_only: bool = False,
    env: EnvSpec = None,
    run: RunSpec = None,
    max_distance: float | None = None,
    one_per_episode: bool = False,
) -> TensorDictBase:
    """Recalls the k stored transitions whose goals are nearest to ``goal``.

    Uses the storage's shared index (:meth:`GoalIndex.for_storage`), built on
    first use and dropped with the storage. Arguments and output are those of
    :meth:`GoalIndex.recall`.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_robotmem.recall import recall
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
        >>> _ = rb.extend(TensorDict({
        ...     "action": torch.randn(10, 4),
        ...     ("next", "achieved_goal"): torch.arange(30.0).view(10, 3),
        ...     ("next", "is_success"): torch.ones(10),
        ...     "episode": torch.tensor([0, 0, 0, 1, 1, 1, 2, 2, 2, 2]),
        ... }, batch_size=[10]))
        >>> out = recall(rb, [0.0, 1.0, 2.0], k=2)
        >>> out["index"], out["distance"]
        (tensor([0, 1]), tensor([0.0000, 5.1962]))
        >>> recall(rb, [0.0, 1.0, 2.0], k=2, one_per_episode=True)["index"]
        tensor([0, 3])
    """
    index = GoalIndex.for_storage(
        storage_or_rb, goal_key=goal_key, success_key=success_key, metric=metric,
        metric_kwargs=metric_kwargs, env_names=env_names,
    )
    return index.recall(goal, k, filter=filter, success_only=success_only, env=env, run=run,
                        max_distance=max_distance, one_per_episode=one_per_episode)
