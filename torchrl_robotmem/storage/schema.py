"""A store's schema: its columns, their data kind and constants, how writes are checked, the arrays created for them.

* **Schema**: ``{array path: {"dtype", "shape"}}`` for every stored leaf
  (``("next", "observation")`` -> ``"next/observation"``), recorded in the
  store's attributes as JSON. Keys may be added after the first write (schema
  evolution: older rows read zeros); a dtype or per-row shape change is an
  error naming the key.
* **Data kinds**: TorchRL storages take TensorDicts, plain tensors, pytrees
  (dicts / tuples / lists of tensors) and tensorclasses. :class:`DataKind`
  turns each into a TensorDict for storage and back, recording what it needs
  as JSON (a pytree's ``treespec_dumps``; a tensorclass's qualified name). Nothing
  stored is ever imported or unpickled: a tensorclass comes back as its class
  only if that class is already imported in the reading process, else as a
  TensorDict.
* **Constants**: non-tensor entries, one JSON scalar shared by every row, kept
  in the store's metadata (:func:`split_constants`, :func:`with_constants`).
* **A store's columns**: :class:`StoreSchema` holds what a store's commit record
  says about its columns (``kind``, ``constants``, with the RAM mirror's
  ``schema`` / ``chunk_rows`` / ``inner_shape``) and makes the changes a write
  brings: the arrays of a first write (:meth:`StoreSchema.create`), columns
  added later (:meth:`StoreSchema.add_columns`, whose older rows read zeros)
  and new constants. Everything above it here is pure functions.

How a row's columns sit in the packed RAM mirror is :mod:`.layout`'s job.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem.storage.handle import StoreHandle
    >>> from torchrl_robotmem.storage.mirror import RamMirror
    >>> from torchrl_robotmem.storage.schema import StoreSchema
    >>> h = StoreHandle("memory://store-schema-doc", read_only=False)
    >>> h.open()
    >>> h.create({}, max_size=8, chunk_rows=4, ndim=1)
    >>> arrays = {}
    >>> cols = StoreSchema(h, RamMirror(8), arrays)
    >>> record = cols.create(TensorDict({"x": torch.zeros(2, 3)}, [2]), single=False)
    >>> record["schema"]["x"], sorted(arrays)
    ({'dtype': 'float32', 'shape': [3]}, ['x'])
    >>> h.release()
"""
from __future__ import annotations

import math
import sys
import warnings
from typing import Any

import torch
from tensordict import NonTensorData, NonTensorStack, TensorDict, TensorDictBase, is_tensor_collection
from tensordict.base import _is_leaf_nontensor
from torch.utils._pytree import tree_flatten, tree_unflatten, treespec_dumps, treespec_loads

from . import _backend
from .context import user_stacklevel
from .format import ARRAY_CONFIG, CHUNK_KEY_SEPARATOR, UNBOUNDED, chunk_separator, write_zero_chunks
from .layout import PackedLayout
from .tags import TAG_KEYS

__all__ = [
    "DataKind", "StoreSchema", "check_against", "create_arrays", "default_chunk_rows", "same_constant",
    "same_constants", "spec_of", "split_constants", "with_constants",
]


# -- data kinds ------------------------------------------------------------------------


