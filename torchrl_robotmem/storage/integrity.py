"""Storage integrity: checksums, the checks made at open, :func:`verify` and :func:`repair`.

A Zarr store is a directory of files any process, disk or copy can damage. Zarr
itself reads a deleted chunk file as zeros and a flipped byte as other data; a
commit record (``len``, cursor) pointing past the written rows would serve
zeros as transitions. This module makes such damage an error that names the
array and the chunk at fault:

* **Checksums.** Stores created by this version append Zarr v3's ``crc32c``
  codec to every array's codec pipeline (after the compressor), and write every
  chunk, also an all-zero one (``write_empty_chunks``), so a chunk file that is
  absent below the committed length is damage, not "all zeros". Both are
  recorded in the format marker (``{"integrity": {"checksum": "crc32c",
  "empty_chunks": "written"}}``). Stores created before keep opening: their
  chunks are not checksummed, and a chunk missing from only some arrays may be
  an all-zero chunk, so only a chunk missing from every array is damage there.
* **At open** (:func:`check_open`, called by ``ZarrStorage`` before anything is
  read or written): the commit record's attributes are sane (integers within
  ``[0, max_size]``, a schema of known dtypes, parseable tag tables and data
  kind), every array of the schema exists with the recorded dtype and shape,
  and every chunk below the committed length is present (one listing of each
  array's chunk keys). Reading the rows then checks every chunk's checksum. A
  damaged store raises :class:`IntegrityError`; nothing is written to it.
* :func:`verify` reads everything and returns an :class:`IntegrityReport`;
  :func:`repair` makes a damaged store openable and writable again, keeping
  every intact row bit-exact (``robotmem verify PATH`` / ``robotmem repair PATH``).

Example:
    >>> import tempfile, torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity import verify
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> report = verify(path)
    >>> report.ok, report.rows, report.checksums
    (True, 10, True)
"""
from __future__ import annotations

import datetime
import itertools
import json
import math
import os
import warnings
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import zarr
from zarr.core.buffer import default_buffer_prototype
from zarr.core.sync import sync as zarr_sync

from . import _backend

__all__ = ["IntegrityError", "IntegrityReport", "Problem", "RepairReport", "check_open", "repair", "verify"]

#: what the format marker of a store created by this version records (``marker["integrity"]``)
MARKER = {"checksum": "crc32c", "empty_chunks": "written"}
#: the Zarr array config every writing handle uses: all-zero chunks are written too
ARRAY_CONFIG = {"write_empty_chunks": True}
_TAGS = ("episode", "run", "env")
_KINDS = ("tensordict", "tensor", "pytree", "tensorclass")
_BACKUP_DIR = "_repair_backup"
_HINT = "Run `robotmem verify {path}` for a full report and `robotmem repair {path}` to make it writable again."


# -- reports ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Problem:
    """One thing found wrong with a store.

    Args:
        kind (str): ``"missing_chunk"``, ``"checksum"``, ``"undecodable"`` (a chunk),
            ``"metadata"`` (a ``zarr.json``), ``"attribute"`` (the commit record),
            ``"format"`` (a newer format) or ``"journal"``.
        what (str): what is wrong, in words.
        array (str, optional): the array path (``"next/observation"``).
        chunk (int, optional): the chunk index along the rows.
        key (str, optional): the store key of the file at fault (``"observation/c/1/0"``).
        rows (tuple, optional): the rows ``[lo, hi)`` (first dimension) the chunk holds.
        severity (str): ``"error"`` (damage) or ``"warning"`` (cannot be told from damage).
    """

    kind: str
    what: str
    array: str | None = None
    chunk: int | None = None
    key: str | None = None
    rows: tuple[int, int] | None = None
    severity: str = "error"

    def __str__(self) -> str:
        where = []
        if self.array is not None:
            where.append(f"array {self.array!r}")
        if self.chunk is not None:
            where.append(f"chunk {self.chunk}")
        loc = " ".join(where)
        extra = ", ".join(x for x in (self.key, self.rows and f"rows {self.rows[0]}-{self.rows[1] - 1}") if x)
        head = f"{loc} ({extra})" if loc and extra else loc or extra
        return f"{head}: {self.what}" if head else self.what


@dataclass
class IntegrityReport:
    """What :func:`verify` found.

    Attributes:
        path: the store.
        problems: every :class:`Problem`, errors and warnings.
        rows: the committed length (``None`` if the commit record is unreadable).
        arrays: arrays checked.
        chunks: chunks read and decoded.
        checksums: whether every array carries the ``crc32c`` codec.
    """

    path: str
    problems: list[Problem] = field(default_factory=list)
    rows: int | None = None
    arrays: int = 0
    chunks: int = 0
    checksums: bool | None = None

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "error"]

    @property
    def ok(self) -> bool:
        """No damage found (warnings allowed)."""
        return not self.errors

    def to_dict(self) -> dict:
        return {"path": self.path, "ok": self.ok, "rows": self.rows, "arrays": self.arrays,
                "chunks": self.chunks, "checksums": self.checksums, "problems": [asdict(p) for p in self.problems]}

    def __str__(self) -> str:
        head = (f"{self.path}: {'intact' if self.ok else 'DAMAGED'} ({self.rows} rows, {self.arrays} arrays, "
                f"{self.chunks} chunks read, checksums {'on' if self.checksums else 'off'})")
        return "\n".join([head] + [f"  {p.severity}: {p}" for p in self.problems])


