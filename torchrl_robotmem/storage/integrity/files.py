"""A store's files as bytes, for ``verify`` and ``repair``: reading a store Zarr cannot open, writing only inside it.

``verify`` and ``repair`` must read stores whose metadata is damaged (no group
``zarr.json``, an array's ``zarr.json`` unreadable), so they read and write keys
as bytes. Every write goes through :func:`set_bytes` / :func:`delete_key`,
which refuse a key that would leave the store's folder or pass a symbolic link.

Example:
    >>> import tempfile, torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity.files import array_metas, open_any, read_group_attrs
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> store, local_dir = open_any(path, None)
    >>> array_metas(store, local_dir), read_group_attrs(store)[0]["len"]
    (['env', 'episode', 'obs', 'run'], 10)
"""
from __future__ import annotations

import json
import os
from typing import Any

from zarr.core.buffer import default_buffer_prototype
from zarr.core.sync import sync as zarr_sync

from .. import _backend
from ..errors import NotAMemoryError, Problem
from ..format import BACKUP_DIR, JOURNAL_DIR

__all__ = ["array_metas", "delete_key", "get_bytes", "local_dir_of", "open_any", "read_group_attrs", "set_bytes"]


def get_bytes(store: Any, key: str) -> bytes | None:
    buf = zarr_sync(store.get(key, prototype=default_buffer_prototype()))
    return None if buf is None else buf.to_bytes()


def set_bytes(store: Any, key: str, data: bytes, local_dir: Any = None) -> None:
    _check_key(key, local_dir)
    zarr_sync(store.set(key, default_buffer_prototype().buffer.from_bytes(data)))


def delete_key(store: Any, key: str, local_dir: Any) -> None:
    _check_key(key, local_dir)
    zarr_sync(store.delete(key))


def _check_key(key: str, local_dir: Any) -> None:
    """Raises unless ``key`` names a file inside the store, reached through no symbolic link (``repair``'s writes)."""
    parts = key.split("/")
    bad = key.startswith("/") or "\\" in key or any(p in ("", ".", "..") for p in parts)
    if not bad and local_dir is not None:
        root = os.path.realpath(os.fspath(local_dir))
        full = os.path.join(root, *parts)
        node = root
        for part in parts:
            node = os.path.join(node, part)
            if os.path.islink(node):
                bad = True
                break
        bad = bad or os.path.commonpath([root, os.path.realpath(full)]) != root
    if bad:
        raise RuntimeError(f"repair refused to write {key!r}: not a file inside the store {local_dir}.")


def open_any(path: Any, storage_options: dict | None, *, writable: bool = False):
    """``(store, local_dir)`` of a memory, damaged or not, or :class:`NotAMemoryError`.

    A directory whose group ``zarr.json`` is gone still counts as a memory when
    it holds this library's layout (an ``episode`` or ``_tensor`` array).
    """
    name = _backend.normalize_path(path)
    if isinstance(name, str) and not _backend.is_url(name) and not name.endswith(".zip"):
        name = os.path.realpath(name)  # the root the user named is followed; links below it are reported
        if not os.path.isdir(name):
            raise NotAMemoryError(f"{name!r} is not a directory" if os.path.exists(name) else f"{name!r} does not exist")
        if not any(os.path.lexists(os.path.join(name, *rel)) for rel in
                   (("zarr.json",), ("episode", "zarr.json"), ("_tensor", "zarr.json"))):
            raise NotAMemoryError(f"{name!r} holds no zarr.json: not a Zarr store")
        from zarr.storage import LocalStore

        return LocalStore(name, read_only=not writable), name
    if isinstance(name, str) and name.endswith(".zip") and not _backend.is_url(name) and not os.path.exists(name):
        raise NotAMemoryError(f"{name!r} does not exist")  # never created by a command that mends a store
    try:
        return _backend.open_store(name, read_only=not writable, storage_options=storage_options)
    except (FileNotFoundError, ValueError) as err:
        raise NotAMemoryError(str(err)) from None


def array_metas(store: Any, local_dir: Any) -> list[str]:
    """Paths of every node metadata file below the root (``next/observation``), journal and backups excluded."""
    if local_dir is not None:
        keys = set()
        for dirpath, dirs, files in os.walk(os.fspath(local_dir)):
            # a column's chunk folder ("c" with no zarr.json of its own: a node may be named "c" too)
            dirs[:] = [d for d in dirs if d not in (JOURNAL_DIR, BACKUP_DIR)
                       and not (d == "c" and not os.path.lexists(os.path.join(dirpath, d, "zarr.json")))]
            if "zarr.json" in files and os.path.abspath(dirpath) != os.path.abspath(os.fspath(local_dir)):
                keys.add(os.path.relpath(dirpath, os.fspath(local_dir)).replace(os.sep, "/"))
        return sorted(keys)

    async def _collect():
        return [k async for k in store.list_prefix("")]

    return sorted({k[: -len("/zarr.json")] for k in zarr_sync(_collect())
                   if k.endswith("/zarr.json")  # never a chunk key (its parts after "c" are numbers)
                   and not k.startswith((JOURNAL_DIR + "/", BACKUP_DIR + "/"))})


def read_group_attrs(store: Any) -> tuple[dict | None, Problem | None]:
    raw = get_bytes(store, "zarr.json")
    if raw is None:
        return None, Problem("metadata", "group metadata missing (no zarr.json)", key="zarr.json")
    try:
        meta = json.loads(raw)
        if not isinstance(meta, dict) or meta.get("node_type") != "group":
            raise ValueError(f"not a group document (node_type {meta.get('node_type') if isinstance(meta, dict) else None!r})")
        attrs = meta.get("attributes") or {}
        if not isinstance(attrs, dict):
            raise ValueError("attributes are not a JSON object")
    except ValueError as err:
        return None, Problem("metadata", f"group metadata unreadable ({str(err)[:100]})", key="zarr.json")
    return attrs, None


def local_dir_of(store: Any) -> Any:
    root = getattr(store, "root", None)
    return root if root is not None and os.path.isdir(os.fspath(root)) else None
