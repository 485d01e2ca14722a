"""``ZarrStorage``: a TorchRL replay-buffer storage that lives in a Zarr v3 store and survives the process.

The TorchRL ``Storage`` contract, composing the parts of this package; ``docs/storage.md``
("Map of storage/") says which part owns which job, the on-disk layout and the commit protocol.
"""
from __future__ import annotations

import contextlib
import os
import weakref
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data.replay_buffers.checkpointers import StorageCheckpointerBase
from torchrl.data.replay_buffers.storages import LazyTensorStorage

from . import lifecycle, loader, writer_sync
from .checkpointer import ZarrCheckpointer
from .commit import CommitEngine
from .format import writing_handles
from .handle import StoreHandle
from .mirror import RamMirror
from .planner import WritePlan, check_rows, completes_chunk, cursor_rows, last_index, plan_write, write_span
from .registry import TagRegistry
from .schema import DataKind, with_constants
from .state import rows_of_state, source_kind, state_rows
from .store_schema import StoreSchema
from .summary import summarize
from .tags import TAG_KEYS, UNKNOWN_ENV

__all__ = ["ZarrStorage", "ZarrCheckpointer", "TAG_KEYS"]



class ZarrStorage(LazyTensorStorage):
    """A persistent, crash-safe TorchRL storage backed by a Zarr v3 store.

    A :class:`~torchrl.data.LazyTensorStorage` whose rows are written through to
    Zarr: samplers read a RAM mirror, a background thread commits whole chunks,
    and reopening the path restores every row, the length and the writer's
    cursor. It composes the parts of ``docs/storage.md``'s "Map of storage/";
    what it stores, how rows are tagged, when they are durable and each argument in full are told there.

    Args:
        path (str or os.PathLike or zarr Store): a local directory, a ``*.zip`` path, or any
            Zarr/fsspec store URL (``"memory://name"``, ``"s3://bucket/key"``, ...).
        max_size (int, optional): capacity in transitions; required to create a store, the stored
            one when reopening (a larger value grows a store that has not wrapped around).

    Keyword Args:
        env (str, optional): the env name rows written from now on are tagged with.
        read_only (bool, optional): open an existing store for reading only. Defaults to ``False``.
        ndim (int, optional): leading batch dims of one stored item, as in TorchRL. Defaults to 1.
        chunk_rows (int, optional): rows per Zarr chunk. Defaults to about 4 MiB of data a chunk.
        compressor (str, optional): ``"blosc"`` (default), ``"zstd"`` or ``None``.
        compression_level (int, optional): codec level. Defaults to 1.
        commit_interval (float, optional): seconds after which written rows are committed even
            if their chunk is not full (what a crash can lose). Defaults to 1.0.
        background (bool, optional): commit from a background thread (default); ``False``:
            every write is durable before ``set`` returns.
        commit_process (bool, optional): with ``background``, split, compress and write chunks
            in a child process (local stores only). Defaults to ``True`` unless
            ``TORCHRL_ROBOTMEM_COMMIT_PROCESS=0``.
        storage_options (dict, optional): passed to fsspec for URL stores.
        device (str, optional): device of the RAM mirror. Defaults to ``"cpu"``.
        compilable (bool, optional): as in TorchRL (plain-int ``len``). Defaults to ``False``.
        shared_init (bool, optional): refused (``True``): a store has one writer process.
        sample_tags (bool, optional): include the ``episode`` / ``run`` / ``env`` tags in what
            ``get`` returns. Defaults to ``False`` (they stay readable as columns).
        on_damage (str, optional): opening a damaged store: ``"raise"`` (default) an
            :class:`~torchrl_robotmem.storage.errors.IntegrityError`, or ``"warn"``
            (``read_only=True`` only) and read the rows before the first damaged chunk.

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
        >>> # ... days later, in another process
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
                 on_damage: str = "raise") -> None:
        loader.check_arguments(path, max_size, chunk_rows=chunk_rows, commit_interval=commit_interval, ndim=ndim,
                               shared_init=shared_init, compressor=compressor, compression_level=compression_level,
                               on_damage=on_damage, read_only=read_only)
        self._on_damage = on_damage
        self._commit_process = commit_process
        self._handle = StoreHandle(path, read_only=read_only, storage_options=storage_options)
        self._handle.flush = self.flush  # a newer writable handle in this process flushes this one first
        self.path = self._handle.path
        self.read_only = self._handle.read_only
        self._storage_options = storage_options
        # what storage.get() (hence rb.sample()) leaves out: the tags, unless asked for
        self._hidden = () if sample_tags else TAG_KEYS
        try:
            previous = self._handle.claim() if not self.read_only else None
        except BaseException:
            self._handle.closed = True  # never registered: the writer stays with the earlier handle
            raise
        try:
            self._open(max_size, env=env, ndim=int(ndim), chunk_rows=chunk_rows, device=device, compilable=compilable,
                       commit_interval=commit_interval, background=background,
                       codec=(compressor, int(compression_level)))
        except BaseException:
            self._release()
            if previous is not None:
                previous.take_back(self._handle)
            raise

    # -- opening ----------------------------------------------------------------------

    def _open(self, max_size, *, env, ndim, chunk_rows, device, compilable, commit_interval, background, codec) -> None:
        handle = self._handle
        attrs = loader.open_record(handle, max_size, chunk_rows=chunk_rows, ndim=ndim, on_damage=self._on_damage)
        stored_max = int(attrs["max_size"])
        super().__init__(max_size=stored_max, device=device, ndim=int(attrs.get("ndim", 1)), compilable=compilable)
        self._mirror = RamMirror(stored_max, ndim=self.ndim, device=self.device, length=self.__len__)
        self._tags = TagRegistry(read_only=self.read_only)
        self._engine = CommitEngine(
            self._mirror, self._handle.group, record=self._meta_snapshot, commit_interval=commit_interval,
            background=background, name=str(self.path),
            worker_path=str(handle.local_dir) if loader.use_worker(handle, background=background,
                                                                    commit_process=self._commit_process) else None,
        )
        self._engine.handle = handle  # the worker gets a copy of its writer lock's descriptor
        self._store_schema = StoreSchema(handle, self._mirror, self._engine.arrays, compressor=codec[0], level=codec[1])
        self._sync_attrs(attrs)
        self._restored_writers: weakref.WeakSet = weakref.WeakSet()  # this session's state
        self._own_writes = 0  # depth of this class's own writes (see _bump_mutation_revision)
        if max_size is not None and int(max_size) != stored_max:
            loader.grow_arrays(handle, self._mirror, self._engine, int(max_size), write_count=self._write_count)
            self.max_size = self._mirror.max_size
        if self._mirror.schema is not None:
            self._load_rows(attrs)
        if not self.read_only:
            self.env = attrs.get("env") if env is None else env  # by default, the previous run's env
            self._engine.arrays.update(writing_handles(self._handle.group, self._mirror.schema or ()))
            lifecycle.register_writer(self)  # flushed at exit and on SIGTERM
            if self._mirror.schema is not None:
                self._close_open_episodes()
                self.flush()

    def _sync_attrs(self, attrs: dict) -> None:
        """Persistent bookkeeping, mirrored from the group attributes."""
        self._store_schema.sync(attrs)
        self._tags.sync(attrs)
        self._write_count = int(attrs.get("write_count", 0))
        self._writer_cursor = int(attrs.get("cursor", 0))
        self._engine.set_committed(attrs)

    def _load_rows(self, attrs: dict) -> None:
        record = attrs
        pending = loader.pending_record(self._handle, attrs)
        if pending is not None:
            attrs = pending
            self._sync_attrs(attrs)
        self._allocate()
        n = loader.load_rows(self._handle, self._mirror, record, attrs, on_damage=self._on_damage)
        n0 = self._mirror.dim0(n)
        self.initialized = True
        self._len = n
        last = int(attrs.get("last_cursor", -1))
        if last >= 0:
            self._set_last_cursor(last)
        if n and "episode" in self._mirror.schema:
            # Rows past the committed metadata may survive a crash (journal
            # replays): never hand out an id that a stored row already uses.
            self._tags.note_stored(self._mirror.views.get("episode")[:n0].max(), self._mirror.views.get("run")[:n0].max())
        with self._own_write():
            self._bump_mutation_revision()

    def _allocate(self) -> None:
        """(Re)builds the packed RAM mirror for the current schema, keeping existing rows."""
        self._mirror.allocate(keep=self.initialized)
        # what TorchRL sees as the storage: the data as the user wrote it (a TensorDict of
        # views, the tensor column, or the tensorclass / pytree built on the views)
        views = self._mirror.views
        self._storage = self._store_schema.as_stored(views)
        self.__dict__.pop("_total_shape_value", None)  # TorchRL caches the storage shape

    # -- episodes ----------------------------------------------------------------------------

    def close_episode_at(self, row: int) -> None:
        """Ends the open episode at ``row`` (done/truncated), for writers that learn of a boundary late."""
        with self._engine.cv:
            self._tags.tagger.close_stream()
        self._mark_truncated(torch.tensor([row]))
        self._engine.kick()  # (the revision bump happens inside _mark_truncated)

    def _mark_truncated(self, rows: torch.Tensor) -> None:
        """Sets ``("next", "done")`` and ``("next", "truncated")`` on flat ``rows`` (RAM, then disk)."""
        with lifecycle.critical(), self._own_write(), self._engine.cv:
            self._engine.mark_dirty(self._mirror.mark_done(rows), self._mirror.chunk_rows)
        with self._own_write():
            self._bump_mutation_revision()

    def _close_open_episodes(self) -> None:
        """Marks the last row of every episode the previous run left open as done/truncated."""
        rows = self._mirror.open_episode_ends(len(self), self._writer_cursor, full=self._is_full)
        if rows.numel():
            self._mark_truncated(rows)

    # -- properties --------------------------------------------------------------------------

    @property
    def env_names(self) -> tuple[str, ...]:
        """Environment names; the ``"env"`` column holds indices into this tuple (-1: unknown)."""
        return tuple(self._tags.env_names)

    @property
    def env(self) -> str | None:
        """The environment name rows written from now on are tagged with."""
        return self._tags.env

    @env.setter
    def env(self, name: str | None) -> None:
        self._tags.env_code = UNKNOWN_ENV if name is None else self.env_code(name, create=True)

    def env_code(self, name: str, *, create: bool = False) -> int:
        """The integer code of an environment name.

        Args:
            name (str): the environment name, e.g. ``"FetchPush-v4"``.

        Keyword Args:
            create (bool): register the name if it is new (writers only).
        """
        with self._engine.cv:
            code, added = self._tags.code(name, create=create)
            if added:
                self._engine.mark_meta_dirty()
        return code

    @property
    def local_dir(self) -> str | None:
        """The store's local directory, or ``None`` for in-memory and remote (URL) stores."""
        return self._handle.local_dir

    @property
    def write_count(self) -> int:
        """Transitions written to this store since it was created (or emptied): the writer's count."""
        return self._write_count

    def resume_writers(self) -> None:
        """Puts the writers of the buffers on this storage back to the store's cursor and write count."""
        self._restore_writers(force=True)

    @property
    def schema(self) -> dict[str, dict] | None:
        """A copy of the stored columns, ``{path: {"dtype", "shape"}}`` with the tags; ``None`` before the first write."""
        return None if self._mirror.schema is None else {p: dict(s) for p, s in self._mirror.schema.items()}

    def record(self) -> dict[str, Any]:
        """The committed record (the store's group attributes) as plain JSON values."""
        return self._handle.group.attrs.asdict()

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
        # ReplayBuffer._init sets the checkpointer right after registering its
        # writer: the one place where the writer exists and can be restored.
        if value is None or type(value) is StorageCheckpointerBase:
            value = ZarrCheckpointer()
        self._checkpointer = value
        if hasattr(self, "_restored_writers"):
            self._restore_writers()

    def _restore_writers(self, force: bool = False) -> None:
        writer_sync.restore_writers(self, self._writer_cursor, self._write_count, self._restored_writers, force=force)

    # -- writes ----------------------------------------------------------------------------------

    def set(self, cursor, data, *, set_cursor: bool = True):
        self._set(cursor, data, set_cursor=set_cursor)

    def _set(self, cursor, data, *, set_cursor: bool = True, as_kind: DataKind | None = None,
             keep_tags: bool = False) -> None:
        """``set``, for rows of any kind written as TensorDicts (``as_kind``) and rows that keep their tags."""
        try:
            self._check_writable()
            view = self._store_schema.view(self.path, self.ndim, self.initialized, self._tags)
            plan = plan_write(view, cursor, data, set_cursor=set_cursor, as_kind=as_kind, keep_tags=keep_tags)
        except Exception:
            if set_cursor:  # the writer moved its cursor before calling us (TORCHRL_NOTES b)
                size = self._mirror.max_dim0 if self.initialized else self.max_size
                rows = cursor_rows(cursor, size)
                writer_sync.rollback_writers(self, int(rows[0]) if len(rows) else 0, len(rows), size)
            raise
        data = self._register(plan)
        n, new_paths, new_constants = plan.n, plan.new_paths, plan.new_constants
        # A signal arriving from here on is handled once the write is complete
        # (a flush must never see RAM rows that are not marked dirty yet).
        with lifecycle.critical(), self._own_write():
            if not self.initialized:
                self._init_schema(data, plan.single)
            elif new_paths:
                self._evolve_schema(data, new_paths, plan.single)
            if new_constants:
                self._engine.update_attrs(self._store_schema.add_constants(new_constants))
            rows = cursor_rows(cursor, self._mirror.max_dim0)
            cursor, dirty = write_span(cursor, data, rows)
            with self._engine.cv:
                self._write_ram(cursor, data, set_cursor)
                if set_cursor:
                    self._write_count += n
                    self._writer_cursor = (int(rows[-1]) + 1) % self._mirror.max_dim0
                self._engine.mark_dirty(dirty, self._mirror.chunk_rows)
            self._engine.kick(notify=completes_chunk(rows, self._mirror.chunk_rows))

    @contextlib.contextmanager
    def _own_write(self):
        """Marks a write made by this class (its rows are marked dirty where they are written)."""
        self._own_writes = getattr(self, "_own_writes", 0) + 1
        try:
            yield
        finally:
            self._own_writes -= 1

    def _bump_mutation_revision(self) -> None:
        super()._bump_mutation_revision()
        if getattr(self, "_own_writes", 1) == 0 and getattr(self, "initialized", False) and not self.read_only and not self._handle.closed:
            # A write that did not go through set(): TorchRL's rb.set_at_ / set_ / update_
            # write into storage[:] in place and then bump the revision. The rows
            # touched are unknown here, so every stored row is committed again.
            n0 = self._len_along_dim0
            if n0:
                with self._engine.cv:
                    self._engine.mark_dirty(slice(0, n0), self._mirror.chunk_rows)
                self._engine.kick()

    def _write_ram(self, cursor, data: TensorDictBase, set_cursor: bool) -> None:
        """TensorStorage.set on the RAM mirror (``data`` is the prepared TensorDict)."""
        if set_cursor:
            self._set_last_cursor(cursor)
            self._get_new_len(data, cursor)
        self._mirror.write(cursor, data)
        self._bump_mutation_revision()

    def _check_writable(self) -> None:
        self._handle.check_writable()
        self._engine.raise_error()

    def _register(self, plan: WritePlan) -> TensorDictBase:
        """Applies what a valid plan changes (env names, data kind, a warning, episode ids and run); returns its rows."""
        for name in plan.new_env_names:
            self.env_code(name, create=True)
        self._store_schema.note(plan)
        if plan.draw is not None and self._tags.tag_rows(plan):
            self._engine.mark_meta_dirty()  # this session's run was allocated
        return plan.rows()

    def check_schema(self, data: TensorDictBase) -> None:
        """Raises, naming the key, unless ``data`` (batch ``[N]``) could be written to this store.

        Nothing is written. The tag columns (``episode``, ``run``, ``env``) are
        ignored; a store with no rows yet accepts any supported dtypes.
        """
        check_rows(self._store_schema.view(self.path, self.ndim, self.initialized, self._tags), data)

    def _init_schema(self, data: TensorDictBase, single: bool) -> None:
        record = self._store_schema.create(data, single)
        self.max_size = self._mirror.max_size  # as TorchRL rounds it for ndim > 1
        self._allocate()
        self.initialized = True
        self._engine.update_attrs(record)

    def _evolve_schema(self, data: TensorDictBase, new_paths: list[str], single: bool) -> None:
        """Adds columns for keys the store did not hold yet (older rows read zeros)."""
        self.flush()  # committed rows first: the new arrays start from a clean state
        self._store_schema.add_columns(data, new_paths, single, filled=self._len_along_dim0)
        with self._engine.cv:
            self._allocate()
        self._engine.update_attrs({"schema": self._mirror.schema})
        with self._own_write():
            self._bump_mutation_revision()

    # Kept for LazyTensorStorage: allocation happens in _init_schema.
    def _init(self, data) -> None:
        if not self.initialized:
            kind = self._store_schema.kind = DataKind.of(data)
            self._init_schema(kind.to_tensordict(data, self.ndim - 1), True)

    def _empty(self) -> None:
        self._check_writable()
        with lifecycle.critical(), self._own_write(), self._engine.cv:
            super()._empty()
            self._writer_cursor = 0
            self._write_count = 0  # as TorchRL's writer restarts its count
            self._tags.tagger.reset()
            self._engine.mark_meta_dirty()
        self.flush()

    # -- reads ---------------------------------------------------------------------------------

    def get(self, index):
        """Rows at ``index``: one gather of whole packed rows, then views per key."""
        if not self.initialized:
            raise RuntimeError("Cannot get elements out of a non-initialized storage.")
        if isinstance(index, str) or (isinstance(index, tuple) and index and all(isinstance(i, str) for i in index)):
            rows = self._mirror.views if self._is_full else self._mirror.views[: self._len_along_dim0]
            if self._store_schema.constants:  # a non-tensor entry is a column too
                rows = with_constants(rows, self._store_schema.constants)
            return rows[index]  # a column, as LazyTensorStorage gives it
        if isinstance(index, list):
            index = torch.as_tensor(index)
        packed = self._mirror.packed if self._is_full else self._mirror.packed[: self._len_along_dim0]
        return self._store_schema.rows_out(self._mirror.layout.views(packed[index], self._hidden))

    def _meta_snapshot(self) -> dict:
        last = last_index(self._last_cursor)
        return {
            "len": len(self),
            "cursor": self._writer_cursor,
            "last_cursor": -1 if last is None else int(last),
            "write_count": self._write_count,
            **self._tags.record(),
        }

    # -- durability ----------------------------------------------------------------------------

    def flush(self) -> None:
        """Blocks until every row written so far is durable and committed."""
        if self.read_only or self._handle.closed:
            return
        self._engine.flush()

    def close(self) -> None:
        """Flushes, stops the writer and releases the store. Idempotent; optional (see "When the process ends").

        If the last rows cannot be written (a full disk), the handle is closed all the same and the
        error says which rows are lost; call :meth:`flush` first to keep them while the cause is fixed.
        """
        if self._handle.closed:
            return
        try:
            with lifecycle.critical():
                self.flush()
        except Exception:
            engine = getattr(self, "_engine", None)
            if engine is not None:
                engine.raise_error(closing=True)  # says which rows are lost
            raise
        finally:
            self._release()

    def _release(self) -> None:
        self._handle.closed = True
        engine = getattr(self, "_engine", None)
        if engine is not None:
            engine.close()
        self._handle.release()

    def __enter__(self) -> ZarrStorage:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            handle = getattr(self, "_handle", None)
            if handle is not None and not handle.closed:
                self.close()
        except Exception:  # noqa: BLE001 - never raise from a finaliser
            pass

    def refresh(self) -> int:
        """Re-reads a store opened ``read_only`` to see rows committed since (a grown store at its new size); returns ``len``.

        Runs the checks an open runs: on an :class:`IntegrityError` the handle keeps the rows it had.
        """
        if not self.read_only:
            return len(self)
        saved = dict(self.__dict__)
        restore = loader.snapshot(self._handle, self._mirror, self._tags, self._store_schema, self._engine)
        try:
            group, attrs = loader.reopen_record(self._handle, on_damage=self._on_damage)
            if attrs.get("schema") is None:
                return 0
            self._handle.group = self._engine.group = group
            if int(attrs["max_size"]) != self.max_size:  # the writer grew the store
                self.max_size = self._mirror.max_size = int(attrs["max_size"])
                self.__dict__.pop("_total_shape_value", None)
            self._sync_attrs(attrs)
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
        """TorchRL's storage state (the rows, ``initialized``, ``_len``) plus this store's bookkeeping (``"zarr"``).

        The rows are the RAM mirror's own tensors (no copy); a ``LazyTensorStorage`` can load this state too.
        """
        self.flush()
        rows = self._mirror.views.exclude(*TAG_KEYS).state_dict() if self.initialized else {}
        tags = self._mirror.views.select(*TAG_KEYS, strict=False).state_dict() if self.initialized else {}
        zarr = {"store": self.path if isinstance(self.path, str) else None, "write_count": self._write_count,
                "cursor": self._writer_cursor, "env_names": list(self._tags.env_names), "ndim": self.ndim, "tags": tags}
        return {"_storage": rows, "initialized": self.initialized, "_len": len(self), "zarr": {**zarr, **self._store_schema.state()}}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Loads another storage's ``state_dict`` (this store's own: only the writer position).

        Rows from another store or a TorchRL storage replace what this store held (a ``ZarrStorage``'s keep their tags).
        """
        meta = state_dict.get("zarr") or {}
        if meta.get("store") is not None and meta.get("store") == self.path:
            self._restore_writers(force=True)
            with self._own_write():
                self._bump_mutation_revision()
            return
        self._check_writable()
        rows = rows_of_state(state_dict.get("_storage"))
        if self.initialized and len(self):
            self._empty()
        rows, n0, tagged = state_rows(rows, state_dict, ndim=self.ndim, env_code=lambda x: self.env_code(x, create=True))
        if rows is not None:
            kind = source_kind(state_dict, self._store_schema.kind, has_schema=self._mirror.schema is not None)
            # written as a TensorDict, read back as the source's kind (or the store's)
            self._set(torch.arange(n0), rows, as_kind=kind, keep_tags=tagged)
            self._writer_cursor = int(meta.get("cursor", n0 % self._mirror.max_dim0)) % self._mirror.max_dim0
            self._write_count = int(meta.get("write_count", n0))
            if tagged:
                self._tags.note_stored(rows.get("episode").max(), rows.get("run").max())
            with self._engine.cv:
                self._engine.mark_meta_dirty()
        self._restore_writers(force=True)
        with self._own_write():
            self._bump_mutation_revision()
        self.flush()

    def __reduce__(self):
        """Pickling gives a read-only handle on the same store in the receiving process (a store has one writer).

        Collector workers, ``ParallelEnv`` workers and ``copy.deepcopy`` see everything written so far (this flushes).
        """
        self._handle.check_shareable()
        self.flush()
        return (_open_read_only, (self.path, self._storage_options, str(self.device)))

    def summary(self) -> dict[str, Any]:
        """Rows, episodes, runs, success rates, env names and size on disk, as a dict (see :func:`.summary.summarize`)."""
        return summarize(self._mirror if self.initialized else None, n=len(self), path=self.path, max_size=self.max_size,
                         env_names=self.env_names, constants=self._store_schema.constants, local_dir=self._handle.local_dir)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(path={self.path!r}, len={len(self)}, max_size={self.max_size}, "
            f"read_only={self.read_only}, envs={list(self._tags.env_names)})"
        )


def _open_read_only(path: str, storage_options: dict | None, device: str) -> ZarrStorage:
    storage = ZarrStorage(path, read_only=True, storage_options=storage_options, device=device)
    storage._handle.received = True  # a pickled copy: writing through it gets the advice of check_writable
    return storage