@dataclass
class RepairReport:
    """What :func:`repair` did: the reports before and after, the actions taken and where the backup is."""

    before: IntegrityReport
    after: IntegrityReport | None
    actions: list[str] = field(default_factory=list)
    backup: str | None = None

    @property
    def ok(self) -> bool:
        return self.after is not None and self.after.ok

    def __str__(self) -> str:
        done = "repaired" if self.after is not None else "would repair (dry run)"
        lines = [f"{self.before.path}: {done if self.actions else 'nothing to repair'}"
                 + (f" (backup of the metadata in {self.backup})" if self.backup else "")]
        lines += [f"  - {a}" for a in self.actions]
        if self.after is not None and not self.after.ok:
            lines.append(str(self.after))
        return "\n".join(lines)


class IntegrityError(ValueError):
    """A store is damaged; ``problems`` lists what was found. Nothing was written to it."""

    def __init__(self, path: Any, problems: list[Problem], *, read_only: bool = True, action: str | None = None):
        self.path = path
        self.problems = list(problems)
        errors = [p for p in self.problems if p.severity == "error"] or self.problems
        lines = [f"The store at {path!r} is damaged ({len(errors)} problem{'s' if len(errors) != 1 else ''}):"]
        lines += [f"  - {p}" for p in errors[:8]]
        if len(errors) > 8:
            lines.append(f"  - ... and {len(errors) - 8} more")
        if action is None:
            action = ("Nothing was changed." if read_only else
                      "Refusing to open it for writing; nothing was changed.")
        hint = _HINT.format(path=path)
        if read_only:
            hint += " ZarrStorage(path, read_only=True, on_damage='warn') reads the intact rows."
        lines.append(f"{action} {hint}")
        super().__init__("\n".join(lines))


class NotAMemoryError(ValueError):
    """The path holds no torchrl_robotmem store."""


# -- attributes ---------------------------------------------------------------------------


def is_strict(attrs: dict) -> bool:
    """Whether every chunk below the committed length must exist (stores created by this version)."""
    marker = attrs.get(_backend.FORMAT_MARKER)
    integ = marker.get("integrity") if isinstance(marker, dict) else None
    return isinstance(integ, dict) and integ.get("empty_chunks") == "written"


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def check_attributes(attrs: dict) -> list[Problem]:
    """Sanity of the commit record (the group attributes); a list of problems."""
    out: list[Problem] = []

    def bad(key, what):
        out.append(Problem("attribute", f"attribute {key!r} {what}", key="zarr.json"))

    marker = attrs.get(_backend.FORMAT_MARKER)
    if not isinstance(marker, dict) or not _is_int(marker.get("format_version")):
        bad(_backend.FORMAT_MARKER, f"is malformed ({marker!r})")
    elif marker["format_version"] > _backend.FORMAT_VERSION:
        out.append(Problem("format", f"written in format version {marker['format_version']} by torchrl_robotmem "
                           f"{marker.get('library_version')}; this version reads format <= "
                           f"{_backend.FORMAT_VERSION}: upgrade torchrl_robotmem", key="zarr.json"))
    max_size = attrs.get("max_size")
    if not _is_int(max_size) or max_size < 1:
        bad("max_size", f"must be a positive integer, got {max_size!r}")
        max_size = None
    for key, lo, default in (("ndim", 1, 1), ("write_count", 0, 0), ("episode_next", 0, 0), ("runs", 0, 0)):
        v = attrs.get(key, default)
        if not _is_int(v) or v < lo:
            bad(key, f"must be an integer >= {lo}, got {v!r}")
    for key, lo, default, hi_off in (("len", 0, 0, 0), ("cursor", 0, 0, 0), ("last_cursor", -1, -1, 1)):
        v = attrs.get(key, default)
        if not _is_int(v) or v < lo or (max_size is not None and v > max_size - hi_off):
            rng = f"[{lo}, {max_size - hi_off}]" if max_size is not None else f">= {lo}"
            bad(key, f"must be an integer in {rng}, got {v!r}")
    cr = attrs.get("chunk_rows")
    if cr is not None and (not _is_int(cr) or cr < 1):
        bad("chunk_rows", f"must be a positive integer, got {cr!r}")
    inner = attrs.get("inner_shape")
    if inner is not None and not (isinstance(inner, list) and all(_is_int(x) and x >= 0 for x in inner)):
        bad("inner_shape", f"must be a list of non-negative integers, got {inner!r}")
    schema = attrs.get("schema")
    if schema is not None:
        if cr is None:
            bad("chunk_rows", "is missing although the store holds arrays")
        if not isinstance(schema, dict) or not schema:
            bad("schema", f"must map array paths to {{dtype, shape}}, got {type(schema).__name__}")
        else:
            for path, spec in schema.items():
                ok = (isinstance(spec, dict) and isinstance(spec.get("dtype"), str) and isinstance(spec.get("shape"), list)
                      and all(_is_int(x) and x >= 0 for x in spec["shape"]) and all(path.split("/")))
                if ok:
                    try:
                        _backend.torch_dtype(spec["dtype"])
                    except ValueError:
                        ok = False
                if not ok:
                    bad("schema", f"entry {path!r} is malformed ({spec!r})")
    elif _is_int(attrs.get("len", 0)) and attrs.get("len", 0) > 0:
        bad("len", f"is {attrs.get('len')} but the store records no schema")
    kind = attrs.get("kind")
    if kind is not None:
        try:
            from .schema import DataKind  # JSON only: nothing is imported or executed

            if not isinstance(kind, dict) or kind.get("kind") not in _KINDS:
                raise ValueError(kind)
            DataKind.from_json(kind)
        except Exception:  # noqa: BLE001 - any failure to parse is the finding
            bad("kind", f"does not parse ({str(kind)[:80]})")
    names = attrs.get("env_names", [])
    if not isinstance(names, list) or not all(isinstance(x, str) for x in names):
        bad("env_names", f"must be a list of names, got {str(names)[:80]}")
    constants = attrs.get("constants") or {}
    if not isinstance(constants, dict) or not all(
        isinstance(k, str) and (v is None or isinstance(v, (str, int, float, bool))) for k, v in constants.items()
    ):
        bad("constants", f"must map keys to JSON scalars, got {str(constants)[:80]}")
    env = attrs.get("env")
    if env is not None and not isinstance(env, str):
        bad("env", f"must be a name or null, got {env!r}")
    journal = attrs.get("journal")
    if journal is not None and not (isinstance(journal, dict) and isinstance(journal.get("meta"), dict)
                                    and isinstance(journal.get("chunks"), list)
                                    and all(_is_int(c) and c >= 0 for c in journal["chunks"])):
        bad("journal", f"is malformed ({str(journal)[:80]})")
    return out


