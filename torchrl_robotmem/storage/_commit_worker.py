"""The commit worker: a child process that writes committed chunks to Zarr.

Why a process: writing a chunk through Zarr v3 costs mostly Python (its event
loop, codec pipeline and store calls: ~70% of a commit holds the GIL), and a
background *thread* doing it competes with the training loop for the GIL. In
a child process the foreground only pays for one ``memcpy`` of the chunk and a
pipe write (which releases the GIL).

This file runs as a script (``python _commit_worker.py``) and imports nothing
from the package: only the standard library, numpy and zarr, and its siblings
:mod:`.contained`, :mod:`.fast_write` (the chunk writer of both commit paths) and
:mod:`.journal` (the commit protocol of both) as top-level modules (this folder is the script's ``sys.path[0]``), never the
package (which imports torch), so it starts in a fraction of a second. The parent side is :class:`CommitWorker`, used by
:class:`~torchrl_robotmem.storage.commit.CommitEngine`.

Protocol: framed messages over a Unix socket pair. A frame is an 8-byte
little-endian header length, a JSON header, then ``header["nbytes"]`` raw
bytes; file descriptors travel with a header (``socket.send_fds``). Nothing is
unpickled. Requests (``op``):

* ``open``: (re)open a store, with a copy of its writer lock's descriptor: the
  store stays locked while the worker may write to it;

* ``commit``: packed chunk snapshots (the payload) to split into arrays and
  write, optionally through the redo journal, then the attributes ``meta``;
* ``attrs``: an attribute update (every attribute write of a store whose
  commits go through the worker goes through it, so none is lost);
* ``reset``: forget the cached arrays of a store (after a resize);
* ``close``: forget a store (and close its lock descriptor).

Every request gets one reply: ``{"ok": true}`` or ``{"ok": false, "error": ...}``.
The worker ignores SIGINT and SIGTERM (its parent flushes through it when it
receives them) and exits within 10 ms of its parent's death, abandoning a
commit in hand exactly as a killed in-process writer would: chunks first,
then one atomic metadata write (or the journal) keep the store consistent, and
the lock it shares keeps a new writer out until it is gone.

The worker is an accelerator, never the only copy of anything: a reply that
does not come within :func:`reply_deadline` (a few seconds plus a per-byte
allowance), a closed channel or a dead process raise :class:`CommitWorkerGone`
after the worker is killed (``SIGKILL`` also ends a stopped process), and the
parent commits in-process from its RAM mirror instead. Its command line
records the pid of the writer that started it (``_commit_worker.py FD
WRITER_PID``): a writer lock held only by a worker whose writer is dead can be
identified and taken over (see ``WriterLock``).
"""
from __future__ import annotations

import json
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from typing import Any

_HEADER = struct.Struct("<Q")
# Seconds the parent waits for one reply: a base plus an allowance per byte of
# payload (a commit of one chunk takes milliseconds; 8 MiB/s is far below what
# compressing and writing a chunk costs even on a loaded box). A worker that
# misses it is stopped or stalled: it is killed and its commit done in-process.
WORKER_TIMEOUT_ENV = "TORCHRL_ROBOTMEM_WORKER_TIMEOUT"
_REPLY_BASE = 5.0
_REPLY_BYTES_PER_S = 8 * 2**20


def reply_deadline(nbytes: int) -> float:
    """Seconds to wait for the reply to a request carrying ``nbytes`` of payload.

    ``TORCHRL_ROBOTMEM_WORKER_TIMEOUT`` (seconds) replaces the 5 s base.
    """
    base = float(os.environ.get(WORKER_TIMEOUT_ENV, _REPLY_BASE))
    return base + nbytes / _REPLY_BYTES_PER_S


# -- framing (both sides) ------------------------------------------------------------------


def _recv_exact(sock: socket.socket, n: int) -> bytearray | None:
    out = bytearray(n)
    view = memoryview(out)
    got = 0
    while got < n:
        k = sock.recv_into(view[got:])
        if k == 0:
            return None
        got += k
    return out


