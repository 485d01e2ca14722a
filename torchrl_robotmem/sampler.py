"""A TorchRL sampler drawing transitions whose achieved goals lie near query goals.

``ReplayBuffer.sample()`` takes no query, so the query is set on the sampler
before sampling, the way TorchRL's ``StalenessAwareSampler`` is steered by its
``consumer_version``::

    with rb.sampler.query(desired_goals):
        batch = rb.sample()
"""
from __future__ import annotations

import contextlib
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from tensordict.utils import NestedKey
from torchrl.data.replay_buffers.samplers import RandomSampler, Sampler
from torchrl.data.replay_buffers.storages import Storage

from torchrl_robotmem.goal_index import GoalIndex, RowFilter
from torchrl_robotmem.goal_index.metrics import GoalMetric
from torchrl_robotmem.goal_index.tracking import live_column
from torchrl_robotmem.samplers.json_state import JsonStateDumps

_UNIFORM = RandomSampler()  # TorchRL's uniform draw: the storage's own indices (ZarrStorage: on the CPU)

__all__ = ["GoalSimilaritySampler"]

_EMPTY_STORAGE_ERROR = "Cannot sample from an empty storage."


def _key_to_json(key: NestedKey):
    return list(key) if isinstance(key, tuple) else key


def _key_from_json(key) -> NestedKey:
    return tuple(key) if isinstance(key, list) else key


