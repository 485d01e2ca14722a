"""A memory as one ``.npz`` file: :func:`export_npz` writes it, :func:`import_npz` reads it into a new memory.

The file holds one array per stored key (nested keys joined with ``/``, e.g.
``next/observation``), rows in write order (oldest first), the tag columns
``episode`` / ``run`` / ``env`` among them, and ``__robotmem__``: a 0-d string
array holding JSON (env names, data kind, ``ndim``, ``max_size``, ``rows``).
Nothing is pickled. ``import`` restores every column and tag, so
npz -> memory -> npz is bit-exact (float64 columns: with ``keep_float64``;
by default they are stored as float32). A file without ``__robotmem__`` is
read as a plain npz of transitions (:mod:`.plain_npz`). Both build their output beside the target
and rename it into place (:mod:`._build`). An imported file is not trusted
(:mod:`._archive`): every member's zip and ``.npy`` headers are checked against
the file's size, and what the import will allocate (the arrays, and the RAM
mirror of ``max_size`` rows) against the memory this process can get, before
anything is read or created; a truncated, damaged or oversized file is one
:class:`~torchrl_robotmem.cli.CLIError` naming it and the member, and nothing is created.
"""
from __future__ import annotations

import json
import math
import os
from typing import Any

import numpy as np

from ._archive import READ_ERRORS, as_count, check_fits, inspect_npz, read_member
from ._build import atomic_target, check_target, new_store, progress
from ._memory import TAGS, column, open_settled, root_attrs, write_order
from .errors import CLIError
from .plain_npz import import_plain_npz
from .transitions import cast_float64

__all__ = ["META_KEY", "NPZ_FORMAT", "NPZ_VERSION", "export_npz", "import_npz", "load_npz", "open_npz"]

META_KEY = "__robotmem__"
NPZ_FORMAT = "torchrl_robotmem.npz"
NPZ_VERSION = 1
_MAX_RECORD = 64 << 20  # the JSON record: a schema of many keys is a few KiB


def export_npz(path: Any, out: str) -> dict[str, Any]:
    """Writes every column of the memory at ``path`` to ``out`` (``.npz``), rows in write order.

    Args:
        path: the memory (opened read-only).
        out (str): the ``.npz`` file to create (refused if it exists).

    Returns:
        the JSON metadata written under ``__robotmem__``.

    Example:
        >>> import tempfile, numpy as np, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.cli.npz_io import export_npz
        >>> d = tempfile.mkdtemp()
        >>> st = ZarrStorage(d + "/m.zarr", 10, env="FetchReach-v4", background=False)
        >>> st.set(slice(0, 3), TensorDict({"obs": torch.arange(3.0), ("next", "done"): torch.ones(3, 1, dtype=torch.bool)}, [3]))
        >>> st.close()
        >>> meta = export_npz(d + "/m.zarr", d + "/m.npz")
        >>> sorted(np.load(d + "/m.npz").files)
        ['__robotmem__', 'env', 'episode', 'next/done', 'obs', 'run']
        >>> np.load(d + "/m.npz")["episode"].tolist(), meta["env_names"]
        ([0, 1, 2], ['FetchReach-v4'])
    """
    check_target(out)
    if not out.endswith(".npz"):
        raise CLIError(f"{out!r}: an npz export's name ends with .npz")
    storage = open_settled(path)
    try:
        attrs = root_attrs(storage)
        schema = attrs.get("schema") or {}
        if META_KEY in schema:
            raise CLIError(f"the memory has a key named {META_KEY!r}, which the npz format reserves")
        order = write_order(storage)
        arrays = {p: column(storage, tuple(p.split("/")) if "/" in p else p, order)
                  for p in progress(sorted(schema), desc="export", unit="key")}
        meta = {
            "format": NPZ_FORMAT,
            "version": NPZ_VERSION,
            "source": str(storage.path),
            "env_names": list(storage.env_names),
            "kind": attrs.get("kind"),
            "ndim": int(attrs.get("ndim", 1)),
            "max_size": int(storage.max_size) if storage.bounded else None,  # None: a memory that grows
            "rows": len(storage),
            "schema": schema,
        }
    finally:
        storage.close()
    with atomic_target(out) as tmp:
        np.savez(tmp, **arrays, **{META_KEY: np.array(json.dumps(meta))})
    return meta


