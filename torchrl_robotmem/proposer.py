"""An env transform that chooses the goal each training episode pursues from the memory's achieved goals.

:class:`GoalProposer` replaces, at each reset, the goal an env hands the agent
with one the memory has already achieved, chosen where the memory is sparsest:
the frontier of what the agent can do. This is MEGA's goal selection (Pitis
et al., "Maximum Entropy Gain Exploration for Long Horizon Multi-goal
Reinforcement Learning," ICML 2020, https://arxiv.org/abs/2007.02832):
sample candidate goals among the achieved ones, estimate the density of the
achieved goals at each, pursue the one of lowest density. The density here
is the distance to the ``k``-th nearest stored achieved goal, answered
exactly by the storage's :class:`~torchrl_robotmem.goal_index.GoalIndex`
(larger distance, sparser region), over every run the memory holds: a second
run starts proposing where the first one's frontier was.

The proposed goal is the goal of the episode everywhere the data sees it:
``desired_goal`` in the observations and the reward and ``is_success`` of
every step are recomputed for it with the task's own ``compute_reward``
(:class:`~torchrl_robotmem.envs.GoalRewardFn`), so stored transitions are
consistent and HER relabels them as any others. Evaluation envs are built
without it and keep the env's own goals.

Example:
    >>> import tempfile, torch
    >>> from torchrl.collectors import Collector
    >>> from torchrl.data import TensorDictReplayBuffer
    >>> from torchrl_robotmem import GoalProposer, ZarrStorage, make_env
    >>> path = tempfile.mkdtemp() + "/reach.zarr"
    >>> rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 10_000, env="FetchReach-v4"))
    >>> collector = Collector(lambda: make_env("FetchReach-v4", seed=0), None, frames_per_batch=100, total_frames=300)
    >>> for data in collector:
    ...     _ = rb.extend(data.reshape(-1))
    >>> collector.shutdown()
    >>> proposer = GoalProposer(rb, "FetchReach-v4", warmup_rows=100, seed=0)
    >>> env = make_env("FetchReach-v4", seed=1, transforms=[proposer])
    >>> episode = env.rollout(3)  # resets, then steps
    >>> goal = episode["desired_goal"][0]
    >>> goals = rb.storage["next", "achieved_goal"][: len(rb)]
    >>> bool((goals == goal).all(-1).any())  # a goal the memory achieved
    True
    >>> bool((episode["next", "desired_goal"] == goal).all())  # pursued for the whole episode
    True
"""
from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data.replay_buffers.storages import Storage
from torchrl.envs import Transform

from .env_resets import reset_mask
from .envs import GoalRewardFn
from .goal_index import GoalIndex, RowFilter
from .goal_index.metrics import GoalMetric, get_metric
from .memory_source import MemorySource

__all__ = ["CANDIDATES", "GoalProposer"]

#: where a proposal's candidates come from (:class:`GoalProposer`'s ``candidates``)
CANDIDATES = ("uniform", "near_goal")


