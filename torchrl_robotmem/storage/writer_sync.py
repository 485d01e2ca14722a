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
  ``ZarrStorage.checkpointer``): before that call the writer does not exist;
* what the store records is the writer's own position (:func:`writer_position`,
  read after each write, an empty and a load): TorchRL's writers move it in ways a
  storage does not see (``write_at`` counts without ``set_cursor``, a consuming
  buffer moves the cursor itself, ``empty(empty_write_count=False)`` keeps the
  count, ``dim_extend`` counts items, not elements);
* ``TensorDictMaxValueWriter`` has no ``state_dict``: its heap of (rank, row) is
  rebuilt from the stored rows' rank key, which is what it held;
* a writer moves its cursor *before* it calls ``storage.set``: a flush that runs
  between the two (a SIGTERM handler) must not record that position, whose rows
  were never written; :func:`writing_now` sees a writer's method on the stack.

``docs/storage.md`` lists these private names.
"""
from __future__ import annotations

import sys
import weakref
from collections.abc import Iterator
from typing import Any

__all__ = ["attached_writers", "restore_writers", "rollback_writers", "writer_position", "writing_now"]


def attached_writers(storage: Any) -> Iterator[Any]:
    """The writers of the buffers this storage is attached to."""
    for entity in list(getattr(storage, "_attached_entities", ())):
        writer = getattr(entity, "_writer", None)
        if writer is not None and getattr(writer, "_storage", None) is storage:
            yield writer


def writer_position(storage: Any) -> tuple[int, int] | None:
    """``(cursor, write_count)`` of the first attached writer that has them (``None``: no such writer).

    Read from the writer's attributes, not its ``state_dict`` (which clones a tracking writer's
    generation stamps): this runs after every write.
    """
    for writer in attached_writers(storage):
        at = _position(writer)
        if at is not None:
            return at
    return None


def writing_now(storage: Any) -> bool:
    """Whether a thread is inside a method of a writer attached to ``storage`` (a signal handler that
    interrupted ``writer.extend`` runs on top of it; a flush from another thread runs beside it): its
    position may have moved for rows not yet written.
    """
    writers = {id(w): w for w in attached_writers(storage)}
    codes = {fn.__code__ for w in writers.values() for cls in type(w).__mro__ for fn in vars(cls).values()
             if hasattr(fn, "__code__")}
    for frame in sys._current_frames().values():
        while frame is not None:
            if frame.f_code in codes and id(frame.f_locals.get("self")) in writers:
                return True
            frame = frame.f_back
    return False


def _is_max_value(writer: Any) -> bool:
    return hasattr(writer, "_current_top_values") and hasattr(writer, "_rank_key")


def _position(writer: Any) -> tuple[int, int] | None:
    """``(cursor, write_count)`` of a writer that keeps them (round-robin and max-value writers), else ``None``."""
    cursor, count = getattr(writer, "_cursor", None), getattr(writer, "_write_count", None)
    if cursor is None or count is None:
        return None
    return int(cursor), int(count)


def restore_writers(storage: Any, cursor: int, write_count: int, done: weakref.WeakSet, *, force: bool = False) -> None:
    """Sets every attached writer to ``cursor`` / ``write_count`` (once per writer unless ``force``)."""
    for writer in attached_writers(storage):
        if writer in done and not force:
            continue
        if _is_max_value(writer):
            _restore_max_value(writer, storage, cursor, write_count)
        elif _position(writer) is not None:
            state = writer.state_dict()
            state.update({"_cursor": cursor, "_write_count": write_count})
            writer.load_state_dict(state)
        done.add(writer)


def _restore_max_value(writer: Any, storage: Any, cursor: int, write_count: int) -> None:
    """A ``TensorDictMaxValueWriter`` at the stored rows: its heap holds (rank, row) of every stored row, as its
    writes left it (rank: the row's ``rank_key``, reduced as the writer reduces it)."""
    import heapq

    from torchrl.data.replay_buffers.writers import max_value

    from .columns import read_column

    n = len(storage)
    top = []
    if n:
        ranks = read_column(storage, writer._rank_key, n).reshape(n, -1)
        values = ranks[:, 0] if ranks.shape[1] == 1 else max_value._reduce(ranks, writer._reduction, dim=1)
        top = list(zip(values.tolist(), range(n)))
    heapq.heapify(top)
    writer._current_top_values = top
    writer._cursor = cursor
    writer._write_count = write_count


def rollback_writers(storage: Any, first_row: int, n: int, max_dim0: int) -> None:
    """Undoes the cursor move a round-robin writer made before calling a ``set`` that failed.

    ``RoundRobinWriter.extend`` advances its cursor before ``storage.set``: if
    ``set`` raises, the next good write would leave a hole.
    """
    if n == 0:  # an empty write did not move the cursor
        return
    for writer in attached_writers(storage):
        pos = None if _is_max_value(writer) else _position(writer)  # a max-value writer has no state_dict
        if pos is not None and pos[0] == (first_row + n) % max_dim0:
            state = writer.state_dict()
            state.update({"_cursor": first_row, "_write_count": pos[1] - n})
            writer.load_state_dict(state)
