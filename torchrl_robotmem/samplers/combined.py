"""Combined experience replay (Zhang & Sutton 2017, "A Deeper Look at Experience Replay").

Every sampled batch holds the newest transition(s) (the rows of the latest write, or the ``k`` newest
rows of the storage); the rest of the batch is drawn by a wrapped base sampler (uniform by default).
Over a reopened :class:`~torchrl_robotmem.ZarrStorage` the newest rows are the store's newest ones.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torchrl.data.replay_buffers.samplers import RandomSampler, Sampler

__all__ = ["CombinedExperienceSampler", "newest_rows"]


def newest_rows(storage, k: int) -> torch.Tensor:
    """The ``k`` newest rows of ``storage`` (oldest first), ending at the last written row, across a ring's wrap.

    Args:
        storage (Storage): a TorchRL storage with ``ndim=1``.
        k (int): how many.

    Example:
        >>> import torch
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> rb = ReplayBuffer(storage=LazyTensorStorage(5))
        >>> _ = rb.extend(torch.arange(7))  # rows 0, 1 hold 5, 6: the ring wrapped
        >>> newest_rows(rb.storage, 3).tolist()
        [4, 0, 1]
    """
    n = len(storage)
    k = min(int(k), n)
    last = getattr(storage, "_last_cursor_index", None)  # TorchRL's last written row (restored by ZarrStorage)
    last = n - 1 if last is None or int(last) < 0 else int(last)
    size = int(storage.max_size) if n >= int(storage.max_size) else n
    return ((last - torch.arange(k - 1, -1, -1)) % max(size, 1)).to(torch.long)


class CombinedExperienceSampler(Sampler):
    """Combined experience replay: every batch holds the newest rows, the rest drawn by a base sampler.

    With ``newest=None`` the newest rows are those of the latest ``extend`` / ``add`` through the buffer
    (after a reopen and before any write: the store's newest row); with ``newest=k`` they are the ``k``
    rows written last, whoever wrote them. When they outnumber the batch, the newest ``batch_size`` of
    them fill it. The batch is shuffled (``shuffle=True``), so ``HERReplayBuffer``'s relabelled first
    ``her_ratio`` rows are a random subset of both kinds.

    The base sampler's info (``"priority_weight"``, ``"goal_distance"``, ...) is given for the newest rows
    too: the base's ``importance_weight(index)`` where it has one (:class:`PersistentPrioritizedSampler
    <torchrl_robotmem.samplers.prioritized.PersistentPrioritizedSampler>`), else ``1.0`` for
    ``"priority_weight"`` and NaN / -1 / ``False`` for other float / integer / bool entries. Priority
    updates (``rb.update_priority``) and writes reach the base sampler; attributes this class does not have
    are the base's (``with rb.sampler.query(goals):`` keeps working over a
    :class:`~torchrl_robotmem.GoalSimilaritySampler`). TorchRL's ``update_tensordict_priority`` only serves
    a ``PrioritizedSampler`` itself: over a prioritized base, call ``rb.update_priority(batch["index"], p)``.

    Args:
        base (Sampler, optional): draws the rest of the batch. Defaults to TorchRL's ``RandomSampler()``.

    Keyword Args:
        newest (int, optional): how many newest rows each batch holds; ``None`` (default): those of the
            latest write.
        shuffle (bool, optional): shuffle the batch. Defaults to ``True``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_robotmem.samplers.combined import CombinedExperienceSampler
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), sampler=CombinedExperienceSampler(),
        ...                             batch_size=32)
        >>> _ = rb.extend(TensorDict({"obs": torch.randn(500, 3)}, [500]))
        >>> _ = rb.extend(TensorDict({"obs": torch.randn(4, 3)}, [4]))  # rows 500..503
        >>> set(range(500, 504)) <= set(rb.sample()["index"].tolist())
        True
    """

    def __init__(self, base: Sampler | None = None, *, newest: int | None = None, shuffle: bool = True) -> None:
        if newest is not None and (isinstance(newest, bool) or int(newest) < 1):
            raise ValueError(f"newest must be a positive integer or None (the rows of the latest write), got "
                             f"{newest!r}.")
        if base is not None and not isinstance(base, Sampler):
            raise TypeError(f"base must be a TorchRL Sampler (e.g. torchrl.data.RandomSampler()), got {type(base)}.")
        self.base = RandomSampler() if base is None else base
        self.newest = None if newest is None else int(newest)
        self.shuffle = bool(shuffle)
        self._latest: torch.Tensor | None = None  # rows of the latest write through the buffer
        self._generator: torch.Generator | None = None

    # the buffer's generator (ReplayBuffer.set_rng) reaches the base sampler too
    @property
    def _rng(self) -> torch.Generator | None:
        return self._generator

    @_rng.setter
    def _rng(self, generator: torch.Generator | None) -> None:
        self._generator = generator
        self.base._rng = generator  # TorchRL's Sampler attribute (ReplayBuffer.set_rng sets it)

    def __getattr__(self, name: str):
        base = self.__dict__.get("base")
        if base is None or name.startswith("__"):
            raise AttributeError(name)
        return getattr(base, name)

    # -- sampling -------------------------------------------------------------------------------

    def newest_index(self, storage) -> torch.Tensor:
        """The rows every batch holds now (oldest first)."""
        if self.newest is not None:
            return newest_rows(storage, self.newest)
        latest = self._latest
        if latest is not None and latest.numel() and int(latest.max()) < len(storage):
            return latest
        return newest_rows(storage, 1)

    def sample(self, storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RuntimeError("Cannot sample from an empty storage.")
        new = self.newest_index(storage)[-batch_size:]
        rest = batch_size - new.numel()
        if rest:
            index, info = self.base.sample(storage, rest)
            if isinstance(index, tuple):
                raise ValueError("CombinedExperienceSampler serves storages with ndim=1 (the base drew a tuple index).")
            index = torch.as_tensor(index)
        else:  # the newest rows fill the batch: the base draws none (a prioritized base still weighs them)
            weigh = getattr(self.base, "importance_weight", None)
            index, info = new[:0], ({} if weigh is None else {"priority_weight": weigh(new)[:0]})
        new = new.to(index.device)
        info = {key: self._info_of_newest(key, value, new, rest) for key, value in info.items()}
        index = torch.cat([new, index.to(torch.long)])
        if self.shuffle:
            perm = torch.randperm(batch_size, generator=self._generator).to(index.device)
            index = index[perm]
            info = {k: v[perm] if isinstance(v, torch.Tensor) and v.shape[:1] == (batch_size,) else v
                    for k, v in info.items()}
        return index, info

    def _info_of_newest(self, key: str, value: Any, new: torch.Tensor, rest: int):
        if not isinstance(value, torch.Tensor) or value.shape[:1] != (rest,):
            return value
        weigh = getattr(self.base, "importance_weight", None)
        if key == "priority_weight" and weigh is not None:
            fill = weigh(new).to(value.device, value.dtype)
        elif key == "priority_weight":
            fill = torch.ones((new.numel(), *value.shape[1:]), dtype=value.dtype, device=value.device)
        else:
            empty = float("nan") if value.dtype.is_floating_point else (False if value.dtype == torch.bool else -1)
            fill = torch.full((new.numel(), *value.shape[1:]), empty, dtype=value.dtype, device=value.device)
        return torch.cat([fill, value])

    # -- the buffer's hooks, forwarded --------------------------------------------------------------

    def extend(self, index) -> None:
        if not isinstance(index, tuple):
            self._latest = torch.as_tensor(index).reshape(-1).to(torch.long).cpu()
        self.base.extend(index)

    def add(self, index) -> None:
        if not isinstance(index, tuple):
            self._latest = torch.as_tensor(index).reshape(-1).to(torch.long).cpu()
        self.base.add(index)

    def mark_update(self, index, *, storage=None) -> None:
        self.base.mark_update(index, storage=storage)

    def update_priority(self, index, priority, *, storage=None):
        return self.base.update_priority(index, priority, storage=storage)

    @property
    def default_priority(self) -> float:
        return self.base.default_priority

    @property
    def ran_out(self) -> bool:
        return self.base.ran_out

    def _empty(self) -> None:
        self._latest = None
        self.base._empty()  # TorchRL's Sampler API: rb.empty() calls sampler._empty()

    # -- state ----------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {"newest": self.newest, "shuffle": self.shuffle, "base": self.base.state_dict(),
                "latest": None if self._latest is None else self._latest.tolist()}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.newest, self.shuffle = state_dict["newest"], bool(state_dict["shuffle"])
        latest = state_dict.get("latest")
        self._latest = None if latest is None else torch.as_tensor(latest, dtype=torch.long)
        self.base.load_state_dict(state_dict["base"])

    def dumps(self, path) -> None:
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        with open(path / "sampler_metadata.json", "w") as f:
            json.dump({"newest": self.newest, "shuffle": self.shuffle,
                       "latest": None if self._latest is None else self._latest.tolist()}, f)
        self.base.dumps(path / "base")

    def loads(self, path) -> None:
        path = Path(path)
        with open(path / "sampler_metadata.json") as f:
            meta = json.load(f)
        self.newest, self.shuffle = meta["newest"], bool(meta["shuffle"])
        self._latest = None if meta["latest"] is None else torch.as_tensor(meta["latest"], dtype=torch.long)
        self.base.loads(path / "base")

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_generator"] = None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(base={self.base!r}, newest={self.newest}, shuffle={self.shuffle})"
