"""The store handle: paths and URLs, the writer lock, codecs, dtypes and key paths.

The one place that turns what a user passes (a directory, ``file://``, an fsspec
URL, a ``*.zip``, a Zarr ``Store``) into a Zarr store and a writer lock (``flock``
for directories, a lease object for ``s3://``), and the one place that
knows how TensorDict keys and torch dtypes map to Zarr arrays. Nothing here
knows about TorchRL.
"""
from __future__ import annotations

import fcntl
import json
import os
import re
import stat
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import zarr
from zarr.codecs import BloscCodec, Crc32cCodec, ZstdCodec
from zarr.core.sync import sync

from .contained import ContainedStore, open_regular
from .errors import ChainedLocalPathError, IntegrityError, LinkError, Problem
from .format import FORMAT_MARKER, FORMAT_VERSION  # noqa: F401 - re-exported: the format lives in .format

_TORCH2NP = {
    torch.float16: np.float16,
    torch.float32: np.float32,
    torch.float64: np.float64,
    torch.int8: np.int8,
    torch.int16: np.int16,
    torch.int32: np.int32,
    torch.int64: np.int64,
    torch.uint8: np.uint8,
    torch.bool: np.bool_,
}
_NAME2TORCH = {str(t).replace("torch.", ""): t for t in _TORCH2NP}


def torch_dtype_name(dtype: torch.dtype) -> str:
    if dtype not in _TORCH2NP:
        raise TypeError(
            f"dtype {dtype} cannot be stored in a ZarrStorage; supported dtypes are "
            f"{sorted(_NAME2TORCH)}."
        )
    return str(dtype).replace("torch.", "")


def torch_dtype(name: str) -> torch.dtype:
    try:
        return _NAME2TORCH[name]
    except KeyError:
        raise ValueError(f"Unknown dtype {name!r} recorded in the store schema.") from None


def numpy_dtype(dtype: torch.dtype) -> np.dtype:
    return np.dtype(_TORCH2NP[dtype])


# -- keys ---------------------------------------------------------------------


def key_to_path(key: str | tuple[str, ...]) -> str:
    """``("next", "observation")`` -> ``"next/observation"``."""
    parts = (key,) if isinstance(key, str) else tuple(key)
    for part in parts:
        if "/" in part or not part:
            raise ValueError(
                f"Key {key!r} cannot be stored in a ZarrStorage: key names must be "
                f"non-empty and must not contain '/'."
            )
    return "/".join(parts)


def path_to_key(path: str) -> str | tuple[str, ...]:
    parts = tuple(path.split("/"))
    return parts[0] if len(parts) == 1 else parts


# -- codecs -------------------------------------------------------------------


def make_compressors(compressor: str | None, level: int, itemsize: int, *, checksum: bool = True) -> tuple:
    """Codec pipeline (bytes-to-bytes codecs) for one array.

    ``"zstd"`` is Zarr's own codec; ``"blosc"`` is zstd behind a byte shuffle.
    On FetchPush transitions plain zstd was both smaller and faster (see
    docs/benchmarks.md). ``checksum`` appends Zarr's ``crc32c`` codec, so a
    changed chunk file fails to decode (see :mod:`.format`).
    """
    tail = (Crc32cCodec(),) if checksum else ()
    if compressor in (None, "none"):
        return tail
    if compressor == "blosc":
        return (BloscCodec(
            cname="zstd", clevel=level, shuffle="shuffle" if itemsize > 1 else "noshuffle", typesize=itemsize
        ), *tail)
    if compressor == "zstd":
        return (ZstdCodec(level=level), *tail)
    raise ValueError(f"compressor must be 'blosc', 'zstd' or None, got {compressor!r}.")


# -- stores -------------------------------------------------------------------


def is_url(path: str) -> bool:
    return "://" in path


#: an fsspec chain: a protocol name, then ``::`` (a local path may hold ``::`` in a folder name)
_CHAIN = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*::")


