"""The on-disk format: the markers a store records, how its rows are laid out in chunks, written and read.

What every part that reads or writes a store's arrays must agree on, in one place:

* the format marker (``FORMAT_MARKER`` attribute, ``FORMAT_VERSION``) and its
  integrity record (:data:`MARKER`: checksummed chunks, all-zero chunks written);
* the store's own folders (``_journal``, ``_repair_backup``), which no array path may use;
* the row layout: a committed length along the first dimension (:func:`dims`),
  one chunk file per ``chunk_rows`` rows (:func:`chunk_keys`, :func:`row_chunk_key`), named
  ``<column>/c.<c>.0`` (:data:`CHUNK_KEY_SEPARATOR`; ``<column>/c/<c>/0`` in stores created before);
* writing: every chunk, an all-zero one too (:func:`writing_config`,
  :func:`writing_handles`, :func:`write_zero_chunks`), so a chunk file missing
  below the committed length is damage, never "all zeros";
* reading: :func:`read_rows` and :func:`decode_chunks` turn a chunk that fails to
  decode into a :class:`~torchrl_robotmem.storage.errors.Problem` naming it.

Nothing here opens a store; checking one is :mod:`.integrity`'s job.

Example:
    >>> from torchrl_robotmem.storage.format import FORMAT_MARKER, MARKER, dims, is_strict
    >>> attrs = {FORMAT_MARKER: {"format_version": 1, "integrity": dict(MARKER)}, "max_size": 100, "len": 10}
    >>> is_strict(attrs), dims(attrs)
    (True, (100, 10, ()))
"""
from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
import zarr

from .errors import IntegrityError, Problem

__all__ = [
    "ARRAY_CONFIG", "BACKUP_DIR", "BOUNDED_FORMAT", "CHUNK_KEY_SEPARATOR", "FORMAT_MARKER", "FORMAT_VERSION",
    "JOURNAL_DIR", "MARKER", "RESERVED", "UNBOUNDED", "UNBOUNDED_SIZE", "grown_size",
    "chunk_keys", "chunk_separator", "classify_read_error", "decode_chunks", "dims", "is_strict", "numel",
    "read_error", "read_rows", "row_chunk_key", "write_zero_chunks", "writing_config", "writing_handles",
]

#: the newest format this library reads and writes; bump on any change readers must know about.
#: 1: a ring of ``max_size`` rows; 2: also a memory without a declared capacity (``"unbounded": true``),
#: which grows (a store of format 1 stays format 1, so that older versions keep reading it)
FORMAT_VERSION = 2
#: the format of a store with a declared capacity
BOUNDED_FORMAT = 1
#: the TorchRL-facing ``max_size`` of a memory without a declared capacity: no writer index wraps around it
UNBOUNDED_SIZE = 1 << 50
#: the record attribute of a memory without a declared capacity (its ``max_size`` is the rows allocated so far)
UNBOUNDED = "unbounded"
#: the group attribute that marks a torchrl_robotmem store (``{"format_version": ..., ...}``)
FORMAT_MARKER = "torchrl_robotmem"
#: what the format marker of a store created by this version records (``marker["integrity"]``)
MARKER = {"checksum": "crc32c", "empty_chunks": "written"}
#: the Zarr array config every writing handle uses: all-zero chunks are written too
ARRAY_CONFIG = {"write_empty_chunks": True}
#: the chunk key separator of the columns a store is created with: ``<column>/c.<c>.0``, one file a chunk
#: and no folder a chunk (stores created before 2026-12 have ``"/"``: ``<column>/c/<c>/0``; both are read)
CHUNK_KEY_SEPARATOR = "."
#: where a pending commit's chunks wait (``_journal/<array path>``)
JOURNAL_DIR = "_journal"
#: where ``repair`` keeps what it replaced (``_repair_backup/<time>/``)
BACKUP_DIR = "_repair_backup"
#: top-level names of the store's own folders: no stored array path may start with one
RESERVED = (JOURNAL_DIR, BACKUP_DIR)


# -- the commit record ----------------------------------------------------------------


