"""Process-end safety for writable :class:`~torchrl_robotmem.ZarrStorage` handles.

A persistent memory must keep every row a process extended, however the process
ends, even if nobody calls ``close()``. This module owns the three mechanisms
that make that true:

* **Interpreter exit** (end of script, ``sys.exit``, an uncaught exception,
  ``KeyboardInterrupt``, hydra's ``main`` returning, a buffer collected in a
  reference cycle): every live writer is closed by a *threading* exit hook.
  A plain :mod:`atexit` hook is too late: at interpreter exit Python first runs
  ``concurrent.futures``' own threading hook, which stops every thread pool,
  Zarr's included (its ``LocalStore`` writes through ``asyncio.to_thread``), and
  a commit attempted afterwards fails with "cannot schedule new futures after
  shutdown". Threading hooks run in reverse registration order, so ours, which
  is registered after ``concurrent.futures.thread`` is imported, runs first.
* **SIGTERM** (what SLURM, Kubernetes and ``kill`` send): a handler installed at
  the first writable open flushes every writer and then does what the handler
  it replaced would have done (by default: terminate with SIGTERM).
* **Finalisers**: a writer collected without ``close()`` is closed by its
  ``__del__``; where the collection interrupted Zarr's or this package's own I/O
  on the same thread (a garbage collection inside a commit's wait, which holds
  the locks of the futures the commit needs), the close is handed to a closer
  thread instead of waiting on itself (:func:`close_from_finalizer`).
* **Critical sections**: a signal that arrives while the main thread is inside a
  storage write is handled when the write is complete, so a flush never sees a
  half-applied write. ``SIGINT`` keeps raising ``KeyboardInterrupt``, only
  deferred to the end of the write in progress.

Set ``TORCHRL_ROBOTMEM_SIGNALS=0`` to leave the process's signal handlers alone
(the exit hook is always installed).
"""
from __future__ import annotations

import atexit
import concurrent.futures
import concurrent.futures.thread  # noqa: F401  (see the module docstring: hook order)
import os
import queue
import signal
import sys
import threading
import weakref
from typing import Any

__all__ = ["register_writer", "critical", "close_from_finalizer", "flush_all_writers"]

_WRITERS: weakref.WeakSet = weakref.WeakSet()
_installed = False
_lock = threading.Lock()
_main_ident = threading.main_thread().ident
_depth = 0  # main-thread nesting of critical sections
_pending: list[tuple[int, Any]] = []  # signals that arrived inside a critical section
_previous: dict[int, Any] = {}  # handlers we replaced


_closing: queue.SimpleQueue = queue.SimpleQueue()  # writers a finaliser handed over (put() is safe there)
_closer: threading.Thread | None = None


def _forget_after_fork() -> None:
    """In a forked child: no writer is the child's own, and no lock or signal state is shared with the parent."""
    global _WRITERS, _lock, _depth, _closing, _closer
    _WRITERS = weakref.WeakSet()
    _lock = threading.Lock()  # may have been held by another thread at the fork
    _depth = 0
    _pending.clear()
    _closing, _closer = queue.SimpleQueue(), None


os.register_at_fork(after_in_child=_forget_after_fork)


def register_writer(storage: Any) -> None:
    """Tracks a writable storage; installs the exit hook and signal handlers once."""
    global _installed
    _WRITERS.add(storage)
    with _lock:
        if _installed:
            return
        _installed = True
    try:
        threading._register_atexit(_close_all_at_exit)  # type: ignore[attr-defined]
    except (AttributeError, RuntimeError):  # no such hook, or already shutting down
        atexit.register(_close_all_at_exit)
    if os.environ.get("TORCHRL_ROBOTMEM_SIGNALS", "1") != "0":
        _install_signal_handlers()


def flush_all_writers() -> list[tuple[str, BaseException]]:
    """Flushes every live writable storage of this process; returns the failures."""
    failures = []
    for storage in list(_WRITERS):
        try:
            storage.flush()
        except BaseException as err:  # noqa: BLE001 - reported, the others still flush
            failures.append((str(getattr(storage, "path", storage)), err))
    return failures


# -- finalisers ---------------------------------------------------------------------------

_IO_MODULES = ("zarr.", "numcodecs.", "concurrent.futures", "asyncio.", "torchrl_robotmem.storage.")


def close_from_finalizer(storage: Any, frame: Any) -> None:
    """Closes ``storage`` for its ``__del__``; ``frame``: the code the collection interrupted.

    Inline, as an explicit ``close()`` would, unless that thread is inside Zarr's or this package's storage
    I/O: a collection can run inside a commit's wait (``concurrent.futures.wait`` holds the locks of the
    futures Zarr's event loop must complete), where a close that commits would wait on itself for ever.
    There the close goes to a closer thread, which runs it once this thread has moved on.
    """
    while frame is not None:
        if frame.f_globals.get("__name__", "").startswith(_IO_MODULES):
            _closing.put(storage)  # SimpleQueue.put: safe in a finaliser (it takes no lock a thread may hold)
            _start_closer()
            return
        frame = frame.f_back
    storage.close()