def normalize_path(path: str | os.PathLike | Any) -> str | Any:
    """The canonical name of a store: an absolute local path, a URL, or the Store itself.

    ``file://`` and ``local://`` URLs become local paths. Two handles on the same store get the
    same name (it keys the in-process writer registry and checkpoint pointers).
    """
    if not isinstance(path, (str, os.PathLike)):
        return path
    spath = os.fspath(path)
    if _CHAIN.match(spath):  # an fsspec chain ("simplecache::file://..."): refused where its last link is local
        chain, inner = spath.rsplit("::", 1)
        if not is_url(inner) or inner.startswith(("file://", "local://")):
            raise ChainedLocalPathError(spath, chain, str(Path(inner.split("://", 1)[-1]).expanduser().absolute()))
    for local in ("file://", "local://"):  # fsspec's names of the local filesystem: a path, walked for links
        if spath.startswith(local):
            spath = spath[len(local):]
    if is_url(spath):
        return spath
    return str(Path(spath).expanduser().absolute())


def _check_zip_store(path: str) -> None:
    """Raises ``ValueError`` unless the zip file at ``path`` is empty or holds a Zarr store (a ``zarr.json``)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except zipfile.BadZipFile:
        raise ValueError(f"{path!r} is not a zip file: refusing to write into it. Name a new '*.zip' path "
                         f"or a Zarr zip store.") from None
    if names and "zarr.json" not in names:
        raise ValueError(f"{path!r} is a zip file that holds no Zarr store (no zarr.json among its "
                         f"{len(names)} members): refusing to write into it. Name a new '*.zip' path.")


def store_exists(path: str | os.PathLike | Any) -> bool:
    """Whether ``path`` holds a Zarr group (without creating anything)."""
    name = normalize_path(path)
    if not isinstance(name, str) or is_url(name):
        try:
            open_group(open_store(name, read_only=True, storage_options=None)[0], read_only=True)
            return True
        except Exception:  # noqa: BLE001 - any failure means "no store here"
            return False
    if name.endswith(".zip"):
        return os.path.exists(name)
    return os.path.exists(os.path.join(name, "zarr.json"))


def fresh_listings(storage_options: dict | None) -> dict:
    """fsspec options for a store URL: no directory listing is reused, no filesystem instance shared.

    fsspec caches one filesystem object per set of options and, in it, every
    directory listing it made. A listing cached by one handle (a reader's
    open-time chunk check) would tell another handle in the same process, or
    the same reader after a ``refresh()``, that chunk files written since do
    not exist: s3fs then reads such a chunk as missing, and Zarr serves the
    fill value (zeros). Options the user passes win.
    """
    return {"use_listings_cache": False, "skip_instance_cache": True, **(storage_options or {})}


def open_store(path: str | os.PathLike | Any, *, read_only: bool, storage_options: dict | None,
               chunk_links: bool = True):
    """Returns ``(store_or_path, local_dir)``.

    ``local_dir`` is the directory of a local store (used for the writer lock),
    else ``None``. ``chunk_links=False``: the columns' chunk folders are not walked for links here (an
    open that reads them walks them first: ``refuse_links(local_dir, path, chunks=None)``; a writer's
    writes go through :class:`.contained.ContainedStore`, which looks at each folder it writes into).
    """
    spath = normalize_path(path)
    if not isinstance(spath, str):
        return spath, None  # a zarr Store instance
    if spath.endswith(".zip") and not is_url(spath):
        from zarr.storage import ZipStore

        if read_only and not os.path.exists(spath):
            raise FileNotFoundError(f"No Zarr zip store at {spath!r}.")
        if not read_only and os.path.exists(spath):
            _check_zip_store(spath)
        # opened here (Store.open), not lazily by the first open_group: integrity checks read keys first
        return sync(ZipStore.open(spath, mode="r" if read_only else "a")), None
    if is_url(spath):
        from zarr.storage import FsspecStore

        return FsspecStore.from_url(spath, storage_options=fresh_listings(storage_options), read_only=read_only), None
    p = Path(os.path.realpath(spath))  # the root the user named is followed, once; no link below it is
    if p.exists() and not p.is_dir():
        raise ValueError(
            f"{spath!r} is a file, not a Zarr store. Pass a directory path, a "
            f"'*.zip' path or a store URL such as 'memory://name'."
        )
    if read_only and not (p / "zarr.json").exists():
        raise FileNotFoundError(f"No Zarr store at {spath!r} (no zarr.json found).")
    if not read_only:
        if p.exists() and any(p.iterdir()) and not (p / "zarr.json").exists():
            raise ValueError(
                f"{spath!r} exists, is not empty and is not a Zarr store. Refusing to "
                f"write into it: pass a new or empty directory, or an existing store."
            )
        p.mkdir(parents=True, exist_ok=True)
    refuse_links(p, spath, chunks=chunk_links)
    if read_only:
        from zarr.storage import LocalStore

        return LocalStore(str(p), read_only=True), p
    return ContainedStore(str(p)), p  # no write goes through a link in a folder the open did not walk


def open_group(store, *, read_only: bool) -> zarr.Group | None:
    """The store's root group; ``None`` for a writable store with no group yet.

    A new store stays without ``zarr.json`` until :func:`create_group` writes the group and its commit
    record in one write: a reader never sees a group without its record.
    """
    try:
        if not read_only:
            try:
                return zarr.open_group(store, mode="r+", zarr_format=3)
            except (FileNotFoundError, zarr.errors.GroupNotFoundError):
                return None
        return zarr.open_group(store, mode="r", zarr_format=3)
    except (FileNotFoundError, zarr.errors.GroupNotFoundError) as err:
        raise FileNotFoundError(f"No Zarr store found at {store}: {err}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:  # a damaged commit record, not a foreign store
        problem = Problem("metadata", f"group metadata unreadable ({err})", key="zarr.json")
        raise IntegrityError(str(getattr(store, "root", store)), [problem], read_only=read_only) from None
    except (ValueError, zarr.errors.NodeTypeValidationError) as err:
        raise ValueError(f"{store} is not a Zarr v3 group: {err}") from None


def create_group(store, attributes: dict) -> zarr.Group:
    """A new root group with ``attributes``: one ``zarr.json`` write, atomic on a local store."""
    return zarr.create_group(store, attributes=attributes, zarr_format=3)


class WriterLock:
    """An exclusive ``flock`` on the store's directory.

    Two writers on one store would interleave chunks; the OS releases the lock
    when the holder dies, so a crashed writer never blocks the next run. The
    lock is taken on the directory itself so that no foreign file appears in
    the Zarr hierarchy.

    The writer's commit worker shares the lock (it may write the store). A
    worker outlives its writer only while it cannot run (``SIGSTOP``: it
    otherwise exits within 10 ms of its writer's death), and would then keep the
    store locked forever. So a refused lock is diagnosed from ``/proc``: the
    error names every other process that has the directory open, and if each
    is a commit worker (its command line runs ``_commit_worker.py`` and records
    the pid of the writer that started it) whose writer is dead (it was
    re-parented), those orphans are killed and the lock taken over.
    """

    def __init__(self, directory: Path):
        self.path = directory
        self._fd = os.open(directory, os.O_RDONLY)
        # a writer that has just died may leave its commit worker alive for a few ms
        # (it shares the lock, see storage/_commit_worker.py): wait a little first
        deadline = time.monotonic() + float(os.environ.get("TORCHRL_ROBOTMEM_LOCK_WAIT", 2.0))
        took_over = False
        while True:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                if time.monotonic() < deadline:
                    time.sleep(0.02)
                    continue
            holders = lock_holders(directory)
            if holders and not took_over and all(h.orphan_worker for h in holders):
                # only commit workers of dead writers hold it: nothing can write through them any more
                _kill_and_wait([h.pid for h in holders])
                took_over = True
                deadline = time.monotonic() + 5.0
                continue
            os.close(self._fd)
            self._fd = None
            who = "; ".join(str(h) for h in holders) if holders else (
                "no other process visible to this user has it open: another ZarrStorage in this process, "
                "or a process of another user")
            raise RuntimeError(
                f"Another process (or another ZarrStorage in this process) is writing to "
                f"{directory} ({who}). A store has one writer at a time; open it with "
                f"read_only=True to read while it is being written."
            )

    @property
    def fd(self) -> int | None:
        """The locked directory's file descriptor (``None`` once released): a commit worker gets a copy."""
        return self._fd

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def check(self) -> None:
        """Nothing to check: the OS holds a ``flock`` for as long as its holder lives."""


class LockHolder:
    """A process that has a store directory open (see :func:`lock_holders`)."""

    def __init__(self, pid: int, cmdline: list[str], writer_pid: int | None, parent_pid: int | None) -> None:
        self.pid = pid
        self.cmdline = cmdline
        self.writer_pid = writer_pid  # for a commit worker: the writer that started it
        self.parent_pid = parent_pid

    @property
    def orphan_worker(self) -> bool:
        """A commit worker whose writer is dead: it was re-parented, and its writer's pid has no process."""
        if self.writer_pid is None or self.parent_pid in (None, self.writer_pid):
            return False
        return _process_state(self.writer_pid) in (None, "Z", "X")  # a live process there (reused pid): refuse

    def __str__(self) -> str:
        if self.writer_pid is None:
            return f"pid {self.pid}: {' '.join(self.cmdline)[:120] or '?'}"
        state = "whose writer is dead" if self.orphan_worker else "alive"
        return f"pid {self.pid}: the commit worker of writer pid {self.writer_pid} ({state})"


def lock_holders(directory: Path) -> list[LockHolder]:
    """Every other process that has ``directory`` open, read from ``/proc`` (Linux; else empty).

    Processes of other users are not visible and not listed.
    """
    try:
        target = os.stat(directory)
        pids = [int(name) for name in os.listdir("/proc") if name.isdigit()]
    except OSError:
        return []
    me, out = os.getpid(), []
    for pid in pids:
        if pid == me:
            continue
        fd_dir = f"/proc/{pid}/fd"
        try:
            fds = os.listdir(fd_dir)
        except OSError:
            continue
        for fd in fds:
            try:
                st = os.stat(f"{fd_dir}/{fd}")
            except OSError:
                continue
            if (st.st_dev, st.st_ino) == (target.st_dev, target.st_ino):
                out.append(_describe_process(pid))
                break
    return out


def _describe_process(pid: int) -> LockHolder:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            cmdline = [a.decode(errors="replace") for a in f.read().split(b"\0") if a]
        with open(f"/proc/{pid}/stat") as f:
            parent = int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return LockHolder(pid, [], None, None)
    writer = None
    for i, arg in enumerate(cmdline):
        # python -s .../storage/_commit_worker.py FD WRITER_PID
        if arg.endswith("_commit_worker.py") and len(cmdline) == i + 3 and cmdline[i + 2].isdigit():
            writer = int(cmdline[i + 2])
    return LockHolder(pid, cmdline, writer, parent)


def _process_state(pid: int) -> str | None:
    """The state letter of a process (``R``, ``S``, ``T``, ``Z``...), ``None`` if there is none."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None


def _kill_and_wait(pids: list[int], timeout: float = 5.0) -> None:
    import signal

    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)  # also ends a stopped process
        except OSError:
            pass
    deadline = time.monotonic() + timeout
    for pid in pids:
        # exited once a zombie (its files are closed) or gone
        while _process_state(pid) not in (None, "Z", "X") and time.monotonic() < deadline:
            time.sleep(0.01)


# -- the writer lock of object stores -----------------------------------------------

_LEASE_TTL_ENV = "TORCHRL_ROBOTMEM_LEASE_TTL"
_LEASE_TTL = 30.0  # seconds a lease outlives its last renewal


class S3Lease:
    """The writer lock of an ``s3://`` store: a lease object beside the store.

    An object store has no ``flock`` and nothing releases a lock when its holder
    dies, so the writer holds a *lease*: the object ``<store key>.writer-lease``
    (JSON: owner id, host, pid, ttl), created with a conditional put
    (``If-None-Match: *``: only one creator succeeds) and renewed every
    ``ttl / 3`` seconds by a daemon thread with ``If-Match: <its ETag>``. A lease
    not renewed for ``ttl`` seconds (its holder was killed, or lost the network)
    is stale: the next writer takes it over with ``If-Match: <stale ETag>``, so
    of two writers racing for a stale lease exactly one wins. Age is measured on
    the server's clock (the object's ``Last-Modified`` against the ``Date`` of the
    same response), so client clocks do not matter. ``close()`` deletes it.

    A lease is a lock, not a fence: a writer paused for longer than ``ttl`` (a
    suspended laptop, ``SIGSTOP``) loses it, learns so at its next write (an
    error), but a commit already in flight still lands. ``ttl`` defaults to 30 s;
    set ``TORCHRL_ROBOTMEM_LEASE_TTL`` (seconds) to change it.

    Args:
        url (str): the store URL (``s3://bucket/key``).
        storage_options (dict, optional): the fsspec options of the store.
        ttl (float, optional): seconds the lease outlives its last renewal.
    """

    def __init__(self, url: str, storage_options: dict | None = None, ttl: float | None = None):
        import json
        import socket
        import threading
        import uuid

        import fsspec

        self._json = json
        self.ttl = float(ttl if ttl is not None else os.environ.get(_LEASE_TTL_ENV, _LEASE_TTL))
        if self.ttl <= 0:
            raise ValueError(f"The lease ttl must be > 0 seconds ({_LEASE_TTL_ENV}), got {self.ttl}.")
        self._fs, path = fsspec.url_to_fs(url, **fresh_listings(storage_options))
        self.bucket, key, _ = self._fs.split_path(path)
        self.key = f"{key.rstrip('/')}.writer-lease" if key else "torchrl_robotmem.writer-lease"
        self.url = f"s3://{self.bucket}/{self.key}"
        self.lost: str | None = None
        self._body = {"owner": uuid.uuid4().hex, "host": socket.gethostname(), "pid": os.getpid(),
                      "ttl": self.ttl}
        self.etag = self._acquire(url)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._renew_loop, name=f"ZarrStorage-lease({url})", daemon=True)
        self._thread.start()

    def _put(self, **condition) -> str:
        body = self._json.dumps(self._body).encode()
        return self._fs.call_s3("put_object", Bucket=self.bucket, Key=self.key, Body=body, **condition)["ETag"]

    def _acquire(self, url: str) -> str:
        try:
            return self._put(IfNoneMatch="*")
        except OSError as err:
            if not _precondition_failed(err):
                raise
        try:
            head = self._fs.call_s3("head_object", Bucket=self.bucket, Key=self.key)
        except FileNotFoundError:  # released meanwhile: try once more
            return self._put(IfNoneMatch="*")
        holder = self._read_holder()
        age = _server_age(head)
        ttl = float(holder.get("ttl", _LEASE_TTL)) if isinstance(holder, dict) else _LEASE_TTL
        if age is not None and age > ttl:
            try:
                return self._put(IfMatch=head["ETag"])  # take the stale lease over; one racer wins
            except OSError as err:
                if not _precondition_failed(err):
                    raise
        who = f"host {holder.get('host')!r} pid {holder.get('pid')}" if isinstance(holder, dict) else "another writer"
        renewed = f"renewed {age:.0f} s ago" if age is not None else "age unknown"
        raise RuntimeError(
            f"Another writer ({who}) holds the writer lease of {url} ({renewed}; a "
            f"lease expires {ttl:.0f} s after its last renewal). A store has one writer at a time; "
            f"open it with read_only=True to read while it is being written. If that writer is "
            f"dead, open again after the lease expires, or delete {self.url}."
        )

    def _read_holder(self) -> dict:
        try:
            holder = self._json.loads(self._fs.cat_file(self.url).decode() or "{}")
            return holder if isinstance(holder, dict) else {}
        except Exception:  # noqa: BLE001 - a foreign or vanished lease: judged by its age only
            return {}

    def _renew_loop(self) -> None:
        while not self._stop.wait(self.ttl / 3):
            try:
                self.etag = self._put(IfMatch=self.etag)
            except OSError as err:
                if _precondition_failed(err) or isinstance(err, FileNotFoundError):
                    self.lost = (
                        f"the writer lease {self.url} was taken over by another writer after this "
                        f"one did not renew it for {self.ttl:.0f} s"
                    )
                    return
            except Exception:  # noqa: BLE001 - a network blip: the next renewal retries
                pass

    def check(self) -> None:
        """Raises if this writer lost its lease (another writer may be writing the store)."""
        if self.lost is not None:
            raise RuntimeError(
                f"This ZarrStorage lost the writer lock of its store: {self.lost}. Rows written "
                f"since its last commit may not be durable; open the store again."
            )

    def release(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=5)
        if self.lost is not None:
            return
        try:
            self._fs.call_s3("delete_object", Bucket=self.bucket, Key=self.key, IfMatch=self.etag)
        except Exception:  # noqa: BLE001 - not ours any more, or gone: nothing to release
            pass


def _precondition_failed(err: BaseException) -> bool:
    cause = getattr(err, "__cause__", None)
    response = getattr(cause, "response", None) or {}
    code = str(response.get("Error", {}).get("Code", ""))
    status = response.get("ResponseMetadata", {}).get("HTTPStatusCode")
    return code in ("PreconditionFailed", "ConditionalRequestConflict") or status in (409, 412)


def _server_age(head: dict) -> float | None:
    """Seconds since the object was last written, on the server's clock."""
    from email.utils import parsedate_to_datetime

    date = head.get("ResponseMetadata", {}).get("HTTPHeaders", {}).get("date")
    modified = head.get("LastModified")
    if date is None or modified is None:
        return None
    return (parsedate_to_datetime(date) - modified).total_seconds()


def url_writer_lock(url: str, storage_options: dict | None) -> S3Lease | None:
    """The writer lock of a URL store: a lease for ``s3://``, none (with a warning) elsewhere.

    ``memory://`` stores live in one process (the in-process writer handover
    covers them). Other object stores get no lock: one writer per URL is then
    the user's responsibility, and a warning says so.
    """
    scheme = url.split("://", 1)[0].lower()
    if scheme == "memory":
        return None
    if scheme in ("s3", "s3a"):
        return S3Lease(url, storage_options)
    import warnings

    warnings.warn(
        f"No writer lock for {scheme}:// stores: make sure only one process writes to {url} "
        f"(two writers would interleave chunks and commit records). s3:// stores hold a lease.",
        stacklevel=3,
    )
    return None


def links_below(directory: str | os.PathLike, *, chunks: bool | None = True) -> list[tuple[str, str]]:
    """``[(key, target)]`` of every symbolic link below ``directory`` (the directory itself is not looked at).

    One ``os.scandir`` walk that follows no link; ``is_symlink`` comes from the directory entry itself,
    so the walk costs a listing per directory, no ``stat`` per file. Hard links are not links here: a
    hard-linked file is a file of the store like any other (``ZarrCheckpointer`` makes them), and no
    write goes into an existing file (Zarr and the journal write a new file and rename it into place),
    so a write never reaches the file's other names.

    ``chunks``: ``True`` walks everything; ``False`` skips the folders of the columns' chunks (``c/<c>/``, in a
    store created before 2026-12; not those of the ``_``-named folders: the journal, a component's group), which
    an open served by a sealed row file never reads (:mod:`.rowfile`); ``None`` walks only the columns' chunks
    (checked before they are read): those folders and the chunk files (``c.<c>.0``) of a store created since,
    which lie in their column's folder. Every walk lists the columns' folders and their ``c/`` folders, so a
    ``False`` walk reports a link or special file at a chunk's name too, and walks whatever in a ``c/`` folder
    is no chunk (a group named ``c`` whose ``zarr.json`` is gone); a link in place of a whole ``c/`` folder is
    reported by every walk.

    Example:
        >>> import os, tempfile
        >>> d = tempfile.mkdtemp()
        >>> os.makedirs(d + "/obs/c"); os.symlink("/etc/hostname", d + "/obs/c/0")
        >>> with open(d + "/obs/zarr.json", "w") as f:
        ...     _ = f.write('{"node_type": "array"}')  # obs is an array: obs/c holds its chunks
        >>> links_below(d), links_below(d, chunks=False), links_below(d, chunks=None)
        ([('obs/c/0', '/etc/hostname')], [('obs/c/0', '/etc/hostname')], [('obs/c/0', '/etc/hostname')])
        >>> os.remove(d + "/obs/c/0"); os.makedirs(d + "/obs/c/0"); os.symlink("/etc/hostname", d + "/obs/c/0/0")
        >>> links_below(d), links_below(d, chunks=False), links_below(d, chunks=None)
        ([('obs/c/0/0', '/etc/hostname')], [], [('obs/c/0/0', '/etc/hostname')])
        >>> os.remove(d + "/obs/c/0/0")
        >>> os.makedirs(d + "/act"); os.symlink("/etc/hostname", d + "/act/c.0.0")
        >>> links_below(d, chunks=False), links_below(d, chunks=None)[0]
        ([('act/c.0.0', '/etc/hostname')], ('act/c.0.0', '/etc/hostname'))
    """
    root = os.fspath(directory)
    # (folder, what it is: "" a node's or another folder, "c" a column's chunk folder, "chunk" a chunk's folder,
    #  in a "_" folder)
    out, stack = [], [(root, "", False)]
    while stack:
        folder, kind, own = stack.pop()
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):
            continue
        for entry in entries:
            inside = own or (folder == root and entry.name.startswith("_"))  # the journal, a component's group
            is_dir = entry.is_dir(follow_symlinks=False)
            if kind == "chunk":
                chunk = True
            elif kind == "c":  # c/<c>: a chunk's folder, or a 1-D column's chunk file; any other name is no chunk
                chunk = entry.name.isascii() and entry.name.isdigit()
            else:  # c.<c>.0: a chunk file in its column's folder; "c": a chunk folder a link replaced
                chunk = (not inside and folder != root and not is_dir
                         and (entry.name.startswith("c.") or entry.name == "c" and entry.is_symlink()))
            if entry.is_symlink():
                if chunks is not None or chunk:
                    try:
                        target = os.readlink(entry.path)
                    except OSError:
                        target = "?"
                    out.append((os.path.relpath(entry.path, root).replace(os.sep, "/"), target))
            elif not is_dir and not entry.is_file(follow_symlinks=False):
                # a named pipe, a socket, a device: a read of one blocks for ever or reads what is not a file
                if chunks is not None or chunk:
                    out.append((os.path.relpath(entry.path, root).replace(os.sep, "/"), special_kind(entry.path)))
            elif is_dir and chunk:  # a chunk's folder: what a sealed open never reads
                if chunks is not False:
                    stack.append((entry.path, "chunk", inside))
            elif is_dir and kind == "" and not inside and folder != root and entry.name == "c" \
                    and (chunks is None or is_array_folder(folder)):
                # a column's chunk folder: "c" in an array's folder (its zarr.json says so: a group may hold a
                # node named "c", or one that lost its zarr.json, and nodes named by digits in it); listed by
                # every walk, what is not a chunk's name in it walked as any folder. A walk before the chunks
                # are read takes any folder named "c" for one (what is below it is reported: never too little)
                stack.append((entry.path, "chunk" if chunks is None else "c", inside))
            elif is_dir and not (inside and chunks is None):
                stack.append((entry.path, "", inside))
    return sorted(out)