def read_frame(sock: socket.socket) -> tuple[dict, bytearray, list[int]] | None:
    """One frame and the file descriptors sent with it (``socket.send_fds``)."""
    raw, fds, _flags, _addr = socket.recv_fds(sock, _HEADER.size, 4, socket.MSG_WAITALL)
    if len(raw) < _HEADER.size:
        if len(raw) == 0:
            return None
        rest = _recv_exact(sock, _HEADER.size - len(raw))
        if rest is None:
            return None
        raw = bytes(raw) + bytes(rest)
    (hlen,) = _HEADER.unpack(raw)
    header_raw = _recv_exact(sock, hlen)
    if header_raw is None:
        return None
    header = json.loads(header_raw.decode())
    nbytes = int(header.get("nbytes", 0))
    payload = _recv_exact(sock, nbytes) if nbytes else bytearray()
    if payload is None:
        return None
    return header, payload, list(fds)


def write_frame(sock: socket.socket, header: dict, payloads: list | tuple = (), fds: list | tuple = ()) -> None:
    body = json.dumps(header).encode()
    head = _HEADER.pack(len(body)) + body
    if fds:
        sent = socket.send_fds(sock, [head], list(fds))
        if sent < len(head):
            sock.sendall(head[sent:])
    else:
        sock.sendall(head)
    for p in payloads:
        view = memoryview(p)
        if view.nbytes:  # an empty array has nothing to send (and cannot be cast to bytes)
            sock.sendall(view.cast("B"))


# -- the child ---------------------------------------------------------------------------


class _Store:
    """One store the worker writes: its group and arrays, and a copy of its writer lock."""

    def __init__(self, path: str, lock_fd: int | None) -> None:
        import zarr
        from contained import ContainedStore  # this folder is the script's sys.path[0]: no package import

        self.group = zarr.open_group(ContainedStore(path), mode="r+", zarr_format=3)
        self.arrays: dict[str, Any] = {}
        self.plans: dict[str, Any] = {}  # how each array's chunks are written (fast_write.write_chunks' cache)
        # the parent's flock, shared: the store stays locked for as long as this
        # worker could still write to it, even if the parent dies first
        self.lock_fd = lock_fd

    def close(self) -> None:
        if self.lock_fd is not None:
            os.close(self.lock_fd)
            self.lock_fd = None

    def array(self, path: str):
        arr = self.arrays.get(path)
        if arr is None:
            # all-zero chunks written too: a chunk missing below len is damage (storage/integrity.py)
            arr = self.arrays[path] = self.group[path].with_config({"write_empty_chunks": True})
        return arr


def _split(payload: bytearray, header: dict) -> dict[int, dict[str, Any]]:
    """Packed chunk snapshots -> ``{chunk: {array path: contiguous values}}``."""
    import numpy as np

    row_bytes, inner = int(header["row_bytes"]), tuple(header["inner"])
    per_row = row_bytes * int(np.prod(inner, dtype=np.int64))
    buf = np.frombuffer(payload, dtype=np.uint8)
    out, pos = {}, 0
    for c, nrows in header["chunks"]:
        rows = buf[pos : pos + nrows * per_row].reshape(nrows, *inner, row_bytes)
        pos += nrows * per_row
        out[c] = {
            path: np.ascontiguousarray(rows[..., off : off + nbytes]).view(dtype).reshape(nrows, *inner, *shape)
            for path, off, nbytes, dtype, shape in header["fields"]
        }
    return out


def _write_chunks(store: _Store, payload: dict, chunk_rows: int, prefix: str = "") -> None:
    """The commit engine's chunk writer (``fast_write.write_chunks``), on this store's arrays."""
    from fast_write import write_chunks  # this folder is the script's sys.path[0]: no package import

    write_chunks(store.array, payload, chunk_rows, prefix, plans=store.plans)


