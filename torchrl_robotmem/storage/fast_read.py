"""Reading a local store's chunk files straight into the RAM mirror, in parallel, checksums checked on the read.

Opening a store reads every committed row. Zarr's own read of ``arr[:n]``
decodes one array at a time through its event loop and hands back a
contiguous copy, which the mirror then copies again into its packed rows. For
the codec pipelines this library writes (``bytes``, then ``blosc`` or
``zstd`` or nothing, then ``crc32c``) this module does the same decode itself:
each chunk file is read once, its crc32c checked on the bytes read (the check
Zarr makes), decompressed into a per-thread buffer and copied into the
mirror's column. Chunks are spread over a thread pool by chunk index (the
codecs and the copies release the GIL), so the packed rows of one chunk are
filled while they are in cache.

A chunk it cannot read exactly as Zarr would (a file that is gone, a checksum
that does not match, a size or codec it does not know) is never guessed at:
the array is reported back and read through Zarr, whose errors name the array
and the chunk (:func:`~torchrl_robotmem.storage.format.read_rows`). Since every
chunk read here came from its file, the read itself is the proof that no chunk
file was missing: the listing after the read is needed only for the arrays read
through Zarr.

Example:
    >>> import tempfile, torch, zarr
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.fast_read import read_into
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100, chunk_rows=4) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.arange(30.).reshape(10, 3)}, [10]))
    >>> group = zarr.open_group(path, mode="r")
    >>> out = torch.zeros(10, 3)
    >>> read_into({"obs": group["obs"]}, {"obs": out}, 10, 4, local_dir=path)
    set()
    >>> out[9].tolist()
    [27.0, 28.0, 29.0]
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import google_crc32c
import numcodecs.blosc
import numcodecs.zstd
import numpy as np
import torch

from .chunk_pipeline import parse_pipeline, usable_cpus
from .contained import open_regular

__all__ = ["ChunkPlan", "plan_array", "read_into", "workers"]

#: threads at most (more add nothing on a page-cached read of a few hundred chunks)
MAX_WORKERS = 8


class ChunkPlan:
    """How to decode one array's row chunks: the file name pattern, the codecs, the chunk size.

    Args:
        arr (zarr.Array): the array (one chunk across every dimension but the rows).
        path (str): its path in the store.
        local_dir (str): the store's directory.

    Raises ValueError when the array's codecs or chunking are not the ones this module decodes.

    Example:
        >>> import tempfile, torch, zarr
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> path = tempfile.mkdtemp() + "/memory.zarr"
        >>> with ZarrStorage(path, 100, chunk_rows=4) as storage:
        ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
        >>> plan = ChunkPlan(zarr.open_group(path, mode="r")["obs"], "obs", path)
        >>> plan.nbytes, plan.codec, plan.checksum
        (48, 'blosc', True)
    """

    def __init__(self, arr: Any, path: str, local_dir: str) -> None:
        try:
            pipe = parse_pipeline(arr)
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None
        self.checksum, self.codec, chunks = pipe.checksum, pipe.kind, pipe.chunk_shape
        self.dtype = np.dtype(arr.dtype)
        self.chunk_shape = chunks
        self.nbytes = int(np.prod(chunks)) * self.dtype.itemsize
        probe = 987654321
        key = arr.metadata.encode_chunk_key((probe, *([0] * (arr.ndim - 1))))
        head, _, tail = os.path.join(os.fspath(local_dir), path, key).partition(str(probe))
        self.head, self.tail = head, tail

    def file(self, c: int) -> str:
        """The file of row chunk ``c``."""
        return f"{self.head}{c}{self.tail}"

    def decode(self, raw: np.ndarray, scratch: np.ndarray) -> np.ndarray:
        """Chunk ``raw`` (the file's bytes) checked and decoded: a ``chunk_shape`` array (in ``scratch`` where it can).

        Raises ValueError on a checksum mismatch or a size other than the chunk's.
        """
        if self.checksum:
            if raw.size < 4 or np.uint32(google_crc32c.value(raw[:-4])).tobytes() != raw[-4:].tobytes():
                raise ValueError("Stored and computed checksum do not match")
            raw = raw[:-4]
        out = scratch[: self.nbytes]
        if self.codec == "blosc":
            size = int.from_bytes(raw[4:8].tobytes(), "little") if raw.size >= 16 else -1  # the header's nbytes
            if size != self.nbytes:
                raise ValueError(f"blosc chunk of {size} bytes, expected {self.nbytes}")
            numcodecs.blosc.decompress(raw, out)
        elif self.codec == "zstd":
            data = numcodecs.zstd.decompress(raw)
            if len(data) != self.nbytes:
                raise ValueError(f"zstd chunk of {len(data)} bytes, expected {self.nbytes}")
            out = np.frombuffer(data, np.uint8)
        else:
            if raw.size != self.nbytes:
                raise ValueError(f"raw chunk of {raw.size} bytes, expected {self.nbytes}")
            out = raw
        return out.view(self.dtype).reshape(self.chunk_shape)


def plan_array(arr: Any, path: str, local_dir: Any) -> ChunkPlan | None:
    """The :class:`ChunkPlan` of ``arr``, or ``None`` where Zarr must read it (another codec, a remote store)."""
    if local_dir is None:
        return None
    try:
        return ChunkPlan(arr, path, local_dir)
    except (ValueError, AttributeError, TypeError):
        return None


def workers(tasks: int) -> int:
    """Threads for ``tasks`` chunk reads: the CPUs this process may use, at most :data:`MAX_WORKERS`."""
    return usable_cpus(tasks, MAX_WORKERS)


class ChunkReads:
    """The arrays of a store read from their chunk files into columns, one row chunk at a time (thread-safe).

    Args:
        arrays (dict): ``{path: zarr.Array}``.
        columns (dict): ``{path: CPU tensor}`` with the array's row shape (views allowed).
        chunk_rows (int): rows per chunk.

    Keyword Args:
        local_dir (str or None): the store's directory (``None``: every path is left for Zarr).

    Attributes:
        left (set): the paths that cannot be read here (another codec, a remote store, a column of
            another dtype or shape): read them through Zarr.
    """

    def __init__(self, arrays: dict, columns: dict, chunk_rows: int, *, local_dir: Any) -> None:
        self.todo, self.left = {}, set()
        self.chunk_rows = int(chunk_rows)
        for p, arr in arrays.items():
            plan, dest = plan_array(arr, p, local_dir), _numpy(columns[p])
            if plan is None or dest is None or dest.dtype != plan.dtype or dest.shape[1:] != tuple(arr.shape[1:]):
                self.left.add(p)
            elif dest.size:
                self.todo[p] = (plan, dest)
        self._local = threading.local()

    def _buffers(self) -> tuple[np.ndarray, np.ndarray]:
        local = self._local
        if not hasattr(local, "scratch"):
            top = max(plan.nbytes for plan, _ in self.todo.values())
            local.raw = np.empty(top + top // 8 + 4096, np.uint8)  # compressed data can outgrow its input a little
            local.scratch = np.empty(top, np.uint8)
        return local.raw, local.scratch

    def read(self, c: int, n0: int, skip: set[str] = frozenset()) -> set[str]:
        """Reads row chunk ``c`` (its rows below ``n0``) of every array not in ``skip``; returns the paths that failed."""
        if not self.todo:
            return set()
        raw_buf, scratch = self._buffers()
        lo, hi = c * self.chunk_rows, min((c + 1) * self.chunk_rows, n0)
        failed = set()
        for p, (plan, dest) in self.todo.items():
            if p in skip:
                continue
            try:
                raw = _read_file(plan.file(c), raw_buf)
                np.copyto(dest[lo:hi], plan.decode(raw, scratch)[: hi - lo])
            except (OSError, ValueError, RuntimeError):
                failed.add(p)
        return failed


def read_into(arrays: dict, columns: dict, n0: int, chunk_rows: int, *, local_dir: Any) -> set[str]:
    """Reads rows ``[0, n0)`` of every array of ``arrays`` into ``columns``; returns the paths left for Zarr.

    Args:
        arrays (dict): ``{path: zarr.Array}``.
        columns (dict): ``{path: CPU tensor}`` with at least ``n0`` rows of the array's row shape (views allowed).
        n0 (int): rows to read along the first dimension.
        chunk_rows (int): rows per chunk.

    Keyword Args:
        local_dir (str or None): the store's directory (``None``: every path is left for Zarr).

    Returns:
        The paths not read here (another codec, a chunk file missing or not as written): read
        them through Zarr, and list their chunk files after the read.
    """
    reads = ChunkReads(arrays, columns, chunk_rows, local_dir=local_dir)
    nchunks = -(-n0 // chunk_rows)
    if not reads.todo or not nchunks:
        return reads.left
    failed: set[str] = set()
    lock = threading.Lock()

    def chunk(c: int) -> None:
        bad = reads.read(c, n0, skip=failed)
        if bad:
            with lock:
                failed.update(bad)

    n_workers = workers(nchunks)
    if n_workers == 1:
        for c in range(nchunks):
            chunk(c)
    else:
        with ThreadPoolExecutor(n_workers, thread_name_prefix="robotmem-open") as pool:
            list(pool.map(chunk, range(nchunks)))
    return reads.left | failed


def _numpy(col: torch.Tensor) -> np.ndarray | None:
    """A NumPy view of a CPU column, or ``None`` (another device, a dtype NumPy lacks)."""
    if col.device.type != "cpu":
        return None
    try:
        return col.numpy()
    except (TypeError, RuntimeError):
        return None


def _read_file(name: str, buf: np.ndarray) -> np.ndarray:
    """The bytes of file ``name`` (in ``buf`` when they fit); a symbolic link is refused (``ELOOP``), never followed."""
    with open(open_regular(name), "rb", buffering=0) as f:  # a named pipe would block the read for ever
        size = os.fstat(f.fileno()).st_size
        if size > buf.size:
            buf = np.empty(size, np.uint8)
        got = f.readinto(memoryview(buf)[:size])
        if got != size:
            raise OSError(f"{name}: read {got} of {size} bytes")
        return buf[:size]