def import_npz(src: str, path: str, *, max_size: int | None = None, env: str | None = None,
               keep_float64: bool = False, notes: list[str] | None = None) -> int:
    """Creates the memory ``path`` from an ``.npz`` written by :func:`export_npz`, or a plain one; returns its rows.

    A file without the ``__robotmem__`` record is a plain npz of transitions
    (any tool's): see :mod:`.plain_npz` for its arrays.

    Args:
        src (str): the ``.npz`` file (loaded with ``allow_pickle=False``).
        path (str): the memory to create (refused if it exists).

    Keyword Args:
        max_size (int, optional): capacity; defaults to the exported memory's.
        env (str, optional): tag every row with this env instead of the exported env tags.
        keep_float64 (bool): keep float64 arrays (default: stored as float32).
        notes (list, optional): what was cast (or, for a plain npz, ignored or recomputed) is appended here.

    Example:
        >>> import tempfile, numpy as np, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.cli.npz_io import export_npz, import_npz
        >>> d = tempfile.mkdtemp()
        >>> st = ZarrStorage(d + "/a.zarr", 10, background=False)
        >>> st.set(slice(0, 4), TensorDict({"obs": torch.arange(4.0)}, [4]))
        >>> st.close()
        >>> _ = export_npz(d + "/a.zarr", d + "/a.npz")
        >>> import_npz(d + "/a.npz", d + "/b.zarr")
        4
        >>> ZarrStorage(d + "/b.zarr", read_only=True)["obs"].tolist()
        [0.0, 1.0, 2.0, 3.0]
    """
    check_target(path)
    if not os.path.isfile(src):
        raise CLIError(f"{src!r} is not a file")
    data = load_npz(src)
    if META_KEY not in data.files:
        return import_plain_npz(data, src, path, max_size=max_size, env=env, keep_float64=keep_float64, notes=notes)
    arrays, meta, capacity = _read_export(src, max_size=max_size, keep_float64=keep_float64)
    cast = cast_float64(arrays, keep_float64=keep_float64)
    if cast and notes is not None:
        notes.append(f"float64 stored as float32 (--keep-float64 keeps it): {', '.join(sorted(cast))}")
    rows, ndim = meta["rows"], meta["ndim"]
    with new_store(path, capacity, ndim=ndim, background=False) as storage:
        if rows:
            _load_rows(storage, arrays, meta, src=src, env=env)
        elif env is not None:
            storage.env = env
    return rows


