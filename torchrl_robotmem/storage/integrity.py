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

from .. import _version
from . import _backend
from .errors import IntegrityError, NotAMemoryError, Problem

# re-exported while ZarrStorage and the commit engine still call them here (they live in .format)
from .format import (  # noqa: F401, I001
    ARRAY_CONFIG,
    BACKUP_DIR,
    FORMAT_MARKER,
    FORMAT_VERSION,
    MARKER,
    RESERVED,
    chunk_keys,
    decode_chunks,
    dims,
    is_strict,
    numel,
    read_error,
    read_rows,
    row_chunk_key,
    write_zero_chunks,
    writing_config,
    writing_handles,
)

__all__ = ["IntegrityError", "IntegrityReport", "Problem", "RepairReport", "check_open", "repair", "verify"]

_TAGS = ("episode", "run", "env")
_KINDS = ("tensordict", "tensor", "pytree", "tensorclass")
_BACKUP_DIR = BACKUP_DIR
#: top-level names of the store's own folders: no stored array path may start with one
_RESERVED = RESERVED
#: what a pending journal's ``meta`` may set (a commit's length, cursor and counters), never the structure
_STRUCTURE = (FORMAT_MARKER, "max_size", "ndim", "inner_shape", "chunk_rows", "schema", "kind",
              "constants", "journal")
#: missing chunks listed one by one per array; the rest are counted in one problem
_LISTED = 8


# -- reports ----------------------------------------------------------------------------


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


# -- attributes ---------------------------------------------------------------------------


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def unsafe_path(path: Any) -> str | None:
    """Why an array path read from a store would leave the store or land on its own files (``None``: safe).

    Stored paths (schema keys, ``next/observation``) become file paths under the
    store: ``..``, absolute paths, backslashes, empty components, control
    characters and the store's own folders (``_journal``, ``_repair_backup``) are
    refused wherever a path read from a store is used.

    Example:
        >>> unsafe_path("next/observation") is None, unsafe_path("../other.zarr/observation")
        (True, "component '..' leaves the folder")
    """
    if not isinstance(path, str) or not path:
        return "not a non-empty string"
    if path.startswith("/"):
        return "an absolute path"
    if "\\" in path:
        return "a backslash (a path separator on Windows)"
    if any(ord(ch) < 32 or ord(ch) == 127 for ch in path):
        return "a control character"
    parts = path.split("/")
    for part in parts:
        if not part:
            return "an empty component"
        if part in (".", ".."):
            return f"component {part!r} leaves the folder"
        if part == "zarr.json":
            return "a component named 'zarr.json' (a metadata file)"
    if parts[0] in _RESERVED:
        return f"the store's own folder {parts[0]!r}"
    return None


def check_attributes(attrs: dict) -> list[Problem]:
    """Sanity of the commit record (the group attributes); a list of problems."""
    out: list[Problem] = []

    def bad(key, what):
        out.append(Problem("attribute", f"attribute {key!r} {what}", key="zarr.json"))

    marker = attrs.get(FORMAT_MARKER)
    if not isinstance(marker, dict) or not _is_int(marker.get("format_version")):
        bad(FORMAT_MARKER, f"is malformed ({marker!r})")
    elif marker["format_version"] > FORMAT_VERSION:
        out.append(Problem("format", f"written in format version {marker['format_version']} by torchrl_robotmem "
                           f"{marker.get('library_version')}; this version reads format <= "
                           f"{FORMAT_VERSION}: upgrade torchrl_robotmem", key="zarr.json"))
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
                why = unsafe_path(path)
                if why is not None:
                    bad("schema", f"key {path!r} is not a path inside the store ({why})")
                    continue
                ok = (isinstance(spec, dict) and isinstance(spec.get("dtype"), str) and isinstance(spec.get("shape"), list)
                      and all(_is_int(x) and x >= 0 for x in spec["shape"]))
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
    if (schema is not None and isinstance(inner, list) and _is_int(attrs.get("ndim", 1))
            and attrs.get("ndim", 1) - 1 > len(inner)):
        bad("ndim", f"is {attrs.get('ndim')}, but 'inner_shape' {inner} has only {len(inner)} dimensions")
    journal = attrs.get("journal")
    if journal is not None and not (isinstance(journal, dict) and isinstance(journal.get("meta"), dict)
                                    and isinstance(journal.get("chunks"), list)
                                    and all(_is_int(c) and c >= 0 for c in journal["chunks"])):
        bad("journal", f"is malformed ({str(journal)[:80]})")
    elif journal and not out:
        out += _journal_record_problems(attrs, journal)
    return out


