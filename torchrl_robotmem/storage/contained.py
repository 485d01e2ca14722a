"""Writes that stay inside a local store: nothing a writer writes or deletes goes through a symbolic link.

A writer's open does not walk every chunk folder for links (that walk costs a listing per chunk,
seconds at tens of millions of rows). Instead each folder a write or delete goes into is looked at
the first time this writer uses it: every directory from the store's root down to the file's folder
must be a directory, not a symbolic link (``lstat``, no link followed); a link refuses the write
with ``ELOOP``, naming the key and the link, and nothing is written. Folders already looked at are
remembered, so a folder costs one look per writer.

This module imports only the standard library and Zarr: the commit worker (``_commit_worker.py``)
loads it by path without the package.

Example:
    >>> import os, tempfile
    >>> root, outside = tempfile.mkdtemp(), tempfile.mkdtemp()
    >>> os.makedirs(root + "/obs"); os.symlink(outside, root + "/obs/c")
    >>> check = FolderCheck(root)
    >>> try:
    ...     check("obs/c/0")
    ... except OSError as err:
    ...     print(err.strerror.split(" (->")[0])
    refusing to write 'obs/c/0': 'obs/c' is a symbolic link inside the store
    >>> check("obs/zarr.json")  # 'obs' itself is a folder
"""
from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from zarr.storage import LocalStore

__all__ = ["ContainedStore", "FolderCheck", "open_regular"]



def open_regular(path: str, flags: int = os.O_RDONLY) -> int:
    """``os.open`` of a regular file below a store: never through a link at its name (``ELOOP``), never blocking
    on a named pipe or a device (opened non-blocking, then refused unless ``fstat`` says it is a regular file:
    ``OSError(EINVAL)``). The one way this package opens a file it reads without a Zarr store in between.

    Example:
        >>> import os, tempfile
        >>> d = tempfile.mkdtemp(); os.mkfifo(d + "/pipe")
        >>> try:
        ...     open_regular(d + "/pipe")
        ... except OSError as err:
        ...     print(err.strerror)
        not a regular file
    """
    fd = os.open(path, flags | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OSError(errno.EINVAL, "not a regular file", path)
    return fd

class FolderCheck:
    """Looks at the folders on the way to a key once each; refuses a symbolic link among them.

    Args:
        root (str or Path): the store's root directory (already resolved: the path a user named is
            followed once, see ``_backend.open_store``).
    """

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = os.fspath(root)
        self._seen: set[str] = set()

    def __call__(self, key: str) -> None:
        """Raises ``OSError(ELOOP)`` if a folder on the way from the root to ``key`` is a symbolic link."""
        folder = key.rpartition("/")[0]
        if folder in self._seen or not folder:
            return
        parts = folder.split("/")
        for i in range(1, len(parts) + 1):
            rel = "/".join(parts[:i])
            if rel in self._seen:
                continue
            full = os.path.join(self.root, rel)
            try:
                mode = os.lstat(full).st_mode
            except FileNotFoundError:
                return  # created by the write, as a directory (nothing below it exists yet)
            if stat.S_ISLNK(mode):
                try:
                    target = os.readlink(full)
                except OSError:
                    target = "?"
                raise OSError(errno.ELOOP, f"refusing to write {key!r}: {rel!r} is a symbolic link inside the "
                                           f"store (-> {target}); nothing was written through it", full)
            if not stat.S_ISDIR(mode):
                raise NotADirectoryError(errno.ENOTDIR, f"refusing to write {key!r}: {rel!r} is a file, "
                                                        f"not a folder of the store", full)
            self._seen.add(rel)  # a set: threads that add the same folder at once agree


class ContainedStore(LocalStore):
    """A writable Zarr ``LocalStore`` whose writes and deletes never go through a symbolic link.

    Used by a store's writer (and its commit worker) for a local store: every ``set`` / ``delete``
    first passes :class:`FolderCheck`. Reads are not checked here: a reader or writer that reads chunks
    walks their folders for links first (``_backend.refuse_links``).

    Args:
        root (str or Path): the store's root directory.
        read_only (bool): as ``LocalStore`` takes it.
    """

    def __init__(self, root: Path | str, *, read_only: bool = False) -> None:
        super().__init__(root, read_only=read_only)
        self.check = FolderCheck(self.root)

    async def _set(self, key: str, value, exclusive: bool = False) -> None:
        self.check(key)
        await super()._set(key, value, exclusive=exclusive)

    def set_sync(self, key: str, value) -> None:
        self.check(key)
        super().set_sync(key, value)

    async def delete(self, key: str) -> None:
        self.check(key)
        await super().delete(key)

    def delete_sync(self, key: str) -> None:
        self.check(key)
        super().delete_sync(key)

    async def delete_dir(self, prefix: str) -> None:
        self.check(prefix.rstrip("/") + "/x")  # the folder itself, and those above it
        await super().delete_dir(prefix)
