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
import torchrl
from tensordict import LazyStackedTensorDict, TensorDict, TensorDictBase, is_tensor_collection
from tensordict.base import _is_leaf_nontensor
from torchrl.data.replay_buffers.checkpointers import StorageCheckpointerBase
from torchrl.data.replay_buffers.storages import LazyTensorStorage

from . import _backend, integrity, lifecycle, writer_sync
from ._backend import FORMAT_MARKER, FORMAT_VERSION
from .checkpointer import ZarrCheckpointer
from .commit import CommitEngine
from .schema import DataKind, PackedLayout, check_against, env_names_of, spec_of, split_constants, with_constants
from .tags import TAG_KEYS, UNKNOWN_ENV, EpisodeTagger, check_user_keys, check_user_tag, open_episode_ends

__all__ = ["ZarrStorage", "ZarrCheckpointer", "TAG_KEYS"]

_DONE_KEY = ("next", "done")
_TRUNCATED_KEY = ("next", "truncated")
_TRAJ_KEY = ("collector", "traj_ids")
# Written into the caller's TensorDict by TorchRL's TensorDictRoundRobinWriter;
# it equals the row position, so it is not stored (sample() adds it back).
_DROPPED_KEYS = ("index",)

# The writable handle of each store opened for writing in this process. A new
# writable handle on the same store takes the writer over from the old one.
_OPEN_WRITERS: dict[str, weakref.ref] = {}


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
        self._on_damage = on_damage
        self._commit_process = commit_process
        self.path = _backend.normalize_path(path)
        self.read_only = bool(read_only)
        self._storage_options = storage_options
        self._compressor = compressor
        self._compression_level = int(compression_level)
        self._lock_file = None
        self._closed = False
        self._retired_by: str | None = None
        # what storage.get() (hence rb.sample()) leaves out: the tags, unless asked for
        self._hidden = () if sample_tags else TAG_KEYS
        try:
            previous = self._claim_writer() if not self.read_only else None
        except BaseException:
            self._closed = True  # never registered: the writer stays with the earlier handle
            raise
        try:
            self._open(max_size, env=env, ndim=int(ndim), chunk_rows=chunk_rows, device=device,
                       compilable=compilable, commit_interval=commit_interval, background=background)
        except BaseException:
            self._release()
            if previous is not None:
                previous._take_back_writer(self)
            raise

    # -- opening ----------------------------------------------------------------------

    def _use_worker(self, background: bool) -> bool:
        if self.read_only or not background or self._local_dir is None:
            return False
        if self._commit_process is not None:
            return bool(self._commit_process)
        return os.environ.get("TORCHRL_ROBOTMEM_COMMIT_PROCESS", "1") != "0"

    def _open(self, max_size, *, env, ndim, chunk_rows, device, compilable, commit_interval, background) -> None:
        store, self._local_dir = _backend.open_store(
            self.path, read_only=self.read_only, storage_options=self._storage_options
        )
        self._store = store
        if self._local_dir is not None and not self.read_only:
            self._lock_file = _backend.WriterLock(self._local_dir)
            _backend.remove_partial_files(self._local_dir)  # left by a writer killed mid-chunk
        elif not self.read_only and isinstance(self.path, str) and _backend.is_url(self.path):
            self._lock_file = _backend.url_writer_lock(self.path, self._storage_options)
        self._group = _backend.open_group(store, read_only=self.read_only)
        attrs = self._group.attrs.asdict()
        if attrs.get(FORMAT_MARKER) is None:
            self._create_new(attrs, max_size, chunk_rows, ndim)
            attrs = self._group.attrs.asdict()
        self._check_format(attrs)
        # before anything is read or written: a damaged store raises, naming the array and chunk
        grows = max_size is not None and int(max_size) != attrs.get("max_size")
        attrs = integrity.check_open(self._group, attrs, store=store, local_dir=self._local_dir, path=self.path,
                                     read_only=self.read_only, on_damage=self._on_damage,
                                     decode=not self.read_only and (bool(attrs.get("journal")) or grows))
        stored_max = int(attrs["max_size"])
        super().__init__(max_size=stored_max, device=device, ndim=int(attrs.get("ndim", 1)), compilable=compilable)
        self._engine = CommitEngine(
            self, self._group, commit_interval=commit_interval, background=background, name=str(self.path),
            worker_path=str(self._local_dir) if self._use_worker(background) else None,
        )
        self._sync_attrs(attrs)
        # This session's state.
        self._run: int | None = None  # allocated at the first write
        self._env_code = UNKNOWN_ENV
        self._restored_writers: weakref.WeakSet = weakref.WeakSet()
        self._warned_items = False
        self._keep_tags = False
        self._own_writes = 0  # depth of this class's own writes (see _bump_mutation_revision)
        if max_size is not None and int(max_size) != stored_max:
            self._grow(int(max_size))
        if self._schema is not None:
            self._load_rows(attrs)
        if env is None and not self.read_only:
            env = attrs.get("env")  # continue tagging with the previous run's env
        if env is not None and not self.read_only:
            self.env = env
        if not self.read_only:
            self._engine.arrays.update(integrity.writing_handles(self._group, self._schema or ()))
            lifecycle.register_writer(self)  # flushed at exit and on SIGTERM
            if self._schema is not None:
                self._close_open_episodes()
                self.flush()

    def _check_format(self, attrs: dict) -> None:
        marker = attrs.get(FORMAT_MARKER)
        version = marker.get("format_version") if isinstance(marker, dict) else None
        if not isinstance(version, int) or isinstance(version, bool):
            raise ValueError(f"{self.path!r} has a malformed {FORMAT_MARKER!r} attribute (format_version {version!r}).")
        if int(marker["format_version"]) > FORMAT_VERSION:
            raise ValueError(
                f"{self.path!r} was written in format version {marker['format_version']} by "
                f"torchrl_robotmem {marker.get('library_version')}; this version reads format "
                f"<= {FORMAT_VERSION}. Upgrade torchrl_robotmem to open it."
            )

    def _create_new(self, attrs: dict, max_size: int | None, chunk_rows: int | None, ndim: int) -> None:
        if self.read_only:
            raise ValueError(f"{self.path!r} is not a torchrl_robotmem store (no {FORMAT_MARKER!r} attribute).")
        if attrs or any(True for _ in self._group.keys()):
            raise ValueError(
                f"{self.path!r} is a Zarr group that was not written by torchrl_robotmem "
                f"(no {FORMAT_MARKER!r} attribute). Refusing to write into it."
            )
        if max_size is None:
            raise ValueError(
                f"No store exists at {self.path!r} yet: pass max_size to create one, e.g. "
                f"ZarrStorage({self.path!r}, max_size=1_000_000)."
            )
        self._group.update_attributes(
            {
                FORMAT_MARKER: {
                    "format_version": FORMAT_VERSION,
                    "library_version": _library_version(),
                    "torchrl_version": torchrl.__version__,
                    "zarr_version": _backend.zarr.__version__,
                    "integrity": dict(integrity.MARKER),  # checksummed chunks, all-zero ones written too
                },
                "max_size": int(max_size),
                "ndim": int(ndim),
                "inner_shape": None,
                "chunk_rows": int(chunk_rows) if chunk_rows is not None else None,
                "schema": None,
                "kind": None,
                "len": 0,
                "cursor": 0,
                "last_cursor": -1,
                "write_count": 0,
                "episode_next": 0,
                "runs": 0,
                "env_names": [],
                "journal": None,
            }
        )

    def _sync_attrs(self, attrs: dict) -> None:
        """Persistent bookkeeping, mirrored from the group attributes."""
        self._chunk_rows = attrs.get("chunk_rows")
        self._schema: dict[str, dict] | None = attrs.get("schema")
        self._constants: dict[str, Any] = dict(attrs.get("constants") or {})  # non-tensor entries
        self._kind = DataKind.from_json(attrs.get("kind"))
        inner = attrs.get("inner_shape")
        self._inner_shape: tuple[int, ...] = tuple(inner) if inner is not None else ()
        self._env_names: list[str] = list(attrs.get("env_names", []))
        self._tagger = EpisodeTagger(int(attrs.get("episode_next", 0)))
        self._runs = int(attrs.get("runs", 0))
        self._write_count = int(attrs.get("write_count", 0))
        self._writer_cursor = int(attrs.get("cursor", 0))
        self._engine.set_committed(attrs)
        self._index_schema()

    def _index_schema(self) -> None:
        """``{key: (dtype, row shape)}`` without the tags, for the hot validation path."""
        self._layout = PackedLayout(self._schema) if self._schema is not None else None
        if self._schema is None:
            self._schema_by_key = None
            return
        self._schema_by_key = {
            _backend.path_to_key(p): (_backend.torch_dtype(spec["dtype"]), torch.Size(spec["shape"]))
            for p, spec in self._schema.items()
            if p not in TAG_KEYS
        }

    # -- shapes along the first dimension -------------------------------------------------

    @property
    def _inner_numel(self) -> int:
        """Elements per first-dimension row that count in ``len`` (the dims up to ``ndim``)."""
        return math.prod(self._inner_shape[: self.ndim - 1]) if self.ndim > 1 else 1

    @property
    def _max_dim0(self) -> int:
        return -(-self.max_size // self._inner_numel)

    def _dim0(self, n: int) -> int:
        return -(-int(n) // self._inner_numel)

    # -- writer handover within a process -------------------------------------------------

    def _claim_writer(self) -> ZarrStorage | None:
        """Takes the writer over from an earlier writable handle on the same store in this process.

        Re-running a notebook cell (``rb = ...ZarrStorage(path)``) or dropping a
        handle that an index still refers to must not lock the user out of their
        own store: the earlier handle is flushed and becomes a read-only
        snapshot. Returns it (to hand the writer back if this open fails).
        """
        key = str(self.path)
        ref = _OPEN_WRITERS.get(key)
        other = ref() if ref is not None else None
        if other is not None and (other._closed or other.read_only):
            other = None
        if other is not None:
            other._hand_over_writer()  # raises if it cannot write its rows: it keeps them, and the writer
        _OPEN_WRITERS[key] = weakref.ref(self)
        return other

    def _hand_over_writer(self) -> None:
        with lifecycle.critical():
            self.flush()
            self._retired_by = "a newer writable ZarrStorage on the same store in this process"
            self._closed = True
            if self._lock_file is not None:
                self._lock_file.release()
                self._lock_file = None

    def _take_back_writer(self, failed: ZarrStorage) -> None:
        """Undoes :meth:`_hand_over_writer` when the newer handle failed to open."""
        key = str(self.path)
        ref = _OPEN_WRITERS.get(key)
        if ref is None or ref() is None or ref() is failed:
            _OPEN_WRITERS[key] = weakref.ref(self)
        if self._local_dir is not None:
            try:
                self._lock_file = _backend.WriterLock(self._local_dir)
            except RuntimeError:
                return  # another process took it meanwhile: stay a snapshot
        self._retired_by = None
        self._closed = False

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
        self.max_size = new_max
        if self._schema is not None:
            for path in self._schema:
                arr = self._group[path]
                arr.resize((self._max_dim0, *arr.shape[1:]))
        self._engine.reset_arrays()
        self._engine.update_attrs({"max_size": new_max})

    def _load_rows(self, attrs: dict) -> None:
        record = attrs
        journal = attrs.get("journal")
        if journal and not self.read_only:
            with integrity.writing_config():
                attrs = CommitEngine.replay_journal(self._group, journal)
            self._sync_attrs(attrs)
        elif journal:  # a reader applies the pending journal in RAM only
            attrs = {**attrs, **journal["meta"]}
            self._sync_attrs(attrs)
        n = int(attrs.get("len", 0))
        n0 = self._dim0(n)
        self._allocate()
        for path in self._schema:
            if n0:
                self._column(path)[:n0] = torch.from_numpy(integrity.read_rows(
                    self._group[path], path, n0, self._chunk_rows, self.path, self.read_only))
        if journal and self.read_only:
            for path, rows, values in CommitEngine.journal_chunks(self._group, journal):
                self._column(path)[rows] = torch.from_numpy(np.ascontiguousarray(values))
        if self.read_only and n0:
            self._reread_overwritten(record, n0)
        if n0:
            # Zarr reads a chunk file that is gone as zeros: one moved away since the open's
            # listing (by `robotmem repair`) is an error here, never zero rows served
            n = self._check_read(attrs if not self.read_only else {**record, "len": min(n, int(record.get("len", 0)))}, n)
            n0 = self._dim0(n)
        self.initialized = True
        self._len = n
        last = int(attrs.get("last_cursor", -1))
        if last >= 0:
            self._set_last_cursor(last)
        if n and "episode" in self._schema:
            # Rows past the committed metadata may survive a crash (journal
            # replays): never hand out an id that a stored row already uses.
            self._tagger.next_id = max(self._tagger.next_id, int(self._views.get("episode")[:n0].max()) + 1)
            self._runs = max(self._runs, int(self._views.get("run")[:n0].max()) + 1)
        with self._own_write():
            self._bump_mutation_revision()

    def _check_read(self, attrs: dict, n: int) -> int:
        """Lists the chunk files below ``attrs["len"]`` again, after the rows were read; returns the rows to keep.

        A chunk missing now was read as zeros: an :class:`IntegrityError` naming it
        (``on_damage="warn"``: a warning, and only the rows before it are kept).
        """
        problems = integrity.missing_after_read(self._group, attrs, store=self._store, local_dir=self._local_dir)
        if not problems:
            return n
        action = "A chunk file disappeared while the rows were read (is `robotmem repair` running?); no row was served."
        if not (self.read_only and self._on_damage == "warn"):
            raise integrity.IntegrityError(self.path, problems, read_only=self.read_only, action=action)
        cut = min(p.rows[0] for p in problems)
        warnings.warn(f"{integrity.IntegrityError(self.path, problems, action='')}\non_damage='warn': reading the "
                      f"{cut} rows before the first missing chunk.", stacklevel=4)
        return min(n, cut * self._inner_numel)

    def _reread_overwritten(self, record: dict, n0: int) -> None:
        """Reads again, chunk by chunk, the rows a writer may have overwritten during a reader's load.

        An overwrite (a ring wrapping around, a journalled in-place write)
        replaces one array's chunk at a time, so a read that overlapped it can
        return rows whose columns come from two writes. When the commit record
        changed during the load and an overwrite was possible, each chunk is read
        until the record is the same before and after (from the journal while
        one names the chunk): every row is whole, possibly newer than ``len``.
        """
        def now() -> dict:
            return _backend.open_group(self._store, read_only=True).attrs.asdict()

        after = now()
        wrapped = int(after.get("write_count", 0)) > self.max_size
        if after == record or not (wrapped or record.get("journal") or after.get("journal")):
            return
        rows = self._chunk_rows
        for lo in range(0, n0, rows):
            hi = min(lo + rows, n0)
            for _ in range(1000):
                before = now()
                journal = before.get("journal")
                prefix = "_journal/" if journal and lo // rows in journal["chunks"] else ""
                values = {path: self._group[prefix + path][lo:hi] for path in self._schema}
                if now() == before:
                    break
            else:
                raise RuntimeError(f"Could not read rows {lo}..{hi} of {self.path!r}: the writer commits too often.")
            for path, v in values.items():
                self._column(path)[lo:hi] = torch.from_numpy(np.ascontiguousarray(v))

    def _allocate(self) -> None:
        """(Re)builds the packed RAM mirror for the current schema, keeping existing rows."""
        old = self._views if self.initialized else None
        self._packed = self._layout.allocate((self._max_dim0, *self._inner_shape), self.device)
        self._views = self._layout.views(self._packed)
        self._columns = dict(self._views.items(include_nested=True, leaves_only=True))
        # what TorchRL sees as the storage: the data as the user wrote it (a TensorDict of
        # views, the tensor column, or the tensorclass / pytree built on the views)
        self._storage = self._kind.from_tensordict(self._views.exclude(*TAG_KEYS) if self._kind.kind != "tensordict" else self._views)
        self.__dict__.pop("_total_shape_value", None)  # TorchRL caches the storage shape
        if old is not None:
            n0 = self._dim0(len(self))
            for path in self._schema:
                key = _backend.path_to_key(path)
                col = old.get(key, None)
                if col is not None:
                    self._views.get(key)[:n0] = col[:n0]
                else:
                    self._views.get(key)[:n0] = 0

    def _column(self, path: str) -> torch.Tensor:
        return self._views.get(_backend.path_to_key(path))

    # -- episodes ----------------------------------------------------------------------------

    def close_episode_at(self, row: int) -> None:
        """Ends the open episode at ``row`` (done/truncated), for writers that learn of a boundary late."""
        with self._engine.cv:
            self._tagger.close_stream()
        self._mark_truncated(torch.tensor([row]))
        self._engine.kick()  # (the revision bump happens inside _mark_truncated)

    def _mark_truncated(self, rows: torch.Tensor) -> None:
        """Sets ``("next", "done")`` and ``("next", "truncated")`` on flat ``rows`` (RAM, then disk)."""
        with lifecycle.critical(), self._own_write(), self._engine.cv:
            done = self._views.get(_DONE_KEY)
            flat = done.reshape(-1, *done.shape[self.ndim:]) if self.ndim > 1 else done
            flat[rows] = True
            if _TRUNCATED_KEY in self._views.keys(True, True):
                trunc = self._views.get(_TRUNCATED_KEY)
                (trunc.reshape(-1, *trunc.shape[self.ndim:]) if self.ndim > 1 else trunc)[rows] = True
            self._engine.mark_dirty(torch.div(rows, self._inner_numel, rounding_mode="floor"), self._chunk_rows)
        with self._own_write():
            self._bump_mutation_revision()

    def _close_open_episodes(self) -> None:
        """Marks the last row of every episode the previous run left open as done/truncated."""
        n = len(self)
        if n == 0 or _DONE_KEY not in self._views.keys(True, True) or "episode" not in self._schema:
            return
        flat = {k: v.cpu() for k, v in self._flat_columns(("run", "episode", _DONE_KEY), n).items()}
        done = flat[_DONE_KEY].reshape(n, -1).any(-1)
        cursor = self._writer_cursor * self._inner_numel
        rows = open_episode_ends(flat["run"], flat["episode"], done, cursor=cursor, full=self._is_full)
        if rows.numel():
            self._mark_truncated(rows)

    def _flat_columns(self, keys, n: int) -> dict:
        out = {}
        n0 = self._dim0(n)
        for key in keys:
            col = self._views.get(key)[:n0]
            if key in TAG_KEYS:
                col = self._lead(col)
            out[key] = col.reshape(-1, *col.shape[self.ndim:])[:n] if self.ndim > 1 else col[:n]
        return out

    # -- properties --------------------------------------------------------------------------

    @property
    def env_names(self) -> tuple[str, ...]:
        """Environment names; the ``"env"`` column holds indices into this tuple (-1: unknown)."""
        return tuple(self._env_names)

    @property
    def env(self) -> str | None:
        """The environment name rows written from now on are tagged with."""
        return None if self._env_code == UNKNOWN_ENV else self._env_names[self._env_code]

    @env.setter
    def env(self, name: str | None) -> None:
        self._env_code = UNKNOWN_ENV if name is None else self.env_code(name, create=True)

    def env_code(self, name: str, *, create: bool = False) -> int:
        """The integer code of an environment name.

        Args:
            name (str): the environment name, e.g. ``"FetchPush-v4"``.

        Keyword Args:
            create (bool): register the name if it is new (writers only).
        """
        if not isinstance(name, str) or not name:
            raise TypeError(f"An environment name must be a non-empty string, got {name!r}.")
        if name in self._env_names:
            return self._env_names.index(name)
        if not create:
            raise ValueError(f"Unknown env {name!r}; this store knows {self._env_names}.")
        if self.read_only:
            raise RuntimeError(f"Cannot register env {name!r} in a store opened read_only.")
        with self._engine.cv:
            self._env_names.append(name)
            self._engine.mark_meta_dirty()
        return len(self._env_names) - 1

    @property
    def local_dir(self) -> str | None:
        """The store's local directory, or ``None`` for in-memory and remote (URL) stores."""
        return self._local_dir

    @property
    def schema(self) -> dict[str, dict] | None:
        """The stored columns as ``{path: {"dtype": str, "shape": list}}`` (tags included), or
        ``None`` before the first write. A copy: editing it changes nothing."""
        return None if self._schema is None else {p: dict(s) for p, s in self._schema.items()}

    def record(self) -> dict[str, Any]:
        """The committed record (the store's group attributes) as plain JSON values."""
        return self._group.attrs.asdict()

    def view(self) -> TensorDictBase:
        """Every row slot of the RAM mirror as a TensorDict of views, ``max_size`` rows
        along the first dimension (tags included). Read it, do not write into it: writes
        go through :meth:`set` / the replay buffer. Raises before the first write.
        """
        if not self.initialized:
            raise RuntimeError(f"{self.path!r} holds no rows yet: there is no view to read.")
        return self._views

    @property
    def chunk_rows(self) -> int | None:
        return self._chunk_rows

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
        try:
            self._check_writable()
            data, n, new_paths, new_constants = self._prepare(cursor, data, set_cursor)
        except Exception:
            if set_cursor:  # the writer moved its cursor before calling us (TORCHRL_NOTES b)
                rows = _cursor_rows(cursor, self._max_dim0 if self.initialized else self.max_size)
                writer_sync.rollback_writers(self, int(rows[0]) if len(rows) else 0, len(rows),
                                             self._max_dim0 if self.initialized else self.max_size)
            raise
        # A signal arriving from here on is handled once the write is complete
        # (a flush must never see RAM rows that are not marked dirty yet).
        with lifecycle.critical(), self._own_write():
            if not self.initialized:
                self._init_schema(data, _is_int_cursor(cursor))
            elif new_paths:
                self._evolve_schema(data, new_paths, _is_int_cursor(cursor))
            if new_constants:
                self._constants = {**self._constants, **new_constants}
                self._engine.update_attrs({"constants": dict(self._constants)})
            rows = dirty = _cursor_rows(cursor, self._max_dim0)
            if len(rows) > 1 and bool((rows[1:] - rows[:-1] == 1).all()):
                dirty = slice(int(rows[0]), int(rows[-1]) + 1)
                if not isinstance(cursor, tuple) and not isinstance(data, LazyStackedTensorDict):
                    cursor = dirty  # a view copy: ~2x an index_put
            with self._engine.cv:
                self._write_ram(cursor, data, set_cursor)
                if set_cursor:
                    self._write_count += n
                    self._writer_cursor = (int(rows[-1]) + 1) % self._max_dim0
                self._engine.mark_dirty(dirty, self._chunk_rows)
            # wake the writer only if a chunk just became complete (its timer covers the rest)
            last = int(rows[-1])
            self._engine.kick(notify=(last + 1) % self._chunk_rows == 0 or len(rows) > self._chunk_rows
                              or int(rows[0]) // self._chunk_rows != last // self._chunk_rows)

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
                    self._engine.mark_dirty(slice(0, n0), self._chunk_rows)
                self._engine.kick()

    def _write_ram(self, cursor, data: TensorDictBase, set_cursor: bool) -> None:
        """TensorStorage.set on the RAM mirror (``data`` is the prepared TensorDict)."""
        if set_cursor:
            self._set_last_cursor(cursor)
            self._get_new_len(data, cursor)
        if isinstance(data, LazyStackedTensorDict) and data.stack_dim == 0:
            self._views.update_at_(data, cursor)  # each stacked TensorDict written in place
        elif isinstance(cursor, slice) and isinstance(data, TensorDict):
            # hot path (appends): one copy per leaf into its column, no TensorDict machinery
            cols = self._columns
            for key, value in data.items(include_nested=True, leaves_only=True):
                cols[key][cursor].copy_(value)
        else:
            self._views[cursor] = data
        self._bump_mutation_revision()

    def _check_writable(self) -> None:
        if self.read_only and getattr(self, "_received", False):
            raise RuntimeError(
                f"This ZarrStorage ({self.path!r}) is read_only: it is the copy another process "
                f"receives when a ZarrStorage is pickled, and a store has one writer process. Do not pass "
                f"replay_buffer= to MultiSyncCollector / MultiAsyncCollector: iterate the collector "
                f"in the writer process and call rb.extend(data), or put the storage in a Ray actor "
                f"(RayReplayBuffer(storage=partial(ZarrStorage, path, max_size))) and extend through "
                f"it. See docs/distributed.md."
            )
        if self.read_only:
            raise RuntimeError(
                f"This ZarrStorage ({self.path!r}) was opened read_only; open it without read_only=True to write."
            )
        if self._retired_by is not None:
            raise RuntimeError(
                f"This ZarrStorage ({self.path!r}) handed its writer to {self._retired_by}; it "
                f"is now a read-only snapshot. Write through the newer handle."
            )
        if self._closed:
            raise RuntimeError(
                f"This ZarrStorage ({self.path!r}) is closed; open ZarrStorage({self.path!r}) again to keep writing."
            )
        if self._lock_file is not None:
            self._lock_file.check()  # an object-store lease can be lost
        self._engine.raise_error()

    def _prepare(self, cursor, data, set_cursor: bool) -> tuple[TensorDictBase, int, list, dict]:
        """Validates ``data`` and adds the tag columns (no side effects).

        Returns the TensorDict to store, the number of transitions, the paths
        of keys the store does not hold yet and the non-tensor entries (constants)
        it does not hold yet.
        """
        single = _is_int_cursor(cursor)
        if isinstance(data, list):
            if not data:
                raise ValueError("Cannot write an empty TensorDict.")
            try:
                data = torch.stack(data, 0) if all(is_tensor_collection(d) for d in data) else _stack_trees(data)
            except Exception as err:  # TorchRL's wording, so callers can match it
                raise RuntimeError(
                    f"Stacking the elements of the list resulted in an error ({err}). ZarrStorage expects all "
                    f"elements of the list to have the same structure and shapes (a list passed to extend is "
                    f"one item per element)."
                ) from err
        kind = DataKind.of(data)
        if getattr(self, "_kind_override", None) is not None:
            kind = DataKind()  # rows loaded as TensorDicts into a store of another kind
        if self._schema is not None and kind.kind == self._kind.kind and not kind.same_as(self._kind):
            raise ValueError(
                f"This {kind.kind}'s structure differs from the one the store at {self.path!r} holds "
                f"({kind.meta} vs {self._kind.meta}); every write must have the same structure."
            )
        if self._schema is not None and not kind.same_as(self._kind):
            raise TypeError(
                f"The store at {self.path!r} holds {self._kind.kind} data; got {kind.kind}. Every "
                f"write to one store must be of the same kind."
            )
        expected_dims = self.ndim - (1 if single else 0)
        td = kind.to_tensordict(data, expected_dims)
        if td.batch_dims < expected_dims:
            raise ValueError(
                f"ZarrStorage(ndim={self.ndim}) expects data with at least {expected_dims} batch "
                f"dimension(s); got batch_size {list(td.batch_size)}."
            )
        if td.batch_dims > expected_dims and kind.kind == "tensordict" and self.ndim == 1 and not self._warned_items:
            self._warned_items = True
            warnings.warn(
                f"ZarrStorage(ndim=1) got a TensorDict with batch_size {list(td.batch_size)}: each of its "
                f"{td.batch_size[0]} items is stored whole, as LazyTensorStorage does (episode tags are per "
                f"item). For collector output, one row per transition is usually meant: pass "
                f"data.reshape(-1) (Collector(..., postproc=lambda td: td.reshape(-1))), or create the "
                f"store with ndim={td.batch_dims - (0 if single else 0)} for a [num_envs, time] layout.",
                stacklevel=4,
            )
        if isinstance(td, LazyStackedTensorDict) and td.stack_dim == 0 and not td.is_locked and not single:
            td = td.copy()  # kept lazy: TorchRL writes each stacked TensorDict in place (update_at_)
        elif not isinstance(td, TensorDict) or td.is_locked:
            td = td.to_tensordict()
        else:
            td = td.copy()  # shallow: tags must not leak into the caller's TensorDict
        if single:
            td = td.unsqueeze(0)
        multi = isinstance(cursor, tuple)  # an element-wise write into a multi-dim storage
        if multi and set_cursor:
            raise ValueError("ZarrStorage appends along the first dimension only; tuple cursors are for in-place writes.")
        inner = tuple(td.batch_size[1:])
        if self._schema is not None and inner != self._inner_shape and not multi:
            raise ValueError(
                f"The store at {self.path!r} holds items of batch shape {list(self._inner_shape)} "
                f"(after the first dimension); got {list(inner)}."
            )
        n0 = td.shape[0]
        if n0 == 0:
            raise ValueError("Cannot write an empty TensorDict.")
        # the dims that count in len; tags are per element of these
        lead = td.batch_size if multi else td.batch_size[: self.ndim]
        n = lead.numel()
        for key in _DROPPED_KEYS:
            td.pop(key, None)
        tags = kind.tag_columns and (getattr(self, "_kind_override", None) or kind).tag_columns
        env = self._env_column(td, lead) if tags else None
        episode = run = None
        if tags and self._keep_tags:  # rows copied from another store keep their tags
            episode, run = td.get("episode", None), td.get("run", None)
        if tags and not set_cursor and episode is None:
            rows = _cursor_rows(cursor, self._max_dim0 if self.initialized else self.max_size)
            if multi and self.initialized and "episode" in self._schema:
                episode = self._views.get("episode")[cursor].reshape(lead)
                run = self._views.get("run")[cursor].reshape(lead)
                env = self._views.get("env")[cursor].reshape(lead) if td.get("env", None) is None else env
            elif self.initialized and "episode" in self._schema and bool((rows < self._max_dim0).all()):
                # in-place writes keep the rows' tags (past len: a placeholder, as the rows are)
                episode = self._lead(self._views.get("episode"))[rows]
                run = self._lead(self._views.get("run"))[rows]
            else:
                episode = torch.full(lead, -1, dtype=torch.long)
                run = torch.full(lead, -1, dtype=torch.long)
        for key in TAG_KEYS:  # env codes / names are input; episode and run are drawn here (reserved names)
            value = td.pop(key, None)
            if value is not None and not (tags and key == "env"):
                check_user_tag(key, value, episode if key == "episode" else run if key == "run" else None)
        fast = self._matches_schema(td)  # the hot path: the keys, dtypes and shapes the store holds, no more
        new_constants = {} if fast else self._check_constants(split_constants(td))
        new_paths = [] if fast else self._validate(td, single)
        clash = [p for p in new_paths if p in self._constants]
        if clash:
            raise TypeError(
                f"Key {_backend.path_to_key(clash[0])!r} is a tensor here, but the store at {self.path!r} holds it as "
                f"a non-tensor value ({self._constants[clash[0]]!r}); every write must keep a key's kind."
            )
        if self._schema is None:
            # recorded with the schema at the first write
            self._kind = getattr(self, "_kind_override", None) or kind
        if tags:
            if episode is None:  # only now, once nothing can fail, draw the episode ids
                episode = self._episode_column(td, n).reshape(lead)
                run = torch.full(lead, self._current_run(), dtype=torch.long)
            td.set("episode", self._expand_tag(episode, lead, td.batch_size))
            td.set("run", self._expand_tag(run, lead, td.batch_size))
            td.set("env", self._expand_tag(env, lead, td.batch_size))
        if single:
            td = td[0]
        return td, n, new_paths, new_constants

    def _check_constants(self, found: dict[str, Any]) -> dict[str, Any]:
        """The non-tensor entries of a write against the store's; returns the new ones."""
        new = {}
        for path, value in found.items():
            key = _backend.path_to_key(path)
            if self._schema is not None and path in self._schema:
                raise TypeError(
                    f"Key {key!r} holds a non-tensor value ({value!r}), but the store at {self.path!r} holds it "
                    f"as a tensor of dtype {self._schema[path]['dtype']}; every write must keep a key's kind."
                )
            if path not in self._constants:
                new[path] = value
            elif self._constants[path] != value or type(self._constants[path]) is not type(value):
                raise ValueError(
                    f"Key {key!r} holds {value!r}, but the store at {self.path!r} holds {self._constants[path]!r} "
                    f"for it. ZarrStorage keeps a non-tensor entry as one value shared by every row (in the "
                    f"store's metadata, as LazyMemmapStorage does); store per-row values as a tensor (e.g. "
                    f"integer codes), or use another store."
                )
        missing = [p for p in self._constants if p not in found]
        if missing and self._schema is not None:
            raise KeyError(
                f"The data does not match the schema of the store at {self.path!r}: missing non-tensor keys "
                f"{[_backend.path_to_key(p) for p in missing]} (held as {[self._constants[p] for p in missing]}). "
                f"Every write must carry the keys the store holds."
            )
        return new

    @staticmethod
    def _expand_tag(value, lead: torch.Size, batch: torch.Size) -> torch.Tensor:
        value = torch.as_tensor(value, dtype=torch.long).reshape(lead)
        extra = len(batch) - len(lead)
        return value.reshape(*lead, *([1] * extra)).expand(batch).clone() if extra else value

    def _lead(self, col: torch.Tensor) -> torch.Tensor:
        """A tag column without the item dims past ``ndim`` (tags are equal along them)."""
        extra = len(self._inner_shape) + 1 - self.ndim
        return col[(..., *([0] * extra))] if extra > 0 else col

    def check_schema(self, data: TensorDictBase) -> None:
        """Raises, naming the key, unless ``data`` (batch ``[N]``) could be written to this store.

        Nothing is written. The tag columns (``episode``, ``run``, ``env``) are
        ignored; a store with no rows yet accepts any supported dtypes.
        """
        data = data.exclude(*TAG_KEYS, *_DROPPED_KEYS)
        self._check_constants(split_constants(data))
        self._validate(data, False)

    def _matches_schema(self, data: TensorDictBase) -> bool:
        """Whether ``data`` holds exactly the store's tensor keys, dtypes and row shapes (no constants)."""
        fast = self._schema_by_key
        if fast is None or self._constants:
            return False
        seen = 0
        dims = 1 + len(self._inner_shape)
        # one dict lookup and two comparisons per leaf; a non-tensor leaf is a leaf here (never in ``fast``)
        for key, value in data.items(include_nested=True, leaves_only=True, is_leaf=_is_leaf_nontensor):
            spec = fast.get(key)
            if spec is None or value.dtype != spec[0] or value.shape[dims:] != spec[1]:
                return False
            seen += 1
        return seen == len(fast)

    def _validate(self, data: TensorDictBase, single: bool) -> list[str]:
        """Raises, naming the key, on a dtype / shape change; returns the paths of new keys."""
        if self._matches_schema(data):
            return []
        check_user_keys(data.keys(include_nested=True), allowed=(DataKind.TENSOR_KEY, DataKind.PYTREE_KEY))
        if self._schema is None:
            for key, value in data.items(include_nested=True, leaves_only=True, is_leaf=_is_leaf_nontensor):
                if not isinstance(value, torch.Tensor):
                    raise TypeError(f"Key {key!r} holds {type(value).__name__}; ZarrStorage stores tensors only.")
                _backend.torch_dtype_name(value.dtype)
                _backend.key_to_path(key)
            return []
        schema = {p: spec for p, spec in self._schema.items() if p not in TAG_KEYS}
        new, missing = check_against(schema, data, data.batch_dims, repr(self.path))
        if missing:
            raise KeyError(
                f"The TensorDict does not match the schema of the store at {self.path!r}: missing keys "
                f"{[_backend.path_to_key(p) for p in missing]}. Every write must carry the keys the "
                f"store holds (new keys may be added)."
            )
        return new

    def _env_column(self, data: TensorDictBase, batch: torch.Size) -> torch.Tensor:
        env = data.get("env", None)
        if env is None:
            return torch.full(batch, self._env_code, dtype=torch.long)
        names = env_names_of(env, batch.numel())
        if names is not None:
            return torch.tensor([self.env_code(x, create=True) for x in names], dtype=torch.long).reshape(batch)
        env = torch.as_tensor(env)
        if env.dtype.is_floating_point or env.dtype == torch.bool:
            raise ValueError(f"Key 'env' must hold integer env codes or names, got dtype {env.dtype}.")
        env = env.reshape(batch).long()
        bad = (env < UNKNOWN_ENV) | (env >= len(self._env_names))
        if bad.any():
            raise ValueError(
                f"Key 'env' holds codes {env[bad].unique().tolist()} unknown to this store "
                f"(known: {dict(enumerate(self._env_names))}). Use storage.env_code(name, create=True)."
            )
        return env

    def _current_run(self) -> int:
        if self._run is None:
            self._run = self._runs
            self._runs += 1
            self._engine.mark_meta_dirty()
        return self._run

    def _episode_column(self, data: TensorDictBase, n: int) -> torch.Tensor:
        """Global episode ids: collector ``traj_ids`` (or done flags) mapped past every stored id."""
        done = data.get(_DONE_KEY, None)
        done = np.zeros(n, dtype=bool) if done is None else done.reshape(n, -1).any(-1).cpu().numpy()
        traj = data.get(_TRAJ_KEY, None)
        if traj is not None and traj.numel() != n:  # per-step ids of whole stored items: their first
            traj = traj.reshape(n, -1)[:, 0] if traj.numel() % n == 0 else None
        traj = traj.reshape(n).long().cpu().numpy() if traj is not None else None
        if self.ndim == 1:
            return self._tagger.assign(done, traj)
        # [items, time...] layouts: each item is its own stream; nothing continues across writes
        if traj is None:
            per_item = done.reshape(data.shape[0], -1)
            seg = np.cumsum(per_item, 1) - per_item
            traj = (np.arange(per_item.shape[0])[:, None] * (per_item.shape[1] + 1) + seg).reshape(-1)
        ids = self._tagger.assign(done, traj, continue_open=False)
        self._tagger.reset()
        return ids

    def _init_schema(self, data: TensorDictBase, single: bool) -> None:
        row = data if single else data[0]
        schema = spec_of(row.reshape(-1)[0] if row.batch_dims else row)
        self._inner_shape = tuple(row.batch_size)
        row_bytes = PackedLayout(schema).row_bytes * self._inner_numel
        if self._chunk_rows is None:
            # ~4 MiB of rows per chunk group: large enough for fast sequential I/O,
            # small enough that a commit of a partial chunk stays cheap.
            target = max(1024, min(65536, 2 ** round(math.log2(max(1, (4 << 20) // max(row_bytes, 1))))))
            self._chunk_rows = min(target, self._max_dim0)
        self.max_size = self._max_dim0 * self._inner_numel  # as TorchRL rounds it for ndim > 1
        self._create_arrays(schema)
        self._schema = schema
        self._index_schema()
        self._allocate()
        self.initialized = True
        # Schema first: a store whose arrays exist but whose schema is unknown would not reopen.
        self._engine.update_attrs(
            {
                "schema": schema,
                "chunk_rows": self._chunk_rows,
                "inner_shape": list(self._inner_shape),
                "kind": self._kind.to_json(),
                "max_size": self.max_size,
            }
        )

    def _create_arrays(self, schema: dict[str, dict]) -> None:
        for path, spec in schema.items():
            dtype = _backend.torch_dtype(spec["dtype"])
            shape = (self._max_dim0, *self._inner_shape, *spec["shape"])
            self._engine.arrays[path] = self._group.create_array(
                path,
                shape=shape,
                chunks=(self._chunk_rows, *shape[1:]),
                dtype=_backend.numpy_dtype(dtype),
                compressors=_backend.make_compressors(
                    self._compressor, self._compression_level, _backend.numpy_dtype(dtype).itemsize
                ),
                fill_value=0,
                overwrite=True,
                config=integrity.ARRAY_CONFIG,  # all-zero chunks written too: a missing one is damage
            )
            if self.initialized:  # a key added later: its older rows are zeros, in chunk files
                integrity.write_zero_chunks(self._engine.arrays[path], self._len_along_dim0, self._chunk_rows)

    def _evolve_schema(self, data: TensorDictBase, new_paths: list[str], single: bool) -> None:
        """Adds columns for keys the store did not hold yet (older rows read zeros)."""
        row = data if single else data[0]
        if self.ndim > 1:
            row = row.reshape(-1)[0]
        added = {p: s for p, s in spec_of(row.select(*[_backend.path_to_key(p) for p in new_paths])).items()}
        self.flush()  # committed rows first: the new arrays start from a clean state
        self._create_arrays(added)
        self._schema = {**self._schema, **added}
        self._index_schema()
        with self._engine.cv:
            self._allocate()
        self._engine.update_attrs({"schema": self._schema})
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
            self._tagger.reset()
            self._engine.mark_meta_dirty()
        self.flush()

    # -- reads ---------------------------------------------------------------------------------

    def get(self, index):
        """Rows at ``index``: one gather of whole packed rows, then views per key."""
        if not self.initialized:
            raise RuntimeError("Cannot get elements out of a non-initialized storage.")
        if isinstance(index, str) or (isinstance(index, tuple) and index and all(isinstance(i, str) for i in index)):
            rows = self._views if self._is_full else self._views[: self._len_along_dim0]
            if self._constants:  # a non-tensor entry is a column too
                rows = with_constants(rows, self._constants)
            return rows[index]  # a column, as LazyTensorStorage gives it
        if isinstance(index, list):
            index = torch.as_tensor(index)
        packed = self._packed if self._is_full else self._packed[: self._len_along_dim0]
        rows = self._layout.views(packed[index], self._hidden)
        if self._constants:
            rows = with_constants(rows, self._constants)
        return self._kind.from_tensordict(rows)

    def _copy_chunk(self, c: int) -> tuple[torch.Tensor, dict]:
        """A snapshot of chunk ``c``: ONE copy of its packed rows (taken under the engine's lock).

        The per-array split happens later, in :meth:`_chunk_arrays`, outside the
        lock, so a foreground ``set`` waits for a memcpy, not for 30 column copies.
        """
        lo = c * self._chunk_rows
        hi = min(lo + self._chunk_rows, self._max_dim0)
        valid = max(0, min(hi, self._len_along_dim0) - lo)
        packed = self._packed[lo:hi].to("cpu", copy=True)  # a CUDA mirror (device="cuda") is written from host memory
        if valid < hi - lo:
            packed[valid:] = 0  # rows past len reach the disk as zeros
        return packed, self._layout

    def _chunk_arrays(self, snapshot: tuple[torch.Tensor, Any]) -> dict[str, np.ndarray]:
        """The per-array contents of a chunk snapshot (see :meth:`_copy_chunk`)."""
        packed, layout = snapshot
        views = layout.views(packed)
        return {path: np.ascontiguousarray(views.get(_backend.path_to_key(path)).cpu().numpy())
                for path in self._schema}

    def _meta_snapshot(self) -> dict:
        last = self._last_cursor_index
        return {
            "len": len(self),
            "cursor": self._writer_cursor,
            "last_cursor": -1 if last is None else int(last),
            "write_count": self._write_count,
            "episode_next": self._tagger.next_id,
            "runs": self._runs,
            "env_names": list(self._env_names),
            "env": self.env,
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
        self._closed = True
        engine = getattr(self, "_engine", None)
        if engine is not None:
            engine.close()
        if getattr(self, "_lock_file", None) is not None:
            self._lock_file.release()
            self._lock_file = None
        ref = _OPEN_WRITERS.get(str(self.path))
        if ref is not None and ref() is self:
            del _OPEN_WRITERS[str(self.path)]
        close = getattr(getattr(self, "_store", None), "close", None)
        if close is not None:
            try:
                close()
            except Exception:  # noqa: BLE001 - nothing to save in a store being closed
                pass

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
        engine_state = {k: v for k, v in vars(self._engine).items() if k in ("group", "committed_len", "committed_write_count")}
        try:
            group = _backend.open_group(self._store, read_only=True)
            attrs = group.attrs.asdict()
            self._check_format(attrs)
            attrs = integrity.check_open(group, attrs, store=self._store, local_dir=self._local_dir, path=self.path,
                                         read_only=True, on_damage=self._on_damage)
            if attrs.get("schema") is None:
                return 0
            self._group = self._engine.group = group
            if int(attrs["max_size"]) != self.max_size:  # the writer grew the store
                self.max_size = int(attrs["max_size"])
                self.__dict__.pop("_total_shape_value", None)
            self._sync_attrs(attrs)
            self.initialized = False
            self._load_rows(attrs)
        except BaseException:
            # a failed refresh leaves the handle as it was (its rows, its length)
            self.__dict__.update(saved)
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
        rows = self._views.exclude(*TAG_KEYS).state_dict() if self.initialized else {}
        tags = self._views.select(*TAG_KEYS, strict=False).state_dict() if self.initialized else {}
        return {
            "_storage": rows,
            "initialized": self.initialized,
            "_len": len(self),
            "zarr": {
                "store": self.path if isinstance(self.path, str) else None,
                "write_count": self._write_count,
                "cursor": self._writer_cursor,
                "env_names": list(self._env_names),
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
            if kind is not None and kind.kind != "tensordict" and self._schema is None:
                self._kind = kind  # written as a TensorDict, read back as the source's kind
            self._keep_tags = tags is not None
            try:
                self._write_rows(torch.arange(n0), rows)
            finally:
                self._keep_tags = False
            self._writer_cursor = int(meta.get("cursor", n0 % self._max_dim0)) % self._max_dim0
            self._write_count = int(meta.get("write_count", n0))
            if tags is not None:
                self._tagger.next_id = max(self._tagger.next_id, int(rows.get("episode").max()) + 1)
                self._runs = max(self._runs, int(rows.get("run").max()) + 1)
            with self._engine.cv:
                self._engine.mark_meta_dirty()
        self._restore_writers(force=True)
        with self._own_write():
            self._bump_mutation_revision()
        self.flush()

    def _write_rows(self, cursor: torch.Tensor, rows: TensorDictBase) -> None:
        """Writes TensorDict rows whatever the store's data kind (for loads)."""
        kind = self._kind
        try:
            self._kind = DataKind()
            self._kind_override = kind
            self.set(cursor, rows)
        finally:
            self._kind = kind
            self._kind_override = None

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
        keys = set(self._views.keys(True, True)) if self.initialized else set()
        if n and "episode" in keys:
            cols = self._flat_columns(
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
        out["bytes_on_disk"] = _backend.store_size_bytes(self._local_dir)
        return out

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(path={self.path!r}, len={len(self)}, max_size={self.max_size}, "
            f"read_only={self.read_only}, envs={list(self._env_names)})"
        )


# -- helpers ------------------------------------------------------------------------------


def _open_read_only(path: str, storage_options: dict | None, device: str) -> ZarrStorage:
    storage = ZarrStorage(path, read_only=True, storage_options=storage_options, device=device)
    storage._received = True  # a pickled copy: writing through it gets the advice below
    return storage


def _library_version() -> str:
    from .. import __version__

    return __version__


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


def _stack_trees(items: list) -> Any:
    from torch.utils._pytree import tree_map

    first = items[0]
    if isinstance(first, torch.Tensor):
        return torch.stack(items, 0)
    return tree_map(lambda *xs: torch.stack(xs, 0), first, *items[1:])


def _is_int_cursor(cursor) -> bool:
    return isinstance(cursor, (int, np.integer)) or (isinstance(cursor, torch.Tensor) and cursor.ndim == 0)


def _cursor_rows(cursor, max_size: int) -> torch.Tensor:
    """The first-dimension rows a cursor touches (a tuple cursor indexes several dims)."""
    if isinstance(cursor, tuple):
        first = cursor[0] if cursor else slice(None)
        rows = _cursor_rows(first, max_size)
        return rows.unique() if rows.numel() > 1 else rows
    if _is_int_cursor(cursor):
        return torch.tensor([int(cursor)], dtype=torch.long)
    if isinstance(cursor, slice):
        return torch.arange(*cursor.indices(max_size), dtype=torch.long)
    if isinstance(cursor, range):
        return torch.tensor(list(cursor), dtype=torch.long)
    return torch.as_tensor(cursor, dtype=torch.long).reshape(-1).cpu()
