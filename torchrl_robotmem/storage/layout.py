"""The packed row: where each column of a row sits in one byte buffer, and the views of it.

Every row's leaves live side by side in one ``uint8`` buffer ``[*batch, row_bytes]``
(:class:`PackedLayout`, computed from a store's schema, :mod:`.schema`). The RAM
mirror (:mod:`.mirror`) and a local store's row file (:mod:`.rowfile`) hold rows
in this layout; the storage's ``_storage`` TensorDict holds strided views of it
(what samplers and TorchRL read), and a sample is ONE gather of whole rows
instead of one per key.
"""
from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from . import _backend

__all__ = ["PackedLayout"]


class PackedLayout:
    """Byte offsets of every leaf inside one packed row.

    Leaves are ordered by item size (largest first) so each starts aligned to
    its own item size, and the row is padded to 8 bytes: every column is then a
    valid strided view of the ``uint8`` buffer.

    Example:
        >>> layout = PackedLayout({"a": {"dtype": "float32", "shape": [3]}, "b": {"dtype": "int64", "shape": []}})
        >>> layout.row_bytes, [(p, o) for p, o, *_ in layout.fields]
        (24, [('b', 0), ('a', 8)])
    """

    def __init__(self, schema: dict[str, dict]) -> None:
        fields = []
        items = sorted(
            schema.items(), key=lambda kv: -_backend.numpy_dtype(_backend.torch_dtype(kv[1]["dtype"])).itemsize
        )
        off = 0
        for path, spec in items:
            dtype = _backend.torch_dtype(spec["dtype"])
            size = _backend.numpy_dtype(dtype).itemsize
            off = -(-off // size) * size
            nbytes = size * math.prod(spec["shape"])
            fields.append((path, off, nbytes, dtype, tuple(spec["shape"])))
            off += nbytes
        self.fields = fields
        self.row_bytes = max(8, -(-off // 8) * 8)
        # nested dict skeleton: ("next", "obs") -> {"next": {"obs": ...}}
        self._keys = [_backend.path_to_key(p) for p, *_ in fields]

    def allocate(self, batch_shape: tuple[int, ...], device: Any) -> torch.Tensor:
        # empty, not zeros: the OS maps untouched pages lazily, so a 1M-row mirror
        # costs nothing until rows arrive (rows past len are never read, and the
        # commit engine zero-fills them before they reach the disk)
        return torch.empty((*batch_shape, self.row_bytes), dtype=torch.uint8, device=device)

    def views(self, buf: torch.Tensor, skip: tuple = ()) -> TensorDictBase:
        """A TensorDict of strided views of ``buf`` (``[*batch, row_bytes]``), one per leaf not in ``skip``."""
        batch = buf.shape[:-1]
        source: dict = {}
        for key, (_, off, nbytes, dtype, shape) in zip(self._keys, self.fields):
            if key in skip:
                continue
            col = buf[..., off : off + nbytes].view(dtype).view(torch.Size((*batch, *shape)))
            if isinstance(key, str):
                source[key] = col
            else:
                node = source
                for part in key[:-1]:
                    node = node.setdefault(part, {})
                node[key[-1]] = col
        return _unsafe_td(source, batch, buf.device)


def _unsafe_td(source: dict, batch: torch.Size, device) -> TensorDictBase:
    """``TensorDict(source, batch)`` without re-validating shapes we built (8x faster)."""
    out = {k: _unsafe_td(v, batch, device) if isinstance(v, dict) else v for k, v in source.items()}
    return TensorDict._new_unsafe(out, batch_size=torch.Size(batch), device=device)