def _read_export(src: str, *, max_size: int | None = None,
                 keep_float64: bool = True) -> tuple[dict[str, np.ndarray], dict[str, Any], int]:
    """``(arrays, metadata, capacity)`` of the npz export ``src``, every array checked against the metadata.

    The headers are checked (shapes against the metadata, sizes against the file,
    the arrays and the new memory's RAM mirror against the memory this process
    can get) before any array is read.
    """
    if not os.path.isfile(src):
        raise CLIError(f"{src!r} is not a file")
    data, meta = open_npz(src)
    if meta.get("format") != NPZ_FORMAT or as_count(meta.get("version", 0), src, "version") > NPZ_VERSION:
        raise CLIError(f"{src!r}: unknown npz format {meta.get('format')!r} version {meta.get('version')!r}")
    keys = [k for k in data.files if k != META_KEY]
    schema = meta.get("schema") or {}
    if not isinstance(schema, dict) or not all(isinstance(v, dict) for v in schema.values()):
        raise CLIError(f"{src!r}: its record's 'schema' is not a map of arrays (an edited export?)")
    missing = sorted(set(schema) - set(keys))
    if missing:
        raise CLIError(f"{src!r} lacks the arrays {missing} its metadata lists (a cut-off export?); export it again")
    rows = meta["rows"] = as_count(meta.get("rows", 0), src, "rows")
    ndim = meta["ndim"] = as_count(meta.get("ndim", 1), src, "ndim")
    if ndim < 1:
        raise CLIError(f"{src!r}: its record's 'ndim' is {ndim}, not a positive integer (an edited export?)")
    members = inspect_npz(src, keys)
    lead = None
    for k in keys:
        m = members.get(k)
        if m is None:
            raise CLIError(f"{src!r}: member {k!r} is not an .npy array; the file is damaged or not a robotmem export")
        spec = schema.get(k)
        if spec is not None and (str(m.dtype) != spec.get("dtype") or
                                 list(m.shape[len(m.shape) - len(spec.get("shape") or []):]) != spec.get("shape")):
            raise CLIError(f"{src!r}: array {k!r} has dtype {m.dtype} and shape {list(m.shape)}, "
                           f"its metadata says {spec.get('dtype')} {spec.get('shape')} per row")
        n0 = m.shape[0] if m.shape else None
        if n0 is None or (lead is not None and n0 != lead[1]) or (ndim == 1 and n0 != rows):
            raise CLIError(f"{src!r}: array {k!r} holds {n0} rows, but "
                           + (f"{lead[0]!r} holds {lead[1]}" if lead is not None and n0 != lead[1]
                              else f"the metadata says {rows}") + " (a cut-off or edited export); export it again")
        lead = lead or (k, n0)
    capacity = _capacity(src, meta, members, max_size, keep_float64)
    arrays = {k: read_member(data, src, k) for k in progress(keys, desc="read", unit="key")}
    return arrays, meta, capacity


def _capacity(src: str, meta: dict[str, Any], members: dict, max_size: int | None, keep_float64: bool) -> int | None:
    """The new memory's ``max_size``, checked: the arrays read and its RAM mirror fit in the memory left.

    ``None``: the export is of a memory without a declared capacity (its record says ``max_size: null``),
    and the import grows as it did.
    """
    rows = meta["rows"]
    if not max_size and "max_size" in meta and meta["max_size"] is None:
        check_fits(members, src, 0, rows, "")
        return None
    capacity = int(max_size) if max_size else as_count(meta.get("max_size") or rows, src, "max_size")
    if capacity < rows:
        raise CLIError(f"--max-size {capacity} is smaller than the {rows} rows in {src!r}")
    n0 = next(iter(members.values())).shape[0] if members else 0
    per_item = rows // n0 if n0 else 1  # transitions per stored item (ndim > 1: [items, time, ...])

    def stored(m) -> int:
        return 4 if m.dtype == np.float64 and not keep_float64 else m.dtype.itemsize

    item_bytes = sum(m.row_bytes(stored(m)) for m in members.values())
    mirror = math.ceil(capacity / max(per_item, 1)) * item_bytes  # allocated at the first write (now, or later)
    check_fits(members, src, mirror, capacity, "--max-size" if max_size else f"its {META_KEY!r} record's max_size")
    return capacity


