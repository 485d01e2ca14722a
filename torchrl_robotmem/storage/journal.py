"""The redo journal: how a commit that overwrites committed rows stays atomic.

Zarr replaces a chunk file atomically, but one array at a time: a crash between
two arrays of a ring wrapping around would leave rows whose columns come from
two writes. So chunks that overwrite committed rows are written twice:

1. their new contents to ``_journal/<array path>``, with the commit record they
   lead to, committed as the ``journal`` attribute;
2. then in place, and the ``journal`` record is cleared.

:func:`commit` is that protocol (and the plain one: chunks, then the record),
the one implementation of both commit paths.

A reopen (or ``robotmem repair``) finds a pending record and redoes step 2
(:func:`replay_journal`); a reader that may not write applies the journalled
chunks in RAM (:func:`journal_chunks`).

Example:
    >>> import numpy as np, zarr
    >>> from torchrl_robotmem.storage.journal import replay_journal
    >>> g = zarr.open_group(zarr.storage.MemoryStore(), mode="w", zarr_format=3)
    >>> _ = g.update_attributes({"chunk_rows": 2, "schema": {"x": {}}, "len": 0})
    >>> _ = g.create_array("x", shape=(4,), chunks=(2,), dtype="f4", fill_value=0)
    >>> j = g.create_array("_journal/x", shape=(4,), chunks=(2,), dtype="f4", fill_value=0)
    >>> j[2:4] = np.array([5.0, 6.0], dtype="f4")
    >>> replay_journal(g, {"chunks": [1], "meta": {"len": 4}})["len"], g["x"][:].tolist()
    (4, [0.0, 0.0, 5.0, 6.0])
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

__all__ = ["OVERWRITES", "PREFIX", "JournalArrayMissing", "commit", "journal_chunks", "replay_journal"]

#: the folder of a pending commit's chunks (``_journal/<array path>``)
PREFIX = "_journal/"
#: the record's count of journalled commits: a write in place changes no other field of the record, and
#: a reader whose load a journalled commit overlapped tells by this count that it must read again
OVERWRITES = "overwrites"


def commit(group: Any, arrays: dict[str, Any], write_chunks: Callable[..., None],
           payload: dict[int, dict[str, np.ndarray]], meta: dict | None, *, chunk_rows: int,
           journal: list | None = None) -> None:
    """The commit protocol, written once: the in-process engine (:mod:`.commit`) and the commit worker call it.

    1. With ``journal`` (the chunks overwrite committed rows): the new contents go to
       ``_journal/<path>`` first, and the ``journal`` record (the chunks, and the record ``meta``
       they lead to) is committed: from here a crash is redone on the next open.
    2. The chunks are written in place.
    3. The record ``meta`` is committed in one attribute write (and the ``journal`` record cleared).

    Without ``meta`` (complete chunks written ahead of their record) only step 2 runs: rows on disk
    past the committed length are not read by anyone until a record names them.

    Args:
        group: the store's Zarr group (writable).
        arrays (dict): the open arrays by path, kept by the caller; the journal's (``_journal/...``)
            are created here, as large as the store (each chunk at its own offset), when absent.
        write_chunks: ``write_chunks(payload, prefix="")``, the caller's chunk writer
            (``fast_write.write_chunks`` on its arrays).
        payload (dict): chunk id -> array path -> the chunk's rows.
        meta (dict or None): the commit record, or ``None`` (chunks only).

    Keyword Args:
        chunk_rows (int): rows per chunk.
        journal (list, optional): ``[path, shape, numpy dtype str]`` of every column's journal array,
            when the chunks overwrite committed rows.

    This module imports only NumPy: the commit worker loads it as a top-level module, without torch.
    """
    if journal is not None:
        for path, shape, dtype in journal:
            jpath = PREFIX + path
            arrays[jpath] = _journal_array(group, arrays.get(jpath), jpath, tuple(shape), np.dtype(dtype), chunk_rows)
        write_chunks(payload, prefix=PREFIX)
        # the journal is complete once this record (with the state it leads to) is committed
        group.update_attributes({"journal": {"chunks": sorted(payload), "meta": meta}})
    write_chunks(payload)
    if meta is not None or journal is not None:
        update = dict(meta or {})
        if journal is not None:
            update["journal"] = None
        group.update_attributes(update)


class JournalArrayMissing(KeyError):
    """A journal array that a pending ``journal`` record names is not in the store (its ``args[0]``: the path).

    Beside a live writer that is a journal ended and replaced since the record was read; with the record
    unchanged, damage.
    """


def _journal_array(group: Any, arr: Any, jpath: str, shape: tuple, dtype: np.dtype, chunk_rows: int) -> Any:
    """The journal array ``jpath`` for rows of ``shape``: the one open or on disk where it fits (grown if the
    store grew), else created. It is never deleted while it fits: a reader that read a pending journal's record
    may still be reading its chunks (a chunk file is replaced atomically; only the named chunks are read)."""
    chunks = (chunk_rows, *shape[1:])
    if arr is None:
        try:
            arr = group[jpath]
        except Exception:  # noqa: BLE001 - missing, or not an array this can reuse: created below
            arr = None
    fits = (arr is not None and getattr(arr, "dtype", None) == dtype and tuple(arr.chunks) == chunks
            and tuple(arr.shape[1:]) == shape[1:] and arr.shape[0] <= shape[0])
    if not fits:
        return group.create_array(jpath, shape=shape, chunks=chunks, dtype=dtype, fill_value=0, overwrite=True)
    if arr.shape[0] < shape[0]:
        arr.resize(shape)
    return arr


def journal_chunks(group: Any, journal: dict) -> Iterator[tuple[str, slice, np.ndarray]]:
    """Yields ``(path, row_slice, values)`` for every journalled chunk.

    Args:
        group: the store's Zarr group.
        journal (dict): its pending ``journal`` record.
    """
    rows = int(group.attrs["chunk_rows"])
    for path in group.attrs["schema"]:
        try:
            src = group[PREFIX + path]
        except KeyError as err:
            raise JournalArrayMissing(PREFIX + path) from err
        size = group[path].shape[0]
        for c in journal["chunks"]:
            lo, hi = c * rows, min(c * rows + rows, size)
            yield path, slice(lo, hi), src[lo:hi]


def replay_journal(group: Any, journal: dict) -> dict:
    """Redoes an interrupted journalled commit; returns the attributes it led to.

    Args:
        group: the store's Zarr group (writable).
        journal (dict): its pending ``journal`` record.
    """
    for path, rows, values in journal_chunks(group, journal):
        group[path][rows] = values
    group.update_attributes({**journal["meta"], "journal": None})
    return group.attrs.asdict()
