"""``ZarrStorage``: a TorchRL replay-buffer storage that lives in a Zarr v3 store and survives the process.

A :class:`~torchrl.data.LazyTensorStorage` whose rows are also written through
to a Zarr group on disk (or any Zarr store URL). Samplers read the RAM mirror,
so sampling runs at in-memory speed; a background thread writes whole chunks
to Zarr and then commits the metadata that makes them visible. Constructing a
``ZarrStorage`` on an existing store restores every row, the length and the
writer's cursor, so a buffer built on it continues where the last process
stopped.

This class composes the package's parts (see :mod:`torchrl_robotmem.storage`);
``docs/storage.md`` describes the on-disk layout and the commit protocol.
"""
from __future__ import annotations

import contextlib
import math
import os
import warnings
import weakref
from typing import Any

import numpy as np
import torch
from tensordict import LazyStackedTensorDict, TensorDict, TensorDictBase
from torchrl.data.replay_buffers.checkpointers import StorageCheckpointerBase
from torchrl.data.replay_buffers.storages import LazyTensorStorage

from . import _backend, integrity, lifecycle, writer_sync
from ._backend import FORMAT_MARKER
from .checkpointer import ZarrCheckpointer
from .commit import CommitEngine
from .errors import IntegrityError
from .format import write_zero_chunks, writing_config, writing_handles
from .handle import StoreHandle
from .journal import replay_journal
from .mirror import RamMirror
from .planner import DROPPED_KEYS, StoreView, WritePlan, check_constants, cursor_rows, plan_write, validate
from .registry import TagRegistry
from .schema import DataKind, PackedLayout, create_arrays, default_chunk_rows, spec_of, split_constants, with_constants
from .tags import TAG_KEYS, UNKNOWN_ENV, open_episode_ends

__all__ = ["ZarrStorage", "ZarrCheckpointer", "TAG_KEYS"]

_DONE_KEY = ("next", "done")
_TRUNCATED_KEY = ("next", "truncated")



