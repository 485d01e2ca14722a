"""The one index a storage shares with every reader, dropped with the storage.

:meth:`GoalIndex.for_storage <torchrl_robotmem.goal_index.GoalIndex.for_storage>`
keeps its indexes here: one per storage object and per key (goal column,
success column, metric, env names). The registry holds storages weakly, so an
index never keeps a storage alive.
"""
from __future__ import annotations

import weakref
from collections.abc import Callable, Hashable
from typing import Any

__all__ = ["SharedIndexes"]


class SharedIndexes:
    """Indexes by storage object and key, each forgotten when its storage is collected.

    Example:
        >>> from torchrl.data import LazyTensorStorage
        >>> from torchrl_robotmem.goal_index.shared import SharedIndexes
        >>> shared, storage = SharedIndexes(), LazyTensorStorage(10)
        >>> a = shared.get(storage, "key", lambda: object())
        >>> a is shared.get(storage, "key", lambda: object()), len(shared)
        (True, 1)
        >>> del storage
        >>> len(shared)
        0
    """

    def __init__(self) -> None:
        # storage id -> (weak ref to the storage, {key: index})
        self._entries: dict[int, tuple[weakref.ref, dict[Hashable, Any]]] = {}

    def get(self, storage: Any, key: Hashable, build: Callable[[], Any]) -> Any:
        """The index of ``storage`` under ``key``, made by ``build()`` on first use."""
        sid = id(storage)
        entry = self._entries.get(sid)
        if entry is None or entry[0]() is not storage:
            entry = self._entries[sid] = (weakref.ref(storage), {})
            weakref.finalize(storage, self._drop, sid, entry[0])
        index = entry[1].get(key)
        if index is None:
            index = entry[1][key] = build()
        return index

    def __len__(self) -> int:
        """Storages with at least one shared index."""
        return len(self._entries)

    def _drop(self, sid: int, ref: weakref.ref) -> None:
        entry = self._entries.get(sid)
        if entry is not None and entry[0] is ref:
            del self._entries[sid]
