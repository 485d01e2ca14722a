"""The packed rows of a store in a memory-mapped file, and the seal that says when that file may be served.

A local store keeps its packed rows (:class:`~.layout.PackedLayout`) in ``_rows/rows.bin``, mapped into
the process (``mmap``): the OS page cache is the RAM tier, so resident memory follows the rows a process
touches, never the memory's size, and pages the process no longer touches can be reclaimed. The file is a
cache of the committed Zarr chunks, never the durable copy.

When the file may be served without reading a chunk: ``_rows/seal.json`` says so. A writer writes it at a
clean close, after its last commit and an ``fsync`` of the file; it binds

- the commit record (a sha256 of the record's canonical JSON, :func:`record_digest`),
- the layout (row bytes, each column's offset, dtype and shape, the rows mapped),
- the file itself (device, inode, size and modification time: a file replaced, grown or written since the
  seal does not match).

A writer removes the seal before its first write into the file, so a killed writer leaves no seal and the
next open fills the file from the chunks. Anything that does not match is filled again, never served.

Locks keep a reader's rows the committed ones: a reader that maps ``rows.bin`` holds ``flock(LOCK_SH)`` on
it; a writer writes in place only if it gets ``flock(LOCK_EX | LOCK_NB)`` (and the file has no other
name); otherwise it writes a file of its own (``rows.<pid>.bin``), renamed over ``rows.bin`` at its clean
close (a reader keeps its inode). A reader that finds no usable seal (a writer is active, a crash) fills a
private file in the cache directory (``$TORCHRL_ROBOTMEM_CACHE``, else the system's temporary directory),
unlinked as soon as it is made, so nothing is left behind whatever happens to the process.

Example:
    >>> import tempfile, torch
    >>> from torchrl_robotmem.storage.rowfile import RowFile
    >>> d = tempfile.mkdtemp()
    >>> rows = RowFile(d, read_only=False)
    >>> rows.open({"len": 0}, layout=None)
    False
    >>> packed = rows.map((4,), 8)
    >>> packed[:2] = 7
    >>> rows.seal({"len": 2}, layout={"row_bytes": 8})
    >>> rows.release()
    >>> again = RowFile(d, read_only=True)
    >>> again.open({"len": 2}, layout={"row_bytes": 8}), again.map((4,), 8)[1].tolist()
    (True, [7, 7, 7, 7, 7, 7, 7, 7])
    >>> again.release()
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import itertools
import json
import math
import mmap
import os
import secrets
import tempfile
from typing import Any

import torch

from .contained import open_regular
from .prefault import Prefault

__all__ = ["CACHE_ENV", "ROWS_DIR", "ROWS_FILE", "SEAL_FILE", "RowFile", "record_digest", "remove_rows", "rows_layout",
           "url_cache_dir"]

ROWS_DIR = "_rows"
ROWS_FILE = "rows.bin"
SEAL_FILE = "seal.json"
SEAL_VERSION = 1
#: the directory a reader's private row file goes to (default: the system's temporary directory), and the
#: root of the row files of URL stores (default: ``$XDG_CACHE_HOME/torchrl_robotmem``, ``~/.cache/...``)
CACHE_ENV = "TORCHRL_ROBOTMEM_CACHE"
_NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
_SERIAL = itertools.count(1)  # names a writer's own files apart within the process


def url_cache_dir(url: str, storage_options: dict | None = None) -> str:
    """The local folder that holds the row file of the store at ``url`` (an ``s3://`` store, say).

    One folder per store URL and set of fsspec options (another endpoint is another store), named by
    their sha256: ``$TORCHRL_ROBOTMEM_CACHE/stores/<digest>`` (default root ``$XDG_CACHE_HOME/torchrl_robotmem``,
    else ``~/.cache/torchrl_robotmem``). It holds ``_rows/`` as a local store does, sealed by the writer's
    clean close for the record it committed; the record names the writing session, so a store replaced
    at the same URL never matches a seal of the one before. Deleting the folder loses nothing.

    Example:
        >>> url_cache_dir("s3://bucket/run.zarr") == url_cache_dir("s3://bucket/run.zarr", {})
        True
        >>> url_cache_dir("s3://bucket/run.zarr") != url_cache_dir("s3://bucket/run.zarr", {"endpoint_url": "x"})
        True
    """
    root = os.environ.get(CACHE_ENV) or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "torchrl_robotmem")
    key = json.dumps([url, storage_options or {}], sort_keys=True, default=str)
    return os.path.join(root, "stores", hashlib.sha256(key.encode()).hexdigest()[:32])


def record_digest(attrs: dict) -> str:
    """The sha256 of a commit record's canonical JSON (keys sorted): what a seal binds the rows to.

    Example:
        >>> record_digest({"len": 1, "cursor": 1}) == record_digest({"cursor": 1, "len": 1})
        True
    """
    text = json.dumps(attrs, sort_keys=True, separators=(",", ":"), allow_nan=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def rows_layout(layout: Any, shape: tuple[int, ...]) -> dict:
    """What a seal binds the rows to: a :class:`~.layout.PackedLayout`'s row bytes and fields, and the rows' shape.

    Example:
        >>> from torchrl_robotmem.storage.layout import PackedLayout
        >>> rows_layout(PackedLayout({"x": {"dtype": "float32", "shape": [2]}}), (10,))
        {'row_bytes': 8, 'fields': [['x', 0, 8, 'float32', [2]]], 'shape': [10]}
    """
    fields = [[p, off, nbytes, str(dtype).removeprefix("torch."), list(shape_)]
              for p, off, nbytes, dtype, shape_ in layout.fields]
    return {"row_bytes": layout.row_bytes, "fields": fields, "shape": [int(s) for s in shape]}


def remove_rows(directory: str | os.PathLike) -> bool:
    """Deletes a local store's row files and seal (a cache: the next open fills it from the chunks).

    Returns whether there was anything to delete. ``robotmem repair`` calls it.

    Example:
        >>> import tempfile
        >>> remove_rows(tempfile.mkdtemp())
        False
    """
    folder = os.path.join(os.fspath(directory), ROWS_DIR)
    try:
        names = os.listdir(folder)
    except FileNotFoundError:
        return False
    for name in names:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(os.path.join(folder, name))
    with contextlib.suppress(OSError):
        os.rmdir(folder)
    return True


def _fsync_dir(path: str) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _lock(fd: int, how: int) -> bool:
    try:
        fcntl.flock(fd, how | fcntl.LOCK_NB)
        return True
    except OSError as err:
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        raise


class RowFile:
    """The file one open store maps its packed rows from, with its lock, and the seal it checks and writes.

    Args:
        directory (str or None): the local store's directory; ``None`` for a store with none (a URL store),
            whose rows always go to a private file in the cache directory.

    Keyword Args:
        read_only (bool): a reader (maps the store's file copy-on-write, never writes the store).

    Example:
        >>> import tempfile
        >>> rows = RowFile(None, read_only=True)
        >>> rows.open({"len": 0}, layout=None)
        False
        >>> rows.map((2, 3), 8).shape
        torch.Size([2, 3, 8])
        >>> rows.release()
    """

    def __init__(self, directory: str | os.PathLike | None, *, read_only: bool) -> None:
        self.folder = None if directory is None else os.path.join(os.fspath(directory), ROWS_DIR)
        self.read_only = bool(read_only)
        self.fd: int | None = None
        self.name: str | None = None  # the path of the file in use (None: a private, unlinked file)
        self.copy_on_write = False  # a reader mapping the store's sealed file
        self.sealed = False  # the file in use holds the rows of the record it was opened for
        self.claimed = False  # a writer has unsealed the file for its writes (claim)
        self.open_ends: list[int] = []  # the seal's rows that end an episode left open (see ``seal``)
        self.maps: list[mmap.mmap] = []  # the newest mappings (a growth maps again; older views keep theirs)
        self.retired: int | None = None  # the file a new layout moved from (closed at release)
        self.made_folder = False  # this handle made ``_rows/`` (an open that fails removes it again)
        self.in_memory = False  # no room for the file: the rows live in private pages (a growth copies them)
        self.scans = 0  # scans under way (readahead on while > 0, see ``scanning``)
        self.ahead = Prefault()  # a writer's pages mapped ahead of its writes (see ``written``)

    # -- choosing the file ---------------------------------------------------------------------

    def open(self, attrs: dict, *, layout: dict | None) -> bool:
        """Picks the file for the record ``attrs`` and locks it; returns whether it holds that record's rows.

        ``layout`` is what :meth:`seal` was given for the rows (``None``: no rows yet, nothing to match).
        """
        self.release()
        if self.folder is not None:
            if self.read_only:
                if self._open_shared(attrs, layout):
                    return True
            else:
                return self._open_writer(attrs, layout)  # a file of its own is made when the rows are mapped
        self._open_private()
        return False

    def _open_shared(self, attrs: dict, layout: dict | None) -> bool:
        """A reader: the store's file, if sealed for ``attrs`` and no writer writes it."""
        path = os.path.join(self.folder, ROWS_FILE)
        try:
            fd = open_regular(path, os.O_RDONLY)
        except OSError:
            return False  # no file, a link (ELOOP), a special file, no permission: fill a private one
        if _lock(fd, fcntl.LOCK_SH):
            seal = self._matching_seal(fd, attrs, layout)
            if seal is not None:
                self.fd, self.name, self.copy_on_write, self.sealed = fd, path, True, True
                self.open_ends = [int(r) for r in seal.get("open_ends", [])]
                return True
        os.close(fd)
        return False

    def _open_writer(self, attrs: dict, layout: dict | None) -> bool:
        """A writer: the store's file, in place, if sealed for ``attrs`` and no reader maps it.

        Anything else gets a file of its own when the rows are mapped (:meth:`map`), renamed over
        ``rows.bin`` at the clean close: an open that fails after this leaves the store as it found it.
        Nothing is written here; :meth:`claim` unseals once the open succeeded.
        """
        path = os.path.join(self.folder, ROWS_FILE)
        try:
            fd = open_regular(path, os.O_RDWR)
        except OSError:
            return False  # none yet (or not a file this writer may use)
        if _lock(fd, fcntl.LOCK_EX) and os.fstat(fd).st_nlink == 1:
            seal = self._matching_seal(fd, attrs, layout)
            if seal is not None:
                self.fd, self.name, self.sealed = fd, path, True
                self.open_ends = [int(r) for r in seal.get("open_ends", [])]
                return True
        os.close(fd)  # stale, mapped by a reader, or linked under another name: never written in place
        return False

    def claim(self) -> None:
        """Before a writer's first write into the file: removes the seal (from then on the file may run ahead
        of the commits) and the own files of writers that are gone. Called by the mapping's owner
        (:class:`~.mirror.RamMirror`) before each write; only the first call does anything, so an open that
        writes nothing (a reader's, a failed one, a writer that only samples) changes nothing here."""
        if self.claimed or self.read_only or self.folder is None or not os.path.isdir(self.folder):
            return
        self.claimed = True
        if self.name == os.path.join(self.folder, ROWS_FILE):
            self._unseal()
        self._remove_stale()

    @contextlib.contextmanager
    def scanning(self):
        """Readahead on while a column is read across all rows (a goal index's snapshot, a summary).

        The mapping is advised ``MADV_RANDOM`` otherwise: a sample touches rows anywhere, so a fault
        reads its own page rather than the 128 KB around it, which a memory-limited process would
        have to reclaim again at once (at 100M rows in a cgroup of a quarter of the rows: 28 s for an
        open and 1,000 cold samples, against not done in 300 s with readahead). A scan reads every page
        in order, where readahead is what makes it fast; nested and concurrent scans count.
        """
        self.scans += 1
        if self.scans == 1:
            for m in self.maps:
                _advise(m, scan=True)
        try:
            yield
        finally:
            self.scans -= 1
            if self.scans == 0:
                for m in self.maps:
                    _advise(m, scan=False)

    def discard(self) -> None:
        """An open that failed: deletes the file of its own this open made, releases the rest."""
        own = self.name if self.name is not None and not self.name.endswith(os.sep + ROWS_FILE) else None
        self.release()
        if own is not None and not self.read_only:
            with contextlib.suppress(OSError):
                os.unlink(own)
        if self.made_folder:
            with contextlib.suppress(OSError):
                os.rmdir(self.folder)

    def _open_own(self) -> None:
        """A writer's own file in the store's folder, renamed over ``rows.bin`` at its clean close."""
        if not os.path.isdir(self.folder):
            os.mkdir(self.folder)
            self.made_folder = True
        path = os.path.join(self.folder, f"rows.{os.getpid()}.{next(_SERIAL)}.bin")
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX)
        self.fd, self.name, self.sealed = fd, path, False

    def _open_private(self) -> None:
        """A file nobody else sees, unlinked at once: a reader's rows (or a store without a directory)."""
        folder = os.environ.get(CACHE_ENV) or tempfile.gettempdir()
        os.makedirs(folder, exist_ok=True)
        fd, path = tempfile.mkstemp(prefix="robotmem-rows-", suffix=".bin", dir=folder)
        os.unlink(path)
        self.fd, self.name, self.sealed = fd, None, False

    def _remove_stale(self) -> None:
        """Deletes the own files of writers that are gone (a killed writer leaves its ``rows.<pid>.*.bin``)."""
        for name in os.listdir(self.folder):
            if name == ROWS_FILE or not (name.startswith("rows.") and name.endswith((".bin", ".tmp"))):
                continue
            path = os.path.join(self.folder, name)
            try:
                fd = open_regular(path, os.O_RDONLY)
            except OSError:
                continue
            try:
                if _lock(fd, fcntl.LOCK_EX):  # no live writer holds it
                    os.unlink(path)
            finally:
                os.close(fd)

    # -- the seal -----------------------------------------------------------------------------

    def _seal_path(self) -> str:
        return os.path.join(self.folder, SEAL_FILE)

    def _matching_seal(self, fd: int, attrs: dict, layout: dict | None) -> dict | None:
        """The seal, if it binds this file (``fd``) to the record ``attrs`` and ``layout``; else ``None``."""
        if layout is None:
            return None
        try:
            sfd = open_regular(self._seal_path(), os.O_RDONLY)
        except OSError:
            return None
        try:
            with os.fdopen(sfd, "rb") as f:
                seal = json.loads(f.read(1 << 20))
        except (OSError, ValueError):
            return None
        st = os.fstat(fd)
        want = {"version": SEAL_VERSION, "record": record_digest(attrs), "layout": layout,
                "file": [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns]}
        if not isinstance(seal, dict) or any(seal.get(k) != v for k, v in want.items()):
            return None
        if not isinstance(seal.get("open_ends", []), list):
            return None
        return seal

    def _unseal(self) -> None:
        # no fsync: a killed process's unlink is seen by the next open (the page cache outlives it), and the
        # commits themselves are not synced either (a power loss is what `fsync` after flush() guards against)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self._seal_path())

    def seal(self, attrs: dict, *, layout: dict, open_ends: list[int] = ()) -> None:
        """A writer's clean close: makes the file durable, names it ``rows.bin`` and seals it for ``attrs``.

        ``open_ends`` are the rows that end an episode left open (the next writer marks them done without
        scanning the rows). Does nothing for a reader or a private file.
        """
        if self.read_only or self.folder is None or self.name is None or self.fd is None or self.in_memory:
            return
        for m in self.maps[-1:]:
            m.flush()
        os.fsync(self.fd)
        target = os.path.join(self.folder, ROWS_FILE)
        if self.name != target:
            os.replace(self.name, target)
            self.name = target
        st = os.fstat(self.fd)
        seal = {"version": SEAL_VERSION, "record": record_digest(attrs), "layout": layout,
                "file": [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns], "open_ends": [int(r) for r in open_ends]}
        tmp = os.path.join(self.folder, f"seal.{os.getpid()}.{secrets.token_hex(4)}.tmp")
        # a new file of its own (O_EXCL | O_NOFOLLOW): a name the store already holds, a link (soft or
        # hard) to a file outside it, is never opened, let alone written
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
        with os.fdopen(fd, "w") as f:
            json.dump(seal, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self._seal_path())
        _fsync_dir(self.folder)
        self.sealed = True

    # -- mapping ------------------------------------------------------------------------------

    def map(self, shape: tuple[int, ...], row_bytes: int, *, new_file: bool = False) -> torch.Tensor:
        """The packed rows ``[*shape, row_bytes]`` as a ``uint8`` tensor over the file (grown if smaller).

        ``new_file``: the rows get a layout of their own (a column added), in a file of their own; the
        caller copies the old rows over from the views it holds.
        """
        if new_file:
            self._switch_file()
        elif self.fd is None:  # a writer's first mapping, or a reader's
            self._open_private() if self.read_only or self.folder is None else self._open_own()
        nbytes = math.prod(shape) * int(row_bytes)
        size = os.fstat(self.fd).st_size
        if self.copy_on_write:
            if size < nbytes:
                raise RuntimeError(f"the sealed row file {self.name!r} holds {size} bytes, not {nbytes}")
            access = mmap.ACCESS_COPY  # a reader's writes (none are made) would stay in its own pages
        elif self.in_memory:
            access = None
        else:
            try:
                if size < nbytes:
                    os.ftruncate(self.fd, nbytes)
                # the blocks taken now: a write into the mapping never meets a full disk (which is SIGBUS)
                os.posix_fallocate(self.fd, 0, max(nbytes, 1))
                access = mmap.ACCESS_WRITE
            except OSError as err:
                if err.errno not in _NO_ROOM:
                    raise
                self.in_memory = True
                access = None
        if access is None:
            # no room on the disk for the file: anonymous memory, as the rows were before the row tier (a
            # private mapping of the file is no way out: a hole of a full tmpfs faults as SIGBUS); the rows
            # the file holds are read over, with read(), which meets no hole
            m = mmap.mmap(-1, max(nbytes, 1))
            view, done = memoryview(m), 0
            while done < min(size, nbytes):
                got = os.preadv(self.fd, [view[done:min(size, nbytes)]], done)
                if got <= 0:
                    break
                done += got
        else:
            m = mmap.mmap(self.fd, max(nbytes, 1), access=access)
            _advise(m, scan=self.scans > 0)
            if access == mmap.ACCESS_WRITE:
                self.ahead.mapped(m, nbytes)
        self.maps = [*self.maps[-1:], m]  # older mappings stay alive through the views that use them
        return torch.frombuffer(m, dtype=torch.uint8, count=nbytes).view(*shape, int(row_bytes))

    def _switch_file(self) -> None:
        """Moves to a fresh file (a new layout): the old one's lock is released once the rows are copied."""
        if self.retired is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self.retired, fcntl.LOCK_UN)
                os.close(self.retired)
        old = self.fd
        if self.read_only or self.folder is None:
            self._open_private()
        else:
            self._open_own()
        self.copy_on_write = False
        self.retired = old  # closed at release (the old views still map it until the copy is done)

    def written(self, end: int) -> None:
        """A write into the mapping ended at byte ``end``: the pages past it are mapped ahead (:mod:`.prefault`)."""
        self.ahead.written(end)

    def release(self) -> None:
        """Releases the file and its lock (mapped views stay readable until dropped). Idempotent."""
        self.ahead.stop()
        for fd in (self.fd, self.retired):
            if fd is not None:
                with contextlib.suppress(OSError):
                    fcntl.flock(fd, fcntl.LOCK_UN)  # a mapping shares the lock (mmap keeps a dup of fd)
                    os.close(fd)
        self.fd, self.retired, self.maps, self.copy_on_write = None, None, [], False

    def describe(self) -> dict[str, Any]:
        """Where the rows are mapped from: ``{"file", "sealed", "shared"}`` (for ``summary`` and tests).

        Example:
            >>> rows = RowFile(None, read_only=True); _ = rows.open({}, layout=None)
            >>> rows.describe()["file"] is None
            True
            >>> rows.release()
        """
        return {"file": self.name, "sealed": self.sealed, "shared": self.copy_on_write}


def _advise(m: mmap.mmap, *, scan: bool) -> None:
    """``MADV_NORMAL`` (the kernel's readahead) for a scan, else ``MADV_RANDOM``; nothing where unsupported."""
    advice = getattr(mmap, "MADV_NORMAL" if scan else "MADV_RANDOM", None)
    if advice is not None:
        with contextlib.suppress(OSError, ValueError):  # a closed mapping (a view outlived it), or no support
            m.madvise(advice)
