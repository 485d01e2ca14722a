"""The pages of a writer's row file faulted in ahead of its writes, by a thread.

A write into a fresh part of the memory-mapped row file (:mod:`.rowfile`) takes a page fault per
4 KB page it touches: the kernel finds or allocates the page-cache page and maps it. Appending
Fetch-shaped rows, those faults are about half of the time ``extend`` spends copying rows (measured
here: 0.72 ms a batch of 1,000 rows into fresh pages, 0.37 ms into pages already mapped; docs/benchmarks.md).
:class:`Prefault` moves them off the training loop: a thread asks the kernel to map the next
:data:`WINDOW` bytes past the newest write with ``madvise(MADV_POPULATE_WRITE)`` (Linux 5.14 and later),
which maps the pages writable *without changing a byte* of them, so it can never race a write. The
call releases the GIL (``ctypes``), so the writer's thread runs on.

Resident memory stays what the writes touch plus one window: only the pages ahead of the newest write
are mapped, never the rows behind it (a reopened memory of 100M rows is not paged in). Where the call
is not supported (an older kernel, another OS) nothing is done and writes fault as before.

Example:
    >>> import mmap
    >>> from torchrl_robotmem.storage.prefault import Prefault
    >>> m = mmap.mmap(-1, 1 << 20)
    >>> ahead = Prefault()
    >>> ahead.mapped(m, 1 << 20)
    >>> ahead.written(4096)       # the thread maps the pages past byte 4096 (where the kernel can)
    >>> ahead.stop()
"""
from __future__ import annotations

import ctypes
import errno
import mmap
import sys
import threading
from typing import Any

__all__ = ["IDLE", "MADV_POPULATE_WRITE", "STEP", "WINDOW", "Prefault"]

#: bytes mapped ahead of the newest write (the thread wakes when the writes are half a window from its end)
WINDOW = 32 << 20
#: bytes per ``madvise`` call (a new mapping or a stop is noticed between calls)
STEP = 4 << 20
#: seconds the thread waits for more work before it ends
IDLE = 2.0
#: Linux's ``MADV_POPULATE_WRITE`` (5.14+); Python's ``mmap`` module names it only from 3.13
MADV_POPULATE_WRITE = getattr(mmap, "MADV_POPULATE_WRITE", 23)

_PAGE = mmap.PAGESIZE


def _madvise() -> Any:
    """libc's ``madvise`` through ctypes (which releases the GIL during the call), or ``None``."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.madvise
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    fn.restype = ctypes.c_int
    return fn


_MADVISE = _madvise()


class Prefault:
    """Maps the pages of one writable mapping ahead of the writes into it, from a daemon thread.

    The owner (:class:`~.rowfile.RowFile`) calls :meth:`mapped` with each new mapping and
    :meth:`written` with the byte offset where a write into it ended; :meth:`stop` when the
    mapping is released. Nothing here writes into the mapping.
    """

    def __init__(self) -> None:
        self.supported = _MADVISE is not None
        self._cv = threading.Condition()
        self._map: Any = None  # the mmap (held: it is not unmapped while a call runs on it)
        self._address = 0
        self._length = 0
        self._done = 0  # bytes mapped so far (from ``_start``)
        self._want = 0  # bytes the thread is asked to map up to
        self._thread: threading.Thread | None = None
        self._stopped = False

    @property
    def done(self) -> int:
        """Bytes of the mapping mapped ahead so far (from the write that started the window)."""
        return self._done

    @property
    def asked(self) -> int:
        """The byte the thread is asked to map up to (0: nothing asked of this mapping)."""
        return self._want

    @property
    def active(self) -> bool:
        """Whether a mapping is followed (a writer's, until released)."""
        return self._map is not None

    def mapped(self, m: mmap.mmap, length: int) -> None:
        """The writes now go into ``m`` (``length`` bytes of it): nothing of it is counted as mapped yet."""
        if not self.supported:
            return
        address = ctypes.addressof(ctypes.c_char.from_buffer(m))  # the export ends with the temporary
        with self._cv:
            self._map, self._address, self._length = m, address, int(length)
            self._done = self._want = 0
            self._stopped = False

    def written(self, end: int) -> None:
        """A write ended at byte ``end`` of the mapping: map ahead of it if the window runs short."""
        if not self.supported or end + WINDOW // 2 <= self._done or self._map is None:
            return  # the fast path: no lock
        with self._cv:
            if self._map is None or self._stopped:
                return
            if end > self._done:  # a jump (a reopened memory, a write past the window): start at the write
                self._done = end - end % _PAGE
            self._want = min(self._length, -(-(end + WINDOW) // _PAGE) * _PAGE)  # whole pages: every call's start is one
            if self._want <= self._done:
                return
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="robotmem-prefault", daemon=True)
                try:
                    self._thread.start()
                except RuntimeError:  # interpreter shutdown: writes fault as before
                    self._thread = None
                    return
            self._cv.notify()

    def stop(self) -> None:
        """No more pages are mapped (the mapping is released); a call under way finishes first."""
        with self._cv:
            self._stopped = True
            self._map = None
            self._cv.notify()

    def drain(self) -> None:
        """Blocks until the pages asked for so far are mapped (or the mapping is released)."""
        with self._cv:
            while self._thread is not None and not self._stopped and self._done < self._want:
                self._cv.wait()

    def _run(self) -> None:
        while True:
            with self._cv:
                idle = False
                while not self._stopped and self._done >= self._want and not idle:
                    idle = not self._cv.wait(IDLE) and self._done >= self._want
                if self._stopped or idle:  # released, or nothing asked for a while: the next write starts another
                    self._thread = None
                    self._cv.notify_all()
                    return
                m, lo = self._map, self._done
                hi = min(self._want, lo + STEP)
                address = self._address
            failed = _MADVISE(address + lo, hi - lo, MADV_POPULATE_WRITE) != 0
            with self._cv:
                if failed and ctypes.get_errno() == errno.EINVAL:
                    self.supported = False  # an older kernel: writes fault as before (the thread ends)
                    self._stopped = True
                elif self._map is m and self._done == lo:
                    self._done = hi  # done, or failed otherwise (the writes will fault there): not tried again
                self._cv.notify_all()