def _dims(attrs: dict) -> tuple[int, int, tuple[int, ...]]:
    """``(max_dim0, committed rows along dim 0, inner_shape)`` of sane attributes."""
    inner = tuple(attrs.get("inner_shape") or ())
    ndim = int(attrs.get("ndim", 1))
    numel = math.prod(inner[: ndim - 1]) if ndim > 1 else 1
    numel = max(numel, 1)
    return -(-int(attrs["max_size"]) // numel), -(-int(attrs.get("len", 0)) // numel), inner


# -- arrays and chunks --------------------------------------------------------------------


def _chunk_keys(arr: Any, path: str, c: int) -> list[str]:
    """The store keys of chunk ``c`` (along the rows) of ``arr``: one per chunk of the other dims."""
    shape, chunks = arr.shape, arr.metadata.chunk_grid.chunk_shape
    other = [range(-(-s // k)) for s, k in zip(shape[1:], chunks[1:])]
    return [f"{path}/{arr.metadata.encode_chunk_key((c, *rest))}" for rest in itertools.product(*other)]


def _list_keys(store: Any, local_dir: Any, prefix: str) -> set[str]:
    """Every key under ``prefix/`` (a directory walk for local stores, ``list_prefix`` otherwise)."""
    if local_dir is not None:
        root = os.path.join(os.fspath(local_dir), prefix)
        out = set()
        for dirpath, _, files in os.walk(root):
            rel = os.path.relpath(dirpath, os.fspath(local_dir)).replace(os.sep, "/")
            out.update(f"{rel}/{f}" for f in files if not f.endswith(".partial"))
        return out

    async def _collect():
        return {k async for k in store.list_prefix(prefix + "/")}

    return zarr_sync(_collect())


def check_arrays(get_array, attrs: dict, *, store: Any, local_dir: Any, list_chunks: bool = True,
                 skip: tuple = ()) -> tuple[list[Problem], dict]:
    """Array metadata against the schema, and chunk presence below the committed length.

    ``get_array(path)`` opens an array (raising if its metadata is unreadable).
    Returns ``(problems, arrays)`` with the arrays that opened and match the schema.
    """
    problems: list[Problem] = []
    arrays: dict[str, Any] = {}
    schema = attrs.get("schema")
    if not schema:
        return problems, arrays
    max_dim0, n0, inner = _dims(attrs)
    chunk_rows = int(attrs["chunk_rows"])
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
        want_dtype = _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
        want_tail = (*inner, *spec["shape"])
        chunks = arr.metadata.chunk_grid.chunk_shape if hasattr(arr.metadata, "chunk_grid") else arr.chunks
        if (not isinstance(arr, zarr.Array) or np.dtype(arr.dtype) != want_dtype or tuple(arr.shape[1:]) != want_tail
                or arr.shape[0] < max_dim0 or chunks[0] != chunk_rows):
            problems.append(Problem(
                "metadata", f"array is {np.dtype(arr.dtype)} {list(arr.shape)} chunked {list(chunks)}, but the "
                f"schema records {want_dtype} [{max_dim0}, {', '.join(map(str, want_tail))}] in chunks of {chunk_rows} rows",
                array=path, key=f"{path}/zarr.json"))
            continue
        arrays[path] = arr
    if list_chunks and n0:
        problems += _missing_chunks(arrays, attrs, store=store, local_dir=local_dir)
    return problems, arrays


def _missing_chunks(arrays: dict, attrs: dict, *, store: Any, local_dir: Any) -> list[Problem]:
    _, n0, _ = _dims(attrs)
    chunk_rows = int(attrs["chunk_rows"])
    nchunks = -(-n0 // chunk_rows)
    missing: dict[str, list[tuple[int, str]]] = {}
    for path, arr in arrays.items():
        if 0 in arr.shape[1:]:
            continue  # an array of empty rows has no chunks
        present = _list_keys(store, local_dir, path)
        for c in range(nchunks):
            for key in _chunk_keys(arr, path, c):
                if key not in present:
                    missing.setdefault(path, []).append((c, key))
                    break
    if is_strict(attrs):
        return [Problem("missing_chunk", "chunk file missing", array=p, chunk=c, key=k,
                        rows=(c * chunk_rows, min((c + 1) * chunk_rows, n0)))
                for p, items in missing.items() for c, k in items]
    # a store created before empty chunks were written: an all-zero chunk has no file
    counted = [p for p, arr in arrays.items() if 0 not in arr.shape[1:]]
    everywhere = set.intersection(*[{c for c, _ in missing.get(p, [])} for p in counted]) if counted else set()
    out = [Problem("missing_chunk", "chunk file missing from every array", array=p, chunk=c, key=k,
                   rows=(c * chunk_rows, min((c + 1) * chunk_rows, n0)))
           for p, items in missing.items() for c, k in items if c in everywhere]
    for p, items in missing.items():
        rest = [c for c, _ in items if c not in everywhere]
        if rest:
            out.append(Problem("missing_chunk", f"{len(rest)} chunk file(s) absent ({rest[:6]}...): read as zeros; this "
                               f"store predates written empty chunks, so an all-zero chunk cannot be told from a "
                               f"deleted one", array=p, severity="warning"))
    return out


def _read_error(err: BaseException) -> tuple[str, str]:
    msg = str(err)
    if "checksum" in msg.lower():
        return "checksum", f"checksum mismatch (crc32c): the chunk file was changed ({msg[:90]})"
    return "undecodable", f"chunk does not decode ({type(err).__name__}: {msg[:90]}): truncated or overwritten"


def decode_chunks(arr: Any, path: str, n0: int, chunk_rows: int) -> tuple[list[Problem], int]:
    """Reads every chunk of ``arr`` below row ``n0`` one by one; ``(problems, chunks read)``."""
    problems = []
    nchunks = -(-n0 // chunk_rows)
    for c in range(nchunks):
        lo, hi = c * chunk_rows, min((c + 1) * chunk_rows, arr.shape[0])
        try:
            arr[lo:hi]
        except Exception as err:  # noqa: BLE001 - codec errors have no common type
            kind, what = _read_error(err)
            problems.append(Problem(kind, what, array=path, chunk=c, key=_chunk_keys(arr, path, c)[0],
                                    rows=(lo, min(hi, n0))))
    return problems, nchunks


def read_error(arr: Any, path: str, n0: int, chunk_rows: int, err: BaseException, store_path: Any,
               read_only: bool) -> IntegrityError:
    """The :class:`IntegrityError` for a failed read of ``arr[:n0]``, naming the chunks at fault."""
    problems, _ = decode_chunks(arr, path, n0, chunk_rows)
    if not problems:
        kind, what = _read_error(err)
        problems = [Problem(kind, what, array=path)]
    return IntegrityError(store_path, problems, read_only=read_only)


# -- at open ------------------------------------------------------------------------------


def check_open(group: Any, attrs: dict, *, store: Any, local_dir: Any, path: Any, read_only: bool,
               on_damage: str = "raise", decode: bool = False, list_chunks: bool = True) -> dict:
    """The checks ``ZarrStorage`` makes at open, before it reads or writes anything.

    Raises :class:`IntegrityError` naming the arrays and chunks at fault. With
    ``on_damage="warn"`` (read-only opens), damaged or missing chunks are
    reported in a warning and the returned attributes commit only the rows
    before the first damaged chunk (in RAM: nothing is written). ``decode``
    also decodes every chunk below the committed length (done for writable
    opens that write before reading: a journal replay or growing the store).

    Returns the attributes to open with.
    """
    problems = check_attributes(attrs)
    if any(p.kind == "format" for p in problems):
        return attrs  # ZarrStorage's own format check says what to do
    if not problems:
        def get_array(p):
            node = group[p]
            if not isinstance(node, zarr.Array):
                raise ValueError(f"{p!r} is a group, not an array")
            return node

        more, arrays = check_arrays(get_array, attrs, store=store, local_dir=local_dir, list_chunks=list_chunks)
        problems += more
        journal = attrs.get("journal")
        if (decode or on_damage == "warn") and not any(p.kind == "metadata" for p in more):
            _, n0, _ = _dims(attrs)
            for p, arr in arrays.items():
                problems += decode_chunks(arr, p, n0, int(attrs["chunk_rows"]))[0]
            if journal and decode:
                for p in attrs["schema"]:
                    for c in journal["chunks"]:
                        try:
                            jarr = group[f"_journal/{p}"]
                            jarr[c * int(attrs["chunk_rows"]):(c + 1) * int(attrs["chunk_rows"])]
                        except Exception as err:  # noqa: BLE001
                            problems.append(Problem("journal", f"pending journal chunk unreadable ({str(err)[:80]})",
                                                    array=f"_journal/{p}", chunk=c))
    # warnings (chunks an old store may have left out as all-zero) are for verify, not every open
    errors = [p for p in problems if p.severity == "error"]
    if not errors:
        return attrs
    data_only = all(p.kind in ("missing_chunk", "checksum", "undecodable") for p in errors)
    if not (read_only and on_damage == "warn" and data_only):
        raise IntegrityError(path, errors, read_only=read_only)
    cut = min(p.rows[0] for p in errors)
    _, n0, inner = _dims(attrs)
    ndim = int(attrs.get("ndim", 1))
    numel = max(math.prod(inner[: ndim - 1]) if ndim > 1 else 1, 1)
    warnings.warn(
        f"{IntegrityError(path, errors, read_only=True, action='')}\non_damage='warn': reading the "
        f"{cut} rows before the first damaged chunk (of {n0} committed).",
        stacklevel=4,
    )
    return {**attrs, "len": min(int(attrs.get("len", 0)), cut * numel), "cursor": cut % _dims(attrs)[0],
            "last_cursor": cut - 1, "journal": None}


# -- verify -------------------------------------------------------------------------------


def _get_bytes(store: Any, key: str) -> bytes | None:
    buf = zarr_sync(store.get(key, prototype=default_buffer_prototype()))
    return None if buf is None else buf.to_bytes()


def _set_bytes(store: Any, key: str, data: bytes) -> None:
    zarr_sync(store.set(key, default_buffer_prototype().buffer.from_bytes(data)))


def _open_any(path: Any, storage_options: dict | None, *, writable: bool = False):
    """``(store, local_dir)`` of a memory, damaged or not, or :class:`NotAMemoryError`.

    A directory whose group ``zarr.json`` is gone still counts as a memory when
    it holds this library's layout (an ``episode`` or ``_tensor`` array).
    """
    name = _backend.normalize_path(path)
    if isinstance(name, str) and not _backend.is_url(name) and not name.endswith(".zip"):
        if not os.path.isdir(name):
            raise NotAMemoryError(f"{name!r} is not a directory" if os.path.exists(name) else f"{name!r} does not exist")
        if not any(os.path.exists(os.path.join(name, *rel)) for rel in
                   (("zarr.json",), ("episode", "zarr.json"), ("_tensor", "zarr.json"))):
            raise NotAMemoryError(f"{name!r} holds no zarr.json: not a Zarr store")
        from zarr.storage import LocalStore

        return LocalStore(name, read_only=not writable), name
    try:
        return _backend.open_store(name, read_only=not writable, storage_options=storage_options)
    except (FileNotFoundError, ValueError) as err:
        raise NotAMemoryError(str(err)) from None


def _array_metas(store: Any, local_dir: Any) -> list[str]:
    """Paths of every node metadata file below the root (``next/observation``), journal and backups excluded."""
    if local_dir is not None:
        keys = set()
        for dirpath, dirs, files in os.walk(os.fspath(local_dir)):
            dirs[:] = [d for d in dirs if d not in ("_journal", _BACKUP_DIR, "c")]
            if "zarr.json" in files and os.path.abspath(dirpath) != os.path.abspath(os.fspath(local_dir)):
                keys.add(os.path.relpath(dirpath, os.fspath(local_dir)).replace(os.sep, "/"))
        return sorted(keys)

    async def _collect():
        return [k async for k in store.list_prefix("")]

    return sorted({k[: -len("/zarr.json")] for k in zarr_sync(_collect())
                   if k.endswith("/zarr.json") and "/c/" not in k
                   and not k.startswith(("_journal/", _BACKUP_DIR + "/"))})


def _read_group_attrs(store: Any) -> tuple[dict | None, Problem | None]:
    raw = _get_bytes(store, "zarr.json")
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


def verify(path: Any, *, storage_options: dict | None = None) -> IntegrityReport:
    """Checks every array and every chunk below the committed length of a store.

    Every chunk is read and decoded (checksums verified where the store has
    them), every array's metadata compared with the recorded schema, the
    commit record's attributes checked, and a pending journal's chunks read.
    Nothing is written; a writer may be running (what it commits meanwhile may
    or may not be seen).

    Args:
        path: the store (a directory, ``*.zip`` or URL), as for ``ZarrStorage``.

    Keyword Args:
        storage_options (dict, optional): fsspec options for URL stores.

    Returns:
        An :class:`IntegrityReport`; ``report.ok`` is ``False`` if anything is damaged.

    Raises:
        NotAMemoryError: nothing at ``path`` is a torchrl_robotmem store.

    Example:
        >>> import tempfile
        >>> from torchrl_robotmem.storage.integrity import verify
        >>> try:
        ...     verify(tempfile.mkdtemp())
        ... except ValueError as err:
        ...     print("not a memory")
        not a memory
    """
    store, local_dir = _open_any(path, storage_options)
    name = str(_backend.normalize_path(path))
    report = IntegrityReport(name)
    attrs, problem = _read_group_attrs(store)
    if problem is not None:
        if not _array_metas(store, local_dir):
            raise NotAMemoryError(f"{name!r} is not a torchrl_robotmem memory ({problem.what}).")
        report.problems.append(problem)
        return report
    if _backend.FORMAT_MARKER not in attrs:
        raise NotAMemoryError(f"{name!r} is a Zarr group without the {_backend.FORMAT_MARKER!r} attribute.")
    report.problems += check_attributes(attrs)
    if report.problems:
        return report
    report.rows = int(attrs.get("len", 0))

    def get_array(p):
        return zarr.open_array(store, path=p, mode="r", zarr_format=3)

    more, arrays = check_arrays(get_array, attrs, store=store, local_dir=local_dir)
    report.problems += more
    report.arrays = len(attrs.get("schema") or {})
    report.checksums = bool(arrays) and all(
        any(type(c).__name__ == "Crc32cCodec" for c in arr.metadata.codecs) for arr in arrays.values())
    if attrs.get("schema"):
        _, n0, _ = _dims(attrs)
        for p, arr in arrays.items():
            found, n = decode_chunks(arr, p, n0, int(attrs["chunk_rows"]))
            report.problems += found
            report.chunks += n
        journal = attrs.get("journal")
        if journal:
            rows = int(attrs["chunk_rows"])
            for p in attrs["schema"]:
                for c in journal["chunks"]:
                    try:
                        zarr.open_array(store, path=f"_journal/{p}", mode="r")[c * rows:(c + 1) * rows]
                    except Exception as err:  # noqa: BLE001
                        report.problems.append(Problem("journal", f"pending journal chunk unreadable ({str(err)[:80]})",
                                                       array=f"_journal/{p}", chunk=c))
    return report


# -- repair -------------------------------------------------------------------------------


def repair(path: Any, *, mode: str = "truncate", storage_options: dict | None = None,
           dry_run: bool = False) -> RepairReport:
    """Makes a damaged store openable and writable again, keeping every intact row bit-exact.

    What it does (``mode="truncate"``, the only mode), after copying every
    metadata file (the group's and each array's ``zarr.json``, damaged or not)
    to ``_repair_backup/<time>/`` inside the store:

    * an unreadable array ``zarr.json`` is rebuilt from the recorded schema and
      the codecs its chunks decode with (checksums tried first);
    * an unreadable group ``zarr.json`` (the commit record) is rebuilt from the
      arrays: schema, capacity and chunking from their metadata, the length from
      the last row holding any non-zero value, episode / run counters from the
      tag columns. Environment *names* cannot be recovered: codes keep their
      rows, named ``"unknown-env-<code>"``. A pytree store cannot be rebuilt (its
      tree structure lived only there);
    * insane attributes are recomputed the same way (a ``len`` past ``max_size``,
      a cursor out of range, malformed tag tables);
    * data damage (a missing, truncated or checksum-failing chunk below the
      committed length) truncates the committed length to the start of the first
      damaged chunk, then past trailing rows that are zero in every array (rows a
      too-large ``len`` would have served). Rows after the cut are dropped, never
      invented: for a ring that had wrapped, that includes the rows stored past
      the damaged chunk. The damaged chunk files move to the backup folder;
    * a pending journal whose chunks are damaged is dropped.

    A store of a newer format version is not touched (upgrade torchrl_robotmem).
    Take the writer lock: no process may be writing the store (local stores are
    checked; for URL stores, stop the writer first).

    Args:
        path: the store, as for ``ZarrStorage``.

    Keyword Args:
        mode (str): ``"truncate"``.
        storage_options (dict, optional): fsspec options for URL stores.
        dry_run (bool): report what would be done, write nothing.

    Returns:
        A :class:`RepairReport` (``before`` / ``after`` reports, ``actions``, ``backup``).

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.storage.integrity import repair
        >>> path = tempfile.mkdtemp() + "/memory.zarr"
        >>> with ZarrStorage(path, 100) as storage:
        ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
        >>> repair(path).actions
        []
    """
    if mode != "truncate":
        raise ValueError(f"mode must be 'truncate', got {mode!r}.")
    before = verify(path, storage_options=storage_options)
    if before.ok:
        return RepairReport(before, before)
    if any(p.kind == "format" for p in before.problems):
        raise IntegrityError(before.path, before.errors, action="repair does not touch a store of a newer format:")
    store, local_dir = _open_any(path, storage_options, writable=not dry_run)
    lock = _backend.WriterLock(local_dir) if local_dir is not None and not dry_run else None
    try:
        return _repair(before, store, local_dir, path, storage_options, dry_run)
    finally:
        if lock is not None:
            lock.release()


def _repair(before, store, local_dir, path, storage_options, dry_run) -> RepairReport:
    actions: list[str] = []
    backup = None
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S-%f")
    if not dry_run:
        backup = f"{_BACKUP_DIR}/{stamp}"
        for key in ["zarr.json"] + [f"{p}/zarr.json" for p in _array_metas(store, local_dir)]:
            raw = _get_bytes(store, key)
            if raw is not None:
                _set_bytes(store, f"{backup}/{key}", raw)
        actions.append(f"backed up the metadata files to {backup}/")
    attrs, problem = _read_group_attrs(store)
    group_rebuilt = attrs is None
    if group_rebuilt:
        attrs = _rebuild_attrs(store, local_dir)
        actions.append(f"rebuilt the commit record (group zarr.json) from the arrays: {problem.what}")
    journal = attrs.get("journal")
    journal_bad = any(p.kind == "journal" for p in before.problems)
    if journal and not group_rebuilt and not journal_bad and not check_attributes(attrs) and not dry_run:
        # an interrupted overwrite: redo it first (as a writable open would), so no row stays torn
        from .commit import CommitEngine

        with writing_config():
            attrs = CommitEngine.replay_journal(zarr.open_group(store, mode="r+", zarr_format=3), journal)
        actions.append(f"replayed the pending journal (chunks {journal['chunks']})")
        journal = None
    new = dict(attrs)
    # -- attributes that make no sense: recomputed from the data below
    bad_attrs = {p.what.split("'")[1] for p in check_attributes(attrs) if p.kind == "attribute"}
    schema_ok = not ({"schema", "chunk_rows", "max_size", "inner_shape", "ndim"} & bad_attrs)
    if not schema_ok:
        rebuilt = _rebuild_attrs(store, local_dir)
        for key in ("schema", "chunk_rows", "max_size", "inner_shape", "ndim", "kind"):
            if key in bad_attrs or key in ("schema", "chunk_rows", "max_size"):
                new[key] = rebuilt[key]
        actions.append(f"recomputed {sorted(bad_attrs)} from the arrays' metadata")
        bad_attrs -= {"schema", "chunk_rows", "max_size", "inner_shape", "ndim", "kind"}
    # -- array metadata
    max_dim0, _, inner = _dims(new)
    for path_ in new.get("schema") or {}:
        try:
            arr = zarr.open_array(store, path=path_, mode="r", zarr_format=3)
            spec = new["schema"][path_]
            if (np.dtype(arr.dtype) == _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
                    and tuple(arr.shape[1:]) == (*inner, *spec["shape"]) and arr.shape[0] >= max_dim0):
                continue
        except Exception:  # noqa: BLE001 - unreadable: rebuilt below
            pass
        meta = _rebuild_array_meta(store, local_dir, path_, new)
        actions.append(f"rebuilt the metadata of array {path_!r} ({path_}/zarr.json)")
        if not dry_run:
            _set_bytes(store, f"{path_}/zarr.json", meta)
    # -- the committed length
    n_dim0 = None
    if "len" in bad_attrs or group_rebuilt:
        n_dim0 = _written_extent(store, new, limit=max_dim0)
    else:
        _, n_dim0, _ = _dims(new)
    if not dry_run:
        data = _data_problems(store, local_dir, {**new, "len": n_dim0 * _numel(new)})
    else:
        data = [p for p in before.problems if p.kind in ("missing_chunk", "checksum", "undecodable") and p.severity == "error"]
    if journal and journal_bad and isinstance(journal, dict) and journal.get("chunks"):
        # its overwrite may have reached some arrays' chunks and not others: those rows may be torn
        rows = int(new["chunk_rows"])
        data += [Problem("journal", "overwritten by an interrupted commit whose journal is damaged", chunk=c,
                         rows=(c * rows, (c + 1) * rows)) for c in journal["chunks"] if c * rows < n_dim0]
    if data:
        cut = min(p.rows[0] for p in data)
        trimmed = _written_extent(store, new, limit=cut)
        actions.append(f"truncated the committed length from {n_dim0 * _numel(new)} to {trimmed * _numel(new)} rows: "
                       + "; ".join(str(p) for p in data[:4]) + (" ..." if len(data) > 4 else ""))
        n_dim0 = trimmed
        for p in data:
            if p.kind != "missing_chunk" and p.key and not dry_run:
                raw = _get_bytes(store, p.key)
                if raw is not None:
                    _set_bytes(store, f"{backup}/{p.key}", raw)
                zarr_sync(store.delete(p.key))
                actions.append(f"moved the damaged chunk {p.key} to {backup}/{p.key}")
    elif "len" in bad_attrs:
        actions.append(f"set the committed length to {n_dim0 * _numel(new)} rows (the written rows)")
    length = n_dim0 * _numel(new)
    full = n_dim0 >= max_dim0
    old_count = attrs.get("write_count") if _is_int(attrs.get("write_count")) and "write_count" not in bad_attrs else None
    changes: dict[str, Any] = {}
    if length != attrs.get("len") or group_rebuilt or {"cursor", "last_cursor"} & bad_attrs:
        cursor = _ring_cursor(store, new, max_dim0) if full else n_dim0
        changes.update(len=length, cursor=cursor % max_dim0, last_cursor=(cursor - 1) % max_dim0 if length else -1)
    if length != attrs.get("len") or group_rebuilt or old_count is None:
        # a ring that stays full keeps its count (it has wrapped); otherwise the count is the length
        changes["write_count"] = max(length, old_count or 0) if full else length
    tags = _tag_maxima(store, new, n_dim0)
    for key in ("episode_next", "runs"):
        if key in bad_attrs or group_rebuilt:
            changes[key] = tags.get(key, 0)
    if "env_names" in bad_attrs or group_rebuilt:
        changes["env_names"] = [f"unknown-env-{i}" for i in range(tags.get("env_codes", 0))]
        changes["env"] = None
        if changes["env_names"]:
            actions.append(f"environment names lost: codes 0..{len(changes['env_names']) - 1} named 'unknown-env-<code>'")
    if "env" in bad_attrs:
        changes["env"] = None
    if "kind" in bad_attrs:
        changes["kind"] = _rebuild_attrs(store, local_dir)["kind"]
    if journal is not None and ("journal" in bad_attrs or journal_bad or data):
        changes["journal"] = None
        actions.append("dropped the pending journal (damaged, or superseded by the truncation)")
    for key in sorted(bad_attrs - set(changes) - {"len"}):
        actions.append(f"attribute {key!r} could not be recomputed")
    changes = {k: v for k, v in changes.items() if new.get(k, object()) != v or group_rebuilt}
    if changes and not any(a.startswith(("truncated", "set the committed")) for a in actions):
        actions.append(f"rewrote attributes {sorted(changes)}")
    if not dry_run:
        final = {**new, **changes}
        if group_rebuilt or new != attrs:
            doc = {"attributes": final, "zarr_format": 3, "consolidated_metadata": None, "node_type": "group"}
            _set_bytes(store, "zarr.json", json.dumps(doc, indent=2).encode())
        elif changes:
            zarr.open_group(store, mode="r+", zarr_format=3).update_attributes(changes)
    after = None if dry_run else verify(path, storage_options=storage_options)
    return RepairReport(before, after, actions, backup)


def _numel(attrs: dict) -> int:
    inner = tuple(attrs.get("inner_shape") or ())
    ndim = int(attrs.get("ndim", 1))
    return max(math.prod(inner[: ndim - 1]) if ndim > 1 else 1, 1)


def _data_problems(store, local_dir, attrs) -> list[Problem]:
    def get_array(p):
        return zarr.open_array(store, path=p, mode="r", zarr_format=3)

    problems, arrays = check_arrays(get_array, attrs, store=store, local_dir=local_dir)
    _, n0, _ = _dims(attrs)
    for p, arr in arrays.items():
        problems += decode_chunks(arr, p, n0, int(attrs["chunk_rows"]))[0]
    return [p for p in problems if p.severity == "error" and p.kind in ("missing_chunk", "checksum", "undecodable")]


def _readable_arrays(store, attrs) -> list:
    out = []
    for p in attrs.get("schema") or {}:
        try:
            out.append(zarr.open_array(store, path=p, mode="r", zarr_format=3))
        except Exception:  # noqa: BLE001 - a damaged array counts for nothing here
            continue
    return out


def _written_extent(store, attrs, *, limit: int) -> int:
    """Rows (dim 0) up to the last one below ``limit`` holding a non-zero value in any array."""
    rows = int(attrs["chunk_rows"])
    arrays = _readable_arrays(store, attrs)
    for c in range(-(-limit // rows) - 1, -1, -1):
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


def _tag_maxima(store, attrs, n0: int) -> dict:
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


def _ring_cursor(store, attrs, max_dim0: int) -> int:
    """Where a full ring's next write goes: after the newest episode's last row (0 if untagged)."""
    try:
        ep = np.asarray(zarr.open_array(store, path="episode", mode="r")[:max_dim0]).reshape(max_dim0, -1)[:, 0]
    except Exception:  # noqa: BLE001
        return 0
    newest = ep == ep.max()
    ends = np.nonzero(newest & ~np.roll(newest, -1))[0]
    return int(ends[-1] + 1) % max_dim0 if ends.size else 0


def _rebuild_attrs(store, local_dir) -> dict:
    """A commit record rebuilt from the arrays' metadata (the length is set by the caller)."""
    arrays = {}
    for p in _array_metas(store, local_dir):
        try:
            node = zarr.open_array(store, path=p, mode="r", zarr_format=3)
        except Exception:  # noqa: BLE001 - groups ("next") and unreadable arrays
            continue
        arrays[p] = node
    if any(p.startswith(_backend_pytree_prefix()) for p in arrays):
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
    from .zarr_storage import _library_version

    marker = {"format_version": _backend.FORMAT_VERSION, "library_version": _library_version(),
              "rebuilt_by": "robotmem repair"}
    if strict:
        marker["integrity"] = dict(MARKER)
    return {_backend.FORMAT_MARKER: marker, "max_size": int(min(a.shape[0] for a in arrays.values())),
            "ndim": 1, "inner_shape": inner, "chunk_rows": int(ref.metadata.chunk_grid.chunk_shape[0]),
            "schema": schema, "kind": kind, "len": 0, "cursor": 0, "last_cursor": -1, "write_count": 0,
            "episode_next": 0, "runs": 0, "env_names": [], "env": None, "journal": None}


def _backend_pytree_prefix() -> str:
    from .schema import DataKind

    return DataKind.PYTREE_KEY + "/"


def _rebuild_array_meta(store, local_dir, path: str, attrs: dict) -> bytes:
    """``zarr.json`` of array ``path`` from the schema, with the codecs its chunks decode with.

    Each candidate pipeline (checksummed ones first) decodes one chunk file of
    the array in a scratch in-memory store; the first that decodes it wins.
    """
    from zarr.storage import MemoryStore

    spec = attrs["schema"][path]
    max_dim0, _, inner = _dims(attrs)
    dtype = _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
    shape = (max_dim0, *inner, *spec["shape"])
    chunks = (int(attrs["chunk_rows"]), *shape[1:])
    keys = sorted(k for k in _list_keys(store, local_dir, path) if k.startswith(f"{path}/c/"))
    raw = _get_bytes(store, keys[0]) if keys else None
    metas = []
    for checksum in (True, False):
        for comp in ("blosc", "zstd", None):
            mem = MemoryStore()
            arr = zarr.create_array(mem, name="a", shape=shape, chunks=chunks, dtype=dtype, fill_value=0,
                                    compressors=_backend.make_compressors(comp, 1, dtype.itemsize, checksum=checksum))
            metas.append(_get_bytes(mem, "a/zarr.json"))
            if raw is None:
                return metas[0]
            rel = keys[0][len(path) + 1:]
            _set_bytes(mem, f"a/{rel}", raw)
            c = int(rel.split("/")[1])
            try:
                arr[c * chunks[0]:(c + 1) * chunks[0]]
                return metas[-1]
            except Exception:  # noqa: BLE001 - not this pipeline
                continue
    return metas[0]  # no pipeline decodes it: the chunk is damaged too (reported by verify)


# -- hooks for ZarrStorage ------------------------------------------------------------------


def read_rows(arr: Any, path: str, n0: int, chunk_rows: int, store_path: Any, read_only: bool) -> np.ndarray:
    """``arr[:n0]`` as a contiguous array, or an :class:`IntegrityError` naming the chunks that fail to decode."""
    try:
        return np.ascontiguousarray(arr[:n0])
    except Exception as err:  # noqa: BLE001 - codec errors have no common type
        raise read_error(arr, path, n0, chunk_rows, err, store_path, read_only) from err


def writing_handles(group: Any, paths: Any) -> dict:
    """Handles on the arrays ``paths`` that write all-zero chunks too (for the commit engine)."""
    return {p: group[p].with_config(ARRAY_CONFIG) for p in paths}


def writing_config():
    """A context in which every Zarr handle writes all-zero chunks (a journal replay opens its own)."""
    return zarr.config.set({"array.write_empty_chunks": True})


def write_zero_chunks(arr: Any, n0: int, chunk_rows: int) -> None:
    """Writes the chunks of a new array below row ``n0`` as zeros (a key added to a store with rows).

    Its older rows read zeros; written as chunk files, a later missing one is damage.
    """
    for lo in range(0, n0, chunk_rows):
        hi = min(lo + chunk_rows, arr.shape[0])
        arr[lo:hi] = np.zeros((hi - lo, *arr.shape[1:]), dtype=arr.dtype)
