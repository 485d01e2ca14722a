"""``ZarrStorage``: a TorchRL replay-buffer storage that lives in a Zarr v3 store and survives the process.

The TorchRL ``Storage`` contract, composing the parts of this package; ``docs/storage.md``
("Map of storage/") says which part owns which job, the on-disk layout and the commit protocol.
"""
from __future__ import annotations

import contextlib
import math
import os
import sys
import weakref
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data.replay_buffers.checkpointers import StorageCheckpointerBase
from torchrl.data.replay_buffers.storages import LazyTensorStorage

from . import compat, lifecycle
from .arguments import check_arguments
from .checkpointer import ZarrCheckpointer
from .format import RESERVED, UNBOUNDED, UNBOUNDED_SIZE
from .indices import HostIndices
from .planner import StoreView, check_rows, completes_chunk, counts_from_the_end, cursor_rows, plan_write, write_span
from .schema import DataKind, with_constants
from .state import rows_of_state, shares_memory, source_kind, state_dim0, state_rows, state_tags
from .store import MemoryStore
from .tags import TAG_KEYS, UNKNOWN_ENV

__all__ = ["ZarrStorage", "ZarrCheckpointer", "TAG_KEYS", "component_group", "flush_before_close"]



class ZarrStorage(HostIndices, LazyTensorStorage):  # HostIndices: HER over a CUDA mirror (indices.py)
    """A persistent, crash-safe TorchRL storage backed by a Zarr v3 store.

    A :class:`~torchrl.data.LazyTensorStorage` written through to Zarr; reopening the path restores every row,
    the length and the writer's cursor. ``docs/storage.md`` tells how, and each argument in full.

    Args:
        path (str or os.PathLike or zarr Store): a directory, a ``*.zip`` path or a Zarr/fsspec URL.
        max_size (int, optional): capacity in transitions; required to create a store.

    Keyword Args:
        env (str, optional): the env name rows written from now on are tagged with.
        read_only (bool, optional): open an existing store for reading only. Defaults to ``False``.
        ndim (int, optional): leading batch dims of one stored item, as in TorchRL. Defaults to 1.
        chunk_rows (int, optional): rows per Zarr chunk. Defaults to about 4 MiB of data a chunk.
        compressor (str, optional): ``"blosc"`` (default), ``"zstd"`` or ``None``.
        compression_level (int, optional): codec level. Defaults to 1.
        commit_interval (float, optional): seconds after which written rows are committed. Defaults to 1.0.
        background (bool, optional): commit from a background thread (default) or on every write.
        commit_process (bool, optional): compress and write chunks in a child process (local stores).
        storage_options (dict, optional): passed to fsspec for URL stores.
        device (str, optional): device of the RAM mirror. Defaults to ``"cpu"``.
        compilable (bool, optional): as in TorchRL (plain-int ``len``). Defaults to ``False``.
        shared_init (bool, optional): refused (``True``): a store has one writer process.
        scratch_dir, existsok, auto_cleanup, consolidated, cleanup_memmap: ``LazyMemmapStorage`` /
            ``LazyTensorStorage``'s, for a one-line swap; ``scratch_dir`` is ignored with a warning (:mod:`.compat`).
        sample_tags (bool, optional): include the tags in what ``get`` returns. Defaults to ``False``.
        on_damage (str, optional): ``"raise"`` (default) or ``"warn"`` (``read_only`` only) on a damaged store.
        goal_conditioned (bool, optional): ``False``: the env has no success flag; none is asked for (recorded).

    Examples:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import TensorDictReplayBuffer
        >>> from torchrl_robotmem import ZarrStorage
        >>> path = tempfile.mkdtemp() + "/memory.zarr"
        >>> rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 1000, env="FetchPush-v4"), batch_size=4)
        >>> data = TensorDict({"obs": torch.randn(10, 3), ("next", "done"): torch.zeros(10, 1, dtype=torch.bool)}, [10])
        >>> _ = rb.extend(data)
        >>> rb.storage.close()
        >>> rb = TensorDictReplayBuffer(storage=ZarrStorage(path), batch_size=4)
        >>> _ = rb.extend(data)  # appends after the 10 old rows
        >>> rb.storage["run"][-1].item(), len(rb)
        (1, 20)
        >>> rb.storage.close()
    """

    _default_checkpointer = ZarrCheckpointer

    def __init__(self, path: str | os.PathLike | Any, max_size: int | None = None, *, env: str | None = None,
                 read_only: bool = False, ndim: int = 1, chunk_rows: int | None = None, compressor: str | None = "blosc",
                 compression_level: int = 1, commit_interval: float = 1.0, background: bool = True,
                 commit_process: bool | None = None, storage_options: dict | None = None, device: str = "cpu",
                 compilable: bool = False, shared_init: bool = False, sample_tags: bool = False,
                 on_damage: str = "raise", goal_conditioned: bool | None = None,
                 scratch_dir: str | os.PathLike | None = None, existsok: bool = False,
                 auto_cleanup: bool | None = None, consolidated: bool = False, cleanup_memmap: bool = True) -> None:
        compat.check_replaced_arguments(path, scratch_dir, existsok, auto_cleanup, consolidated, cleanup_memmap)
        check_arguments(path, max_size, chunk_rows=chunk_rows, commit_interval=commit_interval, ndim=ndim,
                               shared_init=shared_init, compressor=compressor, compression_level=compression_level,
                               on_damage=on_damage, read_only=read_only, goal_conditioned=goal_conditioned)
        self._store = MemoryStore(path, read_only=read_only, storage_options=storage_options, on_damage=on_damage,
                                  commit_process=commit_process, goal_conditioned=goal_conditioned)
        self._handle = self._store.handle  # the parts, as the tests and benchmarks read them
        self.path, self.read_only = self._handle.path, self._handle.read_only
        self._storage_options = storage_options
        self._hidden = () if sample_tags else TAG_KEYS  # what get() (hence rb.sample()) leaves out, unless asked for
        previous = self._store.claim()
        try:
            self._open(max_size, env=env, ndim=int(ndim), chunk_rows=chunk_rows, device=device, compilable=compilable,
                       commit_interval=commit_interval, background=background,
                       codec=(compressor, int(compression_level)))
        except BaseException:
            self._store.abandon(previous)
            raise

    def _open(self, max_size, *, env, ndim, chunk_rows, device, compilable, commit_interval, background, codec) -> None:
        store, handle = self._store, self._handle
        attrs = store.open_record(max_size, chunk_rows=chunk_rows, ndim=ndim, device=device)
        stored_max = int(attrs["max_size"])
        unbounded = bool(attrs.get(UNBOUNDED))
        if unbounded and max_size is not None:
            raise ValueError(f"The store at {handle.path!r} has no declared capacity (it was created with "
                             f"max_size=None and grows as rows arrive); max_size={max_size} cannot bound it. "
                             f"Open it with ZarrStorage({handle.path!r}), and sample its newest rows with "
                             f"WindowSampler(window) if a run should see only those.")
        # TorchRL's max_size: an unbounded memory's is one no writer index wraps around (the rows: storage.capacity)
        super().__init__(max_size=UNBOUNDED_SIZE if unbounded else stored_max, device=device,
                         ndim=int(attrs.get("ndim", 1)), compilable=compilable)
        # the last written row as TorchRL's set() resolved it (a slice against max_size, a tensor's last element)
        record = lambda: store.meta_snapshot(len(self), self._last_cursor_index)  # noqa: E731
        store.build(stored_max, ndim=self.ndim, device=self.device, length=self.__len__, record=record,
                    commit_interval=commit_interval, background=background, codec=codec, attrs=attrs)
        self._own_writes = 0  # depth of this class's own writes (see _bump_mutation_revision)
        if max_size is not None and int(max_size) != stored_max:
            store.grow(int(max_size))
            self.max_size = self._mirror.max_size
        if self._mirror.schema is not None:
            self._load_rows(attrs)
        if not self.read_only:
            self.env = attrs.get("env") if env is None else env  # by default, the previous run's env
            store.open_arrays(attrs)
            lifecycle.register_writer(self)  # flushed at exit and on SIGTERM
            if self._mirror.schema is not None:  # committed with the next commit, as any write (a crash before
                # it leaves them open, and the next open closes them again)
                if store.close_open_episodes(len(self), self._is_full):
                    self._bump_own()
        self._mirror.end_open()  # what a writer's open read before its rows were filled is let go

    def _load_rows(self, attrs: dict) -> None:
        record = attrs
        attrs, pending = self._store.settle_record(attrs)
        self._allocate()
        n = self._store.fill_rows(record, attrs, pending=pending)
        self.initialized = True
        self._len = n
        last = int(attrs.get("last_cursor", -1))
        if last >= 0:
            self._set_last_cursor(last)
        self._bump_own()

    @property
    def _storage(self):
        """What TorchRL reads as the storage: the rows as the user wrote them (views, a column, a tensorclass).

        Filled: waits for a reader's background fill under way (:mod:`.background_fill`); ``get`` (every
        ``sample``) waits only for the chunks of its rows.
        """
        mirror = getattr(self.__dict__.get("_store"), "mirror", None)
        if mirror is not None:
            mirror.finish_fill()
        return self.__dict__.get("_stored")

    @_storage.setter
    def _storage(self, value) -> None:
        self.__dict__["_stored"] = value

    # the engine's parts, owned by the MemoryStore (read here, never copied: a reopen rebuilds them there)
    @property
    def _mirror(self):
        return self._store.mirror

    @property
    def _tags(self):
        return self._store.tags

    @property
    def _engine(self):
        return self._store.engine

    @property
    def _schema(self):
        return self._store.schema

    def _allocate(self) -> None:
        """(Re)builds the packed RAM mirror for the current schema, keeping existing rows."""
        self._mirror.allocate(keep=self.initialized)
        # what TorchRL sees as the storage: the data as the user wrote it (views, a column, a tensorclass / pytree)
        self._storage = self._schema.as_stored(self._mirror.views)
        self.__dict__.pop("_total_shape_value", None)  # TorchRL caches the storage shape

    def close_episode_at(self, row: int) -> None:
        """Ends the open episode at ``row`` (done/truncated), for writers that learn of a boundary late."""
        self._store.close_episode_at(row)
        self._bump_own()

    # -- properties --------------------------------------------------------------------------

    @property
    def bounded(self) -> bool:
        """Whether the memory has a declared capacity (a ring of ``max_size`` rows); ``False``: it grows, no ring."""
        return not self._store.unbounded

    @property
    def capacity(self) -> int:
        """The rows allocated now: ``max_size`` of a bounded memory; what an unbounded one has grown to."""
        return self._mirror.max_size

    @property
    def row_file(self) -> dict | None:
        """Where the rows are mapped from: ``{"file", "sealed", "shared", "background"}``, or ``None`` (rows in RAM).

        ``file``: the row file (``None``: a private, unlinked one); ``sealed``: it held the opened record's
        rows (the open read no chunk); ``shared``: this reader maps the store's own file (copy-on-write);
        ``background``: the open returned before its rows were filled from the chunks (a thread fills them,
        a read or write waits for its chunks only: docs/storage.md).
        """
        rows = self._store.rows
        return None if rows is None else {**rows.describe(), "background": self._mirror.filled_in_background}

    @property
    def env_names(self) -> tuple[str, ...]:
        """Environment names; the ``"env"`` column holds indices into this tuple (-1: unknown)."""
        return tuple(self._tags.env_names)

    @property
    def goal_conditioned(self) -> bool:
        """Whether the rows are goal-conditioned (``False``: no success-flag advice; recorded in the store)."""
        return bool(self._store.goal_conditioned)

    @property
    def env(self) -> str | None:
        """The environment name rows written from now on are tagged with."""
        return self._tags.env

    @env.setter
    def env(self, name: str | None) -> None:
        self._tags.env_code = UNKNOWN_ENV if name is None else self.env_code(name, create=True)

    def env_code(self, name: str, *, create: bool = False) -> int:
        """The integer code of an environment name (``create``: register a new one, writers only)."""
        return self._store.env_code(name, create=create)

    @property
    def local_dir(self) -> str | None:
        """The store's local directory, or ``None`` for in-memory and remote (URL) stores."""
        return self._handle.local_dir

    @property
    def write_count(self) -> int:
        """Transitions written to this store since it was created (or emptied), as the store counts them.

        The attached TorchRL writer keeps its own count (``rb.write_count``; it differs after ``write_at``,
        ``empty(empty_write_count=False)`` or with ``dim_extend=1``): that one is recorded beside this one,
        and a reopen hands it back to the writer."""
        return self._store.write_count

    def resume_writers(self) -> None:
        """Puts the writers of the buffers on this storage back to the store's cursor and write count."""
        self._store.restore_writers(self, force=True)

    @property
    def schema(self) -> dict[str, dict] | None:
        """A copy of the stored columns, ``{path: {"dtype", "shape"}}`` with the tags; ``None`` before the first write."""
        return None if self._mirror.schema is None else {p: dict(s) for p, s in self._mirror.schema.items()}

    def record(self, *, now: bool = False) -> dict[str, Any]:
        """The committed record (the store's group attributes) as plain JSON values.

        Keyword Args:
            now (bool): read it again from the store (a writer may have committed since): the record as
                committed now, not the one this handle loaded (or last refreshed). Default: ``False``.
        """
        return self._handle.current_record() if now else self._handle.group.attrs.asdict()

    def view(self) -> TensorDictBase:
        """Every row slot of the RAM mirror (``max_size`` rows, tags included) as views to read, not write."""
        if not self.initialized:
            raise RuntimeError(f"{self.path!r} holds no rows yet: there is no view to read.")
        return self._mirror.views

    @property
    def chunk_rows(self) -> int | None:
        """Rows (along the first dimension) per Zarr chunk; ``None`` before the first write."""
        return self._mirror.chunk_rows

    # -- the buffer's writer -------------------------------------------------------------------

    @property
    def checkpointer(self):
        return self._checkpointer

    @checkpointer.setter
    def checkpointer(self, value: StorageCheckpointerBase | None) -> None:
        # ReplayBuffer._init sets it right after registering its writer: where the writer can be restored
        if value is None or type(value) is StorageCheckpointerBase:
            value = ZarrCheckpointer()
        if isinstance(value, ZarrCheckpointer):  # its copies open as a ZarrStorage, whatever subclass self is
            value.open_copy = value.open_copy or _open_copy
        self._checkpointer = value
        if getattr(getattr(self, "_store", None), "restored_writers", None) is not None:
            self._store.restore_writers(self)

    # -- writes ----------------------------------------------------------------------------------

    def set(self, cursor, data, *, set_cursor: bool = True):
        self._set(cursor, data, set_cursor=set_cursor)

    def _set(self, cursor, data, *, set_cursor: bool = True, as_kind: DataKind | None = None,
             keep_tags: bool = False) -> None:
        """``set``, for rows of any kind written as TensorDicts (``as_kind``) and rows that keep their tags."""
        try:
            self._store.check_writable()
            if self._store.unbounded and counts_from_the_end(cursor):
                raise IndexError(f"ZarrStorage at {self.path!r} has no declared capacity, so no last row for a "
                                 f"negative index to count from (cursor {cursor!r}): name rows from 0 (len is "
                                 f"{len(self)}).")
            view = StoreView.of(self.path, self.ndim, self.initialized, self._schema, self._tags)
            plan = plan_write(view, cursor, data, set_cursor=set_cursor, as_kind=as_kind, keep_tags=keep_tags)
            if self.initialized:  # a writer's fill under way: the chunks written into are read first (a damaged
                self._mirror.fill_before_write(cursor)  # one refuses the write, changing nothing)
        except Exception:
            if set_cursor:  # the writer moved its cursor before calling us (TORCHRL_NOTES b)
                size = self.max_size if self._store.unbounded or not self.initialized else self._mirror.max_dim0
                self._store.rollback_writers(self, cursor, size)
            raise
        data = self._store.register(plan)
        n, new_paths, new_constants = plan.n, plan.new_paths, plan.new_constants
        # A signal arriving from here on is handled once the write is complete
        # (a flush must never see RAM rows that are not marked dirty yet).
        with lifecycle.critical(), self._own_write():
            if not self.initialized:
                self._init_schema(data, plan.single)
            elif new_paths:
                self._evolve_schema(data, new_paths, plan.single)
            if self._store.unbounded:  # TorchRL counts every row a set names into len, even rows written again
                self._fit(cursor, self._len_along_dim0 + n if set_cursor else 0)
            rows = cursor_rows(cursor, self._mirror.max_dim0)
            span, dirty = write_span(cursor, data, rows)
            with self._engine.cv:
                self._write_ram(cursor, span, data, set_cursor)
                if new_constants:  # with the rows that carry them, under the lock a commit takes its record in
                    self._schema.add_constants(new_constants)  # (never before: _fit's flush, a failed write)
                if set_cursor:
                    self._store.advance(n, int(rows[-1]) + 1)
                else:
                    self._store.note_in_place()
                self._store.follow_writers(self)  # TorchRL's writer moved before this call: its position now
                self._engine.mark_dirty(dirty, self._mirror.chunk_rows)
            self._engine.kick(notify=completes_chunk(rows, self._mirror.chunk_rows))

    def _fit(self, cursor, length: int) -> None:
        """A memory without a declared capacity grows (rows committed first) to hold the rows ``cursor`` writes,
        and ``length`` rows (TorchRL's ``len`` after the write)."""
        need = cursor.stop if isinstance(cursor, slice) and cursor.stop is not None else None
        if need is None:
            rows = cursor_rows(cursor, self._mirror.max_dim0)
            need = int(rows.max()) + 1 if rows.numel() else 0
        need = max(need, length)
        if need > self._mirror.max_dim0:
            self._store.flush()  # not self.flush(): inside a set, TorchRL's writer has moved past rows not written yet
            if self._store.grow_for(need):
                with self._engine.cv:
                    self._allocate()

    @contextlib.contextmanager
    def _own_write(self):
        """Marks a write made by this class (its rows are marked dirty where they are written)."""
        self._own_writes = getattr(self, "_own_writes", 0) + 1
        try:
            yield
        finally:
            self._own_writes -= 1

    def _bump_own(self) -> None:
        """Bumps TorchRL's mutation revision for a write of this class (nothing more to commit)."""
        with self._own_write():
            self._bump_mutation_revision()

    def _bump_mutation_revision(self) -> None:
        super()._bump_mutation_revision()
        if getattr(self, "_own_writes", 1) == 0 and getattr(self, "initialized", False) and not self.read_only and not self._handle.closed:
            # A write that did not go through set(): TorchRL's rb.set_at_ / set_ / update_
            # write into storage[:] in place and then bump the revision. The rows
            # touched are unknown here, so every stored row is committed again.
            self._store.mark_rows_dirty(self._len_along_dim0)

    def _write_ram(self, cursor, span, data: TensorDictBase, set_cursor: bool) -> None:
        """TensorStorage.set on the RAM mirror (``data`` is the prepared TensorDict): TorchRL's own bookkeeping
        of the caller's ``cursor``, the rows written at ``span`` (the same rows: :func:`.planner.write_span`)."""
        if set_cursor:
            self._set_last_cursor(cursor)
            self._get_new_len(data, cursor)
        self._mirror.write(span, data)
        self._bump_mutation_revision()

    def check_schema(self, data: TensorDictBase) -> None:
        """Raises, naming the key, unless ``data`` (batch ``[N]``) could be written (tags ignored; nothing is written)."""
        check_rows(StoreView.of(self.path, self.ndim, self.initialized, self._schema, self._tags), data)

    def _init_schema(self, data: TensorDictBase, single: bool) -> None:
        record = self._schema.create(data, single)
        if not self._store.unbounded:
            self.max_size = self._mirror.max_size  # as TorchRL rounds it for ndim > 1
        self._allocate()
        self.initialized = True
        self._engine.update_attrs(record)

    def _evolve_schema(self, data: TensorDictBase, new_paths: list[str], single: bool) -> None:
        """Adds columns for keys the store did not hold yet (older rows read zeros)."""
        self._store.flush()  # committed rows first: the new arrays start from a clean state
        self._schema.add_columns(data, new_paths, single, filled=self._len_along_dim0)
        with self._engine.cv:
            self._allocate()
        self._engine.update_attrs({"schema": self._mirror.schema})
        self._bump_own()

    # Kept for LazyTensorStorage: allocation happens in _init_schema.
    def _init(self, data) -> None:
        if not self.initialized:
            kind = self._schema.kind = DataKind.of(data)
            self._init_schema(kind.to_tensordict(data, self.ndim - 1), True)

    def _empty(self) -> None:
        self._store.check_writable()
        self._reset_rows()
        self.flush()

    def _reset_rows(self) -> None:
        """The rows emptied in RAM (the next commit records it)."""
        with lifecycle.critical(), self._own_write(), self._engine.cv:
            super()._empty()
            self._store.reset()
            self._store.follow_writers(self)  # the writer emptied first (it may keep its count)

    # -- reads ---------------------------------------------------------------------------------

    def get(self, index):
        """Rows at ``index``: one gather of whole packed rows, then views per key."""
        if not self.initialized:
            raise RuntimeError("Cannot get elements out of a non-initialized storage.")
        if isinstance(index, str) or (isinstance(index, tuple) and index and all(isinstance(i, str) for i in index)):
            return self._store.column(index, None if self._is_full else self._len_along_dim0)
        if isinstance(index, list):
            index = torch.as_tensor(index)
        packed = self._mirror.gather(index, None if self._is_full else self._len_along_dim0)
        return self._schema.rows_out(self._mirror.layout.views(packed, self._hidden))

    # -- durability ----------------------------------------------------------------------------

    def scanning(self):
        """A context for reads that scan whole columns: the row file's readahead is on inside it.

        Outside it the row file is mapped for samples (no readahead: a fault reads only its page),
        which keeps a memory larger than RAM sampleable under a small memory limit; a column read
        across every row (a goal index's snapshot) is many times faster with readahead.
        ``storage.columns.read_column``'s callers use it (:func:`~.columns.scanning`).

        Example:
            >>> import tempfile, torch
            >>> from tensordict import TensorDict
            >>> st = ZarrStorage(tempfile.mkdtemp() + "/m.zarr", 100, goal_conditioned=False)
            >>> st.set(range(10), TensorDict({"obs": torch.arange(10.0)}, [10]))
            >>> with st.scanning():
            ...     total = float(st._storage["obs"][: len(st)].sum())
            >>> total
            45.0
        """
        return self._store.scanning()

    def flush(self) -> None:
        """Blocks until every row written so far is durable and committed (with the attached writer's position)."""
        self._store.follow_writers(self, record=True)
        self._store.flush()

    def close(self) -> None:
        """Flushes, stops the writer and releases the store. Idempotent; optional (see :meth:`MemoryStore.close`)."""
        self._store.follow_writers(self, record=True)
        self._store.close()

    def __enter__(self) -> ZarrStorage:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            store = getattr(self, "_store", None)
            if store is not None and not store.handle.closed:
                if store.read_only:
                    self.close()  # lets go of the rows: no commit, nothing to wait on
                else:  # inline, or on the closer thread where the collection interrupted storage I/O
                    lifecycle.close_from_finalizer(self, sys._getframe(1))
        except Exception:  # noqa: BLE001 - never raise from a finaliser
            pass

    def refresh(self) -> int:
        """Re-reads a ``read_only`` store to see rows committed since; returns ``len`` (on an error, keeps the old rows)."""
        if not self.read_only:
            return len(self)
        self._mirror.finish_fill()  # the rows of the last open or refresh, whole, before anything is replaced
        saved = dict(self.__dict__)
        restore = self._store.snapshot()
        try:
            attrs = self._store.reopen(self.max_size)
            if attrs is None:
                return 0
            if int(attrs["max_size"]) != self.max_size and not self._store.unbounded:  # the writer grew the store
                self.max_size = int(attrs["max_size"])
                self.__dict__.pop("_total_shape_value", None)
            self.initialized = False
            self._load_rows(attrs)
        except BaseException:
            # a failed refresh leaves the handle as it was (its rows, its length)
            self.__dict__.update(saved)
            restore()
            raise
        return len(self)

    # -- state -----------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """TorchRL's storage state (the mirror's own rows, no copy) plus this store's bookkeeping (``"zarr"``)."""
        self.flush()
        rows = self._mirror.views.exclude(*TAG_KEYS).state_dict() if self.initialized else {}
        zarr = self._store.state(self.path, self.ndim, self.initialized)
        return {"_storage": rows, "initialized": self.initialized, "_len": len(self), "zarr": zarr}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Loads a storage's ``state_dict``, replacing the rows, as TorchRL's storages do.

        This store's own state, where the store holds what the state holds: only the writer position. Where the
        store has changed since (rows written or written again after the state was taken; a ``copy.deepcopy``-d
        state loaded to roll back), the state's rows are written back, as ``LazyTensorStorage`` restores them:
        the newer rows are replaced. A state holding this store's live rows (taken without a copy) cannot give
        back the rows of then where the store has moved on, and is refused, naming both counts. A state this
        store cannot hold (more rows than its capacity, a column it lacks, another dtype or shape) is refused
        before anything changes, naming what. The rows are replaced in one commit, after the rows of before are
        committed: a process killed on the way leaves those; an error on the way commits none of it and closes
        this handle (reopen the store to go on).
        """
        meta = state_dict.get("zarr") or {}
        rows = rows_of_state(state_dict.get("_storage"))
        if meta.get("store") is not None and meta.get("store") == self.path:
            then = [state_dict.get("_len"), meta.get("write_count")]
            live = rows is not None and shares_memory(rows, self._mirror.views if self.initialized else None)
            if then == [len(self), self.write_count] and (live or self.holds(state_dict)):
                self._store.restore_writers(self, force=True)
                self._bump_own()
                return
            if live:
                raise ValueError(
                    f"This state_dict is of the store {self.path!r} itself, which has moved on since (len "
                    f"{then[0]} -> {len(self)}, rows written {then[1]} -> {self.write_count}), and it holds the "
                    f"store's live rows, not a copy: the rows of then cannot be restored. Take a copy when taking "
                    f"the state (copy.deepcopy(rb.state_dict())), or build the buffer on the store without "
                    f"load_state_dict to go on from its newest rows."
                )
        self._store.check_writable()
        self._check_state(rows, state_dict)  # before anything changes: LazyTensorStorage raises keeping its rows
        rows, n0, tagged = state_rows(rows, state_dict, ndim=self.ndim, env_code=lambda x: self.env_code(x, create=True))
        kind = source_kind(state_dict, self._schema.kind, has_schema=self._mirror.schema is not None)
        if rows is not None:
            self._prepare_rewrite(torch.arange(n0), rows, kind, tagged)
        self.flush()  # the rows of before, durable: what a load that fails or is killed half-way leaves
        # The rows replaced in ONE commit (journalled where it rewrites committed rows): a process killed before
        # the flush below leaves the rows of before the load, never an emptied or half-replaced memory
        with lifecycle.critical(), self._engine.held():
            try:
                if self.initialized and len(self):
                    self._reset_rows()
                if rows is not None:
                    # written as a TensorDict, read back as the source's kind (or the store's)
                    self._set(torch.arange(n0), rows, as_kind=kind, keep_tags=tagged)
                    self._set_last_cursor(None)  # as TensorStorage.load_state_dict leaves it: no last write
                    self._store.load_position(meta, rows, n0, tagged)
                self._store.restore_writers(self, force=True)
                self._bump_own()
            except BaseException as err:
                # RAM holds neither the rows of before nor the state's: none of it is committed. Given up inside
                # the hold (no commit of the engine's own starts) and the critical section (a signal's flush
                # waits, then finds the handle closed)
                self._store.give_up_writes()
                super()._empty()  # nothing served from the half-replaced rows
                if not isinstance(err, Exception):  # KeyboardInterrupt, SystemExit: as they came (handle closed)
                    raise
                raise RuntimeError(
                    f"load_state_dict into the store at {self.path!r} failed after it began replacing the rows "
                    f"({type(err).__name__}: {err}). Nothing of it was committed: the store holds the rows of "
                    f"before the load. This handle is closed (its rows in RAM were half replaced): reopen the "
                    f"store with ZarrStorage({self.path!r}) and load the state again once the cause is fixed."
                ) from err
        self.flush()

    def _prepare_rewrite(self, cursor: torch.Tensor, rows: TensorDictBase, kind: DataKind, tagged: bool) -> None:
        """What a rewrite of the rows would commit on its way, done first, with the rows of now: the write
        checked (a refusal changes nothing), the rows it names read in (a writer's fill), a memory without a
        capacity grown, the columns the rows add created (older rows read zeros). Inside the hold of
        :meth:`load_state_dict` the write then commits nothing before its flush."""
        view = StoreView.of(self.path, self.ndim, self.initialized, self._schema, self._tags)
        plan = plan_write(view, cursor, rows, set_cursor=True, as_kind=kind, keep_tags=tagged)
        if not self.initialized:  # a first write: it creates the columns itself (checked here all the same)
            return
        with lifecycle.critical(), self._own_write():
            self._mirror.fill_before_write(cursor)
            if self._store.unbounded:  # as _set will ask after the rows are emptied (no length left then)
                self._fit(cursor, plan.n)
            if plan.new_paths:
                self._evolve_schema(plan.data, plan.new_paths, plan.single)

    def holds(self, state_dict: dict[str, Any]) -> bool:
        """Whether this store holds exactly the rows (and episode / run / env tags) of ``state_dict`` (a state of
        this store, or of a copy of it), bit for bit, and as many.

        Example:
            >>> import tempfile, copy, torch
            >>> from tensordict import TensorDict
            >>> st = ZarrStorage(tempfile.mkdtemp() + "/m.zarr", 10, goal_conditioned=False)
            >>> st.set(slice(0, 3), TensorDict({"obs": torch.arange(3.0)}, [3]))
            >>> then = copy.deepcopy(st.state_dict())
            >>> st.holds(then), st.set(1, TensorDict({"obs": torch.tensor(9.0)}, [])), st.holds(then)
            (True, None, False)
            >>> st.close()
        """
        rows = rows_of_state(state_dict.get("_storage"))
        n = int(state_dict.get("_len", 0))
        if n != len(self):
            return False
        if rows is None or not n:
            return not len(self)
        n0 = self._mirror.dim0(n)
        mine = self._mirror.views[:n0]
        tags = state_tags(state_dict.get("zarr") or {})
        theirs = rows[:n0]
        if tags is not None:
            theirs = theirs.clone(False)
            theirs.update(tags[:n0])
        keys = set(mine.keys(True, True))
        return keys == set(theirs.keys(True, True)) and all(_same(mine.get(k), theirs.get(k)) for k in keys)

    def _check_state(self, rows: TensorDictBase | None, state_dict: dict[str, Any]) -> None:
        """Raises, naming what, unless this store can hold the rows of ``state_dict`` (checked before it empties)."""
        n = int(state_dict.get("_len", 0))
        if rows is None or not n:
            return
        n0 = state_dim0(rows, n, ndim=self.ndim)
        # before the first write the capacity is max_size items across the store's ndim dimensions (TorchRL's;
        # a row of an ndim=1 store may have batch dimensions of its own)
        items = n0 * math.prod(rows.batch_size[1:self.ndim]) if len(rows.batch_size) >= self.ndim else n0
        too_many = n0 > self._mirror.max_dim0 if self.initialized else items > self.max_size
        if not self._store.unbounded and too_many:
            raise ValueError(f"The state holds {n0} rows along the first dimension; the store at {self.path!r} "
                             f"holds at most {self._mirror.max_dim0} (max_size={self.max_size}): load it into a "
                             f"store of that capacity. Nothing was changed.")
        if self.initialized and len(rows) >= n0:
            body, constants = rows[:n0], (state_dict.get("zarr") or {}).get("constants")
            if constants:  # the write carries them (state_rows): so does the check
                body = with_constants(body.clone(False), constants)
            check_rows(StoreView.of(self.path, self.ndim, self.initialized, self._schema, self._tags), body)

    def __reduce__(self):
        """Pickling gives a read-only handle on the same store, with every row written so far (this flushes)."""
        self._handle.check_shareable()
        self.flush()
        return (_open_read_only, (self.path, self._storage_options, str(self.device)))

    def summary(self) -> dict[str, Any]:
        """Rows, episodes, runs, success rates, env names and size on disk, as a dict (see :func:`.summary.summarize`)."""
        return self._store.summary(self.initialized, len(self), None if self._store.unbounded else self.max_size)

    def __repr__(self) -> str:
        size = self.max_size if self.bounded else None
        return (f"{type(self).__name__}(path={self.path!r}, len={len(self)}, max_size={size}, "
                f"read_only={self.read_only}, envs={list(self._tags.env_names)})")


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal shapes, dtypes and values, NaN where the other has NaN (a row holding NaN is the same row)."""
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if not a.dtype.is_floating_point:
        return torch.equal(a, b)
    nan = a.isnan()
    return torch.equal(nan, b.isnan()) and torch.equal(a.masked_fill(nan, 0), b.masked_fill(nan, 0))


def _open_copy(path) -> ZarrStorage:
    """A checkpoint's copy of a store, read-only (``ZarrCheckpointer.loads`` reads its rows)."""
    return ZarrStorage(path, read_only=True)


def _open_read_only(path: str, storage_options: dict | None, device: str) -> ZarrStorage:
    storage = ZarrStorage(path, read_only=True, storage_options=storage_options, device=device)
    storage._handle.received = True  # a pickled copy: writing through it gets the advice of check_writable
    return storage


def component_group(storage: ZarrStorage, name: str, *, write: bool = False, fresh: bool = False) -> Any | None:
    """The Zarr group ``name`` of ``storage``'s store in which a component (a sampler) keeps its own state.

    ``name`` is a reserved top-level name (it starts with ``_``, and is not the store's own ``_journal`` or
    ``_repair_backup``): no stored column can use it, and ``robotmem verify`` / ``copy`` / ``repair`` and a
    reopen leave it alone. ``write=True`` first checks that this handle may write (not read-only, not
    closed, not handed over: the error says what to do), then creates the group if it is missing;
    otherwise the group is returned only if it exists (``None`` if not).

    Args:
        storage (ZarrStorage): the open storage.
        name (str): the group's name, e.g. ``"_priority"``.

    Keyword Args:
        write (bool, optional): the caller will write into the group. Defaults to ``False``.
        fresh (bool, optional): with ``write``, the group is created anew, empty (a component whose own
            record cannot be read starts over). Defaults to ``False``.

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> path = tempfile.mkdtemp() + "/memory.zarr"
        >>> with ZarrStorage(path, 100) as storage:
        ...     storage.set(torch.arange(4), TensorDict({"obs": torch.ones(4, 3)}, [4]))
        ...     component_group(storage, "_doc") is None, component_group(storage, "_doc", write=True).path
        (True, '_doc')
    """
    if not isinstance(name, str) or not name.startswith("_") or "/" in name or name in RESERVED:
        raise ValueError(f"component_group name must be one top-level name starting with '_' (not one of "
                         f"{RESERVED}, the store's own folders), got {name!r}.")
    if write:
        storage._store.check_writable()
        if fresh:
            return storage._handle.group.create_group(name, overwrite=True)
        return storage._handle.group.require_group(name)
    try:
        node = storage._handle.group[name]
    except KeyError:
        return None
    return node if hasattr(node, "require_group") else None


def flush_before_close(storage: ZarrStorage, flush: Callable[[], Any]) -> None:
    """Has ``storage.close()`` call ``flush`` (a bound method: held weakly) before it commits its last rows.

    A component that keeps state in the store (:func:`component_group`), such as a sampler's priorities,
    registers its write here, so that closing the storage loses none of it. A failing ``flush`` is reported
    with a warning and the rows still close. A read-only or closed storage ignores the call.

    Args:
        storage (ZarrStorage): the open storage.
        flush (callable): a bound method taking no argument.

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> class Counter:
        ...     calls = 0
        ...     def flush(self):
        ...         Counter.calls += 1
        >>> counter = Counter()
        >>> storage = ZarrStorage(tempfile.mkdtemp() + "/memory.zarr", 100)
        >>> storage.set(torch.arange(4), TensorDict({"obs": torch.ones(4, 3)}, [4]))
        >>> flush_before_close(storage, counter.flush)
        >>> storage.close(); storage.close()
        >>> Counter.calls
        1
    """
    if storage._store.read_only or storage._handle.closed:
        return
    storage._store.before_close.append(weakref.WeakMethod(flush))