def grown_size(capacity: int, need: int, chunk_rows: int) -> int:
    """The rows a memory without a declared capacity grows to, to hold ``need`` rows.

    Doubling up to 1M rows, then 1M rows at a time; whole chunks. The disk is taken as rows arrive.

    Example:
        >>> grown_size(16384, 16385, 16384), grown_size(2**20, 2**20 + 1, 16384)
        (32768, 2097152)
    """
    new = max(int(need), min(2 * capacity, capacity + (1 << 20)))
    return -(-new // chunk_rows) * chunk_rows



def is_strict(attrs: dict) -> bool:
    """Whether every chunk below the committed length must exist (stores created by this version).

    Example:
        >>> is_strict({FORMAT_MARKER: {"format_version": 1}})  # a store written before all-zero chunks were
        False
    """
    marker = attrs.get(FORMAT_MARKER)
    integ = marker.get("integrity") if isinstance(marker, dict) else None
    return isinstance(integ, dict) and integ.get("empty_chunks") == "written"


def numel(attrs: dict) -> int:
    """Rows a slot along the first dimension holds (the product of the leading ``ndim - 1`` inner dims, >= 1).

    Example:
        >>> numel({"ndim": 2, "inner_shape": [4]}), numel({"ndim": 1, "inner_shape": [4]})
        (4, 1)
    """
    inner = tuple(attrs.get("inner_shape") or ())
    ndim = int(attrs.get("ndim", 1))
    return max(math.prod(inner[: ndim - 1]) if ndim > 1 else 1, 1)


def dims(attrs: dict) -> tuple[int, int, tuple[int, ...]]:
    """``(max_dim0, committed rows along dim 0, inner_shape)`` of sane attributes.

    Example:
        >>> dims({"max_size": 100, "len": 10, "ndim": 2, "inner_shape": [4]})
        (25, 3, (4,))
    """
    inner = tuple(attrs.get("inner_shape") or ())
    n = numel(attrs)
    return -(-int(attrs["max_size"]) // n), -(-int(attrs.get("len", 0)) // n), inner


# -- chunks -----------------------------------------------------------------------------


def chunk_separator(arr: Any) -> str:
    """The chunk key separator of a Zarr v3 array: ``"."`` (``c.<c>.0``) or ``"/"`` (``c/<c>/0``).

    Example:
        >>> import zarr
        >>> arr = zarr.create_array(zarr.storage.MemoryStore(), shape=(4,), chunks=(2,), dtype="f4")
        >>> chunk_separator(arr)
        '/'
    """
    return str(getattr(arr.metadata.chunk_key_encoding, "separator", "/"))


def chunk_keys(arr: Any, path: str, c: int) -> list[str]:
    """The store keys of chunk ``c`` (along the rows) of ``arr``: one per chunk of the other dims."""
    shape, chunks = arr.shape, arr.metadata.chunk_grid.chunk_shape
    other = [range(-(-s // k)) for s, k in zip(shape[1:], chunks[1:])]
    return [f"{path}/{arr.metadata.encode_chunk_key((c, *rest))}" for rest in itertools.product(*other)]


def row_chunk_key(arr: Any, path: str) -> tuple[str, str]:
    """``(head, tail)``: chunk ``c`` along the rows of ``arr`` is stored at key ``head + str(c) + tail``.

    Arrays of this library have one chunk across every other dimension (checked
    at open), so each row chunk is one file.
    """
    probe = 987654321
    head, _, tail = f"{path}/{arr.metadata.encode_chunk_key((probe, *([0] * (arr.ndim - 1))))}".partition(str(probe))
    return head, tail


# -- writing ------------------------------------------------------------------------------


def writing_handles(group: Any, paths: Any) -> dict:
    """Handles on the arrays ``paths`` that write all-zero chunks too (for the commit engine)."""
    return {p: group[p].with_config(ARRAY_CONFIG) for p in paths}


def writing_config():
    """A context in which every Zarr handle writes all-zero chunks (a journal replay opens its own)."""
    return zarr.config.set({"array.write_empty_chunks": True})


def write_zero_chunks(arr: Any, n0: int, chunk_rows: int) -> None:
    """Writes the chunks of a new array below row ``n0`` as zeros (a key added to a store with rows).

    Its older rows read zeros; written as chunk files, a later missing one is damage.
    """
    for lo in range(0, n0, chunk_rows):
        hi = min(lo + chunk_rows, arr.shape[0])
        arr[lo:hi] = np.zeros((hi - lo, *arr.shape[1:]), dtype=arr.dtype)


# -- reading ------------------------------------------------------------------------------


def classify_read_error(err: BaseException) -> tuple[str, str]:
    """``(kind, what)`` of a chunk that failed to decode: ``"checksum"`` or ``"undecodable"``."""
    msg = str(err)
    if "checksum" in msg.lower():
        return "checksum", f"checksum mismatch (crc32c): the chunk file was changed ({msg[:90]})"
    return "undecodable", f"chunk does not decode ({type(err).__name__}: {msg[:90]}): truncated or overwritten"


def decode_chunks(arr: Any, path: str, n0: int, chunk_rows: int,
                  present: set[int] | None = None) -> tuple[list[Problem], int]:
    """Reads every chunk of ``arr`` below row ``n0`` one by one; ``(problems, chunks read)``.

    With ``present`` (the chunk indices that have a file), only those are read:
    a missing one is reported by the listing, and a ``len`` claiming more rows
    than exist costs nothing.
    """
    problems = []
    nchunks = -(-n0 // chunk_rows)
    todo = range(nchunks) if present is None else sorted(c for c in present if c < nchunks)
    for c in todo:
        lo, hi = c * chunk_rows, min((c + 1) * chunk_rows, arr.shape[0])
        try:
            arr[lo:hi]
        except Exception as err:  # noqa: BLE001 - codec errors have no common type
            kind, what = classify_read_error(err)
            problems.append(Problem(kind, what, array=path, chunk=c, key=chunk_keys(arr, path, c)[0],
                                    rows=(lo, min(hi, n0))))
    return problems, len(todo)


def read_error(arr: Any, path: str, n0: int, chunk_rows: int, err: BaseException, store_path: Any,
               read_only: bool) -> IntegrityError:
    """The :class:`IntegrityError` for a failed read of ``arr[:n0]``, naming the chunks at fault."""
    problems, _ = decode_chunks(arr, path, n0, chunk_rows)
    if not problems:
        kind, what = classify_read_error(err)
        problems = [Problem(kind, what, array=path)]
    return IntegrityError(store_path, problems, read_only=read_only)


def read_rows(arr: Any, path: str, n0: int, chunk_rows: int, store_path: Any, read_only: bool) -> np.ndarray:
    """``arr[:n0]`` as a contiguous array, or an :class:`IntegrityError` naming the chunks that fail to decode."""
    try:
        return np.ascontiguousarray(arr[:n0])
    except Exception as err:  # noqa: BLE001 - codec errors have no common type
        raise read_error(arr, path, n0, chunk_rows, err, store_path, read_only) from err