def _start_closer() -> None:
    global _closer
    if _closer is None or not _closer.is_alive():
        _closer = threading.Thread(target=_close_handed_over, name="robotmem-closer", daemon=True)
        _closer.start()


def _close_handed_over() -> None:
    while True:
        storage = _closing.get()
        if storage is None:
            return
        try:
            storage.close()
        except BaseException as err:  # noqa: BLE001 - never hide a lost commit
            _warn(f"could not close {getattr(storage, 'path', storage)!r}: {type(err).__name__}: {err}")
        del storage


def _finish_handed_over() -> None:
    """At exit: the closer thread closes what it was handed, then whatever it did not take is closed here."""
    closer = _closer
    if closer is not None and closer.is_alive():
        _closing.put(None)
        closer.join()
    while True:
        try:
            storage = _closing.get_nowait()
        except queue.Empty:
            return
        if storage is not None:
            try:
                storage.close()
            except BaseException as err:  # noqa: BLE001 - never hide a lost commit
                _warn(f"could not close {getattr(storage, 'path', storage)!r} at exit: {type(err).__name__}: {err}")


# CPython 3.12.0 to 3.12.2 start no thread once interpreter exit has begun, not even in the threading exit hook
# that flushes the writers (gh-113964, fixed in 3.12.3): the last commits are made without new threads.
_NO_NEW_THREADS_AT_EXIT = (3, 12, 0) <= sys.version_info[:3] < (3, 12, 3)


class _InlineExecutor(concurrent.futures.ThreadPoolExecutor):
    """Runs each call in the thread that submits it: an executor that never starts a thread."""

    def submit(self, fn, /, *args, **kwargs):
        future = concurrent.futures.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as err:  # noqa: BLE001 - handed to the awaiting coroutine
            future.set_exception(err)
        return future


def _zarr_io_without_new_threads() -> None:
    """Zarr's event loop runs its blocking file I/O itself from now on, not in a thread pool that would grow."""
    import asyncio

    from zarr.core.sync import sync

    async def swap() -> None:
        asyncio.get_running_loop().set_default_executor(_InlineExecutor(max_workers=1))

    try:
        sync(swap())
    except Exception as err:  # noqa: BLE001 - the commits below report what they cannot write
        _warn(f"could not keep Zarr's I/O in its event loop at exit: {type(err).__name__}: {err}")


def _close_all_at_exit() -> None:
    if _NO_NEW_THREADS_AT_EXIT and len(_WRITERS):
        _zarr_io_without_new_threads()
    _finish_handed_over()
    for storage in list(_WRITERS):
        try:
            storage.close()
        except BaseException as err:  # noqa: BLE001 - never hide a lost commit
            _warn(f"could not flush {getattr(storage, 'path', storage)!r} at exit: "
                  f"{type(err).__name__}: {err}")


def _warn(msg: str) -> None:
    try:
        sys.stderr.write(f"torchrl_robotmem: {msg}\n")
        sys.stderr.flush()
    except Exception:  # noqa: BLE001 - stderr may be gone at exit
        pass


# -- signals --------------------------------------------------------------------


def _install_signal_handlers() -> None:
    if threading.get_ident() != _main_ident:
        return  # signal handlers can only be set from the main thread
    try:
        prev = signal.getsignal(signal.SIGTERM)
        if prev is not _on_signal:
            _previous[signal.SIGTERM] = prev
            signal.signal(signal.SIGTERM, _on_signal)
        prev = signal.getsignal(signal.SIGINT)
        if prev is signal.default_int_handler:  # only the default: a user's handler is theirs
            _previous[signal.SIGINT] = prev
            signal.signal(signal.SIGINT, _on_signal)
    except (ValueError, OSError):  # e.g. an embedded interpreter
        pass


def _on_signal(signum: int, frame: Any) -> None:
    if _depth > 0:  # the main thread is inside a storage write: finish it first
        _pending.append((signum, frame))
        return
    _handle(signum, frame)


def _handle(signum: int, frame: Any) -> None:
    prev = _previous.get(signum, signal.SIG_DFL)
    if signum == signal.SIGINT:
        # Ctrl-C: the normal exit path (the exit hook) flushes; a caught
        # KeyboardInterrupt keeps the process and its writers alive.
        if callable(prev):
            prev(signum, frame)
        return
    for path, err in flush_all_writers():
        _warn(f"could not flush {path!r} on signal {signum}: {type(err).__name__}: {err}")
    if callable(prev):
        prev(signum, frame)
    elif prev == signal.SIG_IGN:
        return
    else:  # SIG_DFL (or None: set outside Python): terminate as the signal would have
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)


class _Critical:
    """``with critical():`` defers signal handling in the main thread to the block's end."""

    __slots__ = ()

    def __enter__(self) -> None:
        global _depth
        if threading.get_ident() == _main_ident:
            _depth += 1

    def __exit__(self, *exc) -> None:
        global _depth
        if threading.get_ident() != _main_ident:
            return
        _depth -= 1
        if _depth == 0 and _pending:
            pending = list(_pending)
            _pending.clear()
            for signum, frame in pending:
                _handle(signum, frame)


_CRITICAL = _Critical()


def critical() -> _Critical:
    return _CRITICAL
