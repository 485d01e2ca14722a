"""Writing a local store's chunk files directly: the one chunk writer of both commit paths.

Zarr v3 writes a chunk through its event loop, codec pipeline and store calls:
mostly Python, holding the GIL for most of a commit. For the codec pipelines this
library writes (``bytes``, then ``blosc`` or ``zstd`` or nothing, then
``crc32c`` or not, see ``_backend.make_compressors``) this module encodes a row
chunk itself, with the same codecs built from the array's own metadata
(numcodecs' ``Blosc`` / ``Zstd`` and ``google_crc32c``, called directly: no
event loop), so the file holds the bytes Zarr would write (a test compares them,
for every dtype and codec the library creates). The compressors release the GIL.

A chunk file is written as Zarr's local store writes it: a temporary
``NAME.<uuid>.partial`` file in the chunk's own folder, then ``os.replace``, so a
reader, a crash or a killed writer sees the old chunk or the new one, never part
of one (a left ``.partial`` file is removed by the next writer). The folders are
created below the store's root only, and a folder on the way that is a symbolic
link refuses the write (``ELOOP``): :class:`.contained.FolderCheck`, the store's
own (``store.check``, a :mod:`.contained` store) where it has one. The temporary file is created with ``O_EXCL | O_NOFOLLOW``; the
rename replaces a link at the chunk's name, never what it names.

:func:`write_chunks` is the chunk writer of the commit engine
(:mod:`.commit`, in-process) and of the commit worker (:mod:`._commit_worker`,
which imports this file as a top-level module): a chunk of a local array with a known pipeline
is written here, any other (another store, codec, a write that does not cover
the chunk) through Zarr's ``setitem``, as before.

This module imports only the standard library, NumPy, numcodecs, google_crc32c,
Zarr and its sibling :mod:`.contained`: the commit worker imports it without the package (and without torch).

Example:
    >>> import os, tempfile, numpy as np, zarr
    >>> from torchrl_robotmem.storage.fast_write import write_chunks
    >>> group = zarr.open_group(tempfile.mkdtemp(), mode="w", zarr_format=3)
    >>> arr = group.create_array("obs", shape=(10, 3), chunks=(4, 3), dtype="f4", fill_value=0)
    >>> write_chunks(lambda p: arr, {2: {"obs": np.ones((2, 3), "f4")}}, 4)
    >>> arr[8:].tolist(), sorted(os.listdir(os.path.join(arr.store.root, "obs", "c")))
    ([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]], ['2'])
"""
from __future__ import annotations

import asyncio
import os
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import google_crc32c
import numpy as np
from numcodecs import Blosc, Zstd
from zarr.core.sync import sync as zarr_sync
from zarr.storage import LocalStore

try:
    from .chunk_pipeline import parse_pipeline, usable_cpus
    from .contained import FolderCheck
except ImportError:  # loaded as a top-level module by the commit worker (this folder is its sys.path[0])
    from chunk_pipeline import parse_pipeline, usable_cpus
    from contained import FolderCheck

__all__ = ["ChunkCodec", "MAX_THREADS", "plan_array", "write_chunks", "write_file"]

#: threads at most for one call of :func:`write_chunks` (the codecs release the GIL)
MAX_THREADS = 4

_SHUFFLE = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}
_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)


class ChunkCodec:
    """Encodes one row chunk of one array as Zarr would: its codec pipeline, from its metadata.

    Args:
        arr (zarr.Array): the array (one chunk across every dimension but the rows).

    Raises ValueError when the array's pipeline or chunking is not one this module encodes.

    Example:
        >>> import zarr, numpy as np
        >>> from torchrl_robotmem.storage._backend import make_compressors
        >>> arr = zarr.create_array(zarr.storage.MemoryStore(), shape=(8, 2), chunks=(4, 2), dtype="i2",
        ...                         fill_value=0, compressors=make_compressors("zstd", 1, 2))
        >>> codec = ChunkCodec(arr)
        >>> codec.compressor, codec.checksum, codec.chunk_shape
        ('zstd', True, (4, 2))
        >>> data = b"".join(bytes(b) for b in codec.encode(np.ones((4, 2), "i2")))
        >>> len(data) > 4
        True
    """

    def __init__(self, arr: Any) -> None:
        meta = arr.metadata
        pipe = parse_pipeline(arr)
        self.dtype, self.checksum, self.compressor, chunks = pipe.dtype, pipe.checksum, pipe.kind, pipe.chunk_shape
        self._encode: Callable[[np.ndarray], bytes] | None = None
        c = pipe.compressor
        if pipe.kind == "blosc":
            self._encode = Blosc(cname=_value(c.cname), clevel=int(c.clevel), shuffle=_SHUFFLE[_value(c.shuffle)],
                                 blocksize=int(c.blocksize), typesize=int(c.typesize)).encode
        elif pipe.kind == "zstd":
            self._encode = Zstd(level=int(c.level), checksum=bool(c.checksum)).encode
        self.chunk_shape = chunks
        self.shape0 = int(arr.shape[0])
        self.fill_value = meta.fill_value
        self.path = arr.path
        self._key = meta.encode_chunk_key

    def key(self, c: int) -> str:
        """The store key of row chunk ``c``."""
        return f"{self.path}/{self._key((c, *([0] * (len(self.chunk_shape) - 1))))}"

    def covers(self, c: int, nrows: int) -> bool:
        """Whether ``nrows`` rows written from row chunk ``c``'s start replace the whole chunk (no read needed)."""
        lo = c * self.chunk_shape[0]
        return nrows > 0 and lo + nrows == min(lo + self.chunk_shape[0], self.shape0)

    def encode(self, values: np.ndarray) -> list:
        """The chunk file's bytes for ``values`` (the chunk's rows from its start; the rest is the fill value).

        Returns the buffers to write one after another (the encoded data, then its crc32c).
        """
        values = np.asarray(values)
        if values.shape[1:] != self.chunk_shape[1:] or not 0 < values.shape[0] <= self.chunk_shape[0]:
            raise ValueError(f"{values.shape} rows do not fit a chunk of shape {self.chunk_shape}")
        le = self.dtype.newbyteorder("<") if self.dtype.itemsize > 1 else self.dtype
        if values.shape[0] < self.chunk_shape[0]:  # the array's last chunk: padded as Zarr pads it
            full = np.full(self.chunk_shape, self.fill_value, dtype=le)
            full[: values.shape[0]] = values
            values = full
        raw = np.ascontiguousarray(values, dtype=le).reshape(-1).view(np.uint8)
        data = raw if self._encode is None else self._encode(raw)
        if not self.checksum:
            return [data]
        return [data, np.uint32(google_crc32c.value(data)).tobytes()]


