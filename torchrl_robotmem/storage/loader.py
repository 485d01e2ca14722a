"""Filling the rows of an opened record from the Zarr chunks: at once, or in the background.

A row file sealed for the record needs neither (:mod:`.rowfile`). Otherwise a
large memory's rows are filled by a thread (:func:`fill_in_background`, the
chunks a read or a write needs first) and every other open reads them all before it
returns (:func:`load_rows`), a reader applying a pending journal in RAM and
reading again the chunks a writer overwrote meanwhile.
:meth:`MemoryStore.fill_rows <.store.MemoryStore.fill_rows>` picks which.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> with ZarrStorage("memory://loader-doc", 10) as st:
    ...     st.set(slice(0, 3), TensorDict({"x": torch.arange(3.0)}, [3]))
    ...     st.flush()
    ...     with ZarrStorage("memory://loader-doc", read_only=True) as reader:  # rows read by load_rows
    ...         reader[:3]["x"].tolist()
    [0.0, 1.0, 2.0]
"""
from __future__ import annotations

import os

from .errors import IntegrityError, Problem
from .format import chunk_keys, decode_chunks, is_strict
from .journal import JournalArrayMissing

__all__ = ["BACKGROUND_FILL_BYTES", "BACKGROUND_FILL_ENV", "OPEN_COLUMNS", "fill_in_background", "load_rows"]

#: rows (bytes) from which a reader fills in the background (below it, the open's read is a few
#: tens of milliseconds); ``$TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES`` sets another threshold
BACKGROUND_FILL_BYTES = 64 << 20
BACKGROUND_FILL_ENV = "TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES"


def fill_in_background(handle, mirror, record: dict, attrs: dict, *, on_damage: str) -> bool:
    """Starts a background fill of the rows (:mod:`.background_fill`) where it serves what a synchronous
    load would; returns whether it started (``False``: call :func:`load_rows`).

    Only a local store on the CPU, with one batch dimension, that raises on damage, whose record has no
    pending journal and whose ring has not wrapped, with at least :data:`BACKGROUND_FILL_BYTES` of rows,
    every column read from its chunk files. A reader's fill looks at the commit record around each chunk
    (a writer may commit beside it); the writer's own fill needs no look, but reads the columns its open
    needs before it returns (:data:`OPEN_COLUMNS`: which episodes the previous writer left open, which ids
    are in use), and writes into rows below the opened length wait for their chunk's fill.
    """
    n0 = mirror.dim0(int(attrs.get("len", 0)))
    threshold = int(os.environ.get(BACKGROUND_FILL_ENV, BACKGROUND_FILL_BYTES))
    if not (handle.local_dir is not None and on_damage == "raise" and mirror.ndim == 1
            and str(mirror.device).startswith("cpu") and not record.get("journal")
            and int(attrs.get("write_count", 0)) <= mirror.max_size and n0
            and n0 * mirror.layout.row_bytes >= threshold):
        return False
    if handle.read_only:
        return mirror.start_fill(handle.group, n0, local_dir=handle.local_dir,
                                 record_file=os.path.join(handle.local_dir, "zarr.json"),
                                 fallback=lambda failure: load_rows(handle, mirror, record, attrs, on_damage=on_damage))
    early = [p for p in OPEN_COLUMNS if p in mirror.schema]
    if not mirror.read_columns(handle.group, early, n0, local_dir=handle.local_dir):
        return False  # one of them is not readable from its files: the synchronous load names what is wrong
    if not mirror.start_fill(handle.group, n0, local_dir=handle.local_dir, record_file=None,
                             fallback=lambda failure: _damaged(handle, mirror, n0, failure)):
        return False
    # the chunk the next appends go into holds opened rows too: filled now (its damage refuses the open, as a
    # synchronous load's would), so a chunk the commits write is always whole
    mirror.fill_before_write(slice(n0 - 1, n0))
    return True