class DataKind:
    """How user data maps to a TensorDict and back.

    ``kind`` is ``"tensordict"``, ``"tensor"``, ``"pytree"`` or ``"tensorclass"``;
    ``meta`` is the JSON the reverse mapping needs.
    """

    TENSOR_KEY = "_tensor"
    PYTREE_KEY = "_pytree"

    def __init__(self, kind: str = "tensordict", meta: dict | None = None, cls: type | None = None) -> None:
        self.kind = kind
        self.meta = dict(meta or {})
        self._cls = cls
        self._spec = treespec_loads(self.meta["treespec"]) if kind == "pytree" else None

    @classmethod
    def of(cls, data: Any) -> DataKind:
        if isinstance(data, torch.Tensor):
            return cls("tensor")
        if is_tensor_collection(data):
            if isinstance(data, TensorDictBase):
                groups = cls.groups_of(data)
                return cls("tensordict", {"groups": groups} if groups else None)
            klass = type(data)
            return cls("tensorclass", {"class": f"{klass.__module__}.{klass.__qualname__}"}, klass)
        leaves, spec = tree_flatten(data)
        if not leaves or not all(isinstance(x, torch.Tensor) for x in leaves):
            raise TypeError(
                f"ZarrStorage stores TensorDicts, tensors, tensorclasses and pytrees of tensors; got "
                f"{type(data).__name__} with leaves {sorted({type(x).__name__ for x in leaves})}."
            )
        return cls("pytree", {"treespec": treespec_dumps(spec)})

    @staticmethod
    def groups_of(data: TensorDictBase) -> dict[str, int]:
        """Nested TensorDicts with batch dims of their own: ``{path: extra dims}``.

        A multi-agent group (``data["agents"]``, batch ``[*B, n_agents]`` under a
        ``[*B]`` root) is stored leaf by leaf; this record lets reads give the group
        its batch dims back (:meth:`with_groups`), as ``LazyTensorStorage`` keeps them.

        Example:
            >>> td = TensorDict({"agents": TensorDict({"obs": torch.zeros(4, 2, 3)}, [4, 2])}, [4])
            >>> DataKind.groups_of(td)
            {'agents': 1}
        """
        out = {}
        for key, value in data.items(include_nested=True):
            if type(value) is TensorDict and value.batch_dims > data.batch_dims:
                out[_backend.key_to_path(key)] = value.batch_dims - data.batch_dims
        return out

    def with_groups(self, td: TensorDictBase) -> TensorDictBase:
        """``td`` (rows read back) with the batch dims of each group :meth:`groups_of` recorded, in place."""
        groups = self.meta.get("groups") if self.kind == "tensordict" else None
        for path, extra in sorted((groups or {}).items(), key=lambda kv: kv[0].count("/")):
            sub = td.get(_backend.path_to_key(path), None)
            if type(sub) is not TensorDict or sub.batch_dims != td.batch_dims:
                continue
            leaves = [v for v in sub.values(True, True) if isinstance(v, torch.Tensor)]
            if leaves:
                sub.batch_size = leaves[0].shape[: td.batch_dims + int(extra)]
        return td

    def to_json(self) -> dict:
        return {"kind": self.kind, **self.meta}

    @classmethod
    def from_json(cls, value: dict | None) -> DataKind:
        if not value:
            return cls()
        value = dict(value)
        return cls(value.pop("kind"), value)

    def same_as(self, other: DataKind) -> bool:
        """Same kind and structure (the batch dims of nested groups may differ: they are read back as first stored)."""
        def strip(meta: dict) -> dict:
            return {k: v for k, v in meta.items() if k != "groups"}

        return self.kind == other.kind and strip(self.meta) == strip(other.meta)

    def to_tensordict(self, data: Any, batch_dims: int) -> TensorDictBase:
        if self.kind == "tensordict":
            return data
        if self.kind == "tensor":
            return TensorDict({self.TENSOR_KEY: data}, batch_size=data.shape[:batch_dims])
        if self.kind == "tensorclass":
            td = getattr(data, "_tensordict", None)
            if td is None or any(is_tensor_collection(v) and not isinstance(v, TensorDictBase) for v in td.values()):
                td = data.to_tensordict()  # nested tensorclasses become TensorDicts
            return td
        leaves, spec = tree_flatten(data)
        if treespec_dumps(spec) != self.meta["treespec"]:
            raise ValueError(
                "This pytree's structure differs from the one the store holds "
                f"({spec} vs {self._spec}); every write must have the same structure."
            )
        return TensorDict(
            {self.PYTREE_KEY: {str(i): x for i, x in enumerate(leaves)}}, batch_size=leaves[0].shape[:batch_dims]
        )

    def from_tensordict(self, td: TensorDictBase) -> Any:
        if self.kind == "tensordict":
            return td
        if self.kind == "tensor":
            return td.get(self.TENSOR_KEY)
        if self.kind == "pytree":
            sub = td.get(self.PYTREE_KEY)
            return tree_unflatten([sub.get(str(i)) for i in range(len(sub.keys()))], self._spec)
        cls = self._cls or self._resolve_class()
        return td if cls is None else cls._from_tensordict(td)

    def _resolve_class(self) -> type | None:
        """The tensorclass, only if its module is already imported (nothing is imported here)."""
        module, _, qualname = self.meta.get("class", "").rpartition(".")
        obj = sys.modules.get(module)
        for part in qualname.split("."):
            obj = getattr(obj, part, None)
        if obj is not None and callable(getattr(obj, "_from_tensordict", None)):
            self._cls = obj
        return self._cls

    @property
    def tag_columns(self) -> bool:
        """Whether sampled data carries the tag columns (only TensorDicts have room for them)."""
        return self.kind == "tensordict"


