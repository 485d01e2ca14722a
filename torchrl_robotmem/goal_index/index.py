"""The index facade: :class:`GoalIndex`, the shared index of a storage, and :func:`recall`.

:class:`GoalIndex` answers "which stored transitions achieved the goals
closest to this one?" (top-k, under a :class:`~.filters.RowFilter`: success /
env / run, a distance limit, one match per episode) on the live columns of a
:class:`~torchrl.data.replay_buffers.storages.TensorStorage`
(``LazyTensorStorage``, ``LazyMemmapStorage``, ``ZarrStorage``), exactly.
:meth:`GoalIndex.for_storage` returns *the* index of a storage, the one that
:func:`recall`, :class:`~torchrl_robotmem.GoalSimilaritySampler`,
:class:`~torchrl_robotmem.RecallTransform` and
:class:`~torchrl_robotmem.RobotMemory` share. The work is done by
:mod:`.tracking` (following the storage), :mod:`.views` (one set of segments
per filter), :mod:`.segments` (exact search), :mod:`.queries` (checking the
query) and :mod:`.shared` (the shared indexes).
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data.replay_buffers.storages import TensorStorage

from torchrl_robotmem.goal_index.filters import FilterKey, RowFilter
from torchrl_robotmem.goal_index.metrics import GoalMetric, get_metric
from torchrl_robotmem.goal_index.queries import check_k, parse_goals
from torchrl_robotmem.goal_index.shared import SharedIndexes
from torchrl_robotmem.goal_index.tracking import ColumnTracker, as_tensor_storage, live_column, stored_rows
from torchrl_robotmem.goal_index.views import FilterView
from torchrl_robotmem.storage.context import success_advice

__all__ = ["GoalIndex", "recall"]

GOAL_KEY: NestedKey = ("next", "achieved_goal")
SUCCESS_KEY: NestedKey = ("next", "is_success")

_ALL_ROWS = FilterKey(False, None, None)

FilterArg = RowFilter | Mapping[str, Any] | None

# (goal_key, success_key, metric key, env_names) -> the GoalIndex of each storage
_SHARED = SharedIndexes()


class GoalIndex:
    """Exact k-nearest-goal search over the transitions of a TorchRL storage.

    The index reads the storage's own columns and follows every change to them
    (appends, ring-buffer overwrites, ``loads``): results always equal a
    brute-force search over the rows currently stored (ties aside). Nothing
    is built until the first query. Use :meth:`for_storage` to get the index
    a storage shares with :func:`recall`, the sampler, the transform and
    :class:`~torchrl_robotmem.RobotMemory`; the constructor makes a private one.

    Memory (:meth:`nbytes`): the index holds one snapshot of the goal
    column (float64 for the Euclidean metric, which its KD-tree searches in
    place; the goals' own dtype otherwise) and, per filter view in use, a
    1-byte owner per stored row plus its search structure. For 3-D goals and
    the unfiltered view that is 24 (goals) + 1 (owner) + 8 (KD-tree
    indices) + about 13 (KD-tree nodes) = about **46 bytes a row** (460 MB
    at 10M rows; 74 before issue 41, which held the goals twice and two
    int64 row-id arrays). A filtered view adds 1 byte a stored row and
    about 49 a member row (int32 row id, its own float64 goals, tree); a
    filter column adds its dtype's size a row. Nothing grows past the
    storage's ``max_size``; nothing of the index is on disk (it is rebuilt
    from the storage's columns after a reopen, at about 0.5-0.7 s of CPU per
    million 3-D goals, and kept in step incrementally afterwards).

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
            ``"pose"`` / ``"hand"``, see :mod:`torchrl_robotmem.goal_index.metrics`.
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
        >>> from torchrl_robotmem.goal_index import GoalIndex
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
                                      rebuild_fraction=self.rebuild_fraction,
                                      float64_goals=self.metric.embedding_is_goals)
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
        key = (goal_key, success_key, metric_obj.key, tuple(env_names) if env_names is not None else None)

        def build() -> GoalIndex:
            index = cls.__new__(cls)
            index._init(st, True, goal_key=goal_key, success_key=success_key, metric=metric_obj,
                        metric_kwargs=None, env_names=env_names, env_key="env", run_key="run",
                        episode_key="episode", backend="auto", tail_size=4096, rebuild_fraction=0.05,
                        max_cached_filters=8)
            return index

        return _SHARED.get(st, key, build)

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

    def nbytes(self) -> int:
        """Bytes of RAM the index itself holds, the storage's own columns not counted.

        The snapshot of the goal column (and of each filter column in use),
        the change log, and per filter view: a 1-byte owner per row, the
        int32 row ids of each segment (none for a view every row passes),
        its KD-tree (``intp`` indices, 72-byte nodes, and a float64 copy of
        the goals unless it searches the snapshot itself) or brute-force
        matrix, and the cached :meth:`member_rows`. Allocated rows are
        counted (a snapshot may be ahead of ``len(storage)``, never past its
        ``max_size``). 3-D Euclidean goals, unfiltered: about 46 bytes a row
        (see the class docstring).
        """
        with self._lock:
            return self._tracker.nbytes() + sum(v.nbytes() for v in self._views.values())

    # -- queries ----------------------------------------------------------------
    def refresh(self, filter: FilterArg = None, **filter_keywords) -> GoalIndex:
        """Brings the view of this filter (``filter=`` or its keywords) up to date now (queries do it lazily)."""
        key = self._filter_key(RowFilter.coerce(filter, **filter_keywords))
        with self._lock:
            self._sync()
            if self._tracker.goal_shape is not None:
                self._view(key).sync()
        return self

    def member_rows(self, filter: FilterArg = None, **filter_keywords) -> torch.Tensor:
        """Storage rows passing the filter (int64, sorted; non-finite goals excluded), cached until they change.

        Only ``success_only`` / ``env`` / ``run`` decide membership.
        """
        key = self._filter_key(RowFilter.coerce(filter, **filter_keywords))
        with self._lock:
            self._sync()
            if self._tracker.goal_shape is None or self._tracker.n == 0:
                return torch.zeros(0, dtype=torch.int64)
            return self._view(key).member_rows()

    def draw_rows(self, n: int, filter: FilterArg = None, *, draw: Callable[[int], torch.Tensor] | None = None,
                  generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` rows drawn uniformly, with replacement, among those passing the filter; a row whose goal is NaN
        or inf is never drawn (as :meth:`search` never returns one). Empty when no row passes.

        With no filter the draw is over every row (``draw(count)``, default ``torch.randint`` over
        ``len(storage)``) and a row whose goal is not finite is drawn again, up to 8 times: no pass over the
        rows. With a filter, or when most goals are not finite, the draw is among :meth:`member_rows`.

        Args:
            n (int): rows to draw.
            filter (RowFilter or mapping, optional): which rows may be drawn.

        Keyword Args:
            draw (callable, optional): ``draw(count)`` -> ``count`` rows over every stored row (a TorchRL
                sampler's draw, say).
            generator (torch.Generator, optional): for the default draw and the draw among members.

        Example:
            >>> import torch
            >>> from tensordict import TensorDict
            >>> from torchrl.data import LazyTensorStorage
            >>> from torchrl_robotmem import GoalIndex
            >>> storage = LazyTensorStorage(10)
            >>> goals = torch.tensor([[0.0, 0], [float("nan"), 0], [1.0, 1]])
            >>> storage.set(range(3), TensorDict({("next", "achieved_goal"): goals}, [3]))
            >>> rows = GoalIndex(storage).draw_rows(100, generator=torch.Generator().manual_seed(0))
            >>> sorted(set(rows.tolist()))
            [0, 2]
        """
        flt = RowFilter.coerce(filter)
        column = live_column(self.storage, self.goal_key)
        if column is None or len(self.storage) == 0:
            return torch.zeros(0, dtype=torch.int64)
        if flt.matches_all:
            stored = len(self.storage)
            draw = draw or (lambda count: torch.randint(stored, (count,), generator=generator))
            rows = draw(n).to(torch.long).cpu()
            for _ in range(8):
                bad = ~torch.isfinite(column[rows.to(column.device)].reshape(n, -1)).all(-1).cpu()
                if not bool(bad.any()):
                    return rows
                rows[bad] = draw(int(bad.sum())).to(torch.long).cpu()
        members = self.member_rows(flt)
        if members.numel() == 0:
            return members
        return members[torch.randint(members.numel(), (n,), generator=generator)]

    def search(
        self,
        goal,
        k: int = 5,
        *,
        filter: FilterArg = None,
        **filter_keywords,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The k nearest stored goals: ``(distance, index, mask)``.

        Args:
            goal: ``[goal_dim]`` or ``[B, goal_dim]`` (tensor, array or list).
            k (int): number of neighbours (>= 1). Clamped to the storage's
                capacity (``max_size``: no query can match more rows), and the
                search itself to the rows that pass the filter. A memory without
                a capacity answers ``k`` columns (those past its rows masked); a
                ``k`` past its rows that asks for more than 2**26 results is refused.

        Keyword Args:
            filter (RowFilter or mapping, optional): which rows may match, as
                one value (see :class:`~torchrl_robotmem.goal_index.RowFilter`).
            **filter_keywords: the same as keywords instead: ``success_only``
                (rows whose ``success_key`` is ``> 0.5``), ``env`` (names or
                codes), ``run``, ``max_distance`` (drop farther matches) and
                ``one_per_episode`` (the k results come from k different
                episodes of the ``episode_key`` column: the nearest row of
                each of the k nearest episodes).

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
        k = check_k(k)
        flt = RowFilter.coerce(filter, **filter_keywords)
        key = self._filter_key(flt)
        with self._lock:
            self._sync()
            q, batched = parse_goals(goal, self._tracker.goal_dim, self.goal_key)
            Q = q.shape[0]
            # k is clamped to the rows that can exist (the width of the result, fixed for a
            # given k and storage: callers size specs on it) and to the rows passing the
            # filter (the search): a k far above them allocates nothing for it
            width = min(k, int(self.storage.max_size))
            if getattr(self.storage, "bounded", True) is False and width > len(self.storage) and Q * width > 2**26:
                raise ValueError(  # a memory without a capacity clamps nothing: k columns are k columns
                    f"k={k} for {Q} goal(s) asks for {Q * width:,} results from a memory without a capacity that "
                    f"holds {len(self.storage):,} rows: ask for at most the rows stored (len(storage)).")
            kk = 0
            if width and Q and self._tracker.goal_shape is not None and self._tracker.n:
                if flt.one_per_episode:
                    self._tracker.track(self.episode_key, "one_per_episode")
                view = self._view(key)
                view.sync()
                kk = min(width, view.size)
            if kk:
                max_d = flt.distance_limit
                d, p = (view.search_episodes(q, kk, max_d, self.episode_key) if flt.one_per_episode
                        else view.search(q, kk, max_d))
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
        filter: FilterArg = None,
        **filter_keywords,
    ) -> TensorDictBase:
        """The k stored transitions whose goals are nearest to ``goal``, with their context.

        Same arguments as :meth:`search`. Returns a TensorDict of batch ``[w]``
        (or ``[B, w]``), ``w = min(k, max_size)``, with every stored key of
        those rows (observation, action, goals, ``"next"`` entries, tags...)
        plus ``distance`` (float32), ``mask`` (bool) and ``index`` (int64
        storage row). Masked entries hold zeros.
        """
        dist, index, mask = self.search(goal, k, filter=filter, **filter_keywords)
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

    def _filter_key(self, flt: RowFilter) -> FilterKey:
        return flt.resolve(self.env_names if flt.env is not None else None)

    def _view(self, key: FilterKey) -> FilterView:
        view = self._views.get(key)
        if view is not None:
            self._views.move_to_end(key)
            return view
        tracker = self._tracker
        if key.success_only:
            tracker.track(self.success_key, "success_only", success_advice() if self.success_key == SUCCESS_KEY else "")
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
    filter: FilterArg = None,
    **filter_keywords,
) -> TensorDictBase:
    """Recalls the k stored transitions whose goals are nearest to ``goal``.

    Uses the storage's shared index (:meth:`GoalIndex.for_storage`), built on
    first use and dropped with the storage. Arguments and output are those of
    :meth:`GoalIndex.recall`: the filter is ``filter=RowFilter(...)`` or its
    keywords (``success_only``, ``env``, ``run``, ``max_distance``,
    ``one_per_episode``).

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
    return index.recall(goal, k, filter=filter, **filter_keywords)