def _journal_record_problems(attrs: dict, journal: dict) -> list[Problem]:
    """A pending journal's own record: what its replay would commit must be a sane commit record too."""
    def bad(what, **kw):
        return Problem("journal", f"the pending journal {what}; replaying it would commit that", key="zarr.json", **kw)

    meta = journal["meta"]
    structural = sorted(set(meta) & set(_STRUCTURE))
    if structural:
        return [bad(f"rewrites {structural} (a journal records a commit's length, cursor and counters only)")]
    out = [bad(f"records {p.what}") for p in check_attributes({**attrs, **meta, "journal": None})]
    if out or not attrs.get("schema"):
        return out
    chunks = journal["chunks"]
    nchunks = -(-dims(attrs)[0] // int(attrs["chunk_rows"]))
    if len(set(chunks)) != len(chunks) or any(c >= nchunks for c in chunks):
        out.append(bad(f"names chunks {sorted(chunks)[:8]} (the arrays have chunks 0..{nchunks - 1}, each once)"))
    return out


# -- arrays and chunks --------------------------------------------------------------------


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
        found = _disagreement(arr, path, spec, attrs)
        if found is not None:
            problems.append(found)
            continue
        arrays[path] = arr
    if list_chunks and n0:
        problems += _missing_chunks(arrays, attrs, store=store, local_dir=local_dir, present=present)
    return problems, arrays


def _disagreement(arr: Any, path: str, spec: dict, attrs: dict) -> Problem | None:
    """Where an array's own ``zarr.json`` and the commit record's schema disagree, a problem naming both."""
    max_dim0, _, inner = dims(attrs)
    chunk_rows = int(attrs["chunk_rows"])
    want_dtype = _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
    want_tail = (*inner, *spec["shape"])
    chunks = arr.metadata.chunk_grid.chunk_shape if hasattr(arr.metadata, "chunk_grid") else arr.chunks
    if not isinstance(arr, zarr.Array):
        return Problem("metadata", "is not an array", array=path, key=f"{path}/zarr.json")
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


def present_chunks(arrays: dict, *, store: Any, local_dir: Any) -> dict[str, set[int]]:
    """``{path: indices of the row chunks that have a file}``, one listing per array."""
    out = {}
    for path, arr in arrays.items():
        head, tail = row_chunk_key(arr, path)
        found = set()
        for key in _list_keys(store, local_dir, path):
            if key.startswith(head) and key.endswith(tail):
                mid = key[len(head): len(key) - len(tail)]
                if mid.isdigit():
                    found.add(int(mid))
        out[path] = found
    return out


def _first_missing(present: set[int], n: int, k: int) -> list[int]:
    """The first ``k`` indices below ``n`` not in ``present``: ``len(present) + k`` steps at most."""
    out, c = [], 0
    while c < n and len(out) < k:
        if c not in present:
            out.append(c)
        c += 1
    return out


def _missing_chunks(arrays: dict, attrs: dict, *, store: Any, local_dir: Any, present: dict | None = None) -> list[Problem]:
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
        cs = _first_missing(found, nchunks, _LISTED + 1)
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
    return [p for p in _missing_chunks(arrays, attrs, store=store, local_dir=local_dir) if p.severity == "error"]


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
        gap = _first_missing(covered, last - first, 1)
        if gap:
            c = gap[0] + first
            out.append(Problem(
                "journal", f"the pending journal's 'len' ({journal['meta'].get('len')}) claims rows that neither "
                f"the journal (chunks {sorted(chunks)[:8]}) nor the arrays hold; replaying it would serve them as zeros",
                chunk=c, rows=(c * rows, min((c + 1) * rows, meta_n0)), key="zarr.json"))
    top = (max(chunks) + 1) * rows if chunks else 0
    for p, spec in attrs["schema"].items():
        jp = f"_journal/{p}"
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


# -- what a store's sizes cost --------------------------------------------------------------


def _memory_limit() -> int | None:
    """Bytes this process could ever allocate: RAM + swap, or its address-space / data limit if lower."""
    limit = None
    try:
        limit = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("SwapTotal:"):
                    limit += int(line.split()[1]) * 1024
    except (ValueError, OSError, AttributeError):
        pass
    try:
        import resource

        for which in (resource.RLIMIT_AS, resource.RLIMIT_DATA):
            soft = resource.getrlimit(which)[0]
            if soft != resource.RLIM_INFINITY and soft > 0:
                limit = soft if limit is None else min(limit, soft)
    except (ImportError, OSError, ValueError):
        pass
    return limit


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n} B"


