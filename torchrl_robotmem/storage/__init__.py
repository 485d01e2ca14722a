"""Persistent TorchRL storage on Zarr: :class:`ZarrStorage` and its parts.

One job a module, as TorchRL splits storages, writers and checkpointers:

* :mod:`.zarr_storage`: :class:`ZarrStorage`, the public class, a composition of
* :mod:`._backend`: the store handle (paths, URLs, the writer lock, codecs, dtypes);
* :mod:`.schema`: the row schema, data kinds and the packed RAM mirror;
* :mod:`.tags`: episode / run / env tags (pure tensor functions);
* :mod:`.commit`: the commit engine with its journal and background thread;
* :mod:`.writer_sync`: the only module touching TorchRL writer internals;
* :mod:`.checkpointer`: :class:`ZarrCheckpointer`;
* :mod:`.lifecycle`: flushing at process end and on SIGTERM.
"""
from __future__ import annotations

from ._backend import (  # the store helpers cli/ and memory.py use, public here
    is_url,
    key_to_path,
    normalize_path,
    path_to_key,
    store_exists,
    store_size_bytes,
    torch_dtype,
)
from .tags import TAG_KEYS
from .zarr_storage import ZarrCheckpointer, ZarrStorage

__all__ = [
    "TAG_KEYS", "ZarrCheckpointer", "ZarrStorage", "is_url", "key_to_path", "normalize_path", "path_to_key",
    "store_exists", "store_size_bytes", "torch_dtype",
]
