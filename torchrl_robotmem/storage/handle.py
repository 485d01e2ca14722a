"""The store handle: the one place a store is opened: its path, Zarr store and group, writer lock and record.

A :class:`StoreHandle` opens a store (local directory, ``*.zip``, in-memory or
URL), takes the writer lock of a writable one, checks the format marker,
creates a new store's commit record and reads and checks the record of an
existing one (:meth:`StoreHandle.open_record`; a reader's ``refresh``:
:meth:`StoreHandle.reopen_record`). A store has one writer: within a process,
a new writable handle on the same store takes the writer over from the earlier
one (:meth:`StoreHandle.claim`), which is flushed and becomes a read-only
snapshot, and hands it back if the newer one fails to open
(:meth:`StoreHandle.take_back`).

Example:
    >>> from torchrl_robotmem.storage.handle import StoreHandle
    >>> h = StoreHandle("memory://handle-doc", read_only=False)
    >>> h.open()
    >>> h.create({}, max_size=10, chunk_rows=None, ndim=1)
    >>> h.check_format(h.group.attrs.asdict())
    >>> h.release()
"""
from __future__ import annotations

import os
import warnings
import weakref
from collections.abc import Callable
from typing import Any

import torchrl

from .._version import __version__
from . import _backend, integrity, lifecycle
from .errors import IntegrityError
from .format import BOUNDED_FORMAT, FORMAT_MARKER, FORMAT_VERSION, MARKER, UNBOUNDED, writing_config
from .journal import replay_journal

#: the rows a new memory without a declared capacity starts with (at its first write: one chunk, at least)
UNBOUNDED_START = 1024

__all__ = ["StoreHandle"]

# The writable handle of each store opened for writing in this process. A new
# writable handle on the same store takes the writer over from the old one.
_OPEN_WRITERS: dict[str, weakref.ref] = {}
# A forked child inherits the handles but is not their writer: it starts with no writer of its own.
os.register_at_fork(after_in_child=_OPEN_WRITERS.clear)


#: times a reader reads the record again when the journal it named was gone (a writer committing meanwhile)
_JOURNAL_RACE_TRIES = 20


