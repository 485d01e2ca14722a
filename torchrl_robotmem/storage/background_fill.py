"""Rows filled from the chunk files in the background: the open returns at once, a sample waits only for its chunks.

A reader whose row file is not sealed for the record it opened (a writer is active beside it, a crash
left no seal) must fill its rows from the committed chunks before serving them. For a large memory that
is seconds per ten million rows. :class:`RowFill` does it in a background thread instead, chunk by
chunk in order, while the open returns; a read of some rows (``RamMirror.gather``, which
``ZarrStorage.get`` and so every ``sample`` goes through) first fills the chunks those rows lie in, in
the reader's own thread, unless they are filled already; any other read of the rows (TorchRL's
``storage._storage``, a column, ``recall``, a refresh) waits for the whole fill. No row is served
before its chunk is read.

What is served is what a synchronous fill would serve:

* **Only the open's chunks, from their files.** A fill starts only where the open's record has no
  pending journal, the ring has not wrapped, every column is read from its chunk files
  (:class:`~.fast_read.ChunkReads`: checksums checked on the read) and damage raises
  (``on_damage="raise"``); otherwise the open fills synchronously, as before.
* **A writer beside it.** A writer appending rows rewrites the last chunk with the same old rows; one
  that overwrites committed rows (a ring wrapping, an in-place write) journals them. Each chunk is read
  between two looks at the commit record (``zarr.json``, whose every commit replaces the file): a chunk
  read while the record changed is read again, and a record that names a journal or a wrapped ring
  hands the rest of the fill to the synchronous path, which re-reads what a writer overwrote
  (``RamMirror.reread_overwritten``).
* **Damage.** A chunk that cannot be read from its file (gone, a checksum that does not match) hands the
  fill to the synchronous path too, whose error names the store, the array and the chunk; that error is
  raised by every read of the rows from then on, never a row.

A forked child (a ``DataLoader`` worker) fills what is left itself, in its own thread, into the same
shared file; ``close`` stops the thread.

**The writer's fill** (a writer with no usable row file: after a crash) runs the same way without the looks
at the record (``record_file=None``: no one else commits): every write into rows below ``n0`` first fills
their chunks (:meth:`ready` / :meth:`ensure`, through ``RamMirror.fill_before_write``), so the fill never
writes over a row written since the open, and its ``fallback`` raises the damage it met, naming the chunk
(:func:`.loader.fill_in_background`).

Example:
    >>> import tempfile, numpy as np, torch, zarr
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.fast_read import ChunkReads
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100, chunk_rows=4) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.arange(30.).reshape(10, 3)}, [10]))
    >>> out = torch.zeros(10, 3)
    >>> reads = ChunkReads({"obs": zarr.open_group(path, mode="r")["obs"]}, {"obs": out}, 4, local_dir=path)
    >>> fill = RowFill(reads, 10, record_file=path + "/zarr.json", max_size=100, fallback=lambda failure: None,
    ...                start=False)
    >>> fill.ensure(np.array([9]))  # the chunk of row 9 (rows 8-9) only
    >>> out[9].tolist(), out[0].tolist()
    ([27.0, 28.0, 29.0], [0.0, 0.0, 0.0])
    >>> fill.wait(); out[0].tolist()
    [0.0, 1.0, 2.0]
"""
from __future__ import annotations

import json
import os
import stat
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .contained import open_regular
from .fast_read import ChunkReads, workers

__all__ = ["RowFill"]

_EMPTY, _FILLING, _DONE = 0, 1, 2
#: reads of one chunk that a writer's commits may interrupt before the synchronous path takes over
_RETRIES = 100


class _HandOver(Exception):
    """The rest of the fill goes to the synchronous path (damage, a journal, a wrapped ring)."""