def is_array_folder(folder: str) -> bool:
    """Whether ``folder/zarr.json`` is a regular file describing a Zarr array (read without following a link or
    blocking on a special file, 1 MiB at most; anything else, or unreadable: ``False``).

    Example:
        >>> import tempfile, zarr
        >>> d = tempfile.mkdtemp(); _ = zarr.create_array(d + "/a", shape=(2,), dtype="f4")
        >>> is_array_folder(d + "/a"), is_array_folder(d)
        (True, False)
    """
    meta = os.path.join(folder, "zarr.json")
    try:
        if not stat.S_ISREG(os.lstat(meta).st_mode):
            return False
        with os.fdopen(open_regular(meta), "rb") as f:
            doc = json.loads(f.read(1 << 20) or b"")
    except (OSError, ValueError, TypeError, RecursionError):
        return False
    return isinstance(doc, dict) and doc.get("node_type") == "array"


def special_kind(path: str) -> str:
    """``"<a named pipe>"`` / ``"<a socket>"`` / ``"<a device>"``: how :func:`links_below` names a special file.

    Example:
        >>> import os, tempfile
        >>> d = tempfile.mkdtemp(); os.mkfifo(d + "/p")
        >>> special_kind(d + "/p")
        '<a named pipe>'
    """
    mode = os.lstat(path).st_mode
    kind = "a named pipe" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device"
    return f"<{kind}>"