class StoreHandle:
    """One open store: path, Zarr store and group, writer lock, and its place in the in-process handover.

    Args:
        path (str or os.PathLike or zarr Store): the store.

    Keyword Args:
        read_only (bool): open for reading only.
        storage_options (dict, optional): passed to fsspec for URL stores.

    Example:
        >>> h = StoreHandle("memory://handle-doc2", read_only=True)
        >>> h.path, h.closed
        ('memory://handle-doc2', False)
    """

    def __init__(self, path: Any, *, read_only: bool, storage_options: dict | None = None) -> None:
        self.path = _backend.normalize_path(path)
        self.read_only = bool(read_only)
        self.storage_options = storage_options
        self.store: Any = None
        self.local_dir: str | None = None
        self.group: Any = None
        self.lock: Any = None  # the writer lock (a file lock, or an object-store lease)
        self.closed = False
        self.retired_by: str | None = None  # set when a newer writable handle took the writer over
        self.received = False  # the read-only copy a pickled storage arrives as
        self.flush: Callable[[], None] = lambda: None  # makes the owner's rows durable (before a handover)
        self.pid = os.getpid()  # the process that opened it: a forked child inherits the handle, not the writer

    @property
    def inherited(self) -> bool:
        """Whether this process is a forked child of the one that opened the handle (it may read, never write)."""
        return os.getpid() != self.pid

    # -- opening ------------------------------------------------------------------------

    def open(self) -> None:
        """Opens the store and its group; a writable local store takes the writer lock first."""
        # the columns' chunk folders are walked for links only by an open that reads them (MemoryStore.open_rows,
        # StoreHandle.open_record); a writer's writes look at each folder they go into (storage/contained.py), which
        # also removes the partial files a writer killed mid-chunk left there
        self.store, self.local_dir = _backend.open_store(
            self.path, read_only=self.read_only, storage_options=self.storage_options, chunk_links=False
        )
        if self.local_dir is not None and not self.read_only:
            self.lock = _backend.WriterLock(self.local_dir)
        elif not self.read_only and isinstance(self.path, str) and _backend.is_url(self.path):
            self.lock = _backend.url_writer_lock(self.path, self.storage_options)
        # a new store gets its group together with its commit record (create): no empty group in between
        self.group = _backend.open_group(self.store, read_only=self.read_only)

    def check_format(self, attrs: dict) -> None:
        """Raises unless ``attrs`` carry a format marker this version reads."""
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

    def create(self, attrs: dict, max_size: int | None, chunk_rows: int | None, ndim: int) -> None:
        """Writes the commit record of a new, empty store (refusing a foreign Zarr group)."""
        if self.read_only:
            if not attrs and not any(True for _ in self.group.keys()):
                raise ValueError(
                    f"{self.path!r} is an empty Zarr group, not yet a torchrl_robotmem store: a writer may be "
                    f"creating it this instant (its {FORMAT_MARKER!r} attribute follows the group); open it again."
                )
            raise ValueError(f"{self.path!r} is not a torchrl_robotmem store (no {FORMAT_MARKER!r} attribute).")
        if self.group is not None and (attrs or any(True for _ in self.group.keys())):
            raise ValueError(
                f"{self.path!r} is a Zarr group that was not written by torchrl_robotmem "
                f"(no {FORMAT_MARKER!r} attribute). Refusing to write into it."
            )
        unbounded = max_size is None  # a memory without a declared capacity: it grows as rows arrive
        if unbounded and int(ndim) != 1:
            raise ValueError(
                f"A memory without a declared capacity stores one transition a row (ndim=1), got ndim={ndim}: "
                f"pass max_size to create {self.path!r} with ndim={ndim}, e.g. ZarrStorage(path, 1_000_000, ndim={ndim})."
            )
        record = {
            FORMAT_MARKER: {
                "format_version": FORMAT_VERSION if unbounded else BOUNDED_FORMAT,
                "library_version": __version__,
                "torchrl_version": torchrl.__version__,
                "zarr_version": _backend.zarr.__version__,
                "integrity": dict(MARKER),  # checksummed chunks, all-zero ones written too
            },
            "max_size": UNBOUNDED_START if unbounded else int(max_size),
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
            **({UNBOUNDED: True} if unbounded else {}),
        }
        if self.group is None:  # a new store: the group and its record in one write
            self.group = _backend.create_group(self.store, record)
        else:  # an empty group (left by an older version killed while creating it)
            self.group.update_attributes(record)

    # -- the commit record --------------------------------------------------------------------

    def open_record(self, max_size: int | None, *, chunk_rows: int | None, ndim: int, on_damage: str,
                    served: Callable[[dict], bool] | None = None, mapped: bool = False) -> dict:
        """Opens the store (writing a new store's record), checks its format and integrity; returns the record.

        Args:
                max_size (int or None): the capacity asked for (``None``: the stored one).

        Keyword Args:
            chunk_rows (int or None): rows per chunk of a new store.
            ndim (int): leading batch dimensions of a new store.
            on_damage (str): ``"raise"`` or ``"warn"`` (see ``ZarrStorage``).
            served (callable, optional): asked once the record is sane whether a sealed row file serves the
                rows (then no chunk is listed: none is read). mapped (bool): the rows are mapped from a file.

        Example:
                >>> h = StoreHandle("memory://open-record-doc", read_only=False)
            >>> h.open_record(4, chunk_rows=2, ndim=1, on_damage="raise")["len"]
            0
            >>> h.release()
        """
        if self.store is None:
            self.open()
        attrs = self.group.attrs.asdict() if self.group is not None else {}  # None: a new store
        if attrs.get(FORMAT_MARKER) is None:
            self.create(attrs, max_size, chunk_rows, ndim)
            attrs = self.group.attrs.asdict()
        self.check_format(attrs)
        # before anything is read or written: a damaged store raises, naming the array and chunk
        grows = max_size is not None and int(max_size) != attrs.get("max_size")
        decode = not self.read_only and (bool(attrs.get("journal")) or grows)
        if decode and self.local_dir is not None:  # every chunk below the length is read: walk their folders first
            _backend.refuse_links(self.local_dir, self.path, chunks=None)
        self.group, attrs = self._checked(self.group, attrs, on_damage=on_damage, served=served, mapped=mapped,
                                          decode=decode)
        return attrs

    def current_record(self) -> dict:
        """The commit record as the store holds it now (read again; the handle is unchanged)."""
        return _backend.open_group(self.store, read_only=True).attrs.asdict()

    def reopen_record(self, *, on_damage: str, served: Callable[[dict], bool] | None = None,
                      mapped: bool = False) -> tuple[Any, dict]:
        """A reader's fresh group on its store and the checked record (``refresh``); the handle is unchanged.

            Keyword Args:
            on_damage (str): ``"raise"`` or ``"warn"``. served, mapped: as :meth:`open_record` takes them.
        """
        if self.local_dir is not None:  # what the store holds now: a link or special file made since the open
            _backend.refuse_links(self.local_dir, self.path, chunks=False)
        group = _backend.open_group(self.store, read_only=True)
        attrs = group.attrs.asdict()
        self.check_format(attrs)
        return self._checked(group, attrs, on_damage=on_damage, served=served, mapped=mapped)

    def _checked(self, group: Any, attrs: dict, **kwargs) -> tuple[Any, dict]:
        """``(group, record)`` checked by :func:`integrity.check_open`. A reader whose record named a pending
        journal that is gone by the time it reads it (the writer finished that commit and removed it) reads the
        newer record and checks again; damage that stays under one record raises."""
        for _ in range(_JOURNAL_RACE_TRIES):
            try:
                return group, integrity.check_open(group, attrs, store=self.store, local_dir=self.local_dir,
                                                   path=self.path, read_only=self.read_only, **kwargs)
            except IntegrityError as err:
                if not self.read_only or not any(p.kind == "journal" for p in err.problems):
                    raise
                fresh = _backend.open_group(self.store, read_only=True)
                if fresh.attrs.asdict() == attrs:  # the same record: the journal is damaged
                    raise
                group, attrs = fresh, fresh.attrs.asdict()
                self.check_format(attrs)
        return group, integrity.check_open(group, attrs, store=self.store, local_dir=self.local_dir, path=self.path,
                                           read_only=self.read_only, **kwargs)

    def pending_record(self, attrs: dict) -> dict | None:
        """The record once a pending journal is applied, or ``None`` if none is pending.

        A writer replays the journal on disk; a reader applies its record in RAM only
        (its rows with :meth:`RamMirror.apply_journal <.mirror.RamMirror.apply_journal>`).
        """
        journal = attrs.get("journal")
        if not journal:
            return None
        if not self.read_only:
            with writing_config():
                return replay_journal(self.group, journal)
        return {**attrs, **journal["meta"]}

    # -- writer handover within a process ----------------------------------------------------

    def claim(self) -> StoreHandle | None:
        """Takes the writer over from an earlier writable handle on the same store in this process.

        Re-running a notebook cell (``rb = ...ZarrStorage(path)``) or dropping a
        handle that an index still refers to must not lock the user out of their
        own store: the earlier handle is flushed and becomes a read-only
        snapshot. Returns it (to hand the writer back if this open fails).
        """
        key = str(self.path)
        ref = _OPEN_WRITERS.get(key)
        other = ref() if ref is not None else None
        if other is not None and (other.closed or other.read_only):
            other = None
        if other is not None:
            other.hand_over()  # raises if it cannot write its rows: it keeps them, and the writer
        _OPEN_WRITERS[key] = weakref.ref(self)
        return other

    def hand_over(self) -> None:
        """Flushes and becomes a read-only snapshot, releasing the writer lock."""
        with lifecycle.critical():
            self.flush()
            self.retired_by = "a newer writable ZarrStorage on the same store in this process"
            self.closed = True
            if self.lock is not None:
                self.lock.release()
                self.lock = None

    def take_back(self, failed: StoreHandle) -> None:
        """Undoes :meth:`hand_over` when the newer handle failed to open."""
        key = str(self.path)
        ref = _OPEN_WRITERS.get(key)
        if ref is None or ref() is None or ref() is failed:
            _OPEN_WRITERS[key] = weakref.ref(self)
        if self.local_dir is not None:
            try:
                self.lock = _backend.WriterLock(self.local_dir)
            except RuntimeError:
                return  # another process took it meanwhile: stay a snapshot
        self.retired_by = None
        self.closed = False

    # -- writing and closing -------------------------------------------------------------------

    def check_shareable(self) -> None:
        """Raises unless another process can open this store (pickling gives it a read-only handle)."""
        if not isinstance(self.path, str) or self.path.startswith("memory://"):
            raise RuntimeError(
                f"A ZarrStorage on {self.path!r} cannot be sent to another process: the store lives "
                f"in this process's memory. Use a directory or a shared URL store."
            )

    def check_writable(self) -> None:
        """Raises, saying why and what to do, unless rows may be written through this handle."""
        if self.inherited and not self.read_only:
            raise RuntimeError(
                f"This ZarrStorage ({self.path!r}) was opened for writing by process {self.pid}; this process "
                f"({os.getpid()}) is a forked child of it (multiprocessing with fork, a DataLoader worker) and a "
                f"store has one writer process. Write from process {self.pid}, or open "
                f"ZarrStorage({self.path!r}, read_only=True) in the child to read it."
            )
        if self.read_only and self.received:
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
        if self.retired_by is not None:
            raise RuntimeError(
                f"This ZarrStorage ({self.path!r}) handed its writer to {self.retired_by}; it "
                f"is now a read-only snapshot. Write through the newer handle."
            )
        if self.closed:
            raise RuntimeError(
                f"This ZarrStorage ({self.path!r}) is closed; open ZarrStorage({self.path!r}) again to keep writing."
            )
        if self.lock is not None:
            self.lock.check()  # an object-store lease can be lost

    def check_read(self, attrs: dict, n: int, *, on_damage: str, inner_numel: int) -> int:
        """Lists the chunk files below ``attrs["len"]`` again, after the rows were read; returns the rows to keep.

        Zarr reads a chunk file that is gone as zeros: one missing now (moved away
        by ``robotmem repair`` since the open's listing) raises an
        :class:`IntegrityError` naming it (``on_damage="warn"`` on a reader: a
        warning, and only the ``n`` rows before it are kept).
        """
        problems = integrity.missing_after_read(self.group, attrs, store=self.store, local_dir=self.local_dir)
        if not problems:
            return n
        action = "A chunk file disappeared while the rows were read (is `robotmem repair` running?); no row was served."
        if not (self.read_only and on_damage == "warn"):
            raise IntegrityError(self.path, problems, read_only=self.read_only, action=action)
        cut = min(p.rows[0] for p in problems)
        warnings.warn(f"{IntegrityError(self.path, problems, action='')}\non_damage='warn': reading the "
                      f"{cut} rows before the first missing chunk.", stacklevel=5)
        return min(n, cut * inner_numel)

    def release(self) -> None:
        """Marks the handle closed, releases the writer lock and the store. Idempotent."""
        self.closed = True
        if self.lock is not None:
            self.lock.release()
            self.lock = None
        ref = _OPEN_WRITERS.get(str(self.path))
        if ref is not None and ref() is self:
            del _OPEN_WRITERS[str(self.path)]
        close = getattr(self.store, "close", None)
        if close is not None:
            try:
                close()
            except Exception:  # noqa: BLE001 - nothing to save in a store being closed
                pass
