"""The redo journal: how a commit that overwrites committed rows stays atomic.

Zarr replaces a chunk file atomically, but one array at a time: a crash between
two arrays of a ring wrapping around would leave rows whose columns come from
two writes. So chunks that overwrite committed rows are written twice:

1. their new contents to ``_journal/<array path>`` (:func:`write_journal`, with
   the commit record they lead to, committed as the ``journal`` attribute);
2. then in place, and the ``journal`` record is cleared.

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

from . import _backend

__all__ = ["journal_chunks", "replay_journal", "write_journal"]

#: the folder of a pending commit's chunks (``_journal/<array path>``)
PREFIX = "_journal/"


def write_journal(group: Any, arrays: dict[str, Any], payload: dict[int, dict[str, np.ndarray]], meta: dict, *,
                  schema: dict[str, dict], size: int, inner_shape: tuple[int, ...], chunk_rows: int,
                  write_chunks: Callable[..., None]) -> None:
    """Writes the redo log of ``payload`` (chunk id -> array path -> rows) and commits its record.

    Args:
        group: the store's Zarr group.
        arrays (dict): the journal's open arrays by path (``_journal/...``); created
            here (as large as the store: each chunk goes to its own offset) when absent.
        payload (dict): the chunks' new contents.
        meta (dict): the commit record the journalled chunks lead to.

    Keyword Args:
        schema (dict): the store's columns ``{path: {"dtype", "shape"}}``.
        size (int): the store's rows along the first dimension.
        inner_shape (tuple): the item shape after the first dimension.
        chunk_rows (int): rows per chunk.
        write_chunks: ``write_chunks(payload, prefix=...)``, the commit engine's chunk writer.
    """
    for path, spec in schema.items():
        jpath = PREFIX + path
        shape = (size, *inner_shape, *spec["shape"])
        if jpath not in arrays or arrays[jpath].shape != shape:
            arrays[jpath] = group.create_array(
                jpath,
                shape=shape,
                chunks=(chunk_rows, *shape[1:]),
                dtype=_backend.numpy_dtype(_backend.torch_dtype(spec["dtype"])),
                fill_value=0,
                overwrite=True,
            )
    write_chunks(payload, prefix=PREFIX)
    # the journal is complete once this record (with the state it leads to) is committed
    group.update_attributes({"journal": {"chunks": sorted(payload), "meta": meta}})


def journal_chunks(group: Any, journal: dict) -> Iterator[tuple[str, slice, np.ndarray]]:
    """Yields ``(path, row_slice, values)`` for every journalled chunk.

    Args:
        group: the store's Zarr group.
        journal (dict): its pending ``journal`` record.
    """
    rows = int(group.attrs["chunk_rows"])
    for path in group.attrs["schema"]:
        src = group[PREFIX + path]
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
