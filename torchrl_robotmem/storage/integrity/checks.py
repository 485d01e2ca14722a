"""The checks ``ZarrStorage`` makes at open, before it reads or writes anything (:func:`check_open`).

In order: the commit record's attributes (:mod:`.attributes`), the sizes it
claims (:mod:`.capacity`), every array's metadata against the schema and every
chunk file below the committed length (:mod:`.arrays`, :mod:`.chunks`), a
pending journal, and, where asked, every chunk decoded. A damaged store raises
:class:`~torchrl_robotmem.storage.errors.IntegrityError`; a reader that asked
``on_damage="warn"`` is told, and opens with the rows before the first damaged chunk.

Example:
    >>> import tempfile, torch, zarr
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity import check_open
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> group = zarr.open_group(path, mode="r")
    >>> attrs = group.attrs.asdict()
    >>> check_open(group, attrs, store=group.store, local_dir=path, path=path, read_only=True) == attrs
    True
"""
from __future__ import annotations

import asyncio
import json
import os
import warnings
from collections.abc import Callable
from typing import Any

import zarr
from zarr.core.sync import sync as zarr_sync
from zarr.storage import LocalStore

from .. import _backend
from ..errors import IntegrityError, Problem
from ..format import decode_chunks, dims, numel
from .arrays import ArrayHead, check_arrays, check_journal, decode_journal_chunks
from .attributes import check_attributes
from .capacity import capacity_problem

__all__ = ["check_open", "columns_in_chunk_folders"]


def check_open(group: Any, attrs: dict, *, store: Any, local_dir: Any, path: Any, read_only: bool,
               on_damage: str = "raise", decode: bool = False, list_chunks: bool = True,
               served: Callable[[dict], bool] | None = None, mapped: bool = False) -> dict:
    """The checks ``ZarrStorage`` makes at open, before it reads or writes anything.

    Raises :class:`IntegrityError` naming the arrays and chunks at fault. With
    ``on_damage="warn"`` (read-only opens), damaged or missing chunks are
    reported in a warning and the returned attributes commit only the rows
    before the first damaged chunk (in RAM: nothing is written). ``decode``
    also decodes every chunk below the committed length (done for writable
    opens that write before reading: a journal replay or growing the store).

    ``served`` is asked, once the attributes are sane, whether a sealed row file will serve the rows
    (:meth:`MemoryStore.open_rows <..store.MemoryStore.open_rows>`): then no chunk is listed, since none
    is read (``robotmem verify`` lists and decodes them all). ``mapped``: the rows will be mapped from a
    file, so the capacity that counts is the address space, not RAM.

    Returns the attributes to open with.
    """
    problems = check_attributes(attrs)
    if any(p.kind == "format" for p in problems):
        return attrs  # ZarrStorage's own format check says what to do
    if not problems and local_dir is not None:
        problems += columns_in_chunk_folders(attrs.get("schema") or {}, local_dir)
    capacity = None if problems else capacity_problem(attrs, mapped=mapped)
    if capacity is not None:  # before anything is listed or allocated
        raise ValueError(f"The store at {path!r} cannot be opened on this machine: {capacity.what}. "
                         f"Nothing was read or changed; `robotmem verify {path}` checks it chunk by chunk.")
    sealed = not problems and served is not None and served(attrs)
    if sealed and read_only and not decode and on_damage == "raise":
        return attrs  # a reader reads no array: its rows come from the sealed file
    if sealed and not decode:
        list_chunks = False  # a writer checks the arrays it will write; it reads no chunk (verify lists them)
    if not problems:
        problems += _array_problems(group, attrs, store=store, local_dir=local_dir, list_chunks=list_chunks,
                                    decode=decode or on_damage == "warn", decode_journal=decode)
    # warnings (chunks an old store may have left out as all-zero) are for verify, not every open
    errors = [p for p in problems if p.severity == "error"]
    if not errors:
        return attrs
    data_only = all(p.kind in ("missing_chunk", "checksum", "undecodable") for p in errors)
    if not (read_only and on_damage == "warn" and data_only):
        raise IntegrityError(path, errors, read_only=read_only)
    cut = min(p.rows[0] for p in errors)
    _, n0, _ = dims(attrs)
    warnings.warn(
        f"{IntegrityError(path, errors, read_only=True, action='')}\non_damage='warn': reading the "
        f"{cut} rows before the first damaged chunk (of {n0} committed).",
        stacklevel=4,
    )
    return {**attrs, "len": min(int(attrs.get("len", 0)), cut * numel(attrs)), "cursor": cut % dims(attrs)[0],
            "last_cursor": cut - 1, "journal": None}


