"""Which chunk files a store holds: one listing per array, and the chunks missing below the committed length.

Zarr reads a chunk file that is gone as zeros. Stores created by this version
write every chunk, an all-zero one too, so a chunk file absent below the
committed length is damage; in older stores only a chunk missing from every
array is (an all-zero chunk had no file). A listing costs in proportion to the
files that exist, not to what the commit record claims.

Example:
    >>> import tempfile, torch, zarr
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity.chunks import present_chunks
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100, chunk_rows=4) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> group = zarr.open_group(path, mode="r")
    >>> present_chunks({"obs": group["obs"]}, store=group.store, local_dir=path)
    {'obs': {0, 1, 2}}
"""
from __future__ import annotations

import os
from typing import Any

from zarr.core.sync import sync as zarr_sync

from ..errors import Problem
from ..format import chunk_keys, dims, is_strict, row_chunk_key

__all__ = ["first_missing", "list_keys", "missing_after_read", "missing_chunks", "present_chunks"]

#: missing chunks listed one by one per array; the rest are counted in one problem
_LISTED = 8


def list_keys(store: Any, local_dir: Any, prefix: str) -> set[str]:
    """Every key under ``prefix/`` (a directory walk for local stores, ``list_prefix`` otherwise)."""
    if local_dir is not None:
        out: set[str] = set()
        _walk(os.path.join(os.fspath(local_dir), prefix), prefix.strip("/"), out)
        return out

    async def _collect():
        return {k async for k in store.list_prefix(prefix + "/")}

    return zarr_sync(_collect())


def _walk(directory: str, rel: str, out: set[str]) -> None:
    """Adds ``rel/<name>`` for every file below ``directory`` (``*.partial`` left out) to ``out``."""
    try:
        entries = list(os.scandir(directory))
    except (FileNotFoundError, NotADirectoryError):
        return
    for entry in entries:
        if entry.is_dir(follow_symlinks=False):
            _walk(entry.path, f"{rel}/{entry.name}", out)
        elif not entry.name.endswith(".partial"):
            out.add(f"{rel}/{entry.name}")


def present_chunks(arrays: dict, *, store: Any, local_dir: Any) -> dict[str, set[int]]:
    """``{path: indices of the row chunks that have a file}``, one listing per array."""
    out = {}
    for path, arr in arrays.items():
        head, tail = row_chunk_key(arr, path)
        found = set()
        for key in list_keys(store, local_dir, path):
            if key.startswith(head) and key.endswith(tail):
                mid = key[len(head): len(key) - len(tail)]
                if mid.isdigit():
                    found.add(int(mid))
        out[path] = found
    return out


def first_missing(present: set[int], n: int, k: int) -> list[int]:
    """The first ``k`` indices below ``n`` not in ``present``: ``len(present) + k`` steps at most."""
    out, c = [], 0
    while c < n and len(out) < k:
        if c not in present:
            out.append(c)
        c += 1
    return out


def missing_chunks(arrays: dict, attrs: dict, *, store: Any, local_dir: Any, present: dict | None = None) -> list[Problem]:
    """Chunks below the committed length without a file.

    Costs in proportion to the chunk files that exist, not to what ``len``
    claims: the first missing chunks of each array are listed, the rest counted.
    """
    _, n0, _ = dims(attrs)
    chunk_rows = int(attrs["chunk_rows"])
    nchunks = -(-n0 // chunk_rows)
    counted = {p: arr for p, arr in arrays.items() if 0 not in arr.shape[1:]}  # arrays of empty rows have no chunks
    have = present_chunks(counted, store=store, local_dir=local_dir)
    if present is not None:
        present.update(have)

    def rows(c):
        return (c * chunk_rows, min((c + 1) * chunk_rows, n0))

    def listed(path, arr, found, what):
        cs = first_missing(found, nchunks, _LISTED + 1)
        out = [Problem("missing_chunk", what, array=path, chunk=c, key=chunk_keys(arr, path, c)[0], rows=rows(c))
               for c in cs[:_LISTED]]
        if len(cs) > _LISTED:
            out.append(Problem("missing_chunk", f"{nchunks - len(found) - _LISTED} more chunk files missing: the "
                               f"committed length ({attrs.get('len')} rows) spans {nchunks} chunks, {len(found)} exist",
                               array=path, rows=(rows(cs[-1])[0], n0)))
        return out

    have_below = {p: {c for c in cs if c < nchunks} for p, cs in have.items()}
    if is_strict(attrs):
        out = []
        for p, arr in counted.items():
            if len(have_below[p]) < nchunks:
                out += listed(p, arr, have_below[p], "chunk file missing")
        return out
    # a store created before empty chunks were written: an all-zero chunk has no file,
    # so only a chunk missing from every array is damage
    if not counted:
        return []
    union = set().union(*have_below.values())
    out = []
    if len(union) < nchunks:
        for p, arr in counted.items():
            out += listed(p, arr, union, "chunk file missing from every array")
    for p in counted:
        rest = sorted(union - have_below[p])
        if rest:
            out.append(Problem("missing_chunk", f"{len(rest)} chunk file(s) absent ({rest[:6]}...): read as zeros; this "
                               f"store predates written empty chunks, so an all-zero chunk cannot be told from a "
                               f"deleted one", array=p, severity="warning"))
    return out


def missing_after_read(group: Any, attrs: dict, *, store: Any, local_dir: Any) -> list[Problem]:
    """Chunks below the committed length of ``attrs`` that have no file *now* (listed again after a read).

    Zarr reads a chunk file that is gone as zeros. The open lists the chunk files
    before reading; a chunk moved away between that listing and the read (by
    ``repair``, a copy, a user) would be served as zeros. Listing again after the
    read catches it: a chunk present before and after the read was read from
    its file (chunk files are replaced atomically, never removed, by writers).

    Args:
        group: the store's Zarr group.
        attrs: the attributes the rows were read with (``len``, ``schema``, ...).

    Keyword Args:
        store: the Zarr store; local_dir: its directory (``None`` for other stores).

    Returns:
        The missing chunks as :class:`Problem` s (errors; warnings for stores of
        the format that did not write all-zero chunks).
    """
    if not attrs.get("schema") or not dims(attrs)[1]:
        return []
    arrays = {p: group[p] for p in attrs["schema"]}
    return [p for p in missing_chunks(arrays, attrs, store=store, local_dir=local_dir) if p.severity == "error"]


