"""What ``repair`` recomputes from the data when a record is lost or insane.

The commit record from the arrays' own metadata (:func:`rebuild_attrs`), an
array's ``zarr.json`` from the schema and the codecs its chunks decode with
(:func:`rebuild_array_meta`), the committed length from the last row holding a
non-zero value (:func:`written_extent`), the episode / run counters from the
tag columns (:func:`tag_maxima`) and a full ring's cursor (:func:`ring_cursor`).
Everything here reads; nothing writes.

Example:
    >>> import tempfile, torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity.files import open_any
    >>> from torchrl_robotmem.storage.integrity.rebuild import rebuild_attrs, written_extent
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> store, local_dir = open_any(path, None)
    >>> attrs = rebuild_attrs(store, local_dir)
    >>> attrs["max_size"], sorted(attrs["schema"]), written_extent(store, attrs, limit=100)
    (100, ['env', 'episode', 'obs', 'run'], 10)
"""
from __future__ import annotations

import numpy as np
import zarr
from zarr.storage import MemoryStore

from ..._version import __version__
from .. import _backend
from ..errors import IntegrityError, NotAMemoryError, Problem
from ..format import (
    BOUNDED_FORMAT,
    CHUNK_KEY_SEPARATOR,
    FORMAT_MARKER,
    FORMAT_VERSION,
    MARKER,
    UNBOUNDED,
    decode_chunks,
    dims,
)
from ..schema import DataKind
from .arrays import check_arrays
from .chunks import list_keys, present_chunks
from .files import array_metas, get_bytes, local_dir_of, set_bytes

__all__ = ["data_problems", "rebuild_array_meta", "rebuild_attrs", "ring_cursor", "tag_maxima", "written_extent"]


def data_problems(store, local_dir, attrs) -> list[Problem]:
    """The data damage below the committed length of ``attrs``: missing, checksum-failing, undecodable chunks."""
    def get_array(p):
        return zarr.open_array(store, path=p, mode="r", zarr_format=3)

    present: dict = {}
    problems, arrays = check_arrays(get_array, attrs, store=store, local_dir=local_dir, present=present)
    _, n0, _ = dims(attrs)
    for p, arr in arrays.items():
        problems += decode_chunks(arr, p, n0, int(attrs["chunk_rows"]), present.get(p))[0]
    return [p for p in problems if p.severity == "error" and p.kind in ("missing_chunk", "checksum", "undecodable")]


def _readable_arrays(store, attrs) -> list:
    out = []
    for p in attrs.get("schema") or {}:
        try:
            out.append(zarr.open_array(store, path=p, mode="r", zarr_format=3))
        except Exception:  # noqa: BLE001 - a damaged array counts for nothing here
            continue
    return out


def written_extent(store, attrs, *, limit: int) -> int:
    """Rows (dim 0) up to the last one below ``limit`` holding a non-zero value in any array."""
    rows = int(attrs["chunk_rows"])
    arrays = _readable_arrays(store, attrs)
    # only chunks with a file can hold a non-zero value: the cost follows what the store holds
    present: set[int] = set()
    for found in present_chunks({a.path: a for a in arrays}, store=store, local_dir=local_dir_of(store)).values():
        present |= found
    for c in sorted((c for c in present if c * rows < limit), reverse=True):
        lo, hi = c * rows, min((c + 1) * rows, limit)
        any_nonzero = np.zeros(hi - lo, dtype=bool)
        for arr in arrays:
            try:
                block = np.asarray(arr[lo:hi])
            except Exception:  # noqa: BLE001 - a damaged chunk holds nothing to keep
                continue
            any_nonzero |= block.reshape(hi - lo, -1).any(-1) if block.size else False
        if any_nonzero.any():
            return lo + int(np.nonzero(any_nonzero)[0][-1]) + 1
    return 0


def tag_maxima(store, attrs, n0: int) -> dict:
    out = {}
    if not n0:
        return out
    for tag, key in (("episode", "episode_next"), ("run", "runs"), ("env", "env_codes")):
        if tag in (attrs.get("schema") or {}):
            try:
                out[key] = int(np.asarray(zarr.open_array(store, path=tag, mode="r")[:n0]).max()) + 1
            except Exception:  # noqa: BLE001
                pass
    return out


def ring_cursor(store, attrs, max_dim0: int) -> int:
    """Where a full ring's next write goes: after the newest episode's last row (0 if untagged)."""
    try:
        ep = np.asarray(zarr.open_array(store, path="episode", mode="r")[:max_dim0]).reshape(max_dim0, -1)[:, 0]
    except Exception:  # noqa: BLE001
        return 0
    newest = ep == ep.max()
    ends = np.nonzero(newest & ~np.roll(newest, -1))[0]
    return int(ends[-1] + 1) % max_dim0 if ends.size else 0


