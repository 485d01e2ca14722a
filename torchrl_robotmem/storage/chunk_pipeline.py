"""The Zarr codec pipelines the direct chunk reader and writer handle, and the threads they run on.

:mod:`.fast_read` decodes row chunks from their files and :mod:`.fast_write`
encodes them to theirs, both bypassing Zarr's Python codec path for the
pipelines ``ZarrStorage`` creates: ``bytes`` (little-endian), then at most one
compressor (``blosc`` or ``zstd``), then optionally ``crc32c``, one chunk across
every dimension but the rows. :func:`parse_pipeline` says whether an array has
such a pipeline (and which), once for both; :func:`usable_cpus` how many
threads their chunk pools may use. Standard library, numpy and zarr only: the
commit worker imports it as a top-level module.

Example:
    >>> import zarr
    >>> arr = zarr.create_array(zarr.storage.MemoryStore(), shape=(8, 2), chunks=(4, 2), dtype="f4", fill_value=0)
    >>> pipe = parse_pipeline(arr)
    >>> pipe.compressor is not None, pipe.checksum, pipe.chunk_shape
    (True, False, (4, 2))
"""
from __future__ import annotations

import os
from typing import Any, NamedTuple

import numpy as np
from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, ZstdCodec

__all__ = ["Pipeline", "parse_pipeline", "usable_cpus"]


class Pipeline(NamedTuple):
    """An array's codec pipeline, as the direct reader and writer handle it."""

    #: ``"blosc"``, ``"zstd"`` or ``None`` (raw bytes)
    kind: str | None
    #: the compressor codec itself (its settings), or ``None``
    compressor: Any
    #: whether a ``crc32c`` checksum ends each chunk file
    checksum: bool
    #: the chunk's shape (rows first; the rest is the array's)
    chunk_shape: tuple[int, ...]
    dtype: np.dtype


def parse_pipeline(arr: Any) -> Pipeline:
    """The :class:`Pipeline` of Zarr array ``arr``.

    Raises:
        ValueError: (naming the pipeline) when it is not one the direct reader and writer handle:
            not little-endian ``bytes`` first, another or a second compressor, or chunks that split
            the rows' own dimensions.
    """
    meta = arr.metadata
    codecs = list(meta.codecs)
    first = codecs.pop(0) if codecs else None
    dtype = np.dtype(arr.dtype)
    endian = getattr(getattr(first, "endian", None), "value", getattr(first, "endian", None))
    if not isinstance(first, BytesCodec) or not (endian == "little" or (endian is None and dtype.itemsize == 1)):
        raise ValueError(f"codec pipeline {meta.codecs} starts with no little-endian 'bytes' codec")
    checksum = bool(codecs) and isinstance(codecs[-1], Crc32cCodec)
    if checksum:
        codecs.pop()
    kind = None
    if codecs:
        kind = {BloscCodec: "blosc", ZstdCodec: "zstd"}.get(type(codecs[0]))
        if kind is None or len(codecs) > 1:
            raise ValueError(f"codec pipeline {meta.codecs} is not one the direct chunk reader and writer handle")
    chunks = tuple(int(k) for k in meta.chunk_grid.chunk_shape)
    if chunks[1:] != tuple(arr.shape[1:]):
        raise ValueError(f"chunks {list(chunks)} split the rows' own dimensions {list(arr.shape[1:])}")
    return Pipeline(kind, codecs[0] if codecs else None, checksum, chunks, dtype)


def usable_cpus(tasks: int, most: int) -> int:
    """Threads for ``tasks`` chunk jobs: the CPUs this process may use, at most ``most`` (and at least 1)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(cpus, most, tasks))
