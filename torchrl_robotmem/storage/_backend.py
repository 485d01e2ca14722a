"""The store handle: paths and URLs, the writer lock, codecs, dtypes and key paths.

The one place that turns what a user passes (a directory, ``file://``, an fsspec
URL, a ``*.zip``, a Zarr ``Store``) into a Zarr store, and the one place that
knows how TensorDict keys and torch dtypes map to Zarr arrays. Nothing here
knows about TorchRL.
"""
from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
import zarr
from zarr.codecs import BloscCodec, ZstdCodec

# The format this library writes. Bump on any change readers must know about.
FORMAT_VERSION = 1
FORMAT_MARKER = "torchrl_robotmem"

_TORCH2NP = {
    torch.float16: np.float16,
    torch.float32: np.float32,
    torch.float64: np.float64,
    torch.int8: np.int8,
    torch.int16: np.int16,
    torch.int32: np.int32,
    torch.int64: np.int64,
    torch.uint8: np.uint8,
    torch.bool: np.bool_,
}
_NAME2TORCH = {str(t).replace("torch.", ""): t for t in _TORCH2NP}


def torch_dtype_name(dtype: torch.dtype) -> str:
    if dtype not in _TORCH2NP:
        raise TypeError(
            f"dtype {dtype} cannot be stored in a ZarrStorage; supported dtypes are "
            f"{sorted(_NAME2TORCH)}."
        )
    return str(dtype).replace("torch.", "")


def torch_dtype(name: str) -> torch.dtype:
    try:
        return _NAME2TORCH[name]
    except KeyError:
        raise ValueError(f"Unknown dtype {name!r} recorded in the store schema.") from None


def numpy_dtype(dtype: torch.dtype) -> np.dtype:
    return np.dtype(_TORCH2NP[dtype])


# -- keys ---------------------------------------------------------------------


def key_to_path(key: str | tuple[str, ...]) -> str:
    """``("next", "observation")`` -> ``"next/observation"``."""
    parts = (key,) if isinstance(key, str) else tuple(key)
    for part in parts:
        if "/" in part or not part:
            raise ValueError(
                f"Key {key!r} cannot be stored in a ZarrStorage: key names must be "
                f"non-empty and must not contain '/'."
            )
    return "/".join(parts)


def path_to_key(path: str) -> str | tuple[str, ...]:
    parts = tuple(path.split("/"))
    return parts[0] if len(parts) == 1 else parts


# -- codecs -------------------------------------------------------------------


def make_compressors(compressor: str | None, level: int, itemsize: int):
    """Codec pipeline for one array.

    ``"zstd"`` is Zarr's own codec; ``"blosc"`` is zstd behind a byte shuffle.
    On FetchPush transitions plain zstd was both smaller and faster (see
    docs/benchmarks.md).
    """
    if compressor in (None, "none"):
        return None
    if compressor == "blosc":
        return BloscCodec(
            cname="zstd", clevel=level, shuffle="shuffle" if itemsize > 1 else "noshuffle", typesize=itemsize
        )
    if compressor == "zstd":
        return ZstdCodec(level=level)
    raise ValueError(f"compressor must be 'blosc', 'zstd' or None, got {compressor!r}.")


# -- stores -------------------------------------------------------------------


def is_url(path: str) -> bool:
    return "://" in path


def normalize_path(path: str | os.PathLike | Any) -> str | Any:
    """The canonical name of a store: an absolute local path, a URL, or the Store itself.

    ``file://`` URLs become local paths. Two handles on the same store get the
    same name (it keys the in-process writer registry and checkpoint pointers).
    """
    if not isinstance(path, (str, os.PathLike)):
        return path
    spath = os.fspath(path)
    if spath.startswith("file://"):
        spath = spath[len("file://") :]
    if is_url(spath):
        return spath
    return str(Path(spath).expanduser().absolute())