# -- constants: non-tensor entries -------------------------------------------------------

#: The non-tensor values a store keeps: JSON scalars, in the group's metadata.
CONSTANT_TYPES = (str, int, float, bool, type(None))


def same_constant(a: Any, b: Any) -> bool:
    """Whether two constants are the same value of the same type (``1`` is not ``True`` nor ``1.0``; NaN is NaN).

    Example:
        >>> same_constant(float("nan"), float("nan")), same_constant(1, True), same_constant("a", "a")
        (True, False, True)
    """
    if type(a) is not type(b):
        return False
    return a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b))


def same_constants(a: dict, b: dict) -> bool:
    """Whether two ``{path: constant}`` dicts hold the same keys, each with the :func:`same_constant` value.

    Example:
        >>> same_constants({"t": float("nan")}, {"t": float("nan")}), same_constants({"t": 1}, {})
        (True, False)
    """
    return a.keys() == b.keys() and all(same_constant(v, b[k]) for k, v in a.items())


def split_constants(td: TensorDictBase) -> dict[str, Any]:
    """Pops the non-tensor leaves of ``td`` (in place) and returns ``{path: value}``.

    A store keeps a non-tensor entry (a tensorclass's ``str`` field, a
    ``NonTensorData`` in a TensorDict) as *one value shared by every row*, in
    its metadata as JSON, as ``LazyMemmapStorage`` keeps it in its metadata.
    Nothing is pickled. Callers drop the tag entries first (a non-tensor
    ``"env"`` names the environment of each row, not a constant).

    Raises, naming the key, on a value that is not a JSON scalar
    (``str``, ``int``, ``float``, ``bool``, ``None``) or on rows that carry
    different values.

    Example:
        >>> from tensordict import NonTensorData
        >>> td = TensorDict({"x": torch.zeros(2), "text": NonTensorData("hi", batch_size=[2])}, [2])
        >>> split_constants(td), list(td.keys())
        ({'text': 'hi'}, ['x'])
    """
    found = {}
    for key, value in list(td.items(include_nested=True, leaves_only=True, is_leaf=_is_leaf_nontensor)):
        if isinstance(value, torch.Tensor):
            continue
        if isinstance(value, NonTensorStack):
            values = _flat(value.tolist())
            if any(not same_constant(v, values[0]) for v in values[1:]):
                raise ValueError(
                    f"Key {key!r} holds different non-tensor values across rows ({_preview(values)}). "
                    f"ZarrStorage keeps a non-tensor entry only as one value shared by every row (in the "
                    f"store's metadata); store per-row values as a tensor (e.g. integer codes)."
                )
            value = values[0] if values else None
        elif isinstance(value, NonTensorData):
            value = value.data
        if not isinstance(value, CONSTANT_TYPES):
            raise TypeError(
                f"Key {key!r} holds a non-tensor value of type {type(value).__name__}; ZarrStorage stores "
                f"tensors, and non-tensor entries only as one str / int / float / bool / None value shared "
                f"by every row (nothing stored is ever pickled). Convert it to a tensor or drop the key."
            )
        found[_backend.key_to_path(key)] = value
        td.pop(key)
    return found