def rebuild_attrs(store, local_dir) -> dict:
    """A commit record rebuilt from the arrays' metadata (the length is set by the caller)."""
    arrays = {}
    for p in array_metas(store, local_dir):
        top = p.split("/", 1)[0]
        if top.startswith("_") and top not in (DataKind.TENSOR_KEY, DataKind.PYTREE_KEY):
            continue  # a component's group (a sampler's "_priority"): its own state, not a column
        try:
            node = zarr.open_array(store, path=p, mode="r", zarr_format=3)
        except Exception:  # noqa: BLE001 - groups ("next") and unreadable arrays
            continue
        arrays[p] = node
    if any(p.startswith(DataKind.PYTREE_KEY + "/") for p in arrays):
        raise IntegrityError(_backend.normalize_path(getattr(store, "root", store)), [Problem(
            "metadata", "the commit record of a pytree store is lost: its tree structure cannot be rebuilt",
            key="zarr.json")], action="repair cannot rebuild it:")
    if not arrays:
        raise NotAMemoryError("no readable arrays to rebuild the commit record from")
    ref = arrays.get("episode") or next(iter(arrays.values()))
    inner = list(ref.shape[1:]) if "episode" in arrays else []
    kind = {"kind": "tensordict"} if "episode" in arrays else ({"kind": "tensor"} if "_tensor" in arrays else None)
    schema = {p: {"dtype": str(np.dtype(a.dtype)), "shape": list(a.shape[1 + len(inner):])} for p, a in arrays.items()}
    strict = all(any(type(c).__name__ == "Crc32cCodec" for c in a.metadata.codecs) for a in arrays.values())
    # a memory without a declared capacity says so in its arrays' attributes too (schema.create_arrays); one whose
    # arrays do not (written before they did) said it in the record alone: it comes back as a ring of their length
    unbounded = not inner and any(a.attrs.get(UNBOUNDED) is True for a in arrays.values())
    marker = {"format_version": FORMAT_VERSION if unbounded else BOUNDED_FORMAT, "library_version": __version__,
              "rebuilt_by": "robotmem repair"}
    if strict:
        marker["integrity"] = dict(MARKER)
    return {FORMAT_MARKER: marker, "max_size": int(min(a.shape[0] for a in arrays.values())),
            "ndim": 1, "inner_shape": inner, "chunk_rows": int(ref.metadata.chunk_grid.chunk_shape[0]),
            "schema": schema, "kind": kind, "len": 0, "cursor": 0, "last_cursor": -1, "write_count": 0,
            "episode_next": 0, "runs": 0, "env_names": [], "env": None, "journal": None,
            **({UNBOUNDED: True} if unbounded else {})}


def _chunk_separator(rel: str) -> str | None:
    """``"/"`` or ``"."``: the separator of a chunk file's name below its array (``c/3/0``, ``c.3.0``), else ``None``
    (``zarr.json``, a stray or ``.partial`` file)."""
    for sep in ("/", "."):
        head, *parts = rel.split(sep)
        if head == "c" and parts and all(p.isdigit() for p in parts):
            return sep
    return None


def rebuild_array_meta(store, local_dir, path: str, attrs: dict) -> bytes | None:
    """``zarr.json`` of array ``path`` from the schema, with the codecs its chunks decode with.

    Each candidate pipeline (checksummed ones first) decodes a chunk file of the
    array in a scratch in-memory store; the first that decodes one of its first
    three chunk files wins. ``None`` if none does: the schema does not describe
    these chunks (another dtype or shape), and nothing is rebuilt from it.
    """
    spec = attrs["schema"][path]
    max_dim0, _, inner = dims(attrs)
    dtype = _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
    shape = (max_dim0, *inner, *spec["shape"])
    chunks = (int(attrs["chunk_rows"]), *shape[1:])
    # the chunk files tell the key encoding: c/<c>/0 (a store created before 2026-12) or c.<c>.0
    keys = sorted(k for k in list_keys(store, local_dir, path) if _chunk_separator(k[len(path) + 1:]))[:3]
    separator = _chunk_separator(keys[0][len(path) + 1:]) if keys else CHUNK_KEY_SEPARATOR
    first = None
    for key in keys or [None]:
        raw = get_bytes(store, key) if key is not None else None
        for checksum in (True, False):
            for comp in ("blosc", "zstd", None):
                mem = MemoryStore()
                arr = zarr.create_array(mem, name="a", shape=shape, chunks=chunks, dtype=dtype, fill_value=0,
                                        compressors=_backend.make_compressors(comp, 1, dtype.itemsize, checksum=checksum),
                                        chunk_key_encoding={"name": "default", "separator": separator})
                meta = get_bytes(mem, "a/zarr.json")
                if raw is None:
                    return meta  # no chunk file to decode: the schema's description, checksummed
                first = first or meta
                rel = key[len(path) + 1:]
                set_bytes(mem, f"a/{rel}", raw)
                c = int(rel.split(separator)[1])
                try:
                    arr[c * chunks[0]:(c + 1) * chunks[0]]
                    return meta
                except Exception:  # noqa: BLE001 - not this pipeline
                    continue
    return None


