"""The commit engine: dirty chunks, the background writer thread, ``flush``.

Protocol (see ``docs/storage.md``, "Commit protocol and crash safety"):

1. data first: dirty chunks are written (each chunk file replaced atomically:
   :func:`~.fast_write.write_chunks`, the one chunk writer of this engine and of
   the commit worker);
2. then the metadata, in ONE atomic ``zarr.json`` replacement
   (``Group.update_attributes``): rows below the committed ``len`` are visible;
3. chunks that overwrite committed rows (a ring wrapping around, ``rb[i] = x``)
   go through the redo journal (:mod:`.journal`). A reopen replays a pending
   journal first.

The engine reads rows from the RAM mirror it is given
(:class:`~torchrl_robotmem.storage.mirror.RamMirror`): ``mirror.copy_chunk(c)``
(a snapshot taken under the lock; for a complete chunk past the record, a view
copied after it by ``mirror.copied``), ``mirror.chunk_arrays(snapshot)`` (outside
it), its shapes and schema; and the commit record from the ``record`` callable
it is given (the storage's writer position and tags). It writes nothing but Zarr.

Nothing the process holds is lost to a failed commit: the chunks of a commit
that fails are marked dirty again (the RAM mirror still holds their rows), the
error is raised to the foreground, and the next ``flush()`` tries again. A
commit worker that dies, stops answering or cannot start is killed and this
engine commits in-process from then on (a warning says so, once): a journal
the worker left pending is replayed first, then every row it had not
confirmed is written again from RAM.
"""
from __future__ import annotations

import contextlib
import os
import threading
import time
import warnings
from typing import Any

import numpy as np
import torch
import zarr

from . import _backend
from ._commit_worker import CommitWorker, CommitWorkerError, CommitWorkerGone
from .fast_write import write_chunks
from .format import writing_config, writing_handles
from .journal import OVERWRITES, replay_journal
from .journal import commit as commit_protocol

__all__ = ["CommitEngine"]

# How long the writer thread waits for writes to pause before writing complete
# chunks (seconds): compressing holds the GIL in bursts with some codecs.
_IDLE_GAP = 0.005


