"""A store's columns: its data kind, its non-tensor constants, and the Zarr arrays created for them.

:class:`StoreSchema` holds what a store's commit record says about its columns
(``kind``, ``constants``, with the RAM mirror's ``schema`` / ``chunk_rows`` /
``inner_shape``) and makes the changes a write brings: the arrays of a first
write (:meth:`StoreSchema.create`), columns added later
(:meth:`StoreSchema.add_columns`, whose older rows read zeros) and new
constants. The column specs themselves are :mod:`.schema`'s pure functions.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem.storage.handle import StoreHandle
    >>> from torchrl_robotmem.storage.mirror import RamMirror
    >>> from torchrl_robotmem.storage.store_schema import StoreSchema
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

import warnings
from typing import Any

from tensordict import TensorDictBase

from . import _backend
from .context import user_stacklevel
from .format import write_zero_chunks
from .layout import PackedLayout
from .planner import StoreView, WritePlan
from .schema import DataKind, create_arrays, default_chunk_rows, spec_of, with_constants
from .tags import TAG_KEYS

__all__ = ["StoreSchema"]


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

    def note(self, plan: WritePlan) -> None:
        """What a valid plan says of the columns: the data kind (first write) and a warning, given once."""
        if plan.warning is not None and not self.warned:
            self.warned = True
            warnings.warn(plan.warning, stacklevel=user_stacklevel())  # at the user's line
        if self.mirror.schema is None:
            self.kind = plan.kind  # recorded with the schema at the first write

    def view(self, path: Any, ndim: int, initialized: bool, tags) -> StoreView:
        """What the write planner checks a write against (``tags``: the store's ``TagRegistry``)."""
        return StoreView(path, ndim, initialized, self.mirror, self.kind, self.constants, tags.env_names, tags.env_code)

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

    def add_constants(self, new: dict[str, Any]) -> dict:
        """Records new non-tensor entries; returns the record's ``constants`` update."""
        self.constants = {**self.constants, **new}
        return {"constants": dict(self.constants)}

    def state(self) -> dict:
        """The columns' part of ``ZarrStorage.state_dict()["zarr"]``: the data kind and the constants."""
        return {"kind": self.kind.to_json(), "constants": dict(self.constants)}

    def _create_arrays(self, schema: dict[str, dict], *, filled: int | None) -> None:
        m = self.mirror
        arrays = create_arrays(self.handle.group, schema, rows=m.max_dim0, inner_shape=m.inner_shape,
                               chunk_rows=m.chunk_rows, compressor=self.compressor, level=self.level)
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