def store_exists(path: str | os.PathLike | Any) -> bool:
    """Whether ``path`` holds a Zarr group (without creating anything)."""
    name = normalize_path(path)
    if not isinstance(name, str) or is_url(name):
        try:
            open_group(open_store(name, read_only=True, storage_options=None)[0], read_only=True)
            return True
        except Exception:  # noqa: BLE001 - any failure means "no store here"
            return False
    if name.endswith(".zip"):
        return os.path.exists(name)
    return os.path.exists(os.path.join(name, "zarr.json"))


def open_store(path: str | os.PathLike | Any, *, read_only: bool, storage_options: dict | None):
    """Returns ``(store_or_path, local_dir)``.

    ``local_dir`` is the directory of a local store (used for the writer lock),
    else ``None``.
    """
    spath = normalize_path(path)
    if not isinstance(spath, str):
        return spath, None  # a zarr Store instance
    if spath.endswith(".zip") and not is_url(spath):
        from zarr.storage import ZipStore

        if read_only and not os.path.exists(spath):
            raise FileNotFoundError(f"No Zarr zip store at {spath!r}.")
        return ZipStore(spath, mode="r" if read_only else "a"), None
    if is_url(spath):
        from zarr.storage import FsspecStore

        return FsspecStore.from_url(spath, storage_options=storage_options, read_only=read_only), None
    p = Path(spath)
    if p.exists() and not p.is_dir():
        raise ValueError(
            f"{spath!r} is a file, not a Zarr store. Pass a directory path, a "
            f"'*.zip' path or a store URL such as 'memory://name'."
        )
    if read_only and not (p / "zarr.json").exists():
        raise FileNotFoundError(f"No Zarr store at {spath!r} (no zarr.json found).")
    if not read_only:
        if p.exists() and any(p.iterdir()) and not (p / "zarr.json").exists():
            raise ValueError(
                f"{spath!r} exists, is not empty and is not a Zarr store. Refusing to "
                f"write into it: pass a new or empty directory, or an existing store."
            )
        p.mkdir(parents=True, exist_ok=True)
    from zarr.storage import LocalStore

    return LocalStore(str(p), read_only=read_only), p


def open_group(store, *, read_only: bool) -> zarr.Group:
    try:
        return zarr.open_group(store, mode="r" if read_only else "a", zarr_format=3)
    except (FileNotFoundError, zarr.errors.GroupNotFoundError) as err:
        raise FileNotFoundError(f"No Zarr store found at {store}: {err}") from None
    except (ValueError, zarr.errors.NodeTypeValidationError) as err:
        raise ValueError(f"{store} is not a Zarr v3 group: {err}") from None


class WriterLock:
    """An exclusive ``flock`` on the store's directory.

    Two writers on one store would interleave chunks; the OS releases the lock
    when the holder dies, so a crashed writer never blocks the next run. The
    lock is taken on the directory itself so that no foreign file appears in
    the Zarr hierarchy.
    """

    def __init__(self, directory: Path):
        self.path = directory
        self._fd = os.open(directory, os.O_RDONLY)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._fd)
            self._fd = None
            raise RuntimeError(
                f"Another process (or another ZarrStorage in this process) is writing to "
                f"{directory}. A store has one writer at a time; open it with "
                f"read_only=True to read while it is being written."
            ) from None

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


def remove_partial_files(directory: Path) -> int:
    """Deletes the ``*.partial`` temporary files of chunk writes a killed writer left.

    Only called by the lock holder: no live writer can be writing them.
    """
    removed = 0
    for path in directory.rglob("*.partial"):
        try:
            path.unlink()
            removed += 1
        except OSError:
            pass
    return removed


def store_size_bytes(directory: Path | None) -> int | None:
    if directory is None:
        return None
    total = 0
    for root, _, files in os.walk(directory):
        for f in files:
            try:
                total += os.path.getsize(os.path.join(root, f))
            except OSError:
                pass
    return total