def capacity_problem(attrs: dict, *, mirror: bool = True) -> Problem | None:
    """Sizes of sane attributes that no process here could hold, as a problem naming the field; else ``None``.

    ``mirror``: the RAM mirror a ``ZarrStorage`` allocates (``max_size`` rows);
    otherwise one chunk (what ``verify`` decodes at a time).
    """
    if not attrs.get("schema"):
        return None
    from .schema import PackedLayout

    max_dim0, _, inner = dims(attrs)
    chunk_rows = int(attrs["chunk_rows"])
    per_row = max(math.prod(inner), 1) * PackedLayout(attrs["schema"]).row_bytes
    rows = max(max_dim0, chunk_rows) if mirror else chunk_rows
    limit = _memory_limit()
    if limit is None or rows * per_row <= limit:
        return None

    def leaf(spec):
        return _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"])).itemsize * math.prod(spec["shape"])

    path, spec = max(attrs["schema"].items(), key=lambda kv: leaf(kv[1]))
    if leaf(spec) * max(math.prod(inner), 1) * 1024 > limit:
        field = f"attribute 'schema' entry {path!r} (shape {spec['shape']})"
    elif inner and math.prod(inner) * 1024 > limit:
        field = f"attribute 'inner_shape' ({list(inner)})"
    elif chunk_rows >= max_dim0 or not mirror:
        field = f"attribute 'chunk_rows' ({chunk_rows})"
    else:
        field = f"attribute 'max_size' ({attrs['max_size']})"
    what = "its RAM mirror" if mirror else "one chunk"
    return Problem("capacity", f"{field}: {what} of {rows} rows of {per_row} bytes would take {_size(rows * per_row)}, "
                   f"more than this machine can allocate ({_size(limit)}: RAM + swap, or this process's limit)",
                   key="zarr.json")


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
    capacity = None if problems else capacity_problem(attrs)
    if capacity is not None:  # before anything is listed or allocated
        raise ValueError(f"The store at {path!r} cannot be opened on this machine: {capacity.what}. "
                         f"Nothing was read or changed; `robotmem verify {path}` checks it chunk by chunk.")
    if not problems:
        def get_array(p):
            node = group[p]
            if not isinstance(node, zarr.Array):
                raise ValueError(f"{p!r} is a group, not an array")
            return node

        present: dict = {}
        more, arrays = check_arrays(get_array, attrs, store=store, local_dir=local_dir, list_chunks=list_chunks,
                                    present=present)
        problems += more
        journal = attrs.get("journal")
        if journal and not any(p.kind == "metadata" for p in more):
            problems += check_journal(get_array, attrs, arrays, present if list_chunks else None)
        if (decode or on_damage == "warn") and not any(p.kind in ("metadata", "journal") for p in problems):
            _, n0, _ = dims(attrs)
            for p, arr in arrays.items():
                problems += decode_chunks(arr, p, n0, int(attrs["chunk_rows"]), present.get(p))[0]
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
    _, n0, inner = dims(attrs)
    ndim = int(attrs.get("ndim", 1))
    numel = max(math.prod(inner[: ndim - 1]) if ndim > 1 else 1, 1)
    warnings.warn(
        f"{IntegrityError(path, errors, read_only=True, action='')}\non_damage='warn': reading the "
        f"{cut} rows before the first damaged chunk (of {n0} committed).",
        stacklevel=4,
    )
    return {**attrs, "len": min(int(attrs.get("len", 0)), cut * numel), "cursor": cut % dims(attrs)[0],
            "last_cursor": cut - 1, "journal": None}


# -- verify -------------------------------------------------------------------------------


def _get_bytes(store: Any, key: str) -> bytes | None:
    buf = zarr_sync(store.get(key, prototype=default_buffer_prototype()))
    return None if buf is None else buf.to_bytes()


def _set_bytes(store: Any, key: str, data: bytes, local_dir: Any = None) -> None:
    _check_key(key, local_dir)
    zarr_sync(store.set(key, default_buffer_prototype().buffer.from_bytes(data)))


