"""Storage integrity: the checks made at open, :func:`verify` and :func:`repair`.

A Zarr store is a directory of files any process, disk or copy can damage. Zarr
itself reads a deleted chunk file as zeros and a flipped byte as other data; a
commit record (``len``, cursor) pointing past the written rows would serve
zeros as transitions. This package makes such damage an error that names the
array and the chunk at fault:

* **Checksums.** Stores created by this version append Zarr v3's ``crc32c``
  codec to every array's codec pipeline (after the compressor), and write every
  chunk, also an all-zero one (``write_empty_chunks``), so a chunk file that is
  absent below the committed length is damage, not "all zeros". Both are
  recorded in the format marker (``{"integrity": {"checksum": "crc32c",
  "empty_chunks": "written"}}``, see :mod:`torchrl_robotmem.storage.format`).
  Stores created before keep opening: their chunks are not checksummed, and a
  chunk missing from only some arrays may be an all-zero chunk, so only a chunk
  missing from every array is damage there.
* **At open** (:func:`check_open`, called by ``ZarrStorage`` before anything is
  read or written): the commit record's attributes are sane (integers within
  ``[0, max_size]``, a schema of known dtypes, parseable tag tables and data
  kind), every array of the schema exists with the recorded dtype and shape,
  and every chunk below the committed length is present (one listing of each
  array's chunk keys). Reading the rows then checks every chunk's checksum. A
  damaged store raises :class:`IntegrityError`; nothing is written to it.
* :func:`verify` reads everything and returns an :class:`IntegrityReport`;
  :func:`repair` makes a damaged store openable and writable again, keeping
  every intact row bit-exact (``robotmem verify PATH`` / ``robotmem repair PATH``).

The parts, one job each:

* :mod:`.attributes`: the commit record's checks (and :func:`unsafe_path`);
* :mod:`.chunks`: which chunk files exist, which are missing;
* :mod:`.arrays`: each array's metadata and a pending journal against the record;
* :mod:`.capacity`: sizes no machine here could hold;
* :mod:`.checks`: :func:`check_open`, the checks at open;
* :mod:`.files`: a store's files as bytes (reads of damaged stores, writes that stay inside);
* :mod:`.verify`: :func:`verify` and :class:`IntegrityReport`;
* :mod:`.rebuild`: records recomputed from the data;
* :mod:`.repair`: :func:`repair` and :class:`RepairReport`.

Example:
    >>> import tempfile, torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity import verify
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> report = verify(path)
    >>> report.ok, report.rows, report.checksums
    (True, 10, True)
"""
from __future__ import annotations

from ..errors import IntegrityError, NotAMemoryError, Problem
from ..format import (
    ARRAY_CONFIG,
    MARKER,
    decode_chunks,
    is_strict,
    read_error,
    read_rows,
    write_zero_chunks,
    writing_config,
    writing_handles,
)
from .arrays import check_arrays, check_journal
from .attributes import check_attributes, unsafe_path
from .capacity import capacity_problem
from .checks import check_open
from .chunks import missing_after_read, missing_chunks, present_chunks
from .repair import RepairReport, repair
from .verify import IntegrityReport, verify

__all__ = [
    # what users and `robotmem verify` / `repair` use
    "IntegrityError", "IntegrityReport", "NotAMemoryError", "Problem", "RepairReport", "repair", "verify",
    # the checks ZarrStorage makes at open and after a read
    "capacity_problem", "check_arrays", "check_attributes", "check_journal", "check_open", "missing_after_read",
    "missing_chunks", "present_chunks", "unsafe_path",
    # the on-disk format (defined in torchrl_robotmem.storage.format; re-exported for older imports)
    "ARRAY_CONFIG", "MARKER", "decode_chunks", "is_strict", "read_error", "read_rows", "write_zero_chunks",
    "writing_config", "writing_handles",
]