def _commit(store: _Store, header: dict, payload: bytearray) -> None:
    """One request: the commit protocol (``journal.commit``, the engine's own) on the packed chunks."""
    from journal import commit  # this folder is the script's sys.path[0]: no package import

    rows = int(header["chunk_rows"] or 0)  # None before the first rows (a metadata-only commit)
    commit(store.group, store.arrays, lambda payload, prefix="": _write_chunks(store, payload, rows, prefix),
           _split(payload, header), header.get("meta"), chunk_rows=rows,
           journal=header.get("journal") if header.get("overwrite") else None)


def _watch_parent(ppid: int) -> None:
    """Exits as soon as the parent is gone: a commit it did not see finish is abandoned
    (as a killed in-process writer's would be; the store's protocol keeps it consistent)."""
    import time

    while os.getppid() == ppid:
        time.sleep(0.01)
    os._exit(0)


def _serve(fd: int, ppid: int) -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    threading.Thread(target=_watch_parent, args=(ppid,), daemon=True).start()
    import zarr

    # every chunk is written, all-zero ones too: a chunk file missing below the
    # committed length is damage (see integrity.py), never "all fill value"
    zarr.config.set({"array.write_empty_chunks": True})
    import fast_write  # noqa: F401 - imported before the worker says it is ready (this folder is sys.path[0])
    import journal  # noqa: F401
    sock = socket.socket(fileno=fd)
    sys.stdout = sys.stderr
    stores: dict[str, _Store] = {}
    write_frame(sock, {"ready": True})  # imports done: the parent may switch its commits over
    while True:
        try:
            frame = read_frame(sock)
        except OSError:  # the parent died or closed the channel with a reply unread
            frame = None
        if frame is None:
            os._exit(0)  # nothing in hand
        header, payload, fds = frame
        try:
            op, path = header["op"], header["path"]
            if op in ("open", "close"):
                old = stores.pop(path, None)
                if old is not None:
                    old.close()
                if op == "open":
                    stores[path] = _Store(path, fds[0] if fds else None)
                    fds = []
            elif op == "reset":
                if path in stores:
                    stores[path].arrays.clear()
                    stores[path].plans.clear()
            else:
                store = stores.get(path)
                if store is None:
                    raise RuntimeError(f"{path!r} was not opened in the commit worker")
                if op == "attrs":
                    store.group.update_attributes(header["update"])
                elif op == "commit":
                    _commit(store, header, payload)
                else:
                    raise ValueError(f"unknown request {op!r}")
            reply = {"ok": True}
        except BaseException as err:  # noqa: BLE001 - reported to the parent, which raises it
            reply = {"ok": False, "error": f"{type(err).__name__}: {err}"}
        for extra in fds:
            os.close(extra)
        try:
            write_frame(sock, reply)
        except OSError:
            os._exit(0)  # the parent is gone


# -- the parent side ---------------------------------------------------------------------


class CommitWorkerError(RuntimeError):
    """A request failed in the commit worker (the message carries its error)."""


class CommitWorkerGone(CommitWorkerError):
    """The worker died, stopped answering or could not start; it has been killed.

    Nothing it was asked to write can be trusted to be on disk: the caller
    writes it again in-process.
    """


def _exit_text(code: int | None) -> str:
    if code is None:
        return "still running"
    if code < 0:
        try:
            return f"exit code {code}, killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"exit code {code}"
    return f"exit code {code}"


