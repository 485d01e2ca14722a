"""The commit record's checks: the group attributes a store opens with must make sense.

Integers within ``[0, max_size]``, a format marker this version reads, a schema
of known dtypes whose keys are paths inside the store, parseable tag tables and
data kind, and a pending journal whose replay would commit a sane record too.
Nothing here reads an array: the attributes are JSON.

Example:
    >>> from torchrl_robotmem.storage.integrity.attributes import check_attributes
    >>> [str(p) for p in check_attributes({"torchrl_robotmem": {"format_version": 1}, "max_size": 10, "len": 20})]
    ["zarr.json: attribute 'len' must be an integer in [0, 10], got 20", "zarr.json: attribute 'len' is 20 but the store records no schema"]
"""
from __future__ import annotations

from typing import Any

from .. import _backend
from ..errors import Problem
from ..format import FORMAT_MARKER, FORMAT_VERSION, RESERVED, dims
from ..schema import DataKind, same_constant

__all__ = ["bad_attributes", "check_attributes", "is_int", "unsafe_path"]

_KINDS = ("tensordict", "tensor", "pytree", "tensorclass")
#: what a pending journal's ``meta`` may set (a commit's length, cursor and counters, and constants it adds:
#: ``_added_constants``), never the structure
_STRUCTURE = (FORMAT_MARKER, "max_size", "ndim", "inner_shape", "chunk_rows", "schema", "kind", "journal")


def is_int(v: Any) -> bool:
    """An ``int`` that is not a ``bool`` (JSON ``true`` is no length)."""
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
    if parts[0] in RESERVED:
        return f"the store's own folder {parts[0]!r}"
    return None


def check_attributes(attrs: dict) -> list[Problem]:
    """Sanity of the commit record (the group attributes); a list of problems.

    Args:
        attrs (dict): the group attributes.

    Returns:
        ``"attribute"`` problems naming each insane attribute, a ``"format"``
        problem for a newer format, ``"journal"`` problems for a pending
        journal whose replay would commit an insane record.
    """
    out = _size_problems(attrs) + _layout_problems(attrs) + _table_problems(attrs)
    schema, inner = attrs.get("schema"), attrs.get("inner_shape")
    if (schema is not None and isinstance(inner, list) and is_int(attrs.get("ndim", 1))
            and attrs.get("ndim", 1) - 1 > len(inner)):
        out.append(_bad("ndim", f"is {attrs.get('ndim')}, but 'inner_shape' {inner} has only {len(inner)} dimensions"))
    journal = attrs.get("journal")
    if journal is not None and not (isinstance(journal, dict) and isinstance(journal.get("meta"), dict)
                                    and isinstance(journal.get("chunks"), list)
                                    and all(is_int(c) and c >= 0 for c in journal["chunks"])):
        out.append(_bad("journal", f"is malformed ({str(journal)[:80]})"))
    elif journal and not out:
        out += _journal_record_problems(attrs, journal)
    return out


def bad_attributes(attrs: dict) -> set[str]:
    """The names of the attributes :func:`check_attributes` finds insane (``{"len", "cursor"}``)."""
    return {p.what.split("'")[1] for p in check_attributes(attrs) if p.kind == "attribute"}


def _bad(key: str, what: str) -> Problem:
    return Problem("attribute", f"attribute {key!r} {what}", key="zarr.json")


def _size_problems(attrs: dict) -> list[Problem]:
    """The format marker, the capacity, the counters, the length and the cursors."""
    out = []
    marker = attrs.get(FORMAT_MARKER)
    if not isinstance(marker, dict) or not is_int(marker.get("format_version")):
        out.append(_bad(FORMAT_MARKER, f"is malformed ({marker!r})"))
    elif marker["format_version"] > FORMAT_VERSION:
        out.append(Problem("format", f"written in format version {marker['format_version']} by torchrl_robotmem "
                           f"{marker.get('library_version')}; this version reads format <= "
                           f"{FORMAT_VERSION}: upgrade torchrl_robotmem", key="zarr.json"))
    max_size = attrs.get("max_size")
    if not is_int(max_size) or max_size < 1:
        out.append(_bad("max_size", f"must be a positive integer, got {max_size!r}"))
        max_size = None
    for key, lo, default in (("ndim", 1, 1), ("write_count", 0, 0), ("episode_next", 0, 0), ("runs", 0, 0),
                             ("overwrites", 0, 0)):
        v = attrs.get(key, default)
        if not is_int(v) or v < lo:
            out.append(_bad(key, f"must be an integer >= {lo}, got {v!r}"))
    for key, lo, default, hi_off in (("len", 0, 0, 0), ("cursor", 0, 0, 0), ("last_cursor", -1, -1, 1)):
        v = attrs.get(key, default)
        if not is_int(v) or v < lo or (max_size is not None and v > max_size - hi_off):
            rng = f"[{lo}, {max_size - hi_off}]" if max_size is not None else f">= {lo}"
            out.append(_bad(key, f"must be an integer in {rng}, got {v!r}"))
    return out