def _load_rows(storage, arrays: dict[str, np.ndarray], meta: dict[str, Any], *, src: str, env: str | None) -> None:
    """Loads the exported rows and tags into the new ``storage`` (its ``load_state_dict``)."""
    import torch
    from tensordict import TensorDict

    ndim = int(meta.get("ndim", 1))
    tag_arrays = {k: arrays.pop(k) for k in TAGS if k in arrays}
    lead = next(iter(tag_arrays.values())).shape if tag_arrays else None
    body = {k: torch.from_numpy(a) for k, a in arrays.items()}
    td = TensorDict.from_dict(_nest(body), batch_size=lead or [len(next(iter(body.values())))],
                              auto_batch_size=False)
    env_names = list(meta.get("env_names", []))
    zarr_meta: dict[str, Any] = {"kind": meta.get("kind"), "ndim": ndim, "env_names": env_names}
    if tag_arrays:
        tags = {k: torch.from_numpy(a) for k, a in tag_arrays.items()}
        if env is not None:
            zarr_meta["env_names"] = [env]
            tags["env"] = torch.zeros_like(tags["env"])
        zarr_meta["tags"] = TensorDict(tags, batch_size=lead).state_dict()
    rows = int(meta.get("rows", 0))
    try:
        storage.load_state_dict({"_storage": td, "_len": rows, "initialized": True, "zarr": zarr_meta})
    except (ValueError, TypeError, KeyError) as err:  # what the storage refuses: a reserved key, a bad env code...
        raise CLIError(f"{src!r}: {err}") from None


def open_npz(src: str):
    """``(NpzFile, metadata dict)`` of an npz export, or a :class:`CLIError` naming the file.

    Args:
        src (str): the ``.npz`` file (loaded with ``allow_pickle=False``).

    Example:
        >>> import os, tempfile, numpy as np
        >>> from torchrl_robotmem.cli import CLIError
        >>> from torchrl_robotmem.cli.npz_io import open_npz
        >>> f = os.path.join(tempfile.mkdtemp(), "x.npz")
        >>> np.savez(f, a=np.zeros(3))
        >>> try:
        ...     open_npz(f)
        ... except CLIError as err:
        ...     print(str(err).split("(")[1])
        no '__robotmem__' array)
    """
    data = load_npz(src)
    if META_KEY not in data.files:
        raise CLIError(f"{src!r} is not an npz export of a torchrl_robotmem memory (no {META_KEY!r} array)")
    record = inspect_npz(src, [META_KEY]).get(META_KEY)
    if record is None or record.dtype.kind != "U" or record.shape != () or record.nbytes > _MAX_RECORD:
        raise CLIError(f"{src!r}: its {META_KEY!r} member is not a JSON string (an edited export?)")
    try:
        meta = json.loads(str(_read_npz_array(data, src, META_KEY)))
    except ValueError as err:
        raise CLIError(f"{src!r}: its {META_KEY!r} array is not JSON ({err})") from None
    if not isinstance(meta, dict):
        raise CLIError(f"{src!r}: its {META_KEY!r} array is not a JSON object")
    return data, meta


def load_npz(src: str):
    """``np.load(src, allow_pickle=False)`` as an ``NpzFile``, or a :class:`CLIError` naming the file.

    Args:
        src (str): the ``.npz`` file.

    Example:
        >>> import os, tempfile, numpy as np
        >>> from torchrl_robotmem.cli.npz_io import load_npz
        >>> f = os.path.join(tempfile.mkdtemp(), "x.npz")
        >>> np.savez(f, a=np.zeros(3))
        >>> load_npz(f).files
        ['a']
    """
    try:
        data = np.load(src, allow_pickle=False)
    except MemoryError:
        raise CLIError(f"{src!r} cannot be read as npz (its zip directory does not fit in memory)") from None
    except READ_ERRORS as err:
        raise CLIError(f"{src!r} is not an npz export of a torchrl_robotmem memory (it cannot be read as npz: "
                       f"{type(err).__name__}: {err}; a truncated file?)") from None
    if not hasattr(data, "files"):
        raise CLIError(f"{src!r} is not an npz export of a torchrl_robotmem memory (one .npy array, not an npz)")
    return data


def _read_npz_array(data, src: str, key: str) -> np.ndarray:
    if key not in data.files:
        raise CLIError(f"{src!r} has no array {key!r}")
    return read_member(data, src, key)


def _nest(flat: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for path, value in flat.items():
        node = out
        parts = path.split("/")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out