def _flat(x: Any) -> list:
    return [v for item in x for v in _flat(item)] if isinstance(x, list) else [x]


def _preview(values: list) -> str:
    uniq = list(dict.fromkeys(repr(v) for v in values))
    return ", ".join(uniq[:3]) + (", ..." if len(uniq) > 3 else "")


def with_constants(td: TensorDictBase, constants: dict[str, Any]) -> TensorDictBase:
    """``td`` with every constant set as a ``NonTensorData`` of ``td``'s batch size."""
    for path, value in constants.items():
        td.set(_backend.path_to_key(path), NonTensorData(value, batch_size=td.batch_size, device=td.device))
    return td


# -- schema ---------------------------------------------------------------------------


def spec_of(row: TensorDictBase) -> dict[str, dict]:
    """``{path: {"dtype", "shape"}}`` of one row (a TensorDict with batch size ``[]``)."""
    spec = {}
    for key, value in row.items(include_nested=True, leaves_only=True, is_leaf=_is_leaf_nontensor):
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"Key {key!r} holds {type(value).__name__}; ZarrStorage stores tensors only.")
        spec[_backend.key_to_path(key)] = {
            "dtype": _backend.torch_dtype_name(value.dtype),
            "shape": list(value.shape),
        }
    return spec


def check_against(schema: dict[str, dict], data: TensorDictBase, batch_dims: int, where: str) -> tuple[list, list]:
    """Compares ``data`` (without tags) with ``schema``; returns ``(new_paths, missing_paths)``.

    Raises, naming the key, on a dtype or per-row shape that differs from the
    stored one, or on a leaf that is not a tensor.
    """
    leaves = {}
    for key, value in data.items(include_nested=True, leaves_only=True, is_leaf=_is_leaf_nontensor):
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"Key {key!r} holds {type(value).__name__}; ZarrStorage stores tensors only.")
        leaves[_backend.key_to_path(key)] = value
    new, missing = [], []
    for path, value in leaves.items():
        spec = schema.get(path)
        dtype = _backend.torch_dtype_name(value.dtype)
        if spec is None:
            new.append(path)
            continue
        shape = list(value.shape[batch_dims:])
        if dtype != spec["dtype"] or shape != spec["shape"]:
            raise ValueError(
                f"Key {_backend.path_to_key(path)!r}: got dtype {dtype} and per-row shape {shape}, "
                f"but the store at {where} holds dtype {spec['dtype']} and shape {spec['shape']}. "
                f"Cast or reshape the data before writing."
            )
    for path in schema:
        if path not in leaves:
            missing.append(path)
    return new, missing


# -- the store's arrays ------------------------------------------------------------------


