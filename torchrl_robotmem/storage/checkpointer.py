"""``ZarrCheckpointer``: what ``rb.dumps`` / ``rb.loads`` and ``torchrl.checkpoint`` do with a ZarrStorage.

``dumps(path)`` flushes the store and writes a self-contained copy of it to
``path/store.zarr`` plus a small ``zarr_storage.json`` (the source store, its
length and write count). On a local filesystem the copy is made of hard links:
Zarr replaces chunk files by renaming new ones into place, so a linked chunk
never changes afterwards and the copy costs no disk space until the live store
moves on. ``loads(path)`` into the buffer on the same store only puts the
writer back where the store says; into a buffer on another store it copies the
rows (``load_state_dict``), as TorchRL's storages do.
"""
from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from torchrl.data.replay_buffers.checkpointers import StorageCheckpointerBase

from ._backend import refuse_links
from .rowfile import ROWS_DIR

__all__ = ["ZarrCheckpointer"]

_POINTER = "zarr_storage.json"
_COPY = "store.zarr"


def _link_tree(src: Path, dst: Path) -> None:
    """Copies a directory tree with hard links (plain copies across filesystems).

    The caller refused a store holding a link or special file; one made since is copied as the link it is,
    never followed (a later open of the copy refuses it).
    """

    def link(s: str, d: str) -> None:  # a file made a link after the listing: linked or copied as the link
        try:
            os.link(s, d, follow_symlinks=False)
        except OSError:
            shutil.copy2(s, d, follow_symlinks=False)

    if dst.exists():
        shutil.rmtree(dst)
    # the row file is a cache a writer writes in place: never linked (the copy fills its own at its first open)
    shutil.copytree(src, dst, symlinks=True, copy_function=link, ignore=shutil.ignore_patterns("*.partial", ROWS_DIR))


class ZarrCheckpointer(StorageCheckpointerBase):
    """Checkpointer for :class:`~torchrl_robotmem.ZarrStorage` (see the module docstring).

    Args:
        open_copy (callable, optional): opens a checkpoint's copy of a store read-only (``path -> storage``);
            ``ZarrStorage`` passes one building a ``ZarrStorage`` itself, so that subclasses with other
            constructor signatures load checkpoints too. Defaults to ``type(storage)(path, read_only=True)``.
    """

    def __init__(self, open_copy: Callable[[Path], Any] | None = None) -> None:
        self.open_copy = open_copy

    def dumps(self, storage: Any, path: str | os.PathLike) -> None:
        storage.flush()
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        meta = {"store": storage.path, "len": len(storage), "write_count": storage.write_count, "copy": None}
        local = storage.local_dir
        if local is not None:
            # nothing outside the store reaches the checkpoint: a link (or a named pipe) anywhere in it refuses it
            refuse_links(local, storage.path)
            _link_tree(Path(local), path / _COPY)
            meta["copy"] = _COPY
        with open(path / _POINTER, "w") as f:
            json.dump(meta, f)

    def loads(self, storage: Any, path: str | os.PathLike) -> None:
        path = Path(path)
        pointer = path / _POINTER
        if not pointer.exists():
            raise FileNotFoundError(
                f"{pointer} not found: this checkpoint was not written by a buffer on a ZarrStorage."
            )
        with open(pointer) as f:
            meta = json.load(f)
        source = None
        if meta["store"] == storage.path:
            if [meta.get("len"), meta.get("write_count")] == [len(storage), storage.write_count]:
                source = self._open_copy(storage, path, meta)
                if source is None or storage.holds(source.state_dict()):  # as the checkpoint left it (in place
                    _close(source)  # writes and an emptied-and-refilled store have the same counts)
                    storage.resume_writers()
                    return
            if not meta.get("copy"):
                raise ValueError(
                    f"This checkpoint points to the store {storage.path!r} itself, which has moved on since "
                    f"(len {meta.get('len')} -> {len(storage)}, rows written {meta.get('write_count')} -> "
                    f"{storage.write_count}), and holds no copy of it: its rows cannot be restored. To continue "
                    f"from the store's newest rows, build the buffer on it without loads (the writer resumes "
                    f"where the store stopped)."
                )
            # the store moved on: the checkpoint's rows come back from its copy, as TorchRL's storages restore
            # theirs (the writer TorchRL loads next names the checkpoint's rows, not the newer ones)
        elif not meta.get("copy"):
            raise ValueError(
                f"This checkpoint points to the Zarr store {meta['store']!r} and holds no copy of it; "
                f"the buffer's storage is {storage.path!r}. Build the buffer with "
                f"ZarrStorage({meta['store']!r}) to resume from it."
            )
        if source is None:
            source = self._open_copy(storage, path, meta)
        try:
            storage.load_state_dict(source.state_dict())
        finally:
            _close(source)

    def _open_copy(self, storage: Any, path: Path, meta: dict) -> Any:
        """The checkpoint's copy of the store, read-only (``None``: it holds none, a URL store's checkpoint)."""
        if not meta.get("copy"):
            return None
        if self.open_copy is not None:
            return self.open_copy(path / meta["copy"])
        return type(storage)(path / meta["copy"], read_only=True)


def _close(source: Any) -> None:
    """Closes a checkpoint's copy opened by ``loads`` (a storage without ``close``, or ``None``: nothing)."""
    close = getattr(source, "close", None)
    if close is not None:
        close()