class CommitEngine:
    """Makes the rows of a storage durable, in the background or synchronously.

    Args:
        mirror (RamMirror): the rows to commit (see the module docstring).
        group: the store's Zarr group.

    Keyword Args:
        record: a callable returning the commit record that makes the rows
            written so far visible (``len``, ``cursor``, ``write_count``, tags...).
        commit_interval (float): seconds after which written rows are committed
            even if their chunk is not full.
        background (bool): commit from a background thread (``False``: every
            :meth:`kick` commits before returning).
        name (str): thread name suffix.
        worker_path (str, optional): the local directory of the store, to have the
            commit worker process (:mod:`._commit_worker`) split and write the
            chunks instead of this process; ``None`` writes them here.
    """

    def __init__(self, mirror: Any, group: Any, *, record: Any, commit_interval: float, background: bool,
                 name: str, worker_path: str | None = None) -> None:
        self.mirror = mirror
        self.record = record
        self.handle: Any = None  # the store's handle: the worker gets a copy of its writer lock's descriptor
        self.group = group
        self.commit_interval = float(commit_interval)
        self.background = bool(background)
        self.name = name
        self.cv = threading.Condition()
        self.dirty: dict[int, int] = {}  # chunk id -> smallest dirty row (along dim 0)
        self.first_dirty_time: float | None = None
        self.meta_dirty = False
        self.flush_req = 0
        self.flush_done = 0
        self.inflight = 0  # commits whose payload left the dirty set but is not written yet
        self.holds = 0  # blocks of writes that reach the disk in one commit (held): no commit of its own starts
        self.arrays: dict[str, Any] = {}  # zarr arrays by path, opened once
        self.plans: dict[str, Any] = {}  # how each array's chunks are written (fast_write.write_chunks' cache)
        self.last_set_time = 0.0
        self.thread: threading.Thread | None = None
        # the last commit's failure; its rows stay dirty and the next flush() retries them
        self.error: BaseException | None = None
        self.committed_len = 0  # committed length (transitions)
        self.committed_write_count = 0  # write count of the last commit record
        self.committed_constants: dict = {}  # the store's constants as the last commit record left them
        # journalled commits so far (the record's ``overwrites``): a reader tells by it that rows it was
        # loading were rewritten in place, which leaves every other field of the record as it was
        self.overwrites = 0
        self.worker_path = worker_path
        self.worker_fault: str | None = None  # why this engine stopped using its worker
        self._worker: CommitWorker | None = None  # the worker this store is open in
        self._worker_synced = False  # the worker drops what it cached of this store on our first request
        self._via_worker = False  # switched on (once) when the worker is ready; in-process until then
        self._route_lock = threading.RLock()  # the worker starts once the open has read (MemoryStore.open_arrays)

    def set_committed(self, attrs: dict) -> None:
        """Records the commit record found on disk (at open): ``len``, ``write_count``, ``overwrites`` and the
        constants."""
        self.committed_len = int(attrs.get("len", 0))
        self.committed_write_count = int(attrs.get("write_count", 0))
        self.overwrites = int(attrs.get(OVERWRITES, 0))
        self.committed_constants = dict(attrs.get("constants") or {})

    # -- bookkeeping (called under ``cv``) ----------------------------------------

    def mark_dirty(self, rows: torch.Tensor | slice, chunk_rows: int) -> None:
        """Records the chunks ``rows`` (along dim 0) touched; a slice means contiguous rows."""
        if isinstance(rows, slice):
            for c in range(rows.start // chunk_rows, (rows.stop - 1) // chunk_rows + 1):
                lo = max(rows.start, c * chunk_rows)
                self.dirty[c] = min(self.dirty.get(c, lo), lo)
        else:
            chunks = torch.div(rows, chunk_rows, rounding_mode="floor")
            for c, r in zip(chunks.tolist(), rows.tolist()):
                self.dirty[c] = min(self.dirty.get(c, r), r)
        if self.first_dirty_time is None:
            self.first_dirty_time = time.monotonic()
        self.meta_dirty = True
        self.last_set_time = time.monotonic()

    def mark_meta_dirty(self) -> None:
        self.meta_dirty = True

    def discard_pending(self) -> None:
        """Forgets what RAM holds since the last commit (nothing of it is committed) and waits for a commit
        already begun to end: ``MemoryStore.give_up_writes``, inside a :meth:`held` block, before the handle
        closes."""
        with self.cv:
            self.dirty.clear()
            self.meta_dirty = False
            self.first_dirty_time = None
            while self.inflight:  # a commit begun before the hold (the rows of before): let it end
                self.cv.wait(0.1)

    @contextlib.contextmanager
    def held(self):
        """A block of writes that reaches the disk in one commit: the commits the engine starts on its own (the
        timer, complete chunks, a write's commit without the thread) wait for its end; a ``flush()`` does not.

        ``ZarrStorage.load_state_dict`` replaces the rows inside one, then flushes: a process killed on the way
        leaves the rows of before it, never an emptied or half-replaced memory.
        """
        with self.cv:
            self.holds += 1
        try:
            yield
        finally:
            with self.cv:
                self.holds -= 1
                self.cv.notify_all()

    def reset_arrays(self) -> None:
        self.arrays.clear()
        self.plans.clear()
        with self._route_lock:
            if self._via_worker and self._worker_synced:
                self._worker_request({"op": "reset", "path": self.worker_path})

    def _use_worker(self) -> bool:
        """Whether commits go through the worker; switches over (once) when it is ready."""
        if self._via_worker or self.worker_path is None:
            return self._via_worker
        with self._route_lock:  # no in-process attribute write races the switch
            if not self._via_worker and self.worker_path is not None:
                try:
                    worker = CommitWorker.get()
                    if worker.ready():
                        self._worker = worker
                        self._worker_open()
                        self._via_worker = True
                except CommitWorkerGone as err:
                    self._fall_back(err)
        return self._via_worker

    def update_attrs(self, update: dict) -> None:
        """Writes store attributes; through the worker once it commits (so no update is lost)."""
        with self._route_lock:
            if not (self._use_worker()
                    and self._worker_request({"op": "attrs", "path": self.worker_path, "update": update})):
                self.group.update_attributes(update)

    def _worker_open(self) -> None:
        """(Re)opens the store in the worker, with a copy of the writer lock's descriptor.

        Another handle, or this process before the switch, may have written the
        store since the worker last saw it: it reopens the group and its arrays.
        """
        fd = getattr(getattr(self.handle, "lock", None), "fd", None)
        self._worker.request({"op": "open", "path": self.worker_path}, fds=[fd] if fd is not None else [])
        self._worker_synced = True

    def _worker_request(self, header: dict, payloads: list | tuple = ()) -> bool:
        """Sends one request; ``False`` if the worker failed (it is killed: do the work in-process).

        A failure *in* the worker (its reply carries an error, e.g. a full disk)
        raises :class:`CommitWorkerError`.
        """
        try:
            if not self._worker_synced:
                self._worker_open()
            self._worker.request(header, payloads)
            return True
        except CommitWorkerGone as err:
            with self._route_lock:
                self._fall_back(err)
            return False

    def _fall_back(self, err: CommitWorkerGone) -> None:
        """Stops using the worker for good: warns once, then resyncs with what is on disk.

        Called under ``_route_lock``. The worker is dead when this returns (or
        an error is raised: a worker that survives ``SIGKILL``, stuck in the
        kernel, could still write). What it may have left half-done is
        completed here, as a reopen would: a pending journal is replayed, the
        group's attributes are read again (the worker wrote them), and the
        commit record it may have written counts as committed (so rows below it
        are overwritten through the journal).
        """
        if self.worker_path is None:
            return  # done already (by another thread's request)
        worker = self._worker
        if worker is not None and not worker.gone():
            worker.discard()
            if not worker.gone():
                raise CommitWorkerError(
                    f"the commit worker process (pid {worker.proc.pid}) did not exit after SIGKILL "
                    f"(stuck in the kernel: a stalled disk?); nothing is written in-process until it has"
                )
        self.worker_fault = str(err)
        self.worker_path = None
        self._worker = None
        self._via_worker = False
        self._worker_synced = False
        warnings.warn(
            f"ZarrStorage {self.name!r}: {err}. Its commits are now written by this process (slower, "
            f"nothing lost: every row the worker had not made durable is written again from memory); "
            f"a store opened later starts a new worker.",
            RuntimeWarning, stacklevel=2,
        )
        self._resync_from_disk()

    def _resync_from_disk(self) -> None:
        self.group, attrs = settled_group(self.group.store)
        with self.cv:
            self.committed_len = max(self.committed_len, int(attrs.get("len", 0)))
            self.committed_write_count = max(self.committed_write_count, int(attrs.get("write_count", 0)))
            self.overwrites = max(self.overwrites, int(attrs.get(OVERWRITES, 0)))
            self.committed_constants = dict(attrs.get("constants") or {})
        for path in [p for p in self.arrays if p.startswith("_journal/")]:
            del self.arrays[path]  # the worker may have recreated (or half-created) them

    def close(self) -> None:
        """Lets the worker forget this store (after the last commit); never starts one."""
        if self.worker_path is None or not self._worker_synced:
            return
        self._worker_synced = False
        worker = self._worker
        if worker is None or worker.pid != os.getpid() or worker.broken or worker.gone():
            return
        try:
            worker.request({"op": "close", "path": self.worker_path})
        except Exception:  # noqa: BLE001 - closing: nothing left to write (a silent worker is killed)
            pass

    # -- the writer thread ----------------------------------------------------------

    def kick(self, notify: bool = True) -> None:
        """Wakes the writer (or, without a background thread, commits now).

        ``notify=False`` only makes sure the thread runs: a running writer
        commits on its own timer, and waking it on every write costs the
        foreground a GIL hand-over each time.
        """
        if not self.background:
            self._commit(everything=True, requested=False)
            return
        with self.cv:
            started = self.thread is not None or self._start_thread()
            if self.thread is not None and notify:
                self.cv.notify_all()
        if not started:  # no new thread at interpreter exit (see start_thread): this one commits
            self._commit(everything=True, requested=False)

    def _start_thread(self) -> bool:
        self.thread = start_thread(self._loop, f"ZarrStorage-writer({self.name})")
        return self.thread is not None

    def _complete_chunks(self) -> list[int]:
        mirror = self.mirror
        n, size, rows = mirror.filled(), mirror.max_dim0, mirror.chunk_rows
        return [c for c in self.dirty if min((c + 1) * rows, size) <= n]

    def _loop(self) -> None:
        while True:
            with self.cv:
                while True:
                    if self.error is not None:
                        self.thread = None
                        return
                    flush = self.flush_req > self.flush_done
                    if self.holds and not flush:
                        self.cv.wait()  # the hold's end notifies
                        continue
                    pending = bool(self.dirty) or self.meta_dirty
                    timer = pending and (
                        self.first_dirty_time is None
                        or time.monotonic() - self.first_dirty_time >= self.commit_interval
                    )
                    if flush or timer:
                        break
                    if self._complete_chunks():
                        if self._via_worker:
                            # the worker encodes and writes them in its own process: committed as
                            # they fill, beside the writes (durable rows/s 0.29x -> 0.51x the
                            # memmap's at 1M rows; docs/benchmarks.md "...chunks committed as they fill")
                            break
                        # In-process, complete chunks wait for a pause in the writes (the timer
                        # still bounds the wait): a commit's Python side (chunk copies, Zarr's
                        # event loop) holds the GIL, and committing chunk by chunk during
                        # a tight extend loop made it 3x slower, whatever the codec.
                        idle = time.monotonic() - self.last_set_time
                        if idle >= _IDLE_GAP:
                            break
                        self.cv.wait(_IDLE_GAP - idle)
                        continue
                    if not pending:
                        self.thread = None  # idle: let the storage be collected
                        return
                    self.cv.wait(max(0.0, self.commit_interval - (time.monotonic() - self.first_dirty_time)))
            self._commit(everything=flush or timer, requested=flush)

    def _commit(self, *, everything: bool, requested: bool = True) -> None:
        """Writes dirty chunks (all of them, or only complete ones), then the metadata.

        If the worker fails on the way (dead, silent), the engine falls back to
        writing in-process and commits everything again; any other failure
        leaves the chunks dirty and is raised to the foreground. A commit not ``requested`` by a
        flush is not made under a hold (:meth:`held`: it began after the thread decided to commit).
        """
        mirror = self.mirror
        with self.cv:
            if self.holds and not requested:
                return
            target = self.flush_req
            # Overwriting committed rows (a wrapping ring) commits everything with
            # its metadata, through the journal: rows on disk never lead the
            # metadata, even by a chunk.
            committed0 = mirror.dim0(self.committed_len)
            overwrite = any(lo < committed0 for lo in self.dirty.values())
            everything = everything or overwrite
            chunks = sorted(self.dirty) if everything else sorted(self._complete_chunks())
            try:  # a snapshot or record that raises (a chunk a writer's fill cannot read): nothing was taken, and
                # the error is the commit's (a writer thread that died here left flush() waiting forever)
                # Complete chunks wholly past the record are copied after the lock is released: the
                # foreground waited here for their memcpy, about 2 ms a 4 MiB chunk (RamMirror.copy_chunk).
                # A chunk the record reaches into (a timer commit of it half full) is copied here: a write
                # of its committed rows during the copy would reach the disk without the journal
                unlocked = set() if everything else {c for c in chunks if c * mirror.chunk_rows >= committed0}
                snapshots = {c: mirror.copy_chunk(c, copy=c not in unlocked) for c in chunks}
                meta = self.record() if everything else None
            except BaseException as err:
                self._failed(err, target)  # (the condition's lock is reentrant)
                if not self.background:
                    raise
                return
            taken = {c: self.dirty.pop(c) for c in chunks}
            if overwrite:  # every journalled commit changes the record, even one that rewrites rows in place
                meta[OVERWRITES] = self.overwrites + 1
            if everything:
                self.meta_dirty = False
                self.first_dirty_time = None
            self.inflight += 1
        try:
            snapshots = {c: mirror.copied(snap) if c in unlocked else snap for c, snap in snapshots.items()}
            with self._route_lock:  # an in-process commit and a switch to the worker never overlap
                via_worker = self._use_worker()
                if not via_worker:
                    # split into arrays outside the cv lock: the foreground only waited for the memcpy
                    payload = {c: mirror.chunk_arrays(snap) for c, snap in snapshots.items()}
                    commit_protocol(self.group, self.arrays, self._write_chunks, payload, meta,
                                    chunk_rows=mirror.chunk_rows, journal=journal_specs(mirror) if overwrite else None)
            if via_worker:
                self._commit_in_worker(snapshots, meta, overwrite)
        except CommitWorkerGone as err:
            # the worker may have written some of it, all of it, or a pending journal:
            # mark it all dirty again and commit it (with the metadata) in-process
            self._undo_take(taken)
            try:
                with self._route_lock:
                    self._fall_back(err)
            except BaseException as fail:
                self._failed(fail, target)
                if not self.background:
                    raise
                return
            self._commit(everything=True, requested=requested)  # under a hold, only a flush's commit goes on
            return
        except BaseException as err:  # surfaced to the foreground on its next call
            self._undo_take(taken)
            self._failed(err, target)
            if not self.background:
                raise
            return
        with self.cv:
            self.inflight -= 1
            if meta is not None:
                self.committed_len = int(meta["len"])
                self.committed_write_count = int(meta["write_count"])
                self.overwrites = int(meta.get(OVERWRITES, self.overwrites))
                self.committed_constants = dict(meta.get("constants", self.committed_constants))
                self.flush_done = max(self.flush_done, target)
            self.cv.notify_all()

    def _undo_take(self, taken: dict[int, int]) -> None:
        """A commit failed: its chunks and the metadata are dirty again (RAM still holds them)."""
        with self.cv:
            for c, lo in taken.items():
                self.dirty[c] = min(self.dirty.get(c, lo), lo)
            self.meta_dirty = True
            if self.first_dirty_time is None:
                self.first_dirty_time = time.monotonic()
            self.inflight -= 1

    def _failed(self, err: BaseException, target: int) -> None:
        with self.cv:
            self.error = err
            self.flush_done = max(self.flush_done, target)
            self.cv.notify_all()

    def _commit_in_worker(self, snapshots: dict, meta: dict | None, overwrite: bool) -> None:
        """Sends the packed snapshots to the commit worker, which splits and writes them."""
        header = worker_header(self.mirror, self.worker_path, snapshots, meta, overwrite)
        if not self._worker_synced:
            self._worker_open()
        self._worker.request(header, [snap[0].numpy() for snap in snapshots.values()])  # may raise CommitWorkerGone

    def _array(self, path: str) -> Any:
        arr = self.arrays.get(path)
        if arr is None:  # reopened (after a growth): a handle that writes all-zero chunks too, as every other
            arr = self.arrays[path] = writing_handles(self.group, [path])[path]
        return arr

    def _write_chunks(self, payload: dict[int, dict[str, np.ndarray]], prefix: str = "") -> None:
        """Writes chunks of every array (:func:`~.fast_write.write_chunks`: the chunk files directly, for a local store)."""
        write_chunks(self._array, payload, self.mirror.chunk_rows, prefix, plans=self.plans)

    def pending(self) -> bool:
        return bool(self.dirty or self.meta_dirty or self.inflight) or self.flush_done < self.flush_req

    def flush(self) -> None:
        """Blocks until everything marked dirty so far is durable and committed.

        After a failed commit this is the retry: the rows it could not write
        are still dirty, and are written now if the cause is gone.
        """
        if not self.background:
            with self.cv:
                self.error = None
            if self.dirty or self.meta_dirty:
                self._commit(everything=True)
            self.raise_error()
            return
        with self.cv:
            if self.error is not None and self.inflight == 0:
                self.error = None  # retry: the failed commit's rows are dirty again
            if not self.pending():
                self.raise_error()
                return
            self.flush_req += 1
            target = self.flush_req
        self.kick()
        while True:
            with self.cv:
                if self.flush_done >= target or self.error is not None:
                    break
                if self.thread is not None or self._start_thread():  # it may have gone idle before the request
                    self.cv.wait(0.5)
                    continue
            self._commit(everything=True)  # no new thread at interpreter exit: this one commits
        self.raise_error()

    def not_durable(self) -> str:
        """Which rows the store would lose now: ``"N rows (write numbers A to B)"`` and in-place changes."""
        with self.cv:
            return not_durable(self.mirror, int(self.record()["write_count"]), self.committed_write_count,
                               [c for c, lo in self.dirty.items() if lo < self.mirror.dim0(self.committed_len)])

    def raise_error(self, *, closing: bool = False) -> None:
        """Raises the last commit failure, saying which rows are not durable (or lost, when closing)."""
        err = self.error
        if err is not None:
            raise failure(self.name, err, self.not_durable(), closing=closing) from err


def worker_header(mirror: Any, path: str, snapshots: dict, meta: dict | None, overwrite: bool) -> dict:
    """The commit worker's request for packed chunk ``snapshots`` (see :mod:`._commit_worker`)."""
    layout = next(iter(snapshots.values()))[1] if snapshots else None  # None: a metadata-only commit
    header = {
        "op": "commit",
        "path": path,
        "chunk_rows": mirror.chunk_rows,
        "row_bytes": layout.row_bytes if layout is not None else 0,
        "inner": list(mirror.inner_shape or ()),
        "fields": [[p, off, nbytes, _backend.numpy_dtype(dtype).str, list(shape)]
                   for p, off, nbytes, dtype, shape in (layout.fields if layout is not None else ())
                   if p in mirror.schema],
        "chunks": [[c, int(snap[0].shape[0])] for c, snap in snapshots.items()],
        "overwrite": overwrite,
        "meta": meta,
    }
    if overwrite:
        header["journal"] = journal_specs(mirror)
    return header


def journal_specs(mirror: Any) -> list:
    """``[path, shape, numpy dtype str]`` of each column's journal array (``journal.commit``'s ``journal``)."""
    return [[p, [mirror.max_dim0, *mirror.inner_shape, *spec["shape"]],
             _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"])).str]
            for p, spec in mirror.schema.items()]


def start_thread(target: Any, name: str) -> threading.Thread | None:
    """Starts a daemon thread; ``None`` where the interpreter starts no new thread.

    Python 3.12.0 to 3.12.2 refuse to start a thread once interpreter exit has
    begun, even in the threading exit hooks that flush writers
    (CPython gh-113964, fixed in 3.12.3): a flush at exit then commits in the
    calling thread instead.
    """
    thread = threading.Thread(target=target, name=name, daemon=True)
    try:
        thread.start()
    except RuntimeError:  # "can't create new thread at interpreter shutdown"
        return None
    return thread


def not_durable(mirror: Any, written: int, committed: int, in_place: list[int]) -> str:
    """Which rows a store would lose: ``"N rows (write numbers A to B)"``, or its in-place changes.

    Args:
        mirror (RamMirror): the store's rows.
        written (int): the write count so far.
        committed (int): the write count of the last commit record.
        in_place (list): dirty chunks holding committed rows.
    """
    size, rows = mirror.max_size, mirror.chunk_rows or 0
    first = max(committed, written - size)  # older writes were overwritten in RAM by the ring
    if written > first:
        where = f"at storage index write number % {size}" if written > size else "the same storage indices"
        return f"{written - first} rows (write numbers {first} to {written - 1}, {where})"
    if in_place:
        return "in-place changes to the stored rows " + ", ".join(
            f"{c * rows} to {(c + 1) * rows - 1}" for c in sorted(in_place))
    return "no rows"


def failure(name: str, err: BaseException, rows: str, *, closing: bool) -> RuntimeError:
    """The error a failed commit raises in the foreground, saying which ``rows`` are not durable (or lost)."""
    # a commit worker's error already reads "<its type>: <message>"
    what = str(err) if isinstance(err, CommitWorkerError) else f"{type(err).__name__}: {err}"
    if closing:
        advice = (f"{rows} could not be written and are lost: this handle is closed. "
                  f"Fix the cause (disk space, permissions) and write them again")
    else:
        advice = (f"{rows} are not durable: they are kept in memory. Fix the cause "
                  f"(disk space, permissions), then call flush() on this storage (or close() it, or "
                  f"open ZarrStorage on the same path again) to write them")
    return RuntimeError(f"The background writer of {name!r} failed: {what}. {advice}.")


def settled_group(store: Any) -> tuple[Any, dict]:
    """The store's group opened for writing, a pending journal replayed first; and its attributes."""
    group = zarr.open_group(store, mode="r+", zarr_format=3)
    attrs = group.attrs.asdict()
    if attrs.get("journal"):
        with writing_config():
            attrs = replay_journal(group, attrs["journal"])
    return group, attrs