class ZarrStorage(LazyTensorStorage):
    """A persistent, crash-safe TorchRL storage backed by a Zarr v3 store.

    Rows are served from a RAM mirror (sampling is as fast as
    :class:`~torchrl.data.LazyTensorStorage`) and written through to Zarr by a
    background thread, whole chunks at a time. A new process that constructs a
    ``ZarrStorage`` on the same path gets every committed row back, with the
    length, the last cursor and the writer's cursor and write count: the next
    ``extend`` appends after the old rows, and a full buffer keeps wrapping
    around as if nothing had happened. Nothing needs closing: every writable
    store is flushed when its process ends (exit, exception, Ctrl-C, SIGTERM).

    It takes what :class:`~torchrl.data.LazyTensorStorage` takes: TensorDicts
    (nested keys, lazy stacks, lists), plain tensors, pytrees of tensors and
    tensorclasses, with ``ndim >= 2`` layouts (``[num_envs, time]`` for
    :class:`~torchrl.data.SliceSampler`). Keys may be added after the first
    write (recorded in the store; older rows read zeros).

    TensorDict rows are tagged by the storage with three int64 columns:
    ``"episode"`` (unique across runs), ``"run"`` (one per writing session) and
    ``"env"`` (an integer code; :attr:`env_names` maps codes to names).

    Args:
        path (str or os.PathLike or zarr Store): a local directory, a ``*.zip``
            path, or any Zarr/fsspec store URL (``"memory://name"``,
            ``"s3://bucket/key"``, ...).
        max_size (int, optional): capacity in transitions. Required to create a
            store; when reopening, defaults to the stored capacity. A larger value
            grows a store that has not wrapped around yet; anything else is an error.

    Keyword Args:
        env (str, optional): the environment name rows written from now on are
            tagged with (data that carries its own ``"env"`` entry keeps it).
        read_only (bool, optional): open an existing store for reading only, for
            example while another process writes to it. Defaults to ``False``.
        ndim (int, optional): number of leading batch dimensions one stored item
            spans (as in TorchRL): ``2`` stores ``[num_envs, time]`` data as is.
            Fixed when the store is created. Defaults to 1.
        chunk_rows (int, optional): rows (along the first dimension) per Zarr
            chunk. Defaults to about 4 MiB of data per chunk, capped at ``max_size``.
        compressor (str, optional): ``"blosc"`` (the default: zstd level 1 behind a
            byte shuffle, compressed without holding the GIL), ``"zstd"`` or ``None``.
        compression_level (int, optional): codec level. Defaults to 1.
        commit_interval (float, optional): seconds after which written rows are
            committed even if their chunk is not full. This bounds what a crash
            can lose. Defaults to 1.0.
        background (bool, optional): write to Zarr from a background thread
            (default). ``False`` makes every write durable before ``set`` returns.
        commit_process (bool, optional): with ``background``, have a child process
            (one per Python process, shared by its stores) split, compress and write
            the chunks, so that Zarr's Python-heavy write path does not compete
            with the training loop for the GIL; the background thread only copies
            each chunk once and hands it over a socket. Local stores only (URL,
            zip and in-memory stores always commit in-process). Defaults to
            ``True`` unless the environment sets ``TORCHRL_ROBOTMEM_COMMIT_PROCESS=0``.
        storage_options (dict, optional): passed to fsspec for URL stores.
        device (str, optional): device of the RAM mirror. Defaults to ``"cpu"``.
        compilable (bool, optional): as in TorchRL (keeps ``len`` in a plain int
            instead of a shared ``mp.Value``). Defaults to ``False``.
        sample_tags (bool, optional): include the ``episode`` / ``run`` / ``env`` tags in
            what ``get`` returns (hence in ``rb.sample()``). Defaults to ``False``: a
            buffer gives back exactly the keys written to it; the tags are always
            readable as columns (``storage["episode"]``) and through :func:`recall`.
        shared_init (bool, optional): TorchRL's way for several processes to
            write one storage. A store has a single writer process, so ``True`` is
            refused; see "Multi-process use" in ``docs/storage.md`` (a pickled
            ``ZarrStorage`` is a read-only handle in the receiving process).
        on_damage (str, optional): what opening a damaged store does (a missing or
            corrupt chunk, a commit record pointing past the written rows, see
            "Integrity" in ``docs/storage.md``). ``"raise"`` (default): an
            :class:`~torchrl_robotmem.storage.integrity.IntegrityError` naming the
            arrays and chunks at fault; nothing is written. ``"warn"`` (with
            ``read_only=True`` only): a warning, and the rows before the first
            damaged chunk are read. ``robotmem repair PATH`` makes the store writable again.

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
        >>> len(rb)
        10
        >>> _ = rb.extend(data)  # appends after the old rows
        >>> rb.storage["run"][-1].item(), len(rb)
        (1, 20)
        >>> rb.storage.close()
    """

    _default_checkpointer = ZarrCheckpointer

    def __init__(
        self,
        path: str | os.PathLike | Any,
        max_size: int | None = None,
        *,
        env: str | None = None,
        read_only: bool = False,
        ndim: int = 1,
        chunk_rows: int | None = None,
        compressor: str | None = "blosc",
        compression_level: int = 1,
        commit_interval: float = 1.0,
        background: bool = True,
        commit_process: bool | None = None,
        storage_options: dict | None = None,
        device: str = "cpu",
        compilable: bool = False,
        shared_init: bool = False,
        sample_tags: bool = False,
        on_damage: str = "raise",
    ) -> None:
        _check_arguments(path, max_size, chunk_rows=chunk_rows, commit_interval=commit_interval, ndim=ndim,
                         shared_init=shared_init, compressor=compressor, compression_level=compression_level,
                         on_damage=on_damage, read_only=read_only)
        self._on_damage = on_damage
        self._commit_process = commit_process
        self._handle = StoreHandle(path, read_only=read_only, storage_options=storage_options)
        self._handle.flush = self.flush  # a newer writable handle in this process flushes this one first
        self.path = self._handle.path
        self.read_only = self._handle.read_only
        self._storage_options = storage_options
        self._compressor = compressor
        self._compression_level = int(compression_level)
        # what storage.get() (hence rb.sample()) leaves out: the tags, unless asked for
        self._hidden = () if sample_tags else TAG_KEYS
        try:
            previous = self._handle.claim() if not self.read_only else None
        except BaseException:
            self._handle.closed = True  # never registered: the writer stays with the earlier handle
            raise
        try:
            self._open(max_size, env=env, ndim=int(ndim), chunk_rows=chunk_rows, device=device,
                       compilable=compilable, commit_interval=commit_interval, background=background)
        except BaseException:
            self._release()
            if previous is not None:
                previous.take_back(self._handle)
            raise

    # -- opening ----------------------------------------------------------------------

    def _use_worker(self, background: bool) -> bool:
        if self.read_only or not background or self._handle.local_dir is None:
            return False
        if self._commit_process is not None:
            return bool(self._commit_process)
        return os.environ.get("TORCHRL_ROBOTMEM_COMMIT_PROCESS", "1") != "0"

    def _open(self, max_size, *, env, ndim, chunk_rows, device, compilable, commit_interval, background) -> None:
        handle = self._handle
        handle.open()
        store = handle.store
        attrs = handle.group.attrs.asdict()
        if attrs.get(FORMAT_MARKER) is None:
            handle.create(attrs, max_size, chunk_rows, ndim)
            attrs = handle.group.attrs.asdict()
        handle.check_format(attrs)
        # before anything is read or written: a damaged store raises, naming the array and chunk
        grows = max_size is not None and int(max_size) != attrs.get("max_size")
        attrs = integrity.check_open(self._handle.group, attrs, store=store, local_dir=self._handle.local_dir, path=self.path,
                                     read_only=self.read_only, on_damage=self._on_damage,
                                     decode=not self.read_only and (bool(attrs.get("journal")) or grows))
        stored_max = int(attrs["max_size"])
        super().__init__(max_size=stored_max, device=device, ndim=int(attrs.get("ndim", 1)), compilable=compilable)
        self._mirror = RamMirror(stored_max, ndim=self.ndim, device=self.device, length=self.__len__)
        self._tags = TagRegistry(read_only=self.read_only)
        self._engine = CommitEngine(
            self._mirror, self._handle.group, record=self._meta_snapshot, commit_interval=commit_interval,
            background=background, name=str(self.path),
            worker_path=str(self._handle.local_dir) if self._use_worker(background) else None,
        )
        self._engine.handle = handle  # the worker gets a copy of its writer lock's descriptor
        self._sync_attrs(attrs)
        # This session's state.
        self._restored_writers: weakref.WeakSet = weakref.WeakSet()
        self._warned_items = False
        self._own_writes = 0  # depth of this class's own writes (see _bump_mutation_revision)
        if max_size is not None and int(max_size) != stored_max:
            self._grow(int(max_size))
        if self._mirror.schema is not None:
            self._load_rows(attrs)
        if env is None and not self.read_only:
            env = attrs.get("env")  # continue tagging with the previous run's env
        if env is not None and not self.read_only:
            self.env = env
        if not self.read_only:
            self._engine.arrays.update(writing_handles(self._handle.group, self._mirror.schema or ()))
            lifecycle.register_writer(self)  # flushed at exit and on SIGTERM
            if self._mirror.schema is not None:
                self._close_open_episodes()
                self.flush()

    def _sync_attrs(self, attrs: dict) -> None:
        """Persistent bookkeeping, mirrored from the group attributes."""
        self._constants: dict[str, Any] = dict(attrs.get("constants") or {})  # non-tensor entries
        self._kind = DataKind.from_json(attrs.get("kind"))
        inner = attrs.get("inner_shape")
        self._mirror.inner_shape = tuple(inner) if inner is not None else ()
        self._mirror.chunk_rows = attrs.get("chunk_rows")
        self._mirror.configure(attrs.get("schema"))
        self._tags.sync(attrs)
        self._write_count = int(attrs.get("write_count", 0))
        self._writer_cursor = int(attrs.get("cursor", 0))
        self._engine.set_committed(attrs)

    # -- loading -----------------------------------------------------------------------------

    def _grow(self, new_max: int) -> None:
        old = self.max_size
        if new_max < old:
            raise ValueError(
                f"The store at {self.path!r} holds up to {old} rows; max_size={new_max} would "
                f"shrink it. Shrinking is not supported: pass max_size={old} (or None)."
            )
        if self.read_only:
            raise ValueError(f"Cannot grow a store opened read_only (max_size={old}).")
        if self._write_count > self._committed_len or self._committed_len > old:
            raise ValueError(
                f"The store at {self.path!r} has wrapped around its max_size={old}; it cannot "
                f"grow to {new_max} without reordering rows. Pass max_size={old} (or None)."
            )
        self.max_size = self._mirror.max_size = new_max
        if self._mirror.schema is not None:
            for path in self._mirror.schema:
                arr = self._handle.group[path]
                arr.resize((self._mirror.max_dim0, *arr.shape[1:]))
        self._engine.reset_arrays()
        self._engine.update_attrs({"max_size": new_max})

    def _load_rows(self, attrs: dict) -> None:
        record = attrs
        journal = attrs.get("journal")
        if journal and not self.read_only:
            with writing_config():
                attrs = replay_journal(self._handle.group, journal)
            self._sync_attrs(attrs)
        elif journal:  # a reader applies the pending journal in RAM only
            attrs = {**attrs, **journal["meta"]}
            self._sync_attrs(attrs)
        n = int(attrs.get("len", 0))
        n0 = self._mirror.dim0(n)
        self._allocate()
        self._mirror.load(self._handle.group, n0, store_path=self.path, read_only=self.read_only)
        if journal and self.read_only:
            self._mirror.apply_journal(self._handle.group, journal)
        if self.read_only and n0:
            self._mirror.reread_overwritten(self._handle.store, self._handle.group, record, n0, store_path=self.path)
        if n0:
            # Zarr reads a chunk file that is gone as zeros: one moved away since the open's
            # listing (by `robotmem repair`) is an error here, never zero rows served
            n = self._check_read(attrs if not self.read_only else {**record, "len": min(n, int(record.get("len", 0)))}, n)
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

    def _check_read(self, attrs: dict, n: int) -> int:
        """Lists the chunk files below ``attrs["len"]`` again, after the rows were read; returns the rows to keep.

        A chunk missing now was read as zeros: an :class:`IntegrityError` naming it
        (``on_damage="warn"``: a warning, and only the rows before it are kept).
        """
        problems = integrity.missing_after_read(self._handle.group, attrs, store=self._handle.store, local_dir=self._handle.local_dir)
        if not problems:
            return n
        action = "A chunk file disappeared while the rows were read (is `robotmem repair` running?); no row was served."
        if not (self.read_only and self._on_damage == "warn"):
            raise IntegrityError(self.path, problems, read_only=self.read_only, action=action)
        cut = min(p.rows[0] for p in problems)
        warnings.warn(f"{IntegrityError(self.path, problems, action='')}\non_damage='warn': reading the "
                      f"{cut} rows before the first missing chunk.", stacklevel=4)
        return min(n, cut * self._mirror.inner_numel)

    def _allocate(self) -> None:
        """(Re)builds the packed RAM mirror for the current schema, keeping existing rows."""
        self._mirror.allocate(keep=self.initialized)
        # what TorchRL sees as the storage: the data as the user wrote it (a TensorDict of
        # views, the tensor column, or the tensorclass / pytree built on the views)
        views = self._mirror.views
        self._storage = self._kind.from_tensordict(views.exclude(*TAG_KEYS) if self._kind.kind != "tensordict" else views)
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
            done = self._mirror.views.get(_DONE_KEY)
            flat = done.reshape(-1, *done.shape[self.ndim:]) if self.ndim > 1 else done
            flat[rows] = True
            if _TRUNCATED_KEY in self._mirror.views.keys(True, True):
                trunc = self._mirror.views.get(_TRUNCATED_KEY)
                (trunc.reshape(-1, *trunc.shape[self.ndim:]) if self.ndim > 1 else trunc)[rows] = True
            self._engine.mark_dirty(torch.div(rows, self._mirror.inner_numel, rounding_mode="floor"), self._mirror.chunk_rows)
        with self._own_write():
            self._bump_mutation_revision()

    def _close_open_episodes(self) -> None:
        """Marks the last row of every episode the previous run left open as done/truncated."""
        n = len(self)
        if n == 0 or _DONE_KEY not in self._mirror.views.keys(True, True) or "episode" not in self._mirror.schema:
            return
        flat = {k: v.cpu() for k, v in self._mirror.flat_columns(("run", "episode", _DONE_KEY), n).items()}
        done = flat[_DONE_KEY].reshape(n, -1).any(-1)
        cursor = self._writer_cursor * self._mirror.inner_numel
        rows = open_episode_ends(flat["run"], flat["episode"], done, cursor=cursor, full=self._is_full)
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

    # The store handle's state, under the names the tests and benchmarks read.
    @property
    def _closed(self) -> bool:
        return self._handle.closed

    @property
    def _lock_file(self) -> Any:
        return self._handle.lock

    @property
    def _group(self) -> Any:
        return self._handle.group

    @property
    def _store(self) -> Any:
        return self._handle.store

    @property
    def _local_dir(self) -> str | None:
        return self._handle.local_dir

    @property
    def schema(self) -> dict[str, dict] | None:
        """The stored columns as ``{path: {"dtype": str, "shape": list}}`` (tags included), or
        ``None`` before the first write. A copy: editing it changes nothing."""
        return None if self._mirror.schema is None else {p: dict(s) for p, s in self._mirror.schema.items()}

    def record(self) -> dict[str, Any]:
        """The committed record (the store's group attributes) as plain JSON values."""
        return self._handle.group.attrs.asdict()

    def view(self) -> TensorDictBase:
        """Every row slot of the RAM mirror as a TensorDict of views, ``max_size`` rows
        along the first dimension (tags included). Read it, do not write into it: writes
        go through :meth:`set` / the replay buffer. Raises before the first write.
        """
        if not self.initialized:
            raise RuntimeError(f"{self.path!r} holds no rows yet: there is no view to read.")
        return self._mirror.views

    @property
    def chunk_rows(self) -> int | None:
        """Rows (along the first dimension) per Zarr chunk; ``None`` before the first write."""
        return self._mirror.chunk_rows

    # Views of the mirror, under the names the tests and benchmarks read.
    @property
    def _views(self) -> TensorDictBase | None:
        return self._mirror.views

    @property
    def _schema(self) -> dict[str, dict] | None:
        return self._mirror.schema

    # The commit engine's state, under the names the crash tests inspect.
    @property
    def _dirty(self) -> dict[int, int]:
        return self._engine.dirty

    @property
    def _inflight(self) -> int:
        return self._engine.inflight

    @property
    def _error(self) -> BaseException | None:
        return self._engine.error

    @property
    def _committed_len(self) -> int:
        return self._engine.committed_len

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
            plan = plan_write(self._plan_view(), cursor, data, set_cursor=set_cursor, as_kind=as_kind,
                              keep_tags=keep_tags)
        except Exception:
            if set_cursor:  # the writer moved its cursor before calling us (TORCHRL_NOTES b)
                rows = cursor_rows(cursor, self._mirror.max_dim0 if self.initialized else self.max_size)
                writer_sync.rollback_writers(self, int(rows[0]) if len(rows) else 0, len(rows),
                                             self._mirror.max_dim0 if self.initialized else self.max_size)
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
                self._constants = {**self._constants, **new_constants}
                self._engine.update_attrs({"constants": dict(self._constants)})
            rows = dirty = cursor_rows(cursor, self._mirror.max_dim0)
            if len(rows) > 1 and bool((rows[1:] - rows[:-1] == 1).all()):
                dirty = slice(int(rows[0]), int(rows[-1]) + 1)
                if not isinstance(cursor, tuple) and not isinstance(data, LazyStackedTensorDict):
                    cursor = dirty  # a view copy: ~2x an index_put
            with self._engine.cv:
                self._write_ram(cursor, data, set_cursor)
                if set_cursor:
                    self._write_count += n
                    self._writer_cursor = (int(rows[-1]) + 1) % self._mirror.max_dim0
                self._engine.mark_dirty(dirty, self._mirror.chunk_rows)
            # wake the writer only if a chunk just became complete (its timer covers the rest)
            last = int(rows[-1])
            self._engine.kick(notify=(last + 1) % self._mirror.chunk_rows == 0 or len(rows) > self._mirror.chunk_rows
                              or int(rows[0]) // self._mirror.chunk_rows != last // self._mirror.chunk_rows)

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
        if getattr(self, "_own_writes", 1) == 0 and getattr(self, "initialized", False) and not self.read_only and not self._closed:
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
        if isinstance(data, LazyStackedTensorDict) and data.stack_dim == 0:
            self._mirror.views.update_at_(data, cursor)  # each stacked TensorDict written in place
        elif isinstance(cursor, slice) and isinstance(data, TensorDict):
            # hot path (appends): one copy per leaf into its column, no TensorDict machinery
            cols = self._mirror.columns
            for key, value in data.items(include_nested=True, leaves_only=True):
                cols[key][cursor].copy_(value)
        else:
            self._mirror.views[cursor] = data
        self._bump_mutation_revision()

    def _check_writable(self) -> None:
        self._handle.check_writable()
        self._engine.raise_error()

    def _plan_view(self) -> StoreView:
        return StoreView(self.path, self.ndim, self.initialized, self._mirror, self._kind, self._constants,
                         self._tags.env_names, self._tags.env_code)

    def _register(self, plan: WritePlan) -> TensorDictBase:
        """What a valid plan changes in the store's bookkeeping; returns the rows to write.

        The env names it brings, the data kind (at the first write), a warning
        given once, and the episode ids and run drawn for its rows.
        """
        for name in plan.new_env_names:
            self.env_code(name, create=True)
        if plan.warning is not None and not self._warned_items:
            self._warned_items = True
            warnings.warn(plan.warning, stacklevel=5)
        if self._mirror.schema is None:
            self._kind = plan.kind  # recorded with the schema at the first write
        if plan.draw is not None:
            done, traj, continue_open = plan.draw
            episode = self._tags.draw(done, traj, continue_open=continue_open)
            plan.set_tags(episode.reshape(plan.lead), torch.full(plan.lead, self._current_run(), dtype=torch.long))
        return plan.rows()

    def check_schema(self, data: TensorDictBase) -> None:
        """Raises, naming the key, unless ``data`` (batch ``[N]``) could be written to this store.

        Nothing is written. The tag columns (``episode``, ``run``, ``env``) are
        ignored; a store with no rows yet accepts any supported dtypes.
        """
        data = data.exclude(*TAG_KEYS, *DROPPED_KEYS)
        view = self._plan_view()
        check_constants(view, split_constants(data))
        validate(view, data, False)

    def _current_run(self) -> int:
        run, new = self._tags.current_run()
        if new:
            self._engine.mark_meta_dirty()
        return run

    def _init_schema(self, data: TensorDictBase, single: bool) -> None:
        row = data if single else data[0]
        schema = spec_of(row.reshape(-1)[0] if row.batch_dims else row)
        self._mirror.inner_shape = tuple(row.batch_size)
        row_bytes = PackedLayout(schema).row_bytes * self._mirror.inner_numel
        if self._mirror.chunk_rows is None:
            self._mirror.chunk_rows = default_chunk_rows(row_bytes, self._mirror.max_dim0)
        self.max_size = self._mirror.max_size = self._mirror.max_dim0 * self._mirror.inner_numel  # as TorchRL rounds it for ndim > 1
        self._create_arrays(schema)
        self._mirror.configure(schema)
        self._allocate()
        self.initialized = True
        # Schema first: a store whose arrays exist but whose schema is unknown would not reopen.
        self._engine.update_attrs(
            {
                "schema": schema,
                "chunk_rows": self._mirror.chunk_rows,
                "inner_shape": list(self._mirror.inner_shape),
                "kind": self._kind.to_json(),
                "max_size": self.max_size,
            }
        )

    def _create_arrays(self, schema: dict[str, dict]) -> None:
        m = self._mirror
        arrays = create_arrays(self._handle.group, schema, rows=m.max_dim0, inner_shape=m.inner_shape,
                               chunk_rows=m.chunk_rows, compressor=self._compressor, level=self._compression_level)
        self._engine.arrays.update(arrays)
        if self.initialized:  # keys added later: their older rows are zeros, in chunk files
            for arr in arrays.values():
                write_zero_chunks(arr, self._len_along_dim0, m.chunk_rows)

    def _evolve_schema(self, data: TensorDictBase, new_paths: list[str], single: bool) -> None:
        """Adds columns for keys the store did not hold yet (older rows read zeros)."""
        row = data if single else data[0]
        if self.ndim > 1:
            row = row.reshape(-1)[0]
        added = {p: s for p, s in spec_of(row.select(*[_backend.path_to_key(p) for p in new_paths])).items()}
        self.flush()  # committed rows first: the new arrays start from a clean state
        self._create_arrays(added)
        self._mirror.configure({**self._mirror.schema, **added})
        with self._engine.cv:
            self._allocate()
        self._engine.update_attrs({"schema": self._mirror.schema})
        with self._own_write():
            self._bump_mutation_revision()

    # Kept for LazyTensorStorage: allocation happens in _init_schema.
    def _init(self, data) -> None:
        if not self.initialized:
            kind = DataKind.of(data)
            self._kind = kind
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
            if self._constants:  # a non-tensor entry is a column too
                rows = with_constants(rows, self._constants)
            return rows[index]  # a column, as LazyTensorStorage gives it
        if isinstance(index, list):
            index = torch.as_tensor(index)
        packed = self._mirror.packed if self._is_full else self._mirror.packed[: self._len_along_dim0]
        rows = self._mirror.layout.views(packed[index], self._hidden)
        if self._constants:
            rows = with_constants(rows, self._constants)
        return self._kind.from_tensordict(rows)

    def _meta_snapshot(self) -> dict:
        last = self._last_cursor_index
        return {
            "len": len(self),
            "cursor": self._writer_cursor,
            "last_cursor": -1 if last is None else int(last),
            "write_count": self._write_count,
            **self._tags.record(),
        }

    @property
    def _last_cursor_index(self) -> int | None:
        last = self._last_cursor
        if last is None:
            return None
        if isinstance(last, torch.Tensor):
            return int(last.reshape(-1)[-1]) if last.numel() else None
        if isinstance(last, slice):
            return last.stop - 1
        if isinstance(last, range):
            return last[-1] if len(last) else None
        if isinstance(last, (list, tuple)):
            return int(last[-1]) if last else None
        return int(last)

    # -- durability ----------------------------------------------------------------------------

    def flush(self) -> None:
        """Blocks until every row written so far is durable and committed."""
        if self.read_only or self._closed:
            return
        self._engine.flush()

    def _raise_writer_error(self) -> None:
        self._engine.raise_error()

    def close(self) -> None:
        """Flushes, stops the writer and releases the store. Idempotent.

        Closing is optional: every writable store is also flushed when the
        process exits (end of script, exception, Ctrl-C) or receives SIGTERM.
        If the last rows cannot be written (a full disk), the handle is closed
        all the same and the error says how many rows, and which, are lost;
        call :meth:`flush` first to keep them while the cause is fixed.
        """
        if self._closed:
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
            if not getattr(self, "_closed", True):
                self.close()
        except Exception:  # noqa: BLE001 - never raise from a finaliser
            pass

    def refresh(self) -> int:
        """Re-reads a store opened ``read_only`` to see rows committed since. Returns ``len``.

        Runs the checks an open runs (a commit record pointing past the written
        rows, a missing or corrupt chunk: an :class:`IntegrityError`, and the
        handle keeps the rows it had). A store the writer grew (reopened with a
        larger ``max_size``) is read at its new size.
        """
        if not self.read_only:
            return len(self)
        saved = dict(self.__dict__)
        saved_group = self._handle.group
        mirror_state = dict(vars(self._mirror))
        tags_state = dict(vars(self._tags))
        engine_state = {k: v for k, v in vars(self._engine).items() if k in ("group", "committed_len", "committed_write_count")}
        try:
            group = _backend.open_group(self._handle.store, read_only=True)
            attrs = group.attrs.asdict()
            self._handle.check_format(attrs)
            attrs = integrity.check_open(group, attrs, store=self._handle.store, local_dir=self._handle.local_dir, path=self.path,
                                         read_only=True, on_damage=self._on_damage)
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
            self._handle.group = saved_group
            vars(self._mirror).update(mirror_state)
            vars(self._tags).update(tags_state)
            vars(self._engine).update(engine_state)
            raise
        return len(self)

    # -- state -----------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """TorchRL's storage state (the rows, ``initialized``, ``_len``) plus this store's bookkeeping.

        The rows are the RAM mirror's own tensors (no copy); a
        :class:`~torchrl.data.LazyTensorStorage` can load this state too.
        """
        self.flush()
        rows = self._mirror.views.exclude(*TAG_KEYS).state_dict() if self.initialized else {}
        tags = self._mirror.views.select(*TAG_KEYS, strict=False).state_dict() if self.initialized else {}
        return {
            "_storage": rows,
            "initialized": self.initialized,
            "_len": len(self),
            "zarr": {
                "store": self.path if isinstance(self.path, str) else None,
                "write_count": self._write_count,
                "cursor": self._writer_cursor,
                "env_names": list(self._tags.env_names),
                "kind": self._kind.to_json(),
                "ndim": self.ndim,
                "tags": tags,
                "constants": dict(self._constants),
            },
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Loads another storage's ``state_dict`` (this store's own: only the writer position).

        Rows from another store, or from a TorchRL storage, replace what this
        store held; rows from another ``ZarrStorage`` keep their episode / run /
        env tags.
        """
        meta = state_dict.get("zarr") or {}
        if meta.get("store") is not None and meta.get("store") == self.path:
            self._restore_writers(force=True)
            with self._own_write():
                self._bump_mutation_revision()
            return
        self._check_writable()
        n = int(state_dict.get("_len", 0))
        rows = _rows_of_state(state_dict.get("_storage"))
        if self.initialized and len(self):
            self._empty()
        if n and rows is not None:
            n0 = -(-n // max(1, math.prod(rows.shape[1 : self.ndim])))
            rows = rows[:n0]
            tags = meta.get("tags") or None
            if tags is not None:
                tags = TensorDict().load_state_dict(tags, strict=False)
                tags.batch_size = _leading(tags)
                rows = rows.clone(False)
                rows.update(tags[:n0])
                table = torch.tensor([self.env_code(x, create=True) for x in meta.get("env_names", [])] + [-1])
                rows.set("env", table[rows.get("env").clamp(min=-1)])
            if meta.get("constants"):
                rows = with_constants(rows.clone(False), meta["constants"])
            kind = DataKind.from_json(meta.get("kind")) if meta.get("kind") else None
            if kind is None or kind.kind == "tensordict" or self._mirror.schema is not None:
                kind = self._kind
            # written as a TensorDict, read back as the source's kind (or the store's)
            self._set(torch.arange(n0), rows, as_kind=kind, keep_tags=tags is not None)
            self._writer_cursor = int(meta.get("cursor", n0 % self._mirror.max_dim0)) % self._mirror.max_dim0
            self._write_count = int(meta.get("write_count", n0))
            if tags is not None:
                self._tags.note_stored(rows.get("episode").max(), rows.get("run").max())
            with self._engine.cv:
                self._engine.mark_meta_dirty()
        self._restore_writers(force=True)
        with self._own_write():
            self._bump_mutation_revision()
        self.flush()

    def __reduce__(self):
        """Pickling gives a read-only handle on the same store in the receiving process.

        A store has one writer process: collector workers, ``ParallelEnv``
        workers and ``copy.deepcopy`` get a reader that sees what was committed
        (everything written so far: this flushes first).
        """
        if not isinstance(self.path, str) or self.path.startswith("memory://"):
            raise RuntimeError(
                f"A ZarrStorage on {self.path!r} cannot be sent to another process: the store lives "
                f"in this process's memory. Use a directory or a shared URL store."
            )
        self.flush()
        return (_open_read_only, (self.path, self._storage_options, str(self.device)))

    def summary(self) -> dict[str, Any]:
        """Rows, episodes, runs, success rates, env names and size on disk, as a dict.

        ``success_rate`` is the fraction of transitions with ``("next", "is_success")``;
        ``episode_success_rate`` the fraction of finished episodes that ended in success.
        """
        n = len(self)
        out: dict[str, Any] = {"path": self.path, "rows": n, "max_size": self.max_size}
        keys = set(self._mirror.views.keys(True, True)) if self.initialized else set()
        if n and "episode" in keys:
            cols = self._mirror.flat_columns(
                [k for k in ("episode", "run", ("next", "is_success"), _DONE_KEY) if k in keys], n
            )
            out["episodes"] = int(torch.unique(cols["episode"]).numel())
            out["runs"] = int(torch.unique(cols["run"]).numel())
            succ = ("next", "is_success")
            if succ in cols:
                success = cols[succ].reshape(n, -1)[:, 0] > 0.5
                out["success_rate"] = float(success.float().mean())
                if _DONE_KEY in cols:
                    ends = cols[_DONE_KEY].reshape(n, -1).any(-1)
                    if ends.any():  # success at the last step of each finished episode
                        out["episode_success_rate"] = float(success[ends].float().mean())
        else:
            out["episodes"] = out["runs"] = 0
        out["envs"] = self.env_names
        if self._constants:
            out["constants"] = {str(_backend.path_to_key(p)): v for p, v in self._constants.items()}
        out["bytes_on_disk"] = _backend.store_size_bytes(self._handle.local_dir)
        return out

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(path={self.path!r}, len={len(self)}, max_size={self.max_size}, "
            f"read_only={self.read_only}, envs={list(self._tags.env_names)})"
        )


# -- helpers ------------------------------------------------------------------------------


def _check_arguments(path, max_size, *, chunk_rows, commit_interval, ndim, shared_init, compressor,
                     compression_level, on_damage, read_only) -> None:
    """Raises, saying what to pass instead, on constructor arguments ZarrStorage refuses."""
    if isinstance(path, (int, np.integer)) and not isinstance(path, bool):
        raise TypeError(
            f"ZarrStorage's first argument is the store's path; got the number {path}. "
            f"Use ZarrStorage(path, max_size), e.g. functools.partial(ZarrStorage, 'memory/run.zarr')."
        )
    if max_size is not None and int(max_size) <= 0:
        raise ValueError(f"max_size must be a positive integer, got {max_size}.")
    if chunk_rows is not None and int(chunk_rows) <= 0:
        raise ValueError(f"chunk_rows must be a positive integer, got {chunk_rows}.")
    if commit_interval <= 0:
        raise ValueError(f"commit_interval must be > 0 seconds, got {commit_interval}.")
    if int(ndim) < 1:
        raise ValueError(f"ndim must be >= 1, got {ndim}.")
    if shared_init:
        raise ValueError(
            "ZarrStorage(shared_init=True) is not supported: a store has one writer process. "
            "Write from the main process (iterate the collector there and call rb.extend), and "
            "give other processes read-only handles: pickle the storage (it arrives read_only) "
            "or open ZarrStorage(path, read_only=True) there."
        )
    _backend.make_compressors(compressor, compression_level, 4)  # validates the name
    if on_damage not in ("raise", "warn") or (on_damage == "warn" and not read_only):
        raise ValueError(
            f"on_damage must be 'raise', or 'warn' with read_only=True (a damaged store is not "
            f"opened for writing: run `robotmem repair PATH`), got {on_damage!r} with read_only={read_only}."
        )


def _open_read_only(path: str, storage_options: dict | None, device: str) -> ZarrStorage:
    storage = ZarrStorage(path, read_only=True, storage_options=storage_options, device=device)
    storage._handle.received = True  # a pickled copy: writing through it gets the advice of check_writable
    return storage


def _rows_of_state(source: Any) -> TensorDictBase | None:
    """The rows of a TorchRL storage ``state_dict()["_storage"]`` as a TensorDict."""
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
