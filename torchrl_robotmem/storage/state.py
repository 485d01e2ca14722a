"""A storage ``state_dict`` read back as rows to write: TorchRL's and ``ZarrStorage``'s own.

``ZarrStorage.load_state_dict`` writes the rows of another storage's state
through its ordinary write path; this module turns the state into those rows
(a TensorDict, with the source's episode / run / env tags and constants when it
was a ``ZarrStorage``) and says which data kind they are read back as.

Example:
    >>> import torch
    >>> from torchrl_robotmem.storage.state import rows_of_state, state_rows
    >>> state = {"_storage": torch.arange(6.0).reshape(3, 2), "_len": 2}
    >>> rows, n0, tagged = state_rows(rows_of_state(state["_storage"]), state, ndim=1, env_code=None)
    >>> rows.batch_size, n0, tagged
    (torch.Size([2]), 2, False)
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from .schema import DataKind, with_constants

__all__ = ["rows_of_state", "source_kind", "state_rows"]


#: episode and run ids a loaded state may carry: below it, the store's next id (the largest + 1) stays countable
MAX_TAG = 2**62


def state_rows(rows: TensorDictBase | None, state_dict: dict[str, Any], *, ndim: int,
               env_code: Callable[[str], int] | None) -> tuple[TensorDictBase | None, int, bool]:
    """The rows of a storage ``state_dict`` to write, their first-dimension count, and whether they carry tags.

    Args:
        rows (TensorDict or None): ``rows_of_state(state_dict["_storage"])``.
        state_dict (dict): TorchRL's ``{"_storage", "_len", ...}``, with ``"zarr"`` from a ``ZarrStorage``.

    Keyword Args:
        ndim (int): the receiving storage's ``ndim``.
        env_code (callable): this store's code of an env name (registering it); the source's
            ``"env"`` column is remapped through it.

    Example:
        >>> state_rows(None, {"_storage": {}, "_len": 0}, ndim=1, env_code=None)
        (None, 0, False)
    """
    meta = state_dict.get("zarr") or {}
    n = int(state_dict.get("_len", 0))
    if not n or rows is None:
        return None, 0, False
    n0 = state_dim0(rows, n, ndim=ndim)
    rows = rows[:n0]
    tags = state_tags(meta)
    if tags is not None:
        for key in ("episode", "run"):  # counters the store goes on from: the next id must be one it can count
            ids = tags.get(key, None)
            if ids is not None and ids[:n0].numel() and not (0 <= int(ids[:n0].min()) and int(ids[:n0].max()) < MAX_TAG):
                raise ValueError(f"the state's {key!r} ids must be in [0, 2**62), got {int(ids[:n0].min())} to "
                                 f"{int(ids[:n0].max())}: the store counts new {key} ids on from the largest")
        rows = rows.clone(False)
        rows.update(tags[:n0])
        table = torch.tensor([env_code(x) for x in meta.get("env_names", [])] + [-1])
        rows.set("env", table[rows.get("env").clamp(min=-1)])
    if meta.get("constants"):
        rows = with_constants(rows.clone(False), meta["constants"])
    return rows, n0, tags is not None


def state_dim0(rows: TensorDictBase, n: int, *, ndim: int) -> int:
    """First-dimension rows that ``n`` transitions of a state's ``rows`` span (a storage of ``ndim`` dims).

    Example:
        >>> state_dim0(TensorDict({"a": torch.zeros(4, 3)}, [4, 3]), 7, ndim=2)
        3
    """
    return -(-int(n) // max(1, math.prod(rows.shape[1:ndim])))


def state_tags(meta: dict[str, Any]) -> TensorDictBase | None:
    """The tag columns (``episode``, ``run``, ``env``) of a ``ZarrStorage`` state's ``"zarr"`` entry, or ``None``.

    Example:
        >>> state_tags({"tags": {"episode": torch.zeros(3, dtype=torch.long)}}).batch_size, state_tags({})
        (torch.Size([3]), None)
    """
    tags = meta.get("tags") or None
    if tags is None:
        return None
    tags = TensorDict().load_state_dict(tags, strict=False)
    tags.batch_size = _leading(tags)
    return tags


def source_kind(state_dict: dict[str, Any], stored: DataKind, *, has_schema: bool) -> DataKind:
    """The kind the rows of ``state_dict`` are read back as: the source's, unless the store has one already.

    Example:
        >>> source_kind({}, DataKind.from_json(None), has_schema=False).kind
        'tensordict'
    """
    meta = state_dict.get("zarr") or {}
    kind = DataKind.from_json(meta.get("kind")) if meta.get("kind") else None
    if kind is None or kind.kind == "tensordict" or has_schema:
        return stored
    return kind


def rows_of_state(source: Any) -> TensorDictBase | None:
    """The rows of a TorchRL storage ``state_dict()["_storage"]`` as a TensorDict (``None``: no rows).

    Example:
        >>> rows_of_state(torch.zeros(3, 2)).batch_size
        torch.Size([3])
    """
    if source is None or (isinstance(source, dict) and not source):
        return None
    if isinstance(source, torch.Tensor):
        return TensorDict({DataKind.TENSOR_KEY: source}, batch_size=source.shape[:1])
    if isinstance(source, TensorDictBase):
        return source
    rows = TensorDict().load_state_dict(source, strict=False)
    if not rows.batch_dims:
        rows.batch_size = _leading(rows)
    return rows


def _leading(td: TensorDictBase) -> torch.Size:
    leaf = next(iter(td.values(True, True)))
    return leaf.shape[:1]


def shares_memory(rows: TensorDictBase | None, views: TensorDictBase | None) -> bool:
    """Whether a leaf of ``rows`` is a view of the same memory as a leaf of ``views`` (a ``state_dict`` taken
    from a live storage holds its own tensors, not a copy).

    Example:
        >>> live = TensorDict({"a": torch.zeros(4, 2)}, [4])
        >>> shares_memory(TensorDict({"a": live["a"][:2]}, [2]), live), shares_memory(live.clone(), live)
        (True, False)
    """
    if rows is None or views is None:
        return False
    live = {leaf.untyped_storage().data_ptr() for leaf in views.values(True, True) if isinstance(leaf, torch.Tensor)}
    return any(leaf.untyped_storage().data_ptr() in live for leaf in rows.values(True, True)
               if isinstance(leaf, torch.Tensor) and leaf.numel())