def refuse_links(directory: str | os.PathLike, name: Any, *, chunks: bool | None = True) -> None:
    """Raises :class:`LinkError` naming them if a symbolic link lies below the local store ``directory``.

    Every reader and writer of a local store opens it through here (``open_store``, and ``verify`` /
    ``repair`` / ``copy``), so no chunk, record or journal is read through a link that may leave the
    store, and no commit writes through one. ``chunks``: as :func:`links_below` takes it (a reader walks the
    columns' chunk folders only when it reads them).
    """
    links = links_below(directory, chunks=chunks)
    if links:
        raise LinkError(name, links)


def remove_partial_files(directory: Path, attrs: dict) -> int:
    """Deletes the ``*.partial`` files of writes a killed writer left, where a writer can have left them.

    Zarr writes each file to ``NAME.<uuid>.partial`` beside it and renames it into place. A killed writer's
    partial files lie in the folders it was writing: the metadata folders (the record, each array's
    ``zarr.json``), the ``_``-named groups (the journal, the priorities), and the chunk folders of the rows
    past the committed length or of the chunks a pending journal lists. Those are listed here; the other
    chunk folders are not (that would be a listing per chunk at every open): a partial file elsewhere is
    never read as a chunk (only wasted space) and ``robotmem repair`` removes it. The chunk files of a column
    created since 2026-12 (``c.<c>.0``) lie in its own folder, which is listed whole.

    Only called by the lock holder at its open, before its first write: no partial file of a live write
    exists then. Returns how many were deleted.
    """
    from .format import dims

    root = os.fspath(directory)
    schema = attrs.get("schema") or {}
    rows = int(attrs.get("chunk_rows") or 0)
    first = dims(attrs)[1] // rows if schema and rows else 0
    journal = {int(c) for c in (attrs.get("journal") or {}).get("chunks", ())}
    chunk_folders = {os.path.join(root, *path.split("/"), "c") for path in schema}
    removed, stack = 0, [root]
    while stack:
        folder = stack.pop()
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        in_chunks = folder in chunk_folders
        for entry in entries:
            if entry.is_dir(follow_symlinks=False):
                # in a column's chunk folder, only the folders of chunks past the length or journalled
                if not in_chunks or (entry.name.isdigit() and (int(entry.name) >= first or int(entry.name) in journal)):
                    stack.append(entry.path)
            elif entry.name.endswith(".partial"):
                try:
                    os.unlink(entry.path)
                    removed += 1
                except OSError:
                    pass
    return removed


def store_size_bytes(directory: Path | None) -> int | None:
    if directory is None:
        return None
    total = 0
    for root, _, files in os.walk(directory):
        for f in files:
            try:
                total += os.path.getsize(os.path.join(root, f))
            except OSError:
                pass
    return total