class RowFill:
    """Fills rows ``[0, n0)`` from the chunk files in a background thread; :meth:`ensure` fills chunks first.

    Args:
        reads (ChunkReads): the arrays and the columns they are read into (every array readable from its files).
        n0 (int): the rows to fill (the open's length).

    Keyword Args:
        record_file (str, optional): the store's commit record (``zarr.json``), looked at around every chunk
            read; ``None`` for the store's writer, the only process that commits (nothing to look for).
        max_size (int): the ring's capacity (a record whose ``write_count`` passes it has wrapped).
        fallback (callable): ``fallback(failure)``, what this cannot read: a reader's synchronous fill of
            every row (``loader.load_rows``, raising the store's damage errors); a writer's error naming the
            damage. ``failure`` is ``(chunk, paths)`` for a chunk that could not be read, else ``None``.
        start (bool): start the background thread (``False``: only :meth:`ensure` and :meth:`wait` fill).
    """

    def __init__(self, reads: ChunkReads, n0: int, *, record_file: str | None, max_size: int,
                 fallback: Callable[[tuple | None], None], start: bool = True) -> None:
        self.reads, self.n0 = reads, int(n0)
        self.record_file, self.max_size = record_file, int(max_size)
        self.fallback = fallback
        self.nchunks = -(-self.n0 // reads.chunk_rows)
        self.state = np.zeros(self.nchunks, np.int8)
        self.done = self.nchunks == 0
        self.error: BaseException | None = None
        self.failure: tuple | None = None  # (chunk, paths) that could not be read: handed to ``fallback``
        self._handed_over = False
        self._stop = False
        self._pid = os.getpid()
        self._cv = threading.Condition()
        self._last_record: tuple | None = None
        self._thread: threading.Thread | None = None
        if start and not self.done:
            self._thread = threading.Thread(target=self._run, name="robotmem-fill", daemon=True)
            self._thread.start()

    # -- what readers call -----------------------------------------------------------------------

    def ensure(self, rows: np.ndarray) -> None:
        """Fills (or waits for) the chunks of first-dimension ``rows`` (non-negative, below ``n0``)."""
        self._after_fork()
        if self.done:
            return self._raise()
        chunks = np.unique(np.asarray(rows, dtype=np.int64) // self.reads.chunk_rows)
        self._fill_many(chunks[(chunks >= 0) & (chunks < self.nchunks)])

    def ready(self, rows: np.ndarray) -> bool:
        """Whether every chunk of first-dimension ``rows`` (non-negative, below ``n0``) is filled already."""
        chunks = np.unique(np.asarray(rows, dtype=np.int64) // self.reads.chunk_rows)
        chunks = chunks[(chunks >= 0) & (chunks < self.nchunks)]
        return bool((self.state[chunks] == _DONE).all())

    def wait(self) -> None:
        """Fills every chunk left (in this thread, beside the background one) and waits for the rest."""
        self._after_fork()
        if not self.done:
            self._fill_many(np.flatnonzero(self.state != _DONE))
        self._raise()

    def stop(self) -> None:
        """Stops the background thread (the chunks it has not filled stay unfilled). Idempotent."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread() and os.getpid() == self._pid:
            thread.join()
        self._thread = None

    # -- the fill ------------------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self._fill_chunks(np.arange(self.nchunks), background=True)
        except BaseException:  # noqa: BLE001 - kept in self.error, raised to the reader
            return

    def _fill_many(self, chunks: np.ndarray) -> None:
        """:meth:`_fill_chunks` over a pool of threads (the reads release the GIL), for a reader waiting on them."""
        n = workers(len(chunks))
        if n <= 1:
            return self._fill_chunks(chunks)
        with ThreadPoolExecutor(n, thread_name_prefix="robotmem-fill") as pool:
            list(pool.map(self._fill_chunks, np.array_split(chunks, n)))

    def _fill_chunks(self, chunks: np.ndarray, *, background: bool = False) -> None:
        """Fills ``chunks`` not filled yet, waiting for those another thread is reading; then raises a kept error."""
        for c in chunks.tolist():
            with self._cv:
                while self.state[c] == _FILLING and not self._handed_over:
                    self._cv.wait()
                if self._handed_over or (background and self._stop):
                    break
                if self.state[c] == _DONE:
                    continue
                self.state[c] = _FILLING
            try:
                self._read_chunk(c)
            except BaseException as err:
                with self._cv:
                    self.state[c] = _EMPTY
                    handing = isinstance(err, _HandOver) and not self._handed_over
                    self._handed_over = self._handed_over or isinstance(err, _HandOver)
                    self._cv.notify_all()
                if handing:
                    self._hand_over()
                    break
                if isinstance(err, _HandOver):
                    break
                raise
            with self._cv:
                self.state[c] = _DONE
                if not self._handed_over and bool((self.state == _DONE).all()):
                    self.done = True
                self._cv.notify_all()
        if not background:
            with self._cv:
                while self._handed_over and not self.done:
                    self._cv.wait()
            self._raise()

    def _read_chunk(self, c: int) -> None:
        """Reads chunk ``c`` between two looks at the record that agree (the writer committed nothing meanwhile)."""
        for _ in range(_RETRIES):
            before = self._look()
            failed = self.reads.read(c, self.n0)
            if failed:
                self.failure = self.failure or (c, sorted(failed))
                raise _HandOver  # a file gone or damaged: the fallback names it
            if self._look() == before:
                return
        raise _HandOver

    def _look(self) -> tuple | None:
        """The record file's identity; a new one is read: a journal or a wrapped ring hands the fill over.

        ``None`` for a writer's fill: no one else commits.
        """
        if self.record_file is None:
            return None
        try:
            st = os.stat(self.record_file, follow_symlinks=False)
        except OSError:
            raise _HandOver from None
        if not stat.S_ISREG(st.st_mode):  # a link or a special file: the synchronous load refuses it
            raise _HandOver
        ident = (st.st_ino, st.st_size, st.st_mtime_ns)
        if ident != self._last_record:
            try:  # anything unexpected in the record is the synchronous load's to check and name
                with open(open_regular(self.record_file)) as f:
                    attrs = json.load(f)["attributes"]
                overwrites = bool(attrs.get("journal")) or int(attrs.get("write_count", 0)) > self.max_size
            except Exception:  # noqa: BLE001
                raise _HandOver from None
            if overwrites:
                raise _HandOver
            self._last_record = ident
        return ident

    def _hand_over(self) -> None:
        """Runs the synchronous fill (once, in the thread that met the reason); every reader waits for it."""
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join()  # it stops at its next chunk (it sees the hand-over)
        with self._cv:  # a chunk another reader's thread is still reading is read again by the fallback anyway
            while bool((self.state == _FILLING).any()):
                self._cv.wait()
        try:
            self.fallback(self.failure)
        except BaseException as err:  # noqa: BLE001 - every later read raises it
            self.error = err
        with self._cv:
            self.done = True
            self._cv.notify_all()

    def _raise(self) -> None:
        if self.error is not None:
            raise self.error

    def _after_fork(self) -> None:
        """A forked child: fresh lock, no thread; the chunks the parent was reading are read again here."""
        if os.getpid() == self._pid:
            return
        self._pid = os.getpid()
        self._cv = threading.Condition()
        self._thread = None
        self.state[self.state == _FILLING] = _EMPTY
        if self._handed_over and not self.done:  # the parent was running the synchronous load: run it here
            self._hand_over()
