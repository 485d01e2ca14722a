"""The one module that touches TorchRL writer internals.

A storage that outlives its process must hand the buffer's writer the cursor
and write count it left off at, and must undo the cursor move a writer makes
before a ``set`` that is refused. TorchRL has no storage -> writer channel, so:

* the writers are found through ``storage._attached_entities`` (the buffers
  TorchRL attached) and each buffer's ``_writer``;
* their position is set with the public ``writer.load_state_dict`` where the
  writer has one (``RoundRobinWriter`` and subclasses), and read back with
  ``writer.state_dict()``;
* the moment to do it is the buffer's ``checkpointer`` assignment, which
  ``ReplayBuffer._init`` makes right after ``writer.register_storage`` (see
  ``ZarrStorage.checkpointer``): before that call the writer does not exist.

``docs/storage.md`` lists these private names.
"""
from __future__ import annotations

import weakref
from collections.abc import Iterator
from typing import Any

__all__ = ["attached_writers", "restore_writers", "rollback_writers"]


def attached_writers(storage: Any) -> Iterator[Any]:
    """The writers of the buffers this storage is attached to."""
    for entity in list(getattr(storage, "_attached_entities", ())):
        writer = getattr(entity, "_writer", None)
        if writer is not None and getattr(writer, "_storage", None) is storage:
            yield writer


def _position(writer: Any) -> tuple[int, int] | None:
    try:
        state = writer.state_dict()
    except Exception:  # noqa: BLE001 - writers without a position (e.g. immutable ones)
        return None
    if "_cursor" not in state:
        return None
    return int(state["_cursor"]), int(state.get("_write_count") or 0)


def restore_writers(storage: Any, cursor: int, write_count: int, done: weakref.WeakSet, *, force: bool = False) -> None:
    """Sets every attached writer to ``cursor`` / ``write_count`` (once per writer unless ``force``)."""
    for writer in attached_writers(storage):
        if writer in done and not force:
            continue
        if _position(writer) is not None:
            state = writer.state_dict()
            state.update({"_cursor": cursor, "_write_count": write_count})
            writer.load_state_dict(state)
        done.add(writer)


def rollback_writers(storage: Any, first_row: int, n: int, max_dim0: int) -> None:
    """Undoes the cursor move a round-robin writer made before calling a ``set`` that failed.

    ``RoundRobinWriter.extend`` advances its cursor before ``storage.set``: if
    ``set`` raises, the next good write would leave a hole.
    """
    if n == 0:  # an empty write did not move the cursor
        return
    for writer in attached_writers(storage):
        pos = _position(writer)
        if pos is not None and pos[0] == (first_row + n) % max_dim0:
            state = writer.state_dict()
            state.update({"_cursor": first_row, "_write_count": pos[1] - n})
            writer.load_state_dict(state)