class GoalProposer(Transform):
    """Pursues, in training episodes, remembered achieved goals where the memory is sparsest (MEGA).

    At every reset of an env (all of them, or the rows a batched env's ``"_reset"`` flags), with
    probability ``rate`` the episode's goal becomes a proposed one:

    1. ``num_candidates`` rows are drawn uniformly among the memory's rows (those ``filter`` keeps),
       or, with ``candidates="near_goal"``, the ``num_candidates`` stored achieved goals nearest the
       goal the env handed this episode (exact recall): the frontier in the direction of the task;
    2. for each candidate's achieved goal, the distance to its ``k``-th nearest stored achieved goal
       is found (exact, :meth:`GoalIndex.search <torchrl_robotmem.goal_index.GoalIndex.search>`);
    3. the candidate with the largest such distance (the lowest density) is the goal.

    With ``reached_in=m``, only candidates the agent reaches some of the time compete: goals within
    ``reach_radius`` of rows of at least ``m`` different stored episodes (MEGA filters its candidates
    on a learned value; here the memory counts). Where no candidate of a proposal qualifies, those
    reached in the most episodes compete (then the lowest density among them).

    Until the memory holds ``warmup_rows`` rows, and in the other episodes, the env's own goal is kept,
    and its steps pass through untouched. In an episode pursuing a proposed goal, its ``desired_goal``,
    ``("next", "desired_goal")``, ``("next", "reward")`` and ``("next", "is_success")`` are rewritten
    for that goal at every step, with the task's ``compute_reward`` built with ``gym_kwargs`` (the
    keyword arguments the env was made with, such as ``reward_type="dense"``). Put it on the
    training env only (evaluation keeps the env's goals), *outside* a batched env, and before any
    transform that reads ``desired_goal``, such as :class:`~torchrl_robotmem.RecallTransform` (a
    later transform sees the proposed goal).

    Args:
        memory (str, os.PathLike, Storage or ReplayBuffer): the memory whose achieved goals are
            proposed: the buffer the collector writes into (read live: goals achieved in this run
            join the candidates as they are stored), or a store path (opened ``read_only``).
        env (str): the task id (``"FetchPickAndPlace-v4"``, ``"HandReach-v3"``), whose
            ``compute_reward`` rewards the proposed goals.

    Keyword Args:
        num_candidates (int): candidate goals per proposal. Default: ``100``.
        k (int): the neighbour whose distance measures density. Default: ``10``.
        rate (float): the probability that an episode pursues a proposed goal (``0`` turns the
            proposer off, ``1`` proposes every goal). Default: ``1.0``.
        warmup_rows (int): stored rows below which nothing is proposed. Default: ``1000``.
        in_key (NestedKey): the goal key of the env. Default: ``"desired_goal"``.
        goal_key (NestedKey): the stored column of achieved goals. Default: ``("next", "achieved_goal")``.
        achieved_key (NestedKey): the env's achieved goal, in a step's ``"next"``. Default: ``"achieved_goal"``.
        reward_key, success_key (NestedKey): the step's reward and success, rewritten. Defaults:
            ``"reward"`` and ``"is_success"`` (inside ``"next"``).
        metric (str or GoalMetric): goal distance, as for :class:`~torchrl_robotmem.RecallTransform`.
            Default: ``"euclidean"``.
        filter (RowFilter or mapping, optional): which rows may be proposed and count in the density
            (e.g. ``{"env": "FetchPush-v4"}``). Default: every row.
        candidates (str): where the candidates come from: ``"uniform"`` (drawn among every stored row,
            MEGA) or ``"near_goal"`` (the stored achieved goals nearest the env's goal of the episode,
            so the proposal is the sparsest remembered goal on the way to the task's own goals).
            Default: ``"uniform"``.
        reached_in (int): the episodes (at least) in which the memory reached a goal within
            ``reach_radius`` of a candidate for it to compete; ``0`` keeps every candidate. A candidate
            is a stored row, so its own episode counts: ``1`` keeps every candidate too, ``2`` asks
            for one more episode. Needs the memory's episode ids (the ``episode`` column a
            :class:`~torchrl_robotmem.ZarrStorage` writes). Default: ``0``.
        reach_radius (float, optional): the distance that counts as reaching a goal. Default: the
            task's success distance (``distance_threshold``: 0.05 for Fetch, 0.01 for HandReach; a
            task comparing rotations has none, and needs one given).
        seed (int, optional): seeds the transform's own generator (candidate draws and the ``rate``
            coin). Default: ``None`` (drawn from torch's global generator at the first proposal).
        gym_kwargs (mapping, optional): the keyword arguments the env was made with
            (``make_env(env, reward_type="dense")`` -> ``{"reward_type": "dense"}``), so that the rewards of
            a proposed goal are the env's own kind. Default: none (the id's defaults: sparse rewards).

    Example:
        >>> from torchrl_robotmem import GoalProposer
        >>> GoalProposer("memory/pickandplace.zarr", "FetchPickAndPlace-v4", num_candidates=50, k=5, rate=0.5)
        GoalProposer(memory='memory/pickandplace.zarr', env='FetchPickAndPlace-v4', num_candidates=50, k=5, rate=0.5, warmup_rows=1000)

        MEGA's filter counted in the memory: only goals reached in at least 2 stored episodes compete
        (within the task's success distance, by default):

        >>> mega = GoalProposer("memory/pickandplace.zarr", "FetchPickAndPlace-v4", rate=0.5, reached_in=2)
        >>> mega.reached_in, mega.reach_radius
        (2, 0.05)
    """

    def __init__(
        self,
        memory: str | os.PathLike | Storage | Any,
        env: str,
        *,
        num_candidates: int = 100,
        k: int = 10,
        rate: float = 1.0,
        warmup_rows: int = 1000,
        in_key: NestedKey = "desired_goal",
        goal_key: NestedKey = ("next", "achieved_goal"),
        achieved_key: NestedKey = "achieved_goal",
        reward_key: NestedKey = "reward",
        success_key: NestedKey = "is_success",
        metric: str | GoalMetric | Callable = "euclidean",
        filter: RowFilter | Mapping[str, Any] | None = None,
        candidates: str = "uniform",
        reached_in: int = 0,
        reach_radius: float | None = None,
        seed: int | None = None,
        gym_kwargs: Mapping[str, Any] | None = None,
    ) -> None:
        for name, value, low in (("num_candidates", num_candidates, 1), ("k", k, 1), ("warmup_rows", warmup_rows, 0),
                                 ("reached_in", reached_in, 0)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}.")
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not 0.0 <= float(rate) <= 1.0:
            raise ValueError(f"rate must be a probability in [0, 1], got {rate!r}.")
        if reach_radius is not None and (isinstance(reach_radius, bool) or not isinstance(reach_radius, (int, float))
                                         or not 0 < float(reach_radius) < float("inf")):
            raise ValueError(f"reach_radius must be a finite distance > 0 (or None: the task's success distance), "
                             f"got {reach_radius!r}.")
        if candidates not in CANDIDATES:
            raise ValueError(f"candidates must be one of {CANDIDATES}, got {candidates!r}.")
        if not isinstance(env, str) or not env:
            raise TypeError(f"env must be the task's id (e.g. 'FetchPickAndPlace-v4'), got {env!r}.")
        if gym_kwargs is not None and not (isinstance(gym_kwargs, Mapping) and all(isinstance(k, str) for k in gym_kwargs)):
            raise TypeError(f"gym_kwargs must be a mapping of keyword names to values (e.g. {{'reward_type': 'dense'}}), "
                            f"got {gym_kwargs!r}.")
        in_key, achieved_key = unravel_key(in_key), unravel_key(achieved_key)
        self._source = MemorySource(memory, None)
        self._metric_obj = get_metric(metric)
        self.filter = RowFilter.coerce(filter)
        super().__init__(in_keys=[in_key], out_keys=[in_key])
        self.env_id = env
        self.num_candidates, self.k, self.rate, self.warmup_rows = num_candidates, k, float(rate), warmup_rows
        self.goal_key = unravel_key(goal_key)
        self.achieved_key = achieved_key
        self.reward_key, self.success_key = unravel_key(reward_key), unravel_key(success_key)
        self.metric = metric
        self.candidates = candidates
        self.reached_in = reached_in
        self._reach_radius = None if reach_radius is None else float(reach_radius)
        self.seed = seed
        self.gym_kwargs = dict(gym_kwargs or {})
        self._reward = GoalRewardFn(env, achieved_goal_key=achieved_key, desired_goal_key=in_key, **self.gym_kwargs)
        if reached_in and reach_radius is None and not self._reward.distance_based:
            raise ValueError(f"reached_in={reached_in}: {env} has no success distance between goals (its goals are "
                             f"compared as rotations); give reach_radius= to count the episodes that reached a "
                             f"candidate, or leave reached_in=0.")
        self._generator: torch.Generator | None = None
        self._index: GoalIndex | None = None
        self._goals: torch.Tensor | None = None  # the goal each env pursues, [*B, goal_dim]
        self._replaced: torch.Tensor | None = None  # which envs pursue a proposed goal, flat bool [prod(B)]
        self.proposed = 0  # episodes that pursued a proposed goal
        self.kept = 0  # episodes that kept the env's own goal
        self.seconds = 0.0  # wall time spent choosing goals (candidates, density search)

    # -- memory ---------------------------------------------------------------

    @property
    def memory(self) -> str | Storage | Any:
        """What was passed as ``memory``: a store path, a storage or a replay buffer."""
        return self._source.memory

    @property
    def storage(self) -> Storage:
        """The storage proposed from (a path is opened ``read_only`` on first access)."""
        return self._source.storage

    @property
    def reach_radius(self) -> float:
        """The distance within which a stored goal counts as reaching a candidate (see ``reached_in``)."""
        if self._reach_radius is None:  # the env is built for it (checked at construction: distance-based)
            self._reach_radius = self._reward.distance_threshold
        return self._reach_radius

    @property
    def index(self) -> GoalIndex:
        """The storage's shared :class:`~torchrl_robotmem.goal_index.GoalIndex`."""
        if self._index is None:
            self._index = GoalIndex.for_storage(self.storage, goal_key=self.goal_key, metric=self._metric_obj)
        return self._index

    def propose(self, n: int, near: torch.Tensor | None = None) -> torch.Tensor | None:
        """``n`` proposed goals ``[n, goal_dim]`` (lowest density among fresh candidates each), or ``None``.

        ``None`` while the memory holds fewer than ``warmup_rows`` rows (or none ``filter`` keeps).

        Args:
            n (int): goals to propose.
            near (torch.Tensor, optional): ``[n, goal_dim]`` goals the env handed the episodes: with
                ``candidates="near_goal"``, the candidates of the i-th proposal are the stored achieved
                goals nearest ``near[i]`` (required then, ignored otherwise).

        Example:
            >>> import tempfile, torch
            >>> from torchrl.data import TensorDictReplayBuffer
            >>> from tensordict import TensorDict
            >>> from torchrl_robotmem import GoalProposer, ZarrStorage
            >>> rb = TensorDictReplayBuffer(storage=ZarrStorage(tempfile.mkdtemp() + "/m.zarr", 100, goal_conditioned=False))
            >>> goals = torch.cat([torch.zeros(20, 3), torch.tensor([[1.0, 0, 0], [0, 0, 5.0]])])
            >>> _ = rb.extend(TensorDict({("next", "achieved_goal"): goals}, [22]))
            >>> near = GoalProposer(rb, "FetchReach-v4", k=2, num_candidates=3, candidates="near_goal", warmup_rows=0)
            >>> near.propose(1, near=torch.tensor([[2.0, 0, 0]]))  # the sparse goal on the way, not the far one
            tensor([[1., 0., 0.]])
        """
        if n == 0 or len(self._source) < max(self.warmup_rows, 1):
            return None
        start = time.perf_counter()
        try:
            if self.candidates == "near_goal":
                if near is None or near.shape[0] != n:
                    raise ValueError(f"candidates='near_goal' proposes near the env's goals: pass near of shape "
                                     f"[{n}, goal_dim], got {None if near is None else list(near.shape)}.")
                width = min(self.num_candidates, len(self._source))  # more than the rows stored: the same rows
                _, rows, found = self.index.search(near.reshape(n, -1).float(), width, filter=self.filter)
                if not bool(found[:, 0].all()):  # a goal with no stored goal near it (a filter's max_distance)
                    return None
                # a missing neighbour (fewer stored rows than candidates) repeats the nearest one
                rows = torch.where(found, rows, rows[:, :1])
            else:
                rows = self._candidates(n * self.num_candidates)
                if rows is None:
                    return None
            width = rows.numel() // n
            goals = self._source.column(self.goal_key)[rows.reshape(-1)].reshape(n * width, -1).float()
            # k + 1: a candidate is a stored row itself, at distance 0 from its own goal
            # (at most one more than the rows stored: a k beyond them answers the same, allocating nothing for it)
            dist, _, mask = self.index.search(goals, min(self.k + 1, len(self._source) + 1), filter=self.filter)
            kth = torch.where(mask, dist, torch.full_like(dist, float("inf"))).amax(-1)  # too few rows: sparse
            kth = kth.reshape(n, width)
            if self.reached_in:  # only candidates reached in reached_in episodes (or the most there are) compete
                reached = self._episodes_reaching(goals).reshape(n, width)
                kth = torch.where(reached == reached.amax(-1, keepdim=True), kth, torch.full_like(kth, -float("inf")))
            best = kth.argmax(-1)
            return goals.reshape(n, width, -1)[torch.arange(n), best]
        finally:
            self.seconds += time.perf_counter() - start

    def _episodes_reaching(self, goals: torch.Tensor) -> torch.Tensor:
        """For each goal, the stored episodes (up to ``reached_in``) with a row within ``reach_radius`` of it."""
        reach = dataclasses.replace(self.filter, one_per_episode=True, max_distance=self.reach_radius)
        try:  # no more episodes than rows: a reached_in beyond them answers the same
            _, _, found = self.index.search(goals, min(self.reached_in, len(self._source)), filter=reach)
        except KeyError as e:
            if "'episode'" not in str(e):  # another missing column (the goals'): its own error says which
                raise
            raise ValueError(f"reached_in={self.reached_in} counts the episodes that reached a goal, and the memory "
                             f"has no episode ids to count ({e}): propose from a ZarrStorage (it tags every row "
                             f"with its episode), or leave reached_in=0.") from e
        return found.sum(-1)

    def _candidates(self, m: int) -> torch.Tensor | None:
        """``m`` rows drawn uniformly among the stored rows ``filter`` keeps, goals that are NaN or inf left out
        (``None``: no such row)."""
        rows = self.index.draw_rows(m, self.filter, generator=self._rng())
        return rows if rows.numel() else None

    def _rng(self) -> torch.Generator:
        if self._generator is None:
            seed = self.seed if self.seed is not None else int(torch.randint(2**62, ()).item())
            self._generator = torch.Generator().manual_seed(seed)
        return self._generator

    # -- Transform API ---------------------------------------------------------

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        goals = tensordict_reset.get(self.in_keys[0]).clone()
        batch = goals.shape[:-1]
        flat = goals.reshape(-1, goals.shape[-1])
        reset = self._reset_rows(tensordict, batch)
        replaced = torch.zeros(flat.shape[0], dtype=torch.bool)
        if self._goals is not None and self._goals.shape == goals.shape and reset is not None:
            kept = self._goals.reshape(-1, goals.shape[-1])
            flat = torch.where(reset.unsqueeze(-1), flat, kept)  # running envs keep the goal they pursue
            replaced = self._replaced & ~reset
        rows = torch.arange(flat.shape[0]) if reset is None else reset.nonzero().squeeze(-1)
        if rows.numel():
            coin = torch.rand(rows.numel(), generator=self._rng()) < self.rate
            chosen = rows[coin]
            proposed = self.propose(chosen.numel(), near=flat[chosen])
            if proposed is not None:
                self._check_goal_dim(flat.shape[-1], proposed.shape[-1])
                flat[chosen] = proposed.to(flat.dtype)
                replaced[chosen] = True
                self.proposed += chosen.numel()
                self.kept += rows.numel() - chosen.numel()
            else:
                self.kept += rows.numel()
        self._goals = flat.reshape(goals.shape)
        self._replaced = replaced
        tensordict_reset.set(self.in_keys[0], self._goals.clone())
        return tensordict_reset

    def _reset_rows(self, tensordict: TensorDictBase | None, batch: torch.Size) -> torch.Tensor | None:
        """Flat mask of the envs that reset (``None``: all of them)."""
        mask = reset_mask(self.parent, tensordict, batch)
        return None if mask is None else mask.reshape(-1)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self._goals is None or self._goals.shape != next_tensordict.get(self.in_keys[0]).shape:
            self._goals = next_tensordict.get(self.in_keys[0]).clone()  # stepped without a reset through it
            self._replaced = torch.zeros(self._goals[..., 0].numel(), dtype=torch.bool)
            return next_tensordict
        if not bool(self._replaced.any()):  # every env pursues its own goal: its step stands as it is
            return next_tensordict
        batch = self._goals.shape[:-1]
        replaced = self._replaced.reshape(batch)
        next_tensordict.set(self.in_keys[0], self._goals.clone())
        for key, recompute in ((self.reward_key, self._reward), (self.success_key, self._reward.success)):
            value = next_tensordict.get(key) if key == self.reward_key else next_tensordict.get(key, None)
            if value is None:  # an env without a success flag
                continue
            new = recompute(next_tensordict).reshape(value.shape).to(value.dtype)
            mask = replaced.reshape(tuple(batch) + (1,) * (value.dim() - len(batch)))
            next_tensordict.set(key, torch.where(mask, new, value))  # envs on their own goal keep the env's
        return next_tensordict

    def transform_observation_spec(self, observation_spec):
        """Checks, once the env's goal spec is known, that the memory's goals have its size (if it has rows)."""
        in_key = self.in_keys[0]
        try:
            column = self._source.column(self.goal_key)
        except FileNotFoundError:  # a memory path the run creates later: its first proposal checks the size
            column = None
        if in_key in observation_spec.keys(True, True) and column is not None:
            shape = observation_spec[in_key].shape
            batch = self.parent.batch_size if self.parent is not None else torch.Size([])
            env_dim = int(shape[-1]) if len(shape) > len(batch) else 1
            stored = int(torch.Size(column.shape[1:]).numel())
            self._check_goal_dim(env_dim, stored)
        return observation_spec

    def _check_goal_dim(self, env_dim: int, stored: int) -> None:
        if env_dim != stored:
            raise ValueError(
                f"GoalProposer: the env's {self.in_keys[0]!r} has {env_dim} dimensions but the memory's goals "
                f"{self.goal_key!r} have {stored}: propose from a memory of this task (or give goal_key= the "
                f"stored column of this env's achieved goals).")

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("GoalProposer acts on an env's resets and steps; it has no meaning on stored rows.")

    # -- housekeeping -----------------------------------------------------------

    def __getstate__(self) -> dict[str, Any]:
        state = super().__getstate__()
        state["_index"] = None
        state["_goals"] = None
        state["_replaced"] = None
        state["_generator"] = None
        return state

    def __repr__(self) -> str:
        memory = self.memory if isinstance(self.memory, str) else type(self.memory).__name__
        return (f"{type(self).__name__}(memory={memory!r}, env={self.env_id!r}, num_candidates={self.num_candidates}, "
                f"k={self.k}, rate={self.rate}, warmup_rows={self.warmup_rows}"
                + (f", candidates={self.candidates!r}" if self.candidates != "uniform" else "")
                + (f", reached_in={self.reached_in})" if self.reached_in else ")"))