def _layout_problems(attrs: dict) -> list[Problem]:
    """The chunking, the inner shape and the schema (array paths, dtypes, row shapes)."""
    out = []
    cr = attrs.get("chunk_rows")
    if cr is not None and (not is_int(cr) or cr < 1):
        out.append(_bad("chunk_rows", f"must be a positive integer, got {cr!r}"))
    inner = attrs.get("inner_shape")
    if inner is not None and not (isinstance(inner, list) and all(is_int(x) and x >= 0 for x in inner)):
        out.append(_bad("inner_shape", f"must be a list of non-negative integers, got {inner!r}"))
    schema = attrs.get("schema")
    if schema is not None:
        if cr is None:
            out.append(_bad("chunk_rows", "is missing although the store holds arrays"))
        if not isinstance(schema, dict) or not schema:
            out.append(_bad("schema", f"must map array paths to {{dtype, shape}}, got {type(schema).__name__}"))
        else:
            out += [p for path, spec in schema.items() for p in _schema_entry_problems(path, spec)]
    elif is_int(attrs.get("len", 0)) and attrs.get("len", 0) > 0:
        out.append(_bad("len", f"is {attrs.get('len')} but the store records no schema"))
    return out


def _schema_entry_problems(path: Any, spec: Any) -> list[Problem]:
    why = unsafe_path(path)
    if why is not None:
        return [_bad("schema", f"key {path!r} is not a path inside the store ({why})")]
    ok = (isinstance(spec, dict) and isinstance(spec.get("dtype"), str) and isinstance(spec.get("shape"), list)
          and all(is_int(x) and x >= 0 for x in spec["shape"]))
    if ok:
        try:
            _backend.torch_dtype(spec["dtype"])
        except ValueError:
            ok = False
    return [] if ok else [_bad("schema", f"entry {path!r} is malformed ({spec!r})")]


def _table_problems(attrs: dict) -> list[Problem]:
    """The data kind, the env names, the constants and the current env."""
    out = []
    kind = attrs.get("kind")
    if kind is not None:
        try:  # JSON only: nothing is imported or executed
            if not isinstance(kind, dict) or kind.get("kind") not in _KINDS:
                raise ValueError(kind)
            DataKind.from_json(kind)
        except Exception:  # noqa: BLE001 - any failure to parse is the finding
            out.append(_bad("kind", f"does not parse ({str(kind)[:80]})"))
    names = attrs.get("env_names", [])
    if not isinstance(names, list) or not all(isinstance(x, str) for x in names):
        out.append(_bad("env_names", f"must be a list of names, got {str(names)[:80]}"))
    constants = attrs.get("constants") or {}
    if not isinstance(constants, dict) or not all(
        isinstance(k, str) and (v is None or isinstance(v, (str, int, float, bool))) for k, v in constants.items()
    ):
        out.append(_bad("constants", f"must map keys to JSON scalars, got {str(constants)[:80]}"))
    env = attrs.get("env")
    if env is not None and not isinstance(env, str):
        out.append(_bad("env", f"must be a name or null, got {env!r}"))
    return out


def _added_constants(before: Any, after: Any) -> bool:
    """Whether a journal's ``constants`` keep every constant of the record as it is, type included (a commit
    adds new ones with the rows that carry them; it never changes or drops one: ``1`` is not ``True``)."""
    before = before or {}
    return (isinstance(before, dict) and isinstance(after, dict)
            and all(k in after and same_constant(v, after[k]) for k, v in before.items()))


def _journal_record_problems(attrs: dict, journal: dict) -> list[Problem]:
    """A pending journal's own record: what its replay would commit must be a sane commit record too."""
    def bad(what, **kw):
        return Problem("journal", f"the pending journal {what}; replaying it would commit that", key="zarr.json", **kw)

    meta = journal["meta"]
    structural = sorted(set(meta) & set(_STRUCTURE))
    if "constants" in meta and not _added_constants(attrs.get("constants"), meta["constants"]):
        structural = sorted([*structural, "constants"])
    if structural:
        return [bad(f"rewrites {structural} (a journal records a commit's length, cursor and counters, and "
                    f"constants it adds, only)")]
    out = [bad(f"records {p.what}") for p in check_attributes({**attrs, **meta, "journal": None})]
    if out or not attrs.get("schema"):
        return out
    chunks = journal["chunks"]
    nchunks = -(-dims(attrs)[0] // int(attrs["chunk_rows"]))
    if len(set(chunks)) != len(chunks) or any(c >= nchunks for c in chunks):
        out.append(bad(f"names chunks {sorted(chunks)[:8]} (the arrays have chunks 0..{nchunks - 1}, each once)"))
    return out