class GoalSimilaritySampler(JsonStateDumps, Sampler):
    """Samples transitions whose achieved goals are near query goals.

    Without a query it samples uniformly, like :class:`~torchrl.data.RandomSampler`,
    over the rows that pass the filter's ``success_only`` / ``env`` / ``run``.
    With a query (one goal or ``[Q, goal_dim]`` goals, e.g. the goals the envs
    are chasing now) the batch is spread evenly over the ``Q`` queries; for
    each query the ``num_candidates`` nearest stored rows are found with an
    exact :class:`~torchrl_robotmem.goal_index.GoalIndex` (same filter) and rows
    are drawn, with replacement, with probabilities
    ``softmax(-distance / temperature)`` over those candidates. A fraction
    ``uniform_ratio`` of the batch is drawn uniformly instead (among the rows
    passing the filters). The batch is shuffled, so ``HERReplayBuffer``'s
    "first ``her_ratio`` rows" are a random subset of both kinds.

    The sampled TensorDict gets a ``"goal_distance"`` entry (float32): the
    distance of each row's goal to its query (to the nearest query for the
    uniform rows). Candidates are cached per query and storage revision, so
    repeated ``rb.sample()`` calls under one query and no new data cost a
    multinomial draw.

    The GoalIndex is the storage's shared one (:meth:`GoalIndex.for_storage
    <torchrl_robotmem.goal_index.GoalIndex.for_storage>`, also used by
    :func:`~torchrl_robotmem.recall`, :class:`~torchrl_robotmem.RecallTransform`
    and :class:`~torchrl_robotmem.RobotMemory`) for the same keys and metric. Use ``prefetch=None`` on the buffer: prefetched
    batches would have been drawn under an earlier query.

    Keyword Args:
        goal_key (NestedKey): goals compared to the query. Defaults to
            ``("next", "achieved_goal")``.
        success_key (NestedKey): success flag read by ``success_only``.
            Defaults to ``("next", "is_success")``.
        metric (str): ``"euclidean"`` (default) or ``"pose"`` (see
            :mod:`torchrl_robotmem.goal_index.metrics`).
        metric_kwargs (dict, optional): keyword arguments of the metric.
        temperature (float): softmax temperature, in goal-distance units.
            Defaults to ``0.05`` (5 cm for Fetch goals).
        num_candidates (int): nearest rows considered per query. Defaults to 256.
        env_names (list of str, optional): names of the env codes when the
            storage has no ``env_names`` attribute.
        uniform_ratio (float): fraction of the batch sampled uniformly.
            Defaults to ``0.0``.
        filter (RowFilter or mapping, optional): which rows are sampled (see
            :class:`~torchrl_robotmem.goal_index.RowFilter`): ``success_only``,
            ``env`` (names or codes of the storage's ``env`` column) and
            ``run`` for every draw; ``max_distance`` and ``one_per_episode``
            for the near candidates of a query (a query with no row within
            ``max_distance`` gets no share of the batch; the others share it,
            and if no query has one, ``sample`` raises). Defaults to every row.
        **filter_keywords: the same as keywords instead, e.g.
            ``success_only=True, env="FetchPush-v4"``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_robotmem.sampler import GoalSimilaritySampler
        >>> rb = TensorDictReplayBuffer(
        ...     storage=LazyTensorStorage(10_000),
        ...     sampler=GoalSimilaritySampler(temperature=0.05, uniform_ratio=0.25),
        ...     batch_size=64,
        ... )
        >>> _ = rb.extend(TensorDict({
        ...     "observation": torch.randn(1000, 25),
        ...     ("next", "achieved_goal"): torch.rand(1000, 3),
        ...     ("next", "is_success"): torch.zeros(1000),
        ... }, batch_size=[1000]))
        >>> with rb.sampler.query(torch.tensor([0.5, 0.5, 0.5])):
        ...     batch = rb.sample()
        >>> batch["goal_distance"].shape
        torch.Size([64])
        >>> rb.sample().get("goal_distance", None) is None  # no query: uniform
        True
    """

    def __init__(
        self,
        *,
        goal_key: NestedKey = ("next", "achieved_goal"),
        success_key: NestedKey = ("next", "is_success"),
        metric: str | GoalMetric = "euclidean",
        metric_kwargs: dict | None = None,
        temperature: float = 0.05,
        num_candidates: int = 256,
        env_names: Sequence[str] | None = None,
        uniform_ratio: float = 0.0,
        filter: RowFilter | Mapping[str, Any] | None = None,
        **filter_keywords,
    ):
        self.goal_key = _key_from_json(goal_key)
        self.success_key = _key_from_json(success_key)
        self.metric = metric
        self.metric_kwargs = dict(metric_kwargs or {})
        self.temperature = temperature
        self.num_candidates = num_candidates
        self.filter = RowFilter.coerce(filter, **filter_keywords)
        self.env_names = env_names
        self.uniform_ratio = uniform_ratio
        self._check_config()
        self._query: torch.Tensor | None = None
        self._query_version = 0
        self._cache = None

    def _check_config(self):
        t = float(self.temperature)
        if not math.isfinite(t) or t <= 0:
            raise ValueError(f"temperature must be a finite number > 0, got {self.temperature}.")
        self.temperature = t
        c = self.num_candidates
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or c < 1:
            raise ValueError(f"num_candidates must be a positive integer, got {c!r}.")
        self.num_candidates = int(c)
        u = float(self.uniform_ratio)
        if not 0.0 <= u <= 1.0:
            raise ValueError(f"uniform_ratio must be in [0, 1], got {self.uniform_ratio}.")
        self.uniform_ratio = u
        if self.env_names is not None:
            self.env_names = tuple(self.env_names)

    @property
    def success_only(self) -> bool:
        """``filter.success_only``: only successful rows are sampled."""
        return self.filter.success_only

    @property
    def env(self) -> tuple[str | int, ...] | None:
        """``filter.env``: the envs sampled from (``None``: every env)."""
        return self.filter.env

    # -- query ----------------------------------------------------------------
    @property
    def current_query(self) -> torch.Tensor | None:
        """The query goals ``[Q, goal_dim]`` (float64), or ``None``."""
        return self._query

    def set_query(self, goals) -> None:
        """Sets the goal(s), ``[goal_dim]`` or ``[Q, goal_dim]``, that the next samples are drawn near."""
        if goals is None:
            self.clear_query()
            return
        q = torch.as_tensor(np.asarray(goals.detach().cpu() if isinstance(goals, torch.Tensor) else goals,
                                       dtype=np.float64))
        if q.ndim == 1:
            q = q.unsqueeze(0)
        if q.ndim != 2 or q.shape[0] == 0:
            raise ValueError(
                f"query goals must have shape [goal_dim] or [Q, goal_dim] with Q >= 1, got {tuple(q.shape)}."
            )
        if not torch.isfinite(q).all():
            raise ValueError("query goals contain NaN or infinite values.")
        self._query = q
        self._query_version += 1
        self._cache = None

    def clear_query(self) -> None:
        """Back to uniform sampling."""
        self._query = None
        self._query_version += 1
        self._cache = None

    @contextlib.contextmanager
    def query(self, goals):
        """Context manager: ``with sampler.query(goals): rb.sample()``; restores the previous query."""
        previous = self._query
        self.set_query(goals)
        try:
            yield self
        finally:
            self._query = previous
            self._query_version += 1
            self._cache = None

    # -- sampling -------------------------------------------------------------
    def index_for(self, storage: Storage) -> GoalIndex:
        """The index this sampler searches in ``storage``: the storage's shared :class:`GoalIndex`."""
        return GoalIndex.for_storage(
            storage,
            goal_key=self.goal_key,
            success_key=self.success_key,
            metric=self.metric,
            metric_kwargs=self.metric_kwargs or None,
            env_names=self.env_names,
        )

    def _candidates(self, index: GoalIndex):
        key = (id(index), index.revision, self._query_version, self.num_candidates, self.temperature,
               self.filter)
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        dist, idx, mask = index.search(self._query, self.num_candidates, filter=self.filter)
        found = mask[:, 0]
        if not bool(found.any()):
            raise RuntimeError(
                f"no stored row matches the sampler's filter {self.filter!r}; cannot sample near the query."
            )
        if not bool(found.all()):  # a query with nothing in reach (max_distance): the others share the batch
            dist, idx, mask = dist[found], idx[found], mask[found]
        logits = (-dist.double() / self.temperature).masked_fill(~mask, -math.inf)
        probs = torch.softmax(logits, dim=1)
        cand = (probs, idx, dist)
        self._cache = (key, cand)
        return cand

    def _uniform_rows(self, index: GoalIndex, storage: Storage, n: int) -> torch.Tensor:
        """``n`` rows drawn uniformly among those passing the filters, rows with a non-finite goal left out."""
        rows = index.draw_rows(n, self.filter, draw=lambda count: _UNIFORM.sample(storage, count)[0],
                               generator=self._rng)  # with no filter: TorchRL's draw over every row
        if rows.numel() == 0:
            raise RuntimeError(f"no stored row matches the sampler's filter {self.filter!r}.")
        return rows

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RuntimeError(_EMPTY_STORAGE_ERROR)
        if self._query is None:
            if self.filter.matches_all:
                return _UNIFORM.sample(storage, batch_size)[0], {}
            # no query, but the filters still hold: uniform over the matching rows
            return self._uniform_rows(self.index_for(storage), storage, batch_size).to(torch.long), {}
        index = self.index_for(storage)
        probs, cand_idx, cand_dist = self._candidates(index)
        Q = probs.shape[0]
        n_uniform = int(round(self.uniform_ratio * batch_size))
        n_near = batch_size - n_uniform
        if Q == 1 and n_uniform == 0:  # i.i.d. draws of one query: nothing to spread or shuffle
            draws = torch.multinomial(probs[0], batch_size, replacement=True, generator=self._rng)
            return cand_idx[0][draws], {"goal_distance": cand_dist[0][draws]}
        parts_idx, parts_dist = [], []
        if n_near:
            counts = torch.full((Q,), n_near // Q, dtype=torch.long)
            rem = n_near % Q
            if rem:
                counts[torch.randperm(Q, generator=self._rng)[:rem]] += 1
            width = int(counts.max())
            draws = torch.multinomial(probs, width, replacement=True, generator=self._rng)
            keep = torch.arange(width).unsqueeze(0) < counts.unsqueeze(1)
            parts_idx.append(cand_idx.gather(1, draws)[keep])
            parts_dist.append(cand_dist.gather(1, draws)[keep])
        if n_uniform:
            rows = self._uniform_rows(index, storage, n_uniform).to(torch.long).cpu()
            col = live_column(storage, self.goal_key)
            goals = col[rows.to(col.device)]
            goals = goals.cpu().reshape(n_uniform, -1).double()
            d = index.metric.pairwise(self._query, goals).amin(0).float()
            parts_idx.append(rows)
            parts_dist.append(d)
        idx = torch.cat(parts_idx)
        dist = torch.cat(parts_dist)
        perm = torch.randperm(batch_size, generator=self._rng)
        return idx[perm], {"goal_distance": dist[perm]}

    # -- buffer hooks and persistence -----------------------------------------
    def _empty(self):
        self._cache = None

    def state_dict(self) -> dict[str, Any]:
        metric = self.metric
        if isinstance(metric, GoalMetric):
            if metric.name not in ("euclidean", "pose"):
                raise TypeError(f"cannot serialise the custom metric {metric!r}; pass its name.")
            kwargs = {"rotation_weight": metric.rotation_weight} if metric.name == "pose" else {}
            metric, metric_kwargs = metric.name, kwargs
        else:
            metric_kwargs = dict(self.metric_kwargs)
        return {
            "goal_key": _key_to_json(self.goal_key),
            "success_key": _key_to_json(self.success_key),
            "metric": metric,
            "metric_kwargs": metric_kwargs,
            "temperature": self.temperature,
            "num_candidates": self.num_candidates,
            "filter": self.filter.to_dict(),
            "env_names": list(self.env_names) if self.env_names is not None else None,
            "uniform_ratio": self.uniform_ratio,
            "query": self._query.tolist() if self._query is not None else None,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.goal_key = _key_from_json(state_dict["goal_key"])
        self.success_key = _key_from_json(state_dict["success_key"])
        self.metric = state_dict["metric"]
        self.metric_kwargs = dict(state_dict.get("metric_kwargs") or {})
        self.temperature = state_dict["temperature"]
        self.num_candidates = state_dict["num_candidates"]
        # "success_only" / "env": the state of a sampler saved before the filter was one value
        self.filter = RowFilter.coerce(state_dict.get("filter"), success_only=state_dict.get("success_only"),
                                       env=state_dict.get("env"))
        self.env_names = state_dict.get("env_names")
        self.uniform_ratio = state_dict["uniform_ratio"]
        self._check_config()
        query = state_dict.get("query")
        if query is None:
            self.clear_query()
        else:
            self.set_query(query)

    def __repr__(self) -> str:
        q = None if self._query is None else tuple(self._query.shape)
        return (
            f"{type(self).__name__}(goal_key={self.goal_key}, metric={self.metric!r}, "
            f"temperature={self.temperature}, num_candidates={self.num_candidates}, "
            f"filter={self.filter!r}, "
            f"uniform_ratio={self.uniform_ratio}, query={q})"
        )