def default_chunk_rows(row_bytes: int, max_dim0: int) -> int:
    """Rows per chunk: ~4 MiB of rows, large enough for fast sequential I/O, small enough
    that a commit of a partial chunk stays cheap (a power of two in 1024..65536, at most ``max_dim0``).

    Example:
        >>> default_chunk_rows(64, 10**6), default_chunk_rows(64, 100)
        (65536, 100)
    """
    target = max(1024, min(65536, 2 ** round(math.log2(max(1, (4 << 20) // max(row_bytes, 1))))))
    return min(target, max_dim0)


def create_arrays(group: Any, schema: dict[str, dict], *, rows: int, inner_shape: tuple, chunk_rows: int,
                  compressor: str | None, level: int, unbounded: bool = False,
                  separator: str = CHUNK_KEY_SEPARATOR) -> dict[str, Any]:
    """Creates (replacing) one Zarr array per column of ``schema``; returns them by path.

    Every chunk is written, an all-zero one too (:data:`~.format.ARRAY_CONFIG`): a
    missing chunk file is damage. Chunk ``c`` of a column is the file ``<column>/c.<c>.0``
    (Zarr v3's default chunk key encoding with the ``"."`` separator: one file a chunk in the
    column's folder, no folder a chunk); stores created before keep ``<column>/c/<c>/0``.

    Args:
        group: the store's Zarr group.
        schema (dict): ``{path: {"dtype": str, "shape": list}}``.

    Keyword Args:
        rows (int): rows along the first dimension.
        inner_shape (tuple): the item shape after the first dimension.
        chunk_rows (int): rows per chunk.
        compressor (str, optional): ``"blosc"``, ``"zstd"`` or ``None``.
        level (int): codec level.
        unbounded (bool): the memory has no declared capacity. Each array then says so in its own
            attributes (``{"unbounded": true}``), beside the commit record's flag: ``robotmem repair``
            reads it when the record is lost, so a rebuilt memory grows again instead of wrapping.
        separator (str): ``"."`` (the default: flat chunk files) or ``"/"`` (a folder a chunk, as the
            columns of a store created before: a column added to one follows them).
    """
    out = {}
    attributes = {UNBOUNDED: True} if unbounded else None
    for path, spec in schema.items():
        dtype = _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
        shape = (rows, *inner_shape, *spec["shape"])
        out[path] = group.create_array(
            path, shape=shape, chunks=(chunk_rows, *shape[1:]), dtype=dtype,
            compressors=_backend.make_compressors(compressor, level, dtype.itemsize),
            fill_value=0, overwrite=True, config=ARRAY_CONFIG, attributes=attributes,
            chunk_key_encoding={"name": "default", "separator": separator},
        )
    return out


# -- a store's columns ------------------------------------------------------------------


class StoreSchema:
    """The data kind, constants and arrays of one store's columns.

    Args:
        handle (StoreHandle): the store's handle (its ``group`` holds the arrays).
        mirror (RamMirror): the store's RAM rows (its ``schema`` is the column table).
        arrays (dict): the commit engine's open arrays by path; created arrays are added.

    Keyword Args:
        compressor (str or None): codec of the arrays created. Defaults to ``"blosc"``.
        level (int): codec level. Defaults to 1.

    Example:
        >>> from torchrl_robotmem.storage.mirror import RamMirror
        >>> cols = StoreSchema(None, RamMirror(4), {})
        >>> cols.sync({"kind": None, "constants": {"label": "a"}})
        >>> cols.kind.kind, cols.constants
        ('tensordict', {'label': 'a'})
    """

    def __init__(self, handle, mirror, arrays: dict, *, compressor: str | None = "blosc", level: int = 1) -> None:
        self.handle = handle
        self.mirror = mirror
        self.arrays = arrays
        self.compressor = compressor
        self.level = int(level)
        self.kind = DataKind.from_json(None)
        self.constants: dict[str, Any] = {}  # non-tensor entries, by column path
        self.warned = False  # the planner's warning is given once a store handle

    def sync(self, attrs: dict) -> None:
        """Takes the columns from a commit record (at open, refresh, journal replay)."""
        self.constants = dict(attrs.get("constants") or {})
        self.kind = DataKind.from_json(attrs.get("kind"))
        inner = attrs.get("inner_shape")
        self.mirror.inner_shape = tuple(inner) if inner is not None else ()
        self.mirror.chunk_rows = attrs.get("chunk_rows")
        self.mirror.configure(attrs.get("schema"))

    def note(self, plan) -> None:
        """What a valid plan says of the columns: the data kind (first write) and a warning, given once.

        Args:
            plan (WritePlan): the plan :func:`~.planner.plan_write` made of the write.
        """
        if plan.warning is not None and not self.warned:
            self.warned = True
            warnings.warn(plan.warning, stacklevel=user_stacklevel())  # at the user's line
        if self.mirror.schema is None:
            self.kind = plan.kind  # recorded with the schema at the first write

    def create(self, data: TensorDictBase, single: bool) -> dict:
        """Lays out the first write's columns: arrays, chunk rows, the mirror's schema. Returns their record.

        The mirror's ``max_size`` is rounded to whole items (as TorchRL does for ``ndim > 1``);
        the mirror is to be allocated before the record is committed.
        """
        row = data if single else data[0]
        schema = spec_of(row.reshape(-1)[0] if row.batch_dims else row)
        m = self.mirror
        m.inner_shape = tuple(row.batch_size)
        if m.chunk_rows is None:  # a memory without a declared capacity will grow: chunks of a large memory
            m.chunk_rows = default_chunk_rows(PackedLayout(schema).row_bytes * m.inner_numel,
                                              1 << 30 if m.unbounded else m.max_dim0)
        if m.unbounded:
            m.max_size = max(m.max_size, m.chunk_rows)  # its first rows: one chunk
        m.max_size = m.max_dim0 * m.inner_numel
        self._create_arrays(schema, filled=None)
        m.configure(schema)
        # Schema first: a store whose arrays exist but whose schema is unknown would not reopen.
        return {"schema": schema, "chunk_rows": m.chunk_rows, "inner_shape": list(m.inner_shape),
                "kind": self.kind.to_json(), "max_size": m.max_size}

    def add_columns(self, data: TensorDictBase, new_paths: list[str], single: bool, *, filled: int) -> None:
        """Adds arrays for keys the store did not hold yet; their ``filled`` older rows are zeros."""
        row = data if single else data[0]
        if self.mirror.ndim > 1:
            row = row.reshape(-1)[0]
        added = spec_of(row.select(*[_backend.path_to_key(p) for p in new_paths]))
        self._create_arrays(added, filled=filled)
        self.mirror.configure({**self.mirror.schema, **added})

    def add_constants(self, new: dict[str, Any]) -> None:
        """Records new non-tensor entries (the next commit record carries them: ``MemoryStore.meta_snapshot``)."""
        self.constants = {**self.constants, **new}

    def state(self) -> dict:
        """The columns' part of ``ZarrStorage.state_dict()["zarr"]``: the data kind and the constants."""
        return {"kind": self.kind.to_json(), "constants": dict(self.constants)}

    def _create_arrays(self, schema: dict[str, dict], *, filled: int | None) -> None:
        m = self.mirror
        held = [p for p in (m.schema or {}) if p not in schema]  # a column added: as the store's others
        separator = chunk_separator(self.handle.group[held[0]]) if filled is not None and held else CHUNK_KEY_SEPARATOR
        arrays = create_arrays(self.handle.group, schema, rows=m.max_dim0, inner_shape=m.inner_shape,
                               chunk_rows=m.chunk_rows, compressor=self.compressor, level=self.level,
                               unbounded=m.unbounded, separator=separator)
        self.arrays.update(arrays)
        if filled is not None:  # keys added later: their older rows are zeros, in chunk files
            for arr in arrays.values():
                write_zero_chunks(arr, filled, m.chunk_rows)

    # -- what TorchRL sees ------------------------------------------------------------

    def as_stored(self, views: TensorDictBase) -> Any:
        """The data as the user wrote it, on the mirror's views (a TensorDict, the tensor, a tensorclass, a pytree)."""
        return self.kind.from_tensordict(views.exclude(*TAG_KEYS) if self.kind.kind != "tensordict" else views)

    def rows_out(self, rows: TensorDictBase) -> Any:
        """Rows read from the mirror, with the constants, as the store's data kind."""
        if self.constants:
            rows = with_constants(rows, self.constants)
        return self.kind.from_tensordict(self.kind.with_groups(rows))
