"""``RobotMemory``: robotmem's quick-start API, for code outside TorchRL loops.

The seed product (robotmem) offered ``RobotMemory(db=...)``,
``save_perception(observation, action, reward, metadata)`` and
``recall(desired_goal, top_k)``. :class:`RobotMemory` keeps those calls but
stores into a :class:`~torchrl_robotmem.ZarrStorage` and answers with the
storage's shared :class:`~torchrl_robotmem.GoalIndex` (exact), so a store written by a TorchRL collector
can be read here, and a store written here can be sampled by any TorchRL
buffer (``RobotMemory.buffer``) or opened with ``ZarrStorage(path)``.
"""
from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import TensorDictReplayBuffer

from .goal_index import GoalIndex, RowFilter
from .storage import TAG_KEYS, ZarrStorage, key_to_path, path_to_key, store_exists, torch_dtype

__all__ = ["RobotMemory"]

_GOAL_KEY = ("next", "achieved_goal")
_SUCCESS_KEY = ("next", "is_success")
# robotmem's context_filter keys -> our recall filters
_CONTEXT_FILTERS = {"task.success": "success_only", "success": "success_only", "env": "env", "task.env": "env"}


class RobotMemory:
    """A persistent goal-conditioned memory with robotmem's quick-start API.

    Each :meth:`save_perception` call stores one transition in the layout a
    TorchRL collector produces: the values *after* the step under ``"next"``
    (``("next", "observation")``, ``("next", "achieved_goal")``, ``("next",
    "reward")``, ``("next", "is_success")``, ...), the values before it at the
    root (taken from the previous call of the same episode), and ``"action"``.
    An episode ends when ``metadata`` says ``terminated`` / ``truncated`` /
    ``done``, or when the desired goal changes (Fetch and Hand goals are fixed
    within an episode).

    Args:
        path (str or os.PathLike): the store (a directory, a ``*.zip`` or a Zarr
            store URL). Created when missing. robotmem's spelling
            ``RobotMemory(db="gym_robotics.db")`` is accepted too (the store is
            then a directory named ``gym_robotics.db``).
        max_size (int, optional): capacity in transitions when the store is
            created. Defaults to 1_000_000; ignored for an existing store
            (whose capacity is kept) unless larger (then it grows, see
            :class:`ZarrStorage`). An existing memory without a declared
            capacity (made by ``ZarrStorage(path)``) opens with ``None`` and
            refuses a number. To create one here, create it with
            ``ZarrStorage(path).close()`` first.

    Keyword Args:
        env (str, optional): environment name for rows whose metadata has no
            ``"env"``.
        read_only (bool, optional): open for reading only. Defaults to ``False``.
        metric (str, optional): goal metric for :meth:`recall`: ``"euclidean"``
            (Fetch, HandReach) or ``"pose"`` (HandManipulate*: position plus
            rotation angle). Defaults to ``"euclidean"``.
        **storage_kwargs: passed to :class:`ZarrStorage`.

    Example:
        >>> import numpy as np
        >>> from torchrl_robotmem import RobotMemory
        >>> mem = RobotMemory("memory://robotmemory-doc", max_size=100)
        >>> for episode in range(3):
        ...     for t in range(3):
        ...         _ = mem.save_perception(
        ...             observation=np.zeros(25), action=np.zeros(4), reward=-1.0,
        ...             metadata={"achieved_goal": [episode + 0.1 * t, 0.0, 0.0], "desired_goal": [1.0, 0.0, 0.0],
        ...                       "is_success": t == 2, "env": "FetchPickAndPlace-v4", "truncated": t == 2})
        >>> prior = mem.recall([0.2, 0.0, 0.0], top_k=2)  # the nearest transition of the 2 nearest episodes
        >>> prior["episode"].tolist(), prior["index"].tolist(), prior["mask"].tolist()
        ([0, 1], [2, 3], [True, True])
        >>> mem.recall([0.2, 0.0, 0.0], top_k=2, one_per_episode=False)["index"].tolist()  # rows: one episode
        [2, 1]
        >>> mem.recall([2.0, 0.0, 0.0], top_k=2, success_only=True)["episode"].tolist()
        [2, 1]
        >>> mem.close()
    """

    def __init__(
        self,
        path: str | os.PathLike | None = None,
        max_size: int | None = None,
        *,
        db: str | os.PathLike | None = None,
        env: str | None = None,
        read_only: bool = False,
        metric: str = "euclidean",
        **storage_kwargs: Any,
    ) -> None:
        if (path is None) == (db is None):
            raise TypeError(
                "RobotMemory needs the store's location: RobotMemory('memory/fetch.zarr') or "
                "robotmem's spelling RobotMemory(db='gym_robotics.db'), not both."
            )
        path = db if path is None else path
        if max_size is None and not read_only and not store_exists(path):
            max_size = 1_000_000
        self.storage = ZarrStorage(path, max_size, env=env, read_only=read_only, **storage_kwargs)
        self.buffer = TensorDictReplayBuffer(storage=self.storage, batch_size=256)
        # the storage's shared index: a sampler or RecallTransform on self.storage searches the same one
        self.index = GoalIndex.for_storage(self.storage, goal_key=_GOAL_KEY, success_key=_SUCCESS_KEY, metric=metric)
        self._prev: dict[str, torch.Tensor] | None = None  # the open episode's last "next" values
        self._prev_row: int | None = None

    # -- writing --------------------------------------------------------------

    def save_perception(
        self,
        observation: Any,
        action: Any,
        reward: float | Any,
        metadata: Mapping[str, Any] | None = None,
    ) -> int:
        """Stores one transition; returns its row in the storage.

        Every value is checked before anything is stored: the arrays must be
        finite numbers, ``reward`` and ``is_success`` one finite number each
        (shape ``[]`` or ``[1]``); otherwise a ``ValueError`` / ``TypeError``
        names the argument and the memory is left as it was.

        Args:
            observation: the observation after the step (``obs["observation"]``).
            action: the action taken.
            reward: the reward received (one number).
            metadata (dict): ``achieved_goal`` and ``desired_goal`` (required),
                ``is_success`` (one number or bool), ``env`` (a name), and optionally
                ``terminated``, ``truncated`` or ``done`` to end the episode.
        """
        metadata = dict(metadata or {})
        for key in ("achieved_goal", "desired_goal"):
            if key not in metadata:
                raise KeyError(
                    f"metadata must hold {key!r} (the GoalEnv observation's {key!r}); got keys "
                    f"{sorted(metadata)}."
                )
        step = {
            "observation": _row(observation, "observation"),
            "achieved_goal": _row(metadata.pop("achieved_goal"), "achieved_goal"),
            "desired_goal": _row(metadata.pop("desired_goal"), "desired_goal"),
        }
        terminated = bool(metadata.pop("terminated", False))
        truncated = bool(metadata.pop("truncated", False))
        done = bool(metadata.pop("done", False)) or terminated or truncated
        reward = _scalar(reward, "reward")
        success = _scalar(metadata.pop("is_success", 0.0), "is_success")
        env = metadata.pop("env", None)
        if metadata:
            raise KeyError(
                f"Unknown metadata keys {sorted(metadata)}; expected achieved_goal, desired_goal, "
                f"is_success, env, terminated, truncated, done."
            )
        # a new goal means a new episode, even if the caller never said so
        new_goal = self._prev is not None and (
            self._prev["desired_goal"].shape != step["desired_goal"].shape
            or not torch.equal(self._prev["desired_goal"], step["desired_goal"])
        )
        before = self._prev if self._prev is not None and not new_goal else step
        td = TensorDict(
            {
                "observation": before["observation"],
                "achieved_goal": before["achieved_goal"],
                "desired_goal": step["desired_goal"],
                "action": _row(action, "action"),
                "next": {
                    **step,
                    "reward": torch.tensor([reward], dtype=torch.float32),
                    "done": torch.tensor([done]),
                    "terminated": torch.tensor([terminated]),
                    "truncated": torch.tensor([truncated or (done and not terminated)]),
                    "is_success": torch.tensor(success, dtype=torch.float32),
                },
            },
            [],
        )
        td = self._fit_schema(td)
        # Validate before any side effect: a refused transition leaves the memory
        # (rows, open episode, env names) exactly as it was.
        self.storage.check_schema(td.unsqueeze(0))
        if env is not None:
            self.storage.env = str(env)
        if new_goal:
            self.storage.close_episode_at(self._prev_row)
            self._prev = None
        row = int(self.buffer.add(td))
        self._prev, self._prev_row = (None, None) if done else (step, row)
        return row

    def save_episode(self, episode: TensorDictBase) -> torch.Tensor:
        """Stores a whole episode at once; returns the rows written.

        Args:
            episode (TensorDictBase): transitions of batch size ``[T]`` in TorchRL's
                layout, e.g. ``env.rollout(50)`` of :func:`~torchrl_robotmem.make_env`
                or one trajectory of a collector. Its last transition is marked
                done if it is not already.
        """
        if not isinstance(episode, TensorDictBase) or episode.batch_dims != 1:
            raise TypeError(
                "save_episode expects a TensorDict of batch size [T] (e.g. env.rollout(T)); "
                f"got {type(episode).__name__} {getattr(episode, 'batch_size', '')}."
            )
        episode = episode.clone()
        done = episode.get(("next", "done"), None)
        if done is not None and not bool(done[-1].any()):
            done[-1] = True
            if ("next", "truncated") in episode.keys(True, True):
                episode.get(("next", "truncated"))[-1] = True
        episode = self._fit_schema(episode)
        self.storage.check_schema(episode)  # before any side effect, as save_perception
        if self._prev is not None:  # an episode save_perception left open ends before this one starts
            self.storage.close_episode_at(self._prev_row)
            self._prev = None
        return self.buffer.extend(episode)

    def _fit_schema(self, td: TensorDictBase) -> TensorDictBase:
        """Zero-fills keys an existing store (e.g. written by a collector) has and ``td`` lacks."""
        schema = self.storage.schema
        if schema is None:
            return td
        batch = tuple(td.batch_size)
        have = {key_to_path(k) for k in td.keys(True, True)}
        for path, spec in schema.items():
            key = path_to_key(path)
            if path in have or key in TAG_KEYS:
                continue
            td.set(key, torch.zeros((*batch, *spec["shape"]), dtype=torch_dtype(spec["dtype"])))
        for path in have - set(schema):
            td = td.exclude(path_to_key(path))
        return td

    # -- reading --------------------------------------------------------------

    def recall(
        self,
        desired_goal: Any,
        top_k: int = 5,
        *,
        filter: RowFilter | Mapping[str, Any] | None = None,
        context_filter: Mapping[str, Any] | None = None,
        spatial_sort: Mapping[str, Any] | None = None,
        one_per_episode: bool = True,
        **filter_keywords: Any,
    ) -> TensorDictBase:
        """Past episodes where goals near ``desired_goal`` were achieved: the nearest transition of each.

        By default the ``top_k`` results come from ``top_k`` different episodes: the
        ``top_k`` episodes whose nearest achieved goal is closest, exactly (the
        nearest transition of each, nearest first), as the seed promised ("past
        episodes where similar goals were achieved"). ``one_per_episode=False``
        returns the ``top_k`` nearest transitions instead, which may all come from
        one episode (consecutive steps of a Fetch episode often share a goal).

        Args:
            desired_goal: one goal ``[goal_dim]`` or a batch ``[B, goal_dim]``.
            top_k (int): how many to return. Defaults to 5.

        Keyword Args:
            filter (RowFilter or mapping, optional): which transitions may be
                returned (:class:`~torchrl_robotmem.goal_index.RowFilter`).
            one_per_episode (bool): one result per episode (default ``True``), or
                the nearest transitions whatever their episode (``False``). A
                ``filter=RowFilter(one_per_episode=True)`` asks for episodes too.
            **filter_keywords: the same as keywords instead:
                ``success_only=True`` (only transitions with ``is_success``),
                ``env`` (only these environments), ``run``, ``max_distance``
                (only transitions at most this far).
            context_filter (dict): robotmem-style filters, e.g.
                ``{"task.success": True, "env": "FetchPush-v4"}``.
            spatial_sort (dict): robotmem-style ``{"field": ..., "target": goal}``; the
                ``target`` replaces ``desired_goal`` (results are always sorted by
                distance to the query).

        Returns:
            a TensorDict of batch ``[top_k]`` (or ``[B, top_k]``) with every stored key
            (observation, action, reward, achieved/desired goal, is_success, episode,
            run, env, ...) plus ``distance``, ``mask`` (False where fewer than
            ``top_k`` matched) and ``index``.
        """
        if context_filter:
            for key, value in context_filter.items():
                if key not in _CONTEXT_FILTERS:
                    raise KeyError(
                        f"Unsupported context_filter key {key!r}; supported: {sorted(_CONTEXT_FILTERS)}."
                    )
                name = _CONTEXT_FILTERS[key]
                filter_keywords[name] = bool(value) if name == "success_only" else value
        if spatial_sort is not None:
            if "target" not in spatial_sort:
                raise KeyError("spatial_sort needs a 'target' goal, e.g. {'target': desired_goal}.")
            desired_goal = spatial_sort["target"]
        flt = RowFilter.coerce(filter, **filter_keywords)
        # checked as RowFilter checks it (a bool); a filter= asking for episodes keeps them
        flt = dataclasses.replace(flt, one_per_episode=flt.one_per_episode or one_per_episode)
        return self.index.recall(desired_goal, top_k, filter=flt)

    def __len__(self) -> int:
        return len(self.storage)

    def summary(self) -> dict[str, Any]:
        return self.storage.summary()

    def flush(self) -> None:
        self.storage.flush()

    def close(self) -> None:
        self.storage.close()

    def __enter__(self) -> RobotMemory:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"RobotMemory({self.storage!r})"


def _scalar(value: Any, name: str) -> float:
    """One finite number (a reward, a success flag), or an error naming ``name``."""
    try:
        a = np.asarray(value, dtype=np.float32)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name!r} must be one number, got {type(value).__name__}: {err}") from None
    if a.size != 1 or a.ndim > 1:
        raise ValueError(f"{name!r} must be one number (shape [] or [1]), got shape {list(a.shape)}: {a.tolist()}.")
    x = float(a.reshape(()))
    if not np.isfinite(x):
        raise ValueError(f"{name!r} is {x}; a stored {name} must be a finite number.")
    return x


def _row(value: Any, name: str) -> torch.Tensor:
    try:
        out = torch.as_tensor(np.asarray(value, dtype=np.float32)).reshape(-1)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name!r} must be an array of numbers, got {type(value).__name__}: {err}") from None
    if not torch.isfinite(out).all():
        raise ValueError(f"{name!r} holds NaN or inf values: {out.tolist()}.")
    return out