def _value(x: Any) -> Any:
    return getattr(x, "value", x)


def plan_array(arr: Any) -> tuple[str, ChunkCodec, Callable[[str], None]] | None:
    """``(root, codec, check)`` to write ``arr``'s chunks here, or ``None`` where Zarr must (not a local store...).

    ``check(key)`` is the store's own folder check (a :mod:`.contained` store), or a
    :class:`~.contained.FolderCheck` of its root for a plain ``LocalStore``.
    """
    store = getattr(arr, "store", None)
    if not isinstance(store, LocalStore) or store.read_only:
        return None
    try:
        codec = ChunkCodec(arr)
    except (ValueError, AttributeError, TypeError, KeyError):
        return None
    root = os.fspath(store.root)
    check = getattr(store, "check", None)
    return root, codec, check if callable(check) else FolderCheck(root)


def write_file(root: str, key: str, buffers: list, check: Callable[[str], None] | None = None) -> None:
    """Writes ``buffers`` (one after another) as the file ``key`` below ``root``, atomically.

    A temporary ``NAME.<uuid>.partial`` file in the file's own folder, then ``os.replace``.
    ``check(key)`` (default: a :class:`~.contained.FolderCheck` of ``root``) refuses a folder on the
    way that is a link.
    """
    (FolderCheck(root) if check is None else check)(key)
    folder, _, name = key.rpartition("/")
    where = os.path.join(root, folder) if folder else root
    os.makedirs(where, exist_ok=True)  # below the root only: the folders on the way were checked
    final = os.path.join(where, name)
    tmp = f"{final}.{uuid.uuid4().hex}.partial"
    fd = os.open(tmp, _FLAGS, 0o666)
    try:
        try:
            for buf in buffers:
                view = memoryview(buf).cast("B")
                while view:
                    view = view[os.write(fd, view):]
        finally:
            os.close(fd)
        os.replace(tmp, final)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_chunks(array: Callable[[str], Any], payload: dict[int, dict[str, np.ndarray]], rows: int, prefix: str = "",
                 *, plans: dict | None = None, threads: int | None = None) -> None:
    """Writes ``payload`` (chunk id -> array path -> rows from the chunk's start) to the arrays ``array(path)`` opens.

    A chunk of a local array with a pipeline :class:`ChunkCodec` encodes is encoded and written here
    (:func:`write_file`), on up to ``threads`` threads; any other through Zarr's ``setitem``. Every
    write ends before the first error is raised: none may still write a file once the caller handles it.

    Args:
        array: ``array(path)`` -> the ``zarr.Array`` (a handle that writes all-zero chunks too).
        payload (dict): the chunks' rows.
        rows (int): rows per chunk.
        prefix (str): put before every path (``"_journal/"``).

    Keyword Args:
        plans (dict, optional): a cache of :func:`plan_array` by path, kept by the caller (its handles
            are compared: a reopened array is planned again).
        threads (int, optional): threads at most (default: the CPUs, at most :data:`MAX_THREADS`).
    """
    plans = {} if plans is None else plans
    direct, via_zarr = [], []
    for c, arrays in payload.items():
        for path, values in arrays.items():
            arr = array(prefix + path)
            cached = plans.get(prefix + path)
            if cached is None or cached[0] is not arr:
                cached = plans[prefix + path] = (arr, plan_array(arr))
            plan = cached[1]
            if plan is not None and plan[1].chunk_shape[0] == rows and plan[1].covers(c, len(values)):
                direct.append((plan, c, values))
            else:
                via_zarr.append((arr, c, values))

    def one(task: tuple) -> None:
        (root, codec, check), c, values = task
        write_file(root, codec.key(c), codec.encode(values), check)

    errors: list[BaseException] = []
    n = usable_cpus(len(direct), MAX_THREADS) if threads is None else max(1, min(threads, len(direct)))
    if n <= 1:
        for task in direct:
            try:
                one(task)
            except BaseException as err:  # noqa: BLE001 - the rest are written first, then it is raised
                errors.append(err)
    else:
        with ThreadPoolExecutor(n, thread_name_prefix="robotmem-write") as pool:
            for fut in [pool.submit(one, task) for task in direct]:
                err = fut.exception()
                if err is not None:
                    errors.append(err)
    if via_zarr:
        writes = [arr._async_array.setitem(slice(c * rows, c * rows + len(values)), values)
                  for arr, c, values in via_zarr]

        async def _all() -> list:
            return await asyncio.gather(*writes, return_exceptions=True)

        errors += [r for r in zarr_sync(_all()) if isinstance(r, BaseException)]
    if errors:
        raise errors[0]