def _delete(store: Any, key: str, local_dir: Any) -> None:
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
    if FORMAT_MARKER not in attrs:
        raise NotAMemoryError(f"{name!r} is a Zarr group without the {FORMAT_MARKER!r} attribute.")
    report.problems += check_attributes(attrs)
    if report.problems:
        return report
    report.rows = int(attrs.get("len", 0))
    capacity = capacity_problem(attrs, mirror=False)
    if capacity is not None:  # no chunk of it could be decoded here
        report.problems.append(capacity)
        return report

    def get_array(p):
        return zarr.open_array(store, path=p, mode="r", zarr_format=3)

    present: dict = {}
    more, arrays = check_arrays(get_array, attrs, store=store, local_dir=local_dir, present=present)
    report.problems += more
    report.arrays = len(attrs.get("schema") or {})
    report.checksums = bool(arrays) and all(
        any(type(c).__name__ == "Crc32cCodec" for c in arr.metadata.codecs) for arr in arrays.values())
    if attrs.get("schema"):
        _, n0, _ = dims(attrs)
        for p, arr in arrays.items():
            found, n = decode_chunks(arr, p, n0, int(attrs["chunk_rows"]), present.get(p))
            report.problems += found
            report.chunks += n
        journal = attrs.get("journal")
        if journal:
            report.problems += check_journal(get_array, attrs, arrays, present)
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

    It refuses, changing nothing, where fixing the store would mean trusting one
    record over another or leaving the store's folder: a path read from the store
    (a schema key, ``../other.zarr/observation``) that is not inside it, a
    symbolic link inside it, an array whose own ``zarr.json`` disagrees with the
    schema (dtype, shape, chunking: both records are named; restore the right one
    from a copy), a rebuilt ``zarr.json`` that decodes none of the array's
    chunks, or sizes no machine here can hold. A store of a newer format version
    is not touched (upgrade torchrl_robotmem).

    It takes the writer lock first (an error if a process is writing the store;
    for ``s3://`` stores, the lease; for other URL stores, stop the writer first).
    Readers may keep reading meanwhile: a chunk it moves away is an
    :class:`IntegrityError` naming it in a reader that was reading it, never zeros.

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
    store, local_dir = _open_any(path, storage_options, writable=not dry_run)
    lock = None if dry_run else _writer_lock(path, local_dir, storage_options)
    try:
        before = verify(path, storage_options=storage_options)  # under the lock: no writer changes it meanwhile
        if before.ok:
            return RepairReport(before, before)
        if any(p.kind == "format" for p in before.problems):
            raise IntegrityError(before.path, before.errors, action="repair does not touch a store of a newer format:")
        metas = _refusals(before, store, local_dir)
        return _repair(before, store, local_dir, path, storage_options, dry_run, metas)
    finally:
        if lock is not None:
            lock.release()


def _writer_lock(path: Any, local_dir: Any, storage_options: dict | None):
    """The writer lock of the store, for as long as ``repair`` writes (``None`` where there is none)."""
    name = _backend.normalize_path(path)
    try:
        if local_dir is not None:
            return _backend.WriterLock(local_dir)
        if isinstance(name, str) and _backend.is_url(name):
            return _backend.url_writer_lock(name, storage_options)
    except RuntimeError as err:
        raise RuntimeError(f"robotmem repair needs the store to itself and did not change it: {err} "
                           f"Stop the writer (or let it finish), then run repair again.") from None
    return None


def _refuse(path: Any, problems: list[Problem], why: str) -> IntegrityError:
    return IntegrityError(path, problems, read_only=True, action=f"repair refuses this store: {why}; nothing was changed.",
                          hint=f"`robotmem verify {path}` lists everything found.")


def _refusals(before: IntegrityReport, store: Any, local_dir: Any) -> dict[str, bytes]:
    """What makes ``repair`` refuse, checked before it writes anything; returns the array metadata to rebuild.

    Raises :class:`IntegrityError` naming the records at fault (a path leaving
    the store, a symbolic link, two records that disagree, a rebuilt
    ``zarr.json`` that decodes none of the chunks) or the size no machine here
    can hold.
    """
    name = before.path
    if local_dir is not None:
        links = _symlinks(local_dir)
        if links:
            raise _refuse(name, [Problem("metadata", f"a symbolic link (to {os.readlink(os.path.join(local_dir, k))!r})",
                                         key=k) for k in links], "repair writes only inside the store's folder")
    attrs, _ = _read_group_attrs(store)
    if attrs is None:
        attrs = _rebuild_attrs(store, local_dir)
    schema = attrs.get("schema")
    if isinstance(schema, dict):
        unsafe = [(k, unsafe_path(k)) for k in schema if unsafe_path(k) is not None]
        if unsafe:
            raise _refuse(name, [Problem("attribute", f"schema key {k!r} is not a path inside the store ({why})",
                                         key="zarr.json") for k, why in unsafe], "it names paths outside it")
    if {p.what.split("'")[1] for p in check_attributes(attrs) if p.kind == "attribute"} & {
            "schema", "chunk_rows", "max_size", "inner_shape", "ndim", FORMAT_MARKER}:
        return {}  # the structure is recomputed from the arrays' own metadata: nothing to disagree with
    capacity = capacity_problem(attrs)
    if capacity is not None:
        raise _refuse(name, [capacity], "its sizes are more than this machine can hold")
    found, metas = [], {}
    for p, spec in schema.items():
        try:
            arr = zarr.open_array(store, path=p, mode="r", zarr_format=3)
        except Exception:  # noqa: BLE001 - missing or unreadable: rebuilt, if the chunks agree
            arr = None
        if arr is not None:
            problem = _disagreement(arr, p, spec, attrs)
            if problem is not None:
                found.append(problem)
            continue
        try:
            jarr = zarr.open_array(store, path=f"_journal/{p}", mode="r", zarr_format=3)
        except Exception:  # noqa: BLE001 - no journal array to compare with
            jarr = None
        if jarr is not None and (np.dtype(jarr.dtype) != _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
                                 or tuple(jarr.shape[1 + len(dims(attrs)[2]):]) != tuple(spec["shape"])):
            found.append(Problem("metadata", f"array metadata missing, and the journal's copy (_journal/{p}/zarr.json) "
                                 f"records {np.dtype(jarr.dtype)} {list(jarr.shape)} where the schema records "
                                 f"{spec['dtype']} {spec['shape']}", array=p, key=f"{p}/zarr.json"))
            continue
        meta = _rebuild_array_meta(store, local_dir, p, attrs)
        if meta is None:
            found.append(Problem("metadata", f"array metadata missing, and none of its chunk files decodes as the "
                                 f"schema records it ({spec['dtype']} {spec['shape']} in chunks of "
                                 f"{attrs['chunk_rows']} rows)", array=p, key=f"{p}/zarr.json"))
            continue
        metas[p] = meta
    if found:
        raise _refuse(name, found, "its records disagree, and repair does not choose between them (restore the "
                      "right one from a copy of the store)")
    return metas


def _symlinks(local_dir: Any) -> list[str]:
    """Store keys of the symbolic links inside a local store (repair never writes through one)."""
    out = []
    root = os.fspath(local_dir)
    for dirpath, dirs, files in os.walk(root):
        for entry in dirs + files:
            full = os.path.join(dirpath, entry)
            if os.path.islink(full):
                out.append(os.path.relpath(full, root).replace(os.sep, "/"))
    return sorted(out)


def _repair(before, store, local_dir, path, storage_options, dry_run, metas) -> RepairReport:
    actions: list[str] = []
    backup = None
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S-%f")
    if not dry_run:
        backup = f"{_BACKUP_DIR}/{stamp}"
        for key in ["zarr.json"] + [f"{p}/zarr.json" for p in _array_metas(store, local_dir)]:
            raw = _get_bytes(store, key)
            if raw is not None:
                _set_bytes(store, f"{backup}/{key}", raw, local_dir)
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
    max_dim0, _, inner = dims(new)
    for path_ in new.get("schema") or {}:
        try:
            arr = zarr.open_array(store, path=path_, mode="r", zarr_format=3)
        except Exception:  # noqa: BLE001 - missing or unreadable: rebuilt below
            arr = None
        if arr is not None:
            disagree = _disagreement(arr, path_, new["schema"][path_], new)
            if disagree is not None:  # (the schema was recomputed from these very arrays: never here)
                raise _refuse(before.path, [disagree], "its records disagree")
            continue
        meta = metas.get(path_) or _rebuild_array_meta(store, local_dir, path_, new)
        if meta is None:
            raise _refuse(before.path, [Problem("metadata", "array metadata missing, and none of its chunk files "
                                                "decodes as the schema records it", array=path_)], "its records disagree")
        actions.append(f"rebuilt the metadata of array {path_!r} ({path_}/zarr.json)")
        if not dry_run:
            _set_bytes(store, f"{path_}/zarr.json", meta, local_dir)
    # -- the committed length
    n_dim0 = None
    if "len" in bad_attrs or group_rebuilt:
        n_dim0 = _written_extent(store, new, limit=max_dim0)
    else:
        _, n_dim0, _ = dims(new)
    if not dry_run:
        data = _data_problems(store, local_dir, {**new, "len": n_dim0 * numel(new)})
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
        actions.append(f"truncated the committed length from {n_dim0 * numel(new)} to {trimmed * numel(new)} rows: "
                       + "; ".join(str(p) for p in data[:4]) + (" ..." if len(data) > 4 else ""))
        n_dim0 = trimmed
        for p in data:
            if p.kind != "missing_chunk" and p.key and not dry_run:
                raw = _get_bytes(store, p.key)
                if raw is not None:
                    _set_bytes(store, f"{backup}/{p.key}", raw, local_dir)
                _delete(store, p.key, local_dir)
                actions.append(f"moved the damaged chunk {p.key} to {backup}/{p.key}")
    elif "len" in bad_attrs:
        actions.append(f"set the committed length to {n_dim0 * numel(new)} rows (the written rows)")
    length = n_dim0 * numel(new)
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
            _set_bytes(store, "zarr.json", json.dumps(doc, indent=2).encode(), local_dir)
        elif changes:
            zarr.open_group(store, mode="r+", zarr_format=3).update_attributes(changes)
    after = None if dry_run else verify(path, storage_options=storage_options)
    return RepairReport(before, after, actions, backup)


def _data_problems(store, local_dir, attrs) -> list[Problem]:
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


def _written_extent(store, attrs, *, limit: int) -> int:
    """Rows (dim 0) up to the last one below ``limit`` holding a non-zero value in any array."""
    rows = int(attrs["chunk_rows"])
    arrays = _readable_arrays(store, attrs)
    # only chunks with a file can hold a non-zero value: the cost follows what the store holds
    present: set[int] = set()
    for found in present_chunks({a.path: a for a in arrays}, store=store, local_dir=_local_dir_of(store)).values():
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


def _local_dir_of(store: Any) -> Any:
    root = getattr(store, "root", None)
    return root if root is not None and os.path.isdir(os.fspath(root)) else None


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
    marker = {"format_version": FORMAT_VERSION, "library_version": _version.__version__,
              "rebuilt_by": "robotmem repair"}
    if strict:
        marker["integrity"] = dict(MARKER)
    return {FORMAT_MARKER: marker, "max_size": int(min(a.shape[0] for a in arrays.values())),
            "ndim": 1, "inner_shape": inner, "chunk_rows": int(ref.metadata.chunk_grid.chunk_shape[0]),
            "schema": schema, "kind": kind, "len": 0, "cursor": 0, "last_cursor": -1, "write_count": 0,
            "episode_next": 0, "runs": 0, "env_names": [], "env": None, "journal": None}


def _backend_pytree_prefix() -> str:
    from .schema import DataKind

    return DataKind.PYTREE_KEY + "/"


def _rebuild_array_meta(store, local_dir, path: str, attrs: dict) -> bytes | None:
    """``zarr.json`` of array ``path`` from the schema, with the codecs its chunks decode with.

    Each candidate pipeline (checksummed ones first) decodes a chunk file of the
    array in a scratch in-memory store; the first that decodes one of its first
    three chunk files wins. ``None`` if none does: the schema does not describe
    these chunks (another dtype or shape), and nothing is rebuilt from it.
    """
    from zarr.storage import MemoryStore

    spec = attrs["schema"][path]
    max_dim0, _, inner = dims(attrs)
    dtype = _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
    shape = (max_dim0, *inner, *spec["shape"])
    chunks = (int(attrs["chunk_rows"]), *shape[1:])
    keys = sorted(k for k in _list_keys(store, local_dir, path) if k.startswith(f"{path}/c/"))[:3]
    first = None
    for key in keys or [None]:
        raw = _get_bytes(store, key) if key is not None else None
        for checksum in (True, False):
            for comp in ("blosc", "zstd", None):
                mem = MemoryStore()
                arr = zarr.create_array(mem, name="a", shape=shape, chunks=chunks, dtype=dtype, fill_value=0,
                                        compressors=_backend.make_compressors(comp, 1, dtype.itemsize, checksum=checksum))
                meta = _get_bytes(mem, "a/zarr.json")
                if raw is None:
                    return meta  # no chunk file to decode: the schema's description, checksummed
                first = first or meta
                rel = key[len(path) + 1:]
                _set_bytes(mem, f"a/{rel}", raw)
                c = int(rel.split("/")[1])
                try:
                    arr[c * chunks[0]:(c + 1) * chunks[0]]
                    return meta
                except Exception:  # noqa: BLE001 - not this pipeline
                    continue
    return None