class CommitWorker:
    """The parent's handle on one commit worker process (shared by all its stores).

    Requests are serialised by a lock: each one is sent and answered before the
    next. ``get()`` starts the worker on first use; a forked child starts its own.
    A worker that fails (see :class:`CommitWorkerGone`) is killed and marked
    ``broken``; ``get()`` then starts a new one for the stores opened later.
    """

    _instance: CommitWorker | None = None
    _instance_lock = threading.Lock()

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.pid = os.getpid()
        self._ready = False
        self.broken = False
        self.sock, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-s", os.path.abspath(__file__), str(theirs.fileno()), str(self.pid)],
                stdin=subprocess.DEVNULL, pass_fds=(theirs.fileno(),), start_new_session=True,
            )
        finally:
            theirs.close()

    @classmethod
    def get(cls) -> CommitWorker:
        with cls._instance_lock:
            w = cls._instance
            if w is None or w.pid != os.getpid() or w.broken or w.proc.poll() is not None:
                w = cls._instance = CommitWorker()
            return w

    def ready(self) -> bool:
        """Whether the worker has finished starting (never blocks).

        Until it has, stores commit in-process: a worker still importing zarr must
        not delay the first commits of a fresh process (a short-lived writer
        would otherwise lose more on a kill). Raises :class:`CommitWorkerGone`
        if it died while starting.
        """
        if self._ready:
            return True
        with self.lock:
            if self.broken:
                raise self._gone("was given up earlier")
            if not self._ready and select.select([self.sock], [], [], 0)[0]:
                self._await_ready()
        return self._ready

    def gone(self) -> bool:
        """Whether the worker process has exited (and can write nothing more)."""
        return self.proc.poll() is not None

    def discard(self) -> None:
        """Kills a worker whose channel is broken or silent; the next ``get()`` starts a new one.

        ``SIGKILL`` also ends a stopped (``SIGSTOP``) process. Waits up to 5 s
        for it to exit: only then can nothing it was writing land any more.
        """
        self.broken = True
        try:
            self.proc.kill()
            self.proc.wait(5)
        except Exception:  # noqa: BLE001 - already gone, or stuck in the kernel (gone() says which)
            pass
        try:
            self.sock.close()
        except OSError:
            pass

    def _gone(self, what: str) -> CommitWorkerGone:
        return CommitWorkerGone(f"the commit worker process (pid {self.proc.pid}) {what} "
                                f"({_exit_text(self.proc.poll())})")

    def _await_ready(self) -> None:
        try:
            self.sock.settimeout(reply_deadline(0))
            frame = read_frame(self.sock)
        except OSError:
            frame = None
        finally:
            if not self.broken:
                self.sock.settimeout(None)
        if frame is None or not frame[0].get("ready"):
            self.discard()
            raise self._gone("failed to start")
        self._ready = True

    def request(self, header: dict, payloads: list | tuple = (), fds: list | tuple = ()) -> None:
        """Sends one request and waits for its reply (at most :func:`reply_deadline` seconds).

        Raises :class:`CommitWorkerError` with the worker's own error (the
        request failed there, e.g. a full disk), or :class:`CommitWorkerGone`
        (the worker is dead, silent or its channel broken: it has been killed).
        """
        nbytes = sum(memoryview(p).nbytes for p in payloads)
        header = {**header, "nbytes": nbytes}
        with self.lock:
            if self.broken:
                raise self._gone("was given up earlier")
            if not self._ready:
                self._await_ready()
            if self.proc.poll() is not None:
                self.discard()
                raise self._gone("has exited")
            timeout = reply_deadline(nbytes)
            deadline = time.monotonic() + timeout
            try:
                # never wait long: a worker that stops answering is killed, not waited for
                self.sock.settimeout(timeout)
                write_frame(self.sock, header, payloads, fds)
                self.sock.settimeout(max(0.01, deadline - time.monotonic()))
                frame = read_frame(self.sock)
            except TimeoutError:
                self.discard()
                raise self._gone(f"did not answer within {timeout:.1f} s (stopped, or its disk stalled); "
                                 f"it was killed") from None
            except OSError as err:
                self.discard()
                raise self._gone(f"is gone ({type(err).__name__}: {err})") from None
            except BaseException:  # e.g. KeyboardInterrupt mid-frame: the stream cannot be trusted
                self.discard()
                raise
            finally:
                if not self.broken:
                    self.sock.settimeout(None)
            if frame is None:
                self.discard()
                raise self._gone("is gone")
        reply = frame[0]
        if not reply.get("ok"):
            raise CommitWorkerError(str(reply.get("error")))


if hasattr(os, "register_at_fork"):
    # a forked child never shares its parent's pipes: it starts its own worker
    os.register_at_fork(after_in_child=lambda: setattr(CommitWorker, "_instance", None))


if __name__ == "__main__":
    _serve(int(sys.argv[1]), int(sys.argv[2]))