#: the columns a writer's open reads before it returns when its rows are filled in the background
OPEN_COLUMNS = ("episode", "run", "next/done")


def _damaged(handle, mirror, n0: int, failure: tuple | None) -> None:
    """A writer's fill met a chunk it cannot read: raised by that read and every later one, naming it as the
    synchronous load does (a missing file, a checksum that does not match, a chunk that does not decode)."""
    problems = []
    c, paths = failure if failure is not None else (None, [])
    for path in paths:
        arr = handle.group[path]
        key = chunk_keys(arr, path, c)[0]
        rows = (c * mirror.chunk_rows, min((c + 1) * mirror.chunk_rows, n0))
        if not os.path.lexists(os.path.join(handle.local_dir, *key.split("/"))):
            problems.append(Problem("missing_chunk", "chunk file missing", array=path, chunk=c, key=key, rows=rows))
            continue
        found, _ = decode_chunks(arr, path, n0, mirror.chunk_rows, present={c})
        problems += found or [Problem("undecodable", "the chunk file could not be read", array=path, chunk=c,
                                      key=key, rows=rows)]
    raise IntegrityError(handle.path, problems or [Problem("undecodable", "a chunk could not be read")],
                         read_only=False, action="The rows written since the open are kept in memory; no chunk was "
                                                 "written over.")


def missing_journal(path, err: Exception) -> IntegrityError:
    """The damage of a pending journal whose array ``err`` names is not in the store (and no writer moved on)."""
    jp = str(err.args[0]) if err.args else "_journal"
    return IntegrityError(path, [Problem("journal", "journal array missing or unreadable", array=jp,
                                         key=f"{jp}/zarr.json")], read_only=True)


def load_rows(handle, mirror, record: dict, attrs: dict, *, on_damage: str) -> int:
    """Reads the rows of ``attrs`` into the allocated ``mirror``; returns the transitions kept.

    ``record`` is the record as opened (before a pending journal); a reader applies
    that journal and re-reads chunks a writer overwrote meanwhile. The chunk
    files of the arrays read through Zarr (a missing file reads as zeros there) are
    listed again after the read (:meth:`StoreHandle.check_read <.handle.StoreHandle.check_read>`);
    those read from their files (:mod:`.fast_read`) need no listing.

    Args:
        handle (StoreHandle): the store's handle.
        mirror (RamMirror): the RAM rows, allocated for the record's schema.
        record (dict): the record as opened.
        attrs (dict): the record to load (``record`` with a pending journal applied).

    Keyword Args:
        on_damage (str): ``"raise"`` or ``"warn"``.
    """
    journal = record.get("journal")
    read_only = handle.read_only
    n = int(attrs.get("len", 0))
    n0 = mirror.dim0(n)
    left = mirror.load(handle.group, n0, store_path=handle.path, read_only=read_only, local_dir=handle.local_dir)
    gone = mirror.apply_journal(handle.group, journal) if journal and read_only else None
    try:
        reread = bool(read_only and n0 and mirror.reread_overwritten(handle.store, handle.group, record, n0,
                                                                      store_path=handle.path))
    except JournalArrayMissing as err:
        raise missing_journal(handle.path, err) from None
    if gone is not None and not reread:  # the journal's arrays are missing, and no commit replaced them
        raise missing_journal(handle.path, gone)
    if n0 and (left or reread):
        # Zarr reads a chunk file that is gone as zeros: one moved away since the open's
        # listing (by `robotmem repair`) is an error here, never zero rows served. The
        # arrays read from their chunk files (fast_read) need no listing: each file was read.
        listed = attrs if not read_only else {**record, "len": min(n, int(record.get("len", 0)))}
        if not reread and is_strict(listed):
            listed = {**listed, "schema": {p: spec for p, spec in listed["schema"].items() if p in left}}
        n = handle.check_read(listed, n, on_damage=on_damage, inner_numel=mirror.inner_numel)
    return n
