"""Where an env transform reads its memory: a store path opened on first use, or a live storage.

Example:
    >>> import tempfile, torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.memory_source import MemorySource
    >>> path = tempfile.mkdtemp() + "/m.zarr"
    >>> with ZarrStorage(path, 10, env="FetchReach-v4") as s:
    ...     s.set(slice(0, 3), TensorDict({"obs": torch.ones(3, 2)}, [3]))
    >>> source = MemorySource(path, refresh_every=None)
    >>> len(source), source.column("obs").shape
    (3, torch.Size([10, 2]))
"""
from __future__ import annotations

import os
from typing import Any

import torch
from tensordict.utils import NestedKey
from torchrl.data.replay_buffers.storages import Storage

from .goal_index.tracking import live_column
from .storage import ZarrStorage

__all__ = ["MemorySource", "is_read_only"]


class MemorySource:
    """Where an env transform reads a memory: a store path opened ``read_only`` on
    first use, or a live storage / replay buffer; and when a read-only one is re-read.

    Shared by :class:`~torchrl_robotmem.RecallTransform` and
    :class:`~torchrl_robotmem.GoalProposer`.

    Args:
        memory: a store path (str or os.PathLike), a TorchRL Storage or a replay buffer.
        refresh_every (int, optional): re-read a read-only memory at the first
            reset after this many counted steps.
    """

    def __init__(self, memory: str | os.PathLike | Storage | Any, refresh_every: int | None) -> None:
        if isinstance(memory, os.PathLike):
            memory = os.fspath(memory)
        if not isinstance(memory, str) and not isinstance(getattr(memory, "storage", memory), Storage):
            raise TypeError(
                "memory must be a store path (str), a TorchRL Storage or a replay buffer, "
                f"got {type(memory).__name__}."
            )
        if refresh_every is not None:
            if isinstance(refresh_every, bool) or not isinstance(refresh_every, int) or refresh_every < 1:
                raise ValueError(f"refresh_every must be an integer >= 1 or None, got {refresh_every!r}.")
            if not isinstance(memory, str) and not is_read_only(getattr(memory, "storage", memory)):
                raise ValueError(
                    "refresh_every applies to a read-only memory (a store path, or a ZarrStorage opened "
                    f"read_only=True); a writable {type(getattr(memory, 'storage', memory)).__name__} "
                    "is read live already."
                )
        self.memory = memory
        self.refresh_every = refresh_every
        self._storage: Storage | None = None
        self._steps = 0  # env steps since the memory was last (re)read

    @property
    def storage(self) -> Storage:
        if self._storage is None:
            if isinstance(self.memory, str):
                self._storage = ZarrStorage(self.memory, read_only=True)
            else:
                self._storage = getattr(self.memory, "storage", self.memory)
        return self._storage

    def __len__(self) -> int:
        """Rows stored (0 for a storage not initialized yet)."""
        storage = self.storage
        return len(storage) if storage.initialized else 0

    def column(self, key: NestedKey) -> torch.Tensor | None:
        """The storage's column for ``key`` (``[max_size, *shape]``), or None before any write."""
        return live_column(self.storage, key)

    def count_step(self) -> None:
        self._steps += 1

    def refresh_if_due(self) -> None:
        if self.refresh_every is not None and self._steps >= self.refresh_every:
            self.refresh()

    def refresh(self) -> None:
        storage = self.storage
        if is_read_only(storage):
            storage.refresh()
        self._steps = 0

    def __getstate__(self) -> dict[str, Any]:
        if not isinstance(self.memory, str) and isinstance(self.storage, ZarrStorage):
            raise RuntimeError(
                "A transform over a ZarrStorage object cannot be sent to another process "
                "(multi-process collectors, ParallelEnv workers). Pass the store's path instead, "
                f"e.g. RecallTransform({self.storage.path!r}, ...): each process then opens it read_only."
            )
        state = dict(self.__dict__)
        if isinstance(self.memory, str):  # reopened by whoever unpickles it
            state["_storage"] = None
        state["_steps"] = 0
        return state


def is_read_only(storage: Any) -> bool:
    return bool(getattr(storage, "read_only", False)) and callable(getattr(storage, "refresh", None))
