"""The arrays against the commit record: each array's own ``zarr.json`` and a pending journal's arrays.

Every array of the schema must exist with the recorded dtype, row shape,
capacity and chunking (:func:`check_arrays`, :func:`disagreement`), and a
pending journal must hold what its replay would read and commit
(:func:`check_journal`).

Example:
    >>> import tempfile, torch, zarr
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity.arrays import check_arrays
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> group = zarr.open_group(path, mode="r")
    >>> problems, arrays = check_arrays(group.__getitem__, group.attrs.asdict(), store=group.store, local_dir=path)
    >>> problems, sorted(arrays)
    ([], ['env', 'episode', 'obs', 'run'])
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr

from .. import _backend
from ..errors import Problem
from ..format import JOURNAL_DIR, dims, is_strict
from .chunks import first_missing, missing_chunks

__all__ = ["ArrayHead", "check_arrays", "check_journal", "decode_journal_chunks", "disagreement"]


def check_arrays(get_array, attrs: dict, *, store: Any, local_dir: Any, list_chunks: bool = True,
                 skip: tuple = (), present: dict | None = None) -> tuple[list[Problem], dict]:
    """Array metadata against the schema, and chunk presence below the committed length.

    ``get_array(path)`` opens an array (raising if its metadata is unreadable).
    Returns ``(problems, arrays)`` with the arrays that opened and match the schema.
    ``present``, if given, receives ``{path: chunk indices (along the rows) that have files}``.
    """
    problems: list[Problem] = []
    arrays: dict[str, Any] = {}
    schema = attrs.get("schema")
    if not schema:
        return problems, arrays
    _, n0, _ = dims(attrs)
    for path, spec in schema.items():
        if path in skip:
            continue
        try:
            arr = get_array(path)
        except (KeyError, FileNotFoundError):
            problems.append(Problem("metadata", "array metadata missing (no zarr.json)", array=path, key=f"{path}/zarr.json"))
            continue
        except Exception as err:  # noqa: BLE001 - JSON or metadata errors: the finding
            problems.append(Problem("metadata", f"array metadata unreadable ({type(err).__name__}: {str(err)[:100]})",
                                    array=path, key=f"{path}/zarr.json"))
            continue
        found = disagreement(arr, path, spec, attrs)
        if found is not None:
            problems.append(found)
            continue
        arrays[path] = arr
    if list_chunks and n0:
        problems += missing_chunks(arrays, attrs, store=store, local_dir=local_dir, present=present)
    return problems, arrays


@dataclass(frozen=True)
class ArrayHead:
    """What :func:`disagreement` reads of an array (its dtype, shape and chunk shape), from its ``zarr.json``.

    A writer whose rows come from a sealed row file checks its arrays with these alone: it reads no chunk,
    and Zarr's own array objects (codec pipelines) cost more to build than the whole rest of its open.
    """

    dtype: np.dtype
    shape: tuple
    chunks: tuple

    @classmethod
    def of(cls, meta: Any) -> ArrayHead | None:
        """From a parsed Zarr v3 ``zarr.json``; ``None`` for anything but a plain regular-chunked array."""
        try:
            if meta.get("node_type") != "array" or meta.get("zarr_format") != 3 \
                    or meta["chunk_grid"]["name"] != "regular" or not isinstance(meta["data_type"], str):
                return None
            return cls(np.dtype(meta["data_type"]), tuple(int(n) for n in meta["shape"]),
                       tuple(int(n) for n in meta["chunk_grid"]["configuration"]["chunk_shape"]))
        except (AttributeError, KeyError, TypeError, ValueError):
            return None


def disagreement(arr: Any, path: str, spec: dict, attrs: dict) -> Problem | None:
    """Where an array's own ``zarr.json`` and the commit record's schema disagree, a problem naming both."""
    max_dim0, _, inner = dims(attrs)
    chunk_rows = int(attrs["chunk_rows"])
    want_dtype = _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
    want_tail = (*inner, *spec["shape"])
    if not isinstance(arr, (zarr.Array, ArrayHead)):
        return Problem("metadata", "is not an array", array=path, key=f"{path}/zarr.json")
    chunks = arr.metadata.chunk_grid.chunk_shape if hasattr(getattr(arr, "metadata", None), "chunk_grid") \
        else arr.chunks
    if (np.dtype(arr.dtype) == want_dtype and tuple(arr.shape[1:]) == want_tail and arr.shape[0] >= max_dim0
            and chunks[0] == chunk_rows and tuple(chunks[1:]) == tuple(arr.shape[1:])):
        return None
    if np.dtype(arr.dtype) == want_dtype and tuple(arr.shape[1:]) == want_tail and arr.shape[0] < max_dim0:
        return Problem("metadata", f"{path}/zarr.json holds {arr.shape[0]} rows, but attribute 'max_size' "
                       f"({attrs['max_size']}) claims {max_dim0}", array=path, key=f"{path}/zarr.json")
    return Problem(
        "metadata", f"array is {np.dtype(arr.dtype)} {list(arr.shape)} chunked {list(chunks)} ({path}/zarr.json), "
        f"but the schema (attribute 'schema' of zarr.json) records {want_dtype} "
        f"[{max_dim0}, {', '.join(map(str, want_tail))}] in chunks of {chunk_rows} rows",
        array=path, key=f"{path}/zarr.json")


def check_journal(get_array, attrs: dict, arrays: dict, present: dict | None) -> list[Problem]:
    """A pending journal against the arrays: what its replay would read and commit must exist as recorded.

    The journal's arrays must have the dtype and row shape the schema records
    (a replay would cast them silently otherwise), and every row below the
    journal's ``len`` must be in a journalled chunk or already in the arrays
    (a replay would commit zeros otherwise). ``arrays`` are the store's arrays
    that match the schema; ``present`` the chunk files of each (see
    :func:`present_chunks`), if listed.
    """
    journal = attrs.get("journal")
    if not journal or not attrs.get("schema"):
        return []
    out = []
    rows = int(attrs["chunk_rows"])
    max_dim0, n0, inner = dims(attrs)
    meta_n0 = dims({**attrs, **journal["meta"]})[1]
    chunks = set(journal["chunks"])
    if meta_n0 > n0 and present:
        sets = list(present.values())
        on_disk = set.intersection(*sets) if is_strict(attrs) else set.union(*sets)
        first, last = n0 // rows, -(-meta_n0 // rows)
        covered = {c - first for c in chunks | on_disk if first <= c < last}
        gap = first_missing(covered, last - first, 1)
        if gap:
            c = gap[0] + first
            out.append(Problem(
                "journal", f"the pending journal's 'len' ({journal['meta'].get('len')}) claims rows that neither "
                f"the journal (chunks {sorted(chunks)[:8]}) nor the arrays hold; replaying it would serve them as zeros",
                chunk=c, rows=(c * rows, min((c + 1) * rows, meta_n0)), key="zarr.json"))
    top = (max(chunks) + 1) * rows if chunks else 0
    for p, spec in attrs["schema"].items():
        jp = f"{JOURNAL_DIR}/{p}"
        try:
            jarr = get_array(jp)
        except Exception as err:  # noqa: BLE001 - missing or unreadable: the finding
            out.append(Problem("journal", f"journal array missing or unreadable ({type(err).__name__})",
                               array=jp, key=f"{jp}/zarr.json"))
            continue
        want_dtype = _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
        want_tail = (*inner, *spec["shape"])
        size = arrays[p].shape[0] if p in arrays else max_dim0
        if (not isinstance(jarr, zarr.Array) or np.dtype(jarr.dtype) != want_dtype
                or tuple(jarr.shape[1:]) != want_tail or jarr.shape[0] < min(size, top)):
            out.append(Problem(
                "journal", f"journal array is {np.dtype(jarr.dtype)} {list(jarr.shape)} ({jp}/zarr.json), but the "
                f"schema records {want_dtype} [{max_dim0}, {', '.join(map(str, want_tail))}]: replaying it would "
                f"cast or misplace the rows of {p!r}", array=jp, key=f"{jp}/zarr.json"))
    return out




def decode_journal_chunks(open_array, attrs: dict) -> list[Problem]:
    """Reads every chunk of a pending journal; a problem for each that does not decode.

    ``open_array(path)`` opens ``_journal/<array path>`` (raising if it cannot).
    """
    out = []
    rows = int(attrs["chunk_rows"])
    for p in attrs["schema"]:
        for c in attrs["journal"]["chunks"]:
            try:
                open_array(f"{JOURNAL_DIR}/{p}")[c * rows:(c + 1) * rows]
            except Exception as err:  # noqa: BLE001
                out.append(Problem("journal", f"pending journal chunk unreadable ({str(err)[:80]})",
                                   array=f"{JOURNAL_DIR}/{p}", chunk=c))
    return out