def columns_in_chunk_folders(schema: dict, local_dir: Any) -> list[Problem]:
    """Columns whose folder lies in an array's chunk folder (``<array>/c/<digits>/...``): Zarr keeps no node below
    an array, and a sealed open does not walk those folders for links (:func:`~.._backend.links_below`), so a
    record naming one is refused before any of its files is read.

    Example:
        >>> import tempfile, zarr
        >>> d = tempfile.mkdtemp(); _ = zarr.create_array(d + "/obs", shape=(2,), dtype="f4")
        >>> columns_in_chunk_folders({"obs": {}, "obs/c/0/x": {}, "next/c/0": {}}, d)[0].array
        'obs/c/0/x'
    """
    out = []
    for path in schema:
        parts = str(path).split("/")
        for i in range(1, len(parts) - 1):
            if parts[i] == "c" and parts[i + 1].isascii() and parts[i + 1].isdigit() \
                    and _backend.is_array_folder(os.path.join(os.fspath(local_dir), *parts[:i])):
                out.append(Problem("metadata", f"lies in the chunk folder of the array {'/'.join(parts[:i])!r} (Zarr "
                                               f"keeps no node below an array)", array=path, key=f"{path}/zarr.json"))
                break
    return out


def _array_problems(group: Any, attrs: dict, *, store: Any, local_dir: Any, list_chunks: bool, decode: bool,
                    decode_journal: bool) -> list[Problem]:
    """The arrays and chunk files of sane attributes; with ``decode``, every chunk below the length decoded."""
    # a sealed writer's check (no chunk listed or decoded, no journal) needs each array's head only
    heads = not list_chunks and not decode and not attrs.get("journal")
    nodes = _open_nodes(group, list(attrs.get("schema") or ()), heads=heads)

    def get_array(p):
        node = nodes[p] if p in nodes else group[p]
        if isinstance(node, BaseException):
            raise node
        if not isinstance(node, (zarr.Array, ArrayHead)):
            raise ValueError(f"{p!r} is a group, not an array")
        return node

    present: dict = {}
    problems, arrays = check_arrays(get_array, attrs, store=store, local_dir=local_dir, list_chunks=list_chunks,
                                    present=present)
    journal = attrs.get("journal")
    if journal and not any(p.kind == "metadata" for p in problems):
        problems += check_journal(get_array, attrs, arrays, present if list_chunks else None)
    if decode and not any(p.kind in ("metadata", "journal") for p in problems):
        _, n0, _ = dims(attrs)
        for p, arr in arrays.items():
            problems += decode_chunks(arr, p, n0, int(attrs["chunk_rows"]), present.get(p))[0]
        if journal and decode_journal:
            problems += decode_journal_chunks(group.__getitem__, attrs)
    return problems


def _open_nodes(group: Any, paths: list[str], *, heads: bool) -> dict[str, Any]:
    """The nodes at ``paths`` opened together, in one round trip to Zarr's event loop (not one per array).

    Each value is the node (``zarr.Array`` / ``zarr.Group``), or the exception its open raised (raised by the
    caller as ``group[path]`` would have raised it). ``heads``: an array of a local store whose ``zarr.json``
    reads as a plain one is an :class:`~.arrays.ArrayHead` instead (what its check reads, no Zarr object).
    """
    nodes = _local_heads(group, paths) if heads else {}
    async_group = group._async_group

    async def one(path):
        try:
            node = await async_group.getitem(path)
        except Exception as err:  # noqa: BLE001 - handed to the caller, which raises it where group[path] would
            return err
        return zarr.Array(node) if isinstance(node, zarr.AsyncArray) else zarr.Group(node)

    async def every():
        return await asyncio.gather(*(one(p) for p in rest))

    rest = [p for p in paths if p not in nodes]
    if rest:
        nodes.update(zip(rest, zarr_sync(every())))
    return nodes


def _local_heads(group: Any, paths: list[str]) -> dict[str, Any]:
    """The heads of a local store's arrays read straight from their ``zarr.json`` files.

    An array whose file does not read or parse as a plain one is left out: the caller opens it through
    Zarr, whose error names what is wrong. (The metadata folders were walked for links at the open.)
    """
    store = group.store
    if not isinstance(store, LocalStore):
        return {}
    out = {}
    for path in paths:
        try:
            with open(os.path.join(store.root, *path.split("/"), "zarr.json"), "rb") as f:
                head = ArrayHead.of(json.loads(f.read()))
        except (OSError, ValueError):
            continue
        if head is not None:
            out[path] = head
    return out
