"""An env transform that shows a goal-conditioned agent what it remembers about its goal.

:class:`RecallTransform` sits in a TorchRL env (``TransformedEnv`` or the
``transforms=`` of :func:`~torchrl_robotmem.make_env`). Each time an env
resets, it looks up the ``k`` stored transitions whose achieved goals lie
nearest to the new ``desired_goal`` (a :class:`~torchrl_robotmem.goal_index.GoalIndex`
search over a :class:`~torchrl_robotmem.ZarrStorage` or any TorchRL tensor
storage) and writes them into the observation as ``prior_goals``
``[*B, k, goal_dim]``, ``prior_goals_dist`` ``[*B, k]`` and ``prior_goals_mask``
``[*B, k]``, plus any recalled context (``prior_actions``, ...). A goal does
not change within an episode, so the result is cached per env at reset and
repeated at every step: the memory is queried once per episode.

This is the retrieval step of episodic-memory and retrieval-augmented agents
(e.g. Blundell et al., "Model-Free Episodic Control," 2016,
https://arxiv.org/abs/1606.04460; Goyal et al., "Retrieval-Augmented
Reinforcement Learning," 2022, https://arxiv.org/abs/2202.08417), applied to
the multi-goal tasks of Gymnasium-Robotics. See ``docs/transform.md``.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.data.replay_buffers.storages import Storage
from torchrl.envs import Transform

from .env_resets import reset_mask
from .goal_index import GoalIndex, RowFilter
from .goal_index.metrics import GoalMetric, get_metric
from .memory_source import MemorySource

__all__ = ["RecallTransform"]

_DEFAULT_OUT_KEYS = ("prior_goals", "prior_goals_dist", "prior_goals_mask")


class RecallTransform(Transform):
    """Recalls, at each reset, the remembered goals nearest to the new desired goal.

    For every env that resets (all of them, or the rows flagged by ``"_reset"``
    in a batched env's partial reset), the ``k`` stored transitions whose
    ``goal_key`` (by default the *achieved* goal) is nearest to the env's
    ``in_key`` (its *desired* goal) are recalled, and the observation gets:

    * ``out_keys[0]`` (``"prior_goals"``): float32 ``[*B, k, goal_dim]``, the
      recalled achieved goals, nearest first;
    * ``out_keys[1]`` (``"prior_goals_dist"``): float32 ``[*B, k]``, their
      distances to the desired goal under ``metric``;
    * ``out_keys[2]`` (``"prior_goals_mask"``): bool ``[*B, k]``, ``False``
      where fewer than ``k`` rows match (those slots hold zeros);
    * one ``[*B, k, *shape]`` entry per ``context_keys`` item, e.g.
      ``{"action": "prior_actions"}``, with the stored key's dtype.

    The result is cached per env and repeated at every step until that env
    resets again: one memory query per episode. An empty memory (even an
    uninitialized storage with no rows yet) gives zeros and an all-``False``
    mask. The entries are part of the observation spec, so collectors store
    them with each transition. The search runs on the storage's shared
    :class:`~torchrl_robotmem.goal_index.GoalIndex` (:meth:`GoalIndex.for_storage
    <torchrl_robotmem.goal_index.GoalIndex.for_storage>`), the one a sampler or a
    :class:`~torchrl_robotmem.RobotMemory` on the same storage also uses.

    Put the transform *outside* a batched env (``TransformedEnv(SerialEnv(...),
    t)`` or ``make_env(..., num_envs=N, transforms=[t])``): it then runs once
    on the ``[N]`` batch in the main process. Envs built in other processes
    (``MultiSyncCollector``, ``MultiAsyncCollector``, ``ParallelEnv`` with the
    transform inside) cannot share a :class:`~torchrl_robotmem.ZarrStorage`
    object: pass the store's path instead, and every process opens it
    ``read_only`` on first use.

    Args:
        memory (str, os.PathLike, Storage or ReplayBuffer): where to recall
            from. A path or store URL opens ``ZarrStorage(path, read_only=True)``
            lazily, on first use (so the transform pickles and works in spawned
            workers; the memory is the store as it was when opened, or as
            re-read every ``refresh_every`` steps). A storage
            or replay buffer is read live: pass the buffer a collector writes
            into and later episodes recall earlier ones.
        k (int, optional): goals recalled per env. Default: ``5``.

    Keyword Args:
        in_key (NestedKey): the goal being pursued. Default: ``"desired_goal"``.
        out_keys (sequence of 3 NestedKeys): names of the recalled goals, their
            distances and the validity mask. Default:
            ``("prior_goals", "prior_goals_dist", "prior_goals_mask")``.
        metric (str, GoalMetric or callable): ``"euclidean"`` (Fetch, HandReach)
            or ``"pose"`` (HandManipulate: position + rotation angle), see
            :mod:`torchrl_robotmem.goal_index.metrics`. Default: ``"euclidean"``.
        goal_key (NestedKey): stored column searched and returned as
            ``prior_goals``. Default: ``("next", "achieved_goal")``.
        context_keys (mapping, optional): stored key -> output key of extra
            entries recalled with each goal, e.g. ``{"action": "prior_actions",
            ("next", "reward"): "prior_rewards"}``. Default: none.
        goal_dim (int, optional): size of a goal. Read from the memory, or from
            the env's ``in_key`` spec when the memory has no rows yet; pass it
            only when neither is available.
        refresh_every (int, optional): for a read-only memory (a path, or a
            ``ZarrStorage`` opened ``read_only``) that another process is
            writing: re-read the store at the first reset after every
            ``refresh_every`` steps of the transformed env (a batched step
            counts once), so that later episodes recall the rows committed
            since. ``ZarrStorage.refresh()`` reads the whole store again, so
            pick ``N`` in thousands for large memories. Default: ``None``
            (the memory is read once).
        filter (RowFilter or mapping, optional): which rows may be recalled
            (:class:`~torchrl_robotmem.goal_index.RowFilter`). Default: any.
        **filter_keywords: the same as keywords instead: ``success_only=True``
            (transitions that succeeded, ``("next", "is_success") > 0.5``),
            ``env="FetchPush-v4"`` (names from the storage's ``env_names``, or
            codes), ``run``, ``max_distance``, ``one_per_episode=True`` (the
            ``k`` goals come from ``k`` different episodes: the nearest
            transition of each of the ``k`` nearest; needs the ``"episode"``
            column ``ZarrStorage`` writes).

    Example:
        >>> import tempfile, torch
        >>> from torchrl.collectors import Collector
        >>> from torchrl.data import TensorDictReplayBuffer
        >>> from torchrl_robotmem import RecallTransform, ZarrStorage, make_env
        >>> path = tempfile.mkdtemp() + "/push.zarr"
        >>> rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 10_000, env="FetchPush-v4"))
        >>> collector = Collector(lambda: make_env("FetchPush-v4", seed=0), None,
        ...                       frames_per_batch=100, total_frames=200)
        >>> for data in collector:
        ...     _ = rb.extend(data.reshape(-1))
        >>> collector.shutdown(); rb.storage.close()
        >>> env = make_env("FetchPush-v4", seed=1, transforms=[RecallTransform(path, k=3)])
        >>> td = env.reset()
        >>> td["prior_goals"].shape, td["prior_goals_dist"].shape, td["prior_goals_mask"].all().item()
        (torch.Size([3, 3]), torch.Size([3]), True)
        >>> bool((td["prior_goals_dist"][:-1] <= td["prior_goals_dist"][1:]).all())  # nearest first
        True
        >>> rollout = env.rollout(5)  # constant within the episode
        >>> bool((rollout["next", "prior_goals"] == rollout["prior_goals"][:1]).all())
        True
    """

    def __init__(
        self,
        memory: str | os.PathLike | Storage | Any,
        k: int = 5,
        *,
        in_key: NestedKey = "desired_goal",
        out_keys: Sequence[NestedKey] = _DEFAULT_OUT_KEYS,
        metric: str | GoalMetric | Callable = "euclidean",
        goal_key: NestedKey = ("next", "achieved_goal"),
        context_keys: Mapping[NestedKey, NestedKey] | None = None,
        goal_dim: int | None = None,
        refresh_every: int | None = None,
        filter: RowFilter | Mapping[str, Any] | None = None,
        **filter_keywords: Any,
    ) -> None:
        source = MemorySource(memory, refresh_every)
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"k must be an integer >= 1, got {k!r}.")
        if goal_dim is not None and (
            isinstance(goal_dim, bool) or not isinstance(goal_dim, int) or goal_dim < 1
        ):
            raise ValueError(f"goal_dim must be an integer >= 1, got {goal_dim!r}.")
        out_keys, context = _output_keys(out_keys, context_keys)
        self.filter = RowFilter.coerce(filter, **filter_keywords)
        # Validates the name now rather than at the first reset, in a worker.
        metric_obj = get_metric(metric)
        super().__init__(in_keys=[unravel_key(in_key)], out_keys=[*out_keys, *context.values()])
        self._source = source
        self.k = k
        self.metric = metric
        self.goal_key = unravel_key(goal_key)
        self.context_keys = context
        self.goal_dim = goal_dim
        self._metric_obj = metric_obj
        self._index: GoalIndex | None = None
        self._cache: TensorDictBase | None = None

    # -- memory ---------------------------------------------------------------

    @property
    def memory(self) -> str | Storage | Any:
        """What was passed as ``memory``: a store path, a storage or a replay buffer."""
        return self._source.memory

    @property
    def refresh_every(self) -> int | None:
        """Steps between re-reads of a read-only memory (``None``: read once)."""
        return self._source.refresh_every

    @property
    def storage(self) -> Storage:
        """The storage recalled from (a path is opened ``read_only`` on first access)."""
        return self._source.storage

    @property
    def index(self) -> GoalIndex:
        """The storage's shared :class:`~torchrl_robotmem.goal_index.GoalIndex`, searched at each reset."""
        if self._index is None:
            self._index = GoalIndex.for_storage(self.storage, goal_key=self.goal_key, metric=self._metric_obj)
        return self._index

    def refresh(self) -> None:
        """Re-reads a read-only memory now, to see the rows committed since it was opened."""
        self._source.refresh()

    @property
    def success_only(self) -> bool:
        """``filter.success_only``: only transitions that succeeded are recalled."""
        return self.filter.success_only

    @property
    def env_filter(self) -> tuple[str | int, ...] | None:
        """``filter.env``: the envs recalled from (``None``: every env)."""
        return self.filter.env

    @property
    def one_per_episode(self) -> bool:
        """``filter.one_per_episode``: the ``k`` goals come from ``k`` different episodes."""
        return self.filter.one_per_episode

    # -- priors ---------------------------------------------------------------

    def _priors(self, goals: torch.Tensor) -> TensorDictBase:
        """Recalled entries for goals ``[*B, goal_dim]``, as a TensorDict of batch ``[*B]``."""
        batch = goals.shape[:-1]
        flat = goals.reshape(-1, goals.shape[-1])
        n, k = flat.shape[0], self.k
        device = goals.device
        goal_out, dist_out, mask_out = self.out_keys[:3]
        shapes = self._feature_shapes(goals.shape[-1])
        out = TensorDict(
            {
                key: torch.zeros((n, k, *shape), dtype=dtype, device=device)
                for key, (shape, dtype) in shapes.items()
            },
            batch_size=[n],
            device=device,
        )
        if n and len(self._source):
            # search + the few columns needed: GoalIndex.recall would gather every stored key.
            dist, index, mask = self.index.search(flat, k, filter=self.filter)
            if mask.shape[-1] < k:  # k above the storage's capacity: the index returns max_size, the spec has k
                w = mask.shape[-1]
                dist = torch.cat([dist, dist.new_full((n, k - w), float("inf"))], -1)
                index = torch.cat([index, index.new_full((n, k - w), -1)], -1)
                mask = torch.cat([mask, mask.new_zeros((n, k - w))], -1)
            if bool(mask.any()):
                out.set(mask_out, mask.to(device))
                out.set(dist_out, dist.masked_fill(~mask, 0.0).to(device))
                rows = index.clamp_min(0)
                for src, dst in ((self.goal_key, goal_out), *self.context_keys.items()):
                    column = self._source.column(src)
                    value = column[rows.to(column.device)].reshape(n, k, *shapes[dst][0])
                    value[~mask.to(value.device)] = 0
                    out.set(dst, value.to(device, shapes[dst][1]))
        return out.reshape(batch)

    def _feature_shapes(self, goal_dim: int) -> dict[NestedKey, tuple[tuple[int, ...], torch.dtype]]:
        goal_out, dist_out, mask_out = self.out_keys[:3]
        shapes = {
            goal_out: ((goal_dim,), torch.float32),
            dist_out: ((), torch.float32),
            mask_out: ((), torch.bool),
        }
        for src, dst in self.context_keys.items():
            shapes[dst] = self._context_shape(src)
        return shapes

    def _context_shape(self, key: NestedKey) -> tuple[tuple[int, ...], torch.dtype]:
        column = self._source.column(key)
        if column is not None:
            return tuple(column.shape[1:]), column.dtype
        # No rows yet: the stored key will be what the env emits.
        parent = self.parent
        spec = None
        if parent is not None:
            env_key = key[1:] if isinstance(key, tuple) and key[0] == "next" else key
            env_key = unravel_key(env_key)
            for full in (
                parent.full_observation_spec,
                parent.full_action_spec,
                parent.full_state_spec,
                parent.full_reward_spec,
                parent.full_done_spec,
            ):
                if env_key in full.keys(True, True):
                    spec = full[env_key]
                    break
        if spec is None:
            raise KeyError(
                f"context key {key!r}: the memory has no rows yet and the env has no such key, "
                "so its shape is unknown. Recall it from a memory that holds data."
            )
        batch = parent.batch_size
        return tuple(spec.shape[len(batch) :]), spec.dtype

    def _resolve_goal_dim(self, spec_dim: int | None) -> int:
        column = self._source.column(self.goal_key)
        stored = None if column is None else int(torch.Size(column.shape[1:]).numel())
        dims = {"goal_dim": self.goal_dim, "memory": stored, "env spec": spec_dim}
        known = {name: d for name, d in dims.items() if d is not None}
        if not known:
            raise ValueError(
                "goal_dim is unknown: the memory has no rows yet and the env has no "
                f"{self.in_keys[0]!r} spec. Pass goal_dim=."
            )
        if len(set(known.values())) > 1:
            raise ValueError(
                f"Goal sizes disagree: {known}. The memory's {self.goal_key!r} must have the "
                f"size of the env's {self.in_keys[0]!r}."
            )
        return next(iter(known.values()))

    # -- Transform API ---------------------------------------------------------

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._source.refresh_if_due()
        goals = tensordict_reset.get(self.in_keys[0])
        batch = tensordict_reset.batch_size
        reset = self._reset_mask(tensordict, batch)
        cache = self._cache
        if cache is None or cache.batch_size != batch or reset is None or bool(reset.all()):
            self._cache = self._priors(goals)
        elif bool(reset.any()):
            # A new cache, not an in-place update: earlier steps may still hold
            # views of the old one.
            cache = cache.clone()
            cache[reset] = self._priors(goals[reset])
            self._cache = cache
        return self._write(tensordict_reset)

    def _reset_on_native_autoreset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._reset(tensordict, tensordict_reset)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        self._source.count_step()
        cache = self._cache
        if cache is None or cache.batch_size != next_tensordict.batch_size:
            # Stepped without a reset through this transform (e.g. appended to a
            # running env): recall for the current goal now.
            self._cache = self._priors(next_tensordict.get(self.in_keys[0]))
        return self._write(next_tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Recalls for every row of ``tensordict[in_key]`` (stateless; replay buffers, offline use)."""
        return tensordict.update(self._priors(tensordict.get(self.in_keys[0])))

    def _write(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Clones are a few hundred bytes; handing out the cached tensors would
        # let an in-place edit downstream corrupt the rest of the episode.
        for key, value in self._cache.items(True, True):
            tensordict.set(key, value.clone())
        return tensordict

    def _reset_mask(self, tensordict: TensorDictBase | None, batch: torch.Size) -> torch.Tensor | None:
        """Rows to recompute (``[*batch]`` bool), or None for all of them."""
        return reset_mask(self.parent, tensordict, batch)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        in_key = self.in_keys[0]
        batch = observation_spec.shape
        device = observation_spec.device
        spec_dim = None
        if in_key in observation_spec.keys(True, True):
            in_shape = observation_spec[in_key].shape
            spec_dim = int(in_shape[-1]) if len(in_shape) > len(batch) else None
        goal_dim = self._resolve_goal_dim(spec_dim)
        self._metric_obj.check_goal_dim(goal_dim)
        for key, (shape, dtype) in self._feature_shapes(goal_dim).items():
            full = (*batch, self.k, *shape)
            if dtype == torch.bool:
                observation_spec[key] = Categorical(2, shape=full, dtype=dtype, device=device)
            else:
                observation_spec[key] = Unbounded(shape=full, dtype=dtype, device=device)
        return observation_spec

    # -- housekeeping -----------------------------------------------------------

    def __getstate__(self) -> dict[str, Any]:
        state = super().__getstate__()
        state["_index"] = None  # the shared index of the storage where it lands
        state["_cache"] = None
        return state

    def __repr__(self) -> str:
        memory = self.memory if isinstance(self.memory, str) else type(self.memory).__name__
        extra = "".join(
            f", {name}={value!r}"
            for name, value in (
                ("filter", None if self.filter == RowFilter() else self.filter),
                ("context_keys", self.context_keys or None),
                ("refresh_every", self.refresh_every),
            )
            if value
        )
        return (
            f"{type(self).__name__}(memory={memory!r}, k={self.k}, in_key={self.in_keys[0]!r}, "
            f"out_keys={self.out_keys}, metric={self._metric_obj!r}{extra})"
        )


def _output_keys(out_keys: Sequence[NestedKey], context_keys: Mapping[NestedKey, NestedKey] | None
                 ) -> tuple[list[NestedKey], dict[NestedKey, NestedKey]]:
    """The 3 output keys and the context map (stored key -> output key), checked: all distinct."""
    out_keys = [unravel_key(key) for key in out_keys]
    if len(out_keys) != 3:
        raise ValueError(
            "out_keys must name 3 entries (goals, distances, mask), got "
            f"{len(out_keys)}: {out_keys}."
        )
    context = {unravel_key(src): unravel_key(dst) for src, dst in dict(context_keys or {}).items()}
    all_out = [*out_keys, *context.values()]
    if len(set(all_out)) != len(all_out):
        raise ValueError(f"output keys must be distinct, got {all_out}.")
    return out_keys, context
