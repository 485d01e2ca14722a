"""Reading one column of any TorchRL tensor storage: the one place that reaches into ``storage._storage``.

Samplers, the goal index and the transform read stored columns (achieved
goals, success flags, tags) without going through ``storage.get`` (which
gathers whole rows). ``LazyTensorStorage``, ``LazyMemmapStorage`` and
``ZarrStorage`` all keep their rows in a TensorDict at ``storage._storage``.
"""
from __future__ import annotations

import contextlib
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

__all__ = ["has_rows", "read_column", "read_rows", "scanning"]


def _key_str(key: NestedKey) -> str:
    return repr(key) if isinstance(key, str) else repr(tuple(key))


def has_rows(storage: Any) -> bool:
    """Whether ``storage`` is an initialised TensorDict-backed storage."""
    return bool(getattr(storage, "initialized", False)) and isinstance(getattr(storage, "_storage", None), TensorDictBase)


def read_column(storage: Any, key: NestedKey, n: int | None = None) -> torch.Tensor:
    """The column ``key`` of ``storage``'s first ``n`` rows (all rows by default), without a copy.

    Raises a ``KeyError`` listing the stored keys when the column does not exist.

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage
        >>> st = LazyTensorStorage(10)
        >>> st.set(range(3), TensorDict({"g": torch.arange(6.0).reshape(3, 2)}, [3]))
        >>> read_column(st, "g", 2).tolist()
        [[0.0, 1.0], [2.0, 3.0]]
    """
    data = storage._storage
    col = data.get(key, None) if isinstance(data, TensorDictBase) else None
    if col is None:
        keys = sorted(_key_str(k) for k in data.keys(True, True)) if isinstance(data, TensorDictBase) else []
        raise KeyError(f"the storage has no column {_key_str(key)}; available keys: {', '.join(keys)}.")
    return col if n is None else col[:n]


def scanning(storage: Any):
    """The storage's context for reading whole columns (``ZarrStorage.scanning``), else one that does nothing.

    Example:
        >>> from torchrl.data import LazyTensorStorage
        >>> with scanning(LazyTensorStorage(10)):
        ...     pass
    """
    scan = getattr(storage, "scanning", None)
    return scan() if callable(scan) else contextlib.nullcontext()


def read_rows(storage: Any, rows: torch.Tensor) -> TensorDictBase:
    """Every stored column of ``rows`` (int64, any shape; ``-1`` reads row 0), tags included.

    Unlike ``storage.get``, this returns the columns a ``ZarrStorage`` keeps out of
    sampled batches (its ``episode`` / ``run`` / ``env`` tags).

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage
        >>> st = LazyTensorStorage(10)
        >>> st.set(range(3), TensorDict({"g": torch.arange(3.0)}, [3]))
        >>> read_rows(st, torch.tensor([2, -1]))["g"].tolist()
        [2.0, 0.0]
    """
    data = storage._storage
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"{type(storage).__name__} keeps no TensorDict of rows; read_rows needs a TensorDict-backed storage.")
    return data[rows.clamp_min(0).to(getattr(data, "device", None) or "cpu")]
