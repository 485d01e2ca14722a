"""Persistent TorchRL storage on Zarr: :class:`ZarrStorage` and its parts.

One job a module, as TorchRL splits storages, writers and checkpointers
(``docs/storage.md``, "Map of storage/", says which way a write and an open go):

* :mod:`.zarr_storage`: :class:`ZarrStorage`, the TorchRL ``Storage`` contract (and the reserved groups
  components such as a sampler keep their state in: ``component_group``, ``flush_before_close``), a composition of
* :mod:`.handle`: the store handle (store, group, writer lock, format check, in-process handover);
* :mod:`.loader`: the steps of an open and a reader's refresh (record, growth, journal, rows into the mirror);
* :mod:`.planner`: a write validated and normalised into a plan, without side effects;
* :mod:`.mirror`: the packed RAM mirror (allocation, loading, episode ends, the chunk snapshots commits write);
* :mod:`.schema`: a store's schema: column specs and checks, data kinds, constants, the arrays created for its
  columns (:class:`~.schema.StoreSchema`);
* :mod:`.layout`: the packed row (where each column sits in one byte buffer) and its views;
* :mod:`.state` and :mod:`.summary`: a ``state_dict`` as rows to write; a store's statistics;
* :mod:`.tags`: episode / run / env tags: the functions and the registry a store draws them from
  (:class:`~.tags.TagRegistry`: the env table and counters);
* :mod:`.commit`: the commit engine (dirty chunks, background thread, ``flush``), writing through
  :mod:`.journal` (the redo journal) and :mod:`._commit_worker` (the commit worker process);
* :mod:`.format`, :mod:`._backend`, :mod:`.errors`: the on-disk format, store plumbing, error types;
* :mod:`.integrity`: the checks made at open, ``verify`` and ``repair``;
* :mod:`.writer_sync`: the only module touching TorchRL writer internals;
* :mod:`.checkpointer`: :class:`ZarrCheckpointer`;
* :mod:`.lifecycle`: flushing at process end and on SIGTERM;
* :mod:`.columns`: reading one column of any TorchRL tensor storage.
"""
from __future__ import annotations

from ._backend import (  # the store helpers cli/ and memory.py use, public here
    is_url,
    key_to_path,
    make_compressors,
    normalize_path,
    path_to_key,
    refuse_links,
    store_exists,
    store_size_bytes,
    torch_dtype,
)
from .tags import TAG_KEYS
from .zarr_storage import ZarrCheckpointer, ZarrStorage, component_group, flush_before_close

__all__ = [
    "TAG_KEYS", "ZarrCheckpointer", "ZarrStorage", "component_group", "flush_before_close", "is_url", "key_to_path",
    "make_compressors", "normalize_path", "path_to_key", "refuse_links", "store_exists", "store_size_bytes",
    "torch_dtype",
]
