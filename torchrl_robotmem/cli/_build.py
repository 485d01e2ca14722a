"""Building an output atomically: what the commands that create a store or a file share.

A command that creates something (the memory of ``import``, the ``.npz`` or
dataset directory of ``export``) refuses an existing target
(:func:`check_target`), builds it in a hidden sibling ``.NAME.partial-PID``
(:func:`atomic_target`; :func:`new_store` for a new memory) and renames that
into place once it is complete: a command killed at any moment leaves nothing
at the target, only the sibling, which the next run on the same target removes
once its process is gone (:func:`remove_stale_partials`). A target that is a
store URL (``s3://...``, ``memory://...``) cannot be renamed into place and is
written directly.

A write that finds no room (a full disk, a used-up quota, the file-size limit
``ulimit -f``) or memory is one line for every command (:func:`write_failed`,
called by :func:`~torchrl_robotmem.cli.main` and ``copy``): the command, the
target, the cause and what is left at the target (nothing: the build was
removed; or the build that could not be, by name). Running the command again
once there is room rebuilds it from the start.

Example:
    >>> import os, tempfile
    >>> from torchrl_robotmem.cli._build import atomic_target
    >>> d = tempfile.mkdtemp()
    >>> with atomic_target(d + "/out.txt") as tmp:
    ...     with open(tmp, "w") as f:
    ...         _ = f.write("complete")
    >>> os.listdir(d)
    ['out.txt']
"""
from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import shutil
import sys
import threading
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from ._memory import partial_builds, partial_path
from .errors import CLIError

if TYPE_CHECKING:
    from torchrl_robotmem.storage import ZarrStorage

__all__ = ["NO_ROOM", "atomic_target", "check_target", "is_local", "new_store", "no_room", "progress",
           "remove_stale_partials", "write_failed"]

#: the errno of a write that found no room, and what it means
NO_ROOM = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "the disk quota is used up",
           errno.EFBIG: "a file would pass the file-size limit (ulimit -f) or the file system's largest file"}


def progress(iterable, **kwargs):
    """``iterable`` with a tqdm progress bar, shown only on a terminal.

    Args:
        iterable: what to iterate over.
        **kwargs: passed to :class:`tqdm.auto.tqdm` (``desc``, ``unit``, ...).

    Example:
        >>> from torchrl_robotmem.cli._build import progress
        >>> sum(progress(range(4), desc="rows"))
        6
    """
    from tqdm.auto import tqdm

    return tqdm(iterable, disable=None, leave=False, **kwargs)  # disable=None: only on a terminal


def check_target(path: str) -> None:
    """Raises a :class:`CLIError` if ``path`` exists: an output is never overwritten.

    Args:
        path (str): the output a command is about to create.

    Example:
        >>> import tempfile
        >>> from torchrl_robotmem.cli._build import check_target
        >>> check_target(tempfile.mkdtemp() + "/new.npz")  # free: no error
    """
    if os.path.lexists(path):
        raise CLIError(f"{path!r} exists; refusing to overwrite it. Remove it or choose another name.")


def is_local(path: Any) -> bool:
    """Whether ``path`` names a local file or directory (not a store URL), which can be renamed into place.

    Args:
        path: a path, ``os.PathLike`` or store URL.

    Example:
        >>> from torchrl_robotmem.cli._build import is_local
        >>> is_local("memory/fetch.zarr"), is_local("s3://bucket/fetch.zarr")
        (True, False)
    """
    from torchrl_robotmem.storage import is_url, normalize_path

    name = normalize_path(path)
    return isinstance(name, str) and not is_url(name)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _settle_writes(timeout: float = 60.0) -> None:
    """Waits until Zarr's I/O loop has no task in flight (at most ``timeout`` seconds).

    A failed ``asyncio.gather`` of chunk writes (a full disk) raises at the first
    failure and leaves the other writes running: they would write into a build
    being removed, and leave it behind.
    """
    sync = sys.modules.get("zarr.core.sync")
    loop = (getattr(sync, "loop", None) or [None])[0]
    if loop is None or loop.is_closed() or not loop.is_running() or threading.current_thread() in (
            getattr(sync, "iothread", None) or [None]):
        return

    async def drain() -> None:
        pending = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        if pending:
            await asyncio.wait(pending, timeout=timeout)

    with contextlib.suppress(Exception):  # cleaning up after a failure: the removal below says what is left
        asyncio.run_coroutine_threadsafe(drain(), loop).result(timeout + 5)


def _remove(path: str) -> None:
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path)
    else:
        os.unlink(path)


def remove_stale_partials(path: str) -> list[str]:
    """Removes the partial builds of ``path`` whose process is gone (killed); returns their paths.

    Only names of the form ``.NAME.partial-PID`` in the target's own directory
    are considered; nothing else is touched.

    Args:
        path (str): the target whose leftover builds to remove.

    Example:
        >>> import os, tempfile
        >>> from torchrl_robotmem.cli._build import remove_stale_partials
        >>> d = tempfile.mkdtemp()
        >>> os.mkdir(d + "/.m.zarr.partial-999999999")  # no such process
        >>> [os.path.basename(p) for p in remove_stale_partials(d + "/m.zarr")], os.listdir(d)
        (['.m.zarr.partial-999999999'], [])
    """
    removed = []
    for partial, pid in partial_builds(path):
        if pid == os.getpid() or _pid_alive(pid):
            continue
        _remove(partial)
        removed.append(partial)
    return removed


@contextlib.contextmanager
def atomic_target(path: str, *, inner: str | None = None) -> Iterator[str]:
    """Yields the hidden sibling to build ``path`` in; renames it to ``path`` if the block succeeds.

    On any error, and on a ``KeyboardInterrupt``, the sibling is removed (with
    the parent directories made for it); a SIGKILL leaves it, and the next
    command on ``path`` removes it.

    Args:
        path (str): the target (a local path).

    Keyword Args:
        inner (str, optional): the block builds ``SIBLING/inner`` (a Minari
            dataset inside its datasets root), which is what becomes ``path``.

    Example: see the module docstring.
    """
    parent = os.path.dirname(os.path.abspath(path))
    missing = []  # the directories made for the target, deepest first: removed again if it is not made
    d = parent
    while not os.path.isdir(d) and os.path.dirname(d) != d:
        missing.append(d)
        d = os.path.dirname(d)
    os.makedirs(parent, exist_ok=True)
    remove_stale_partials(path)
    tmp = partial_path(path)
    if os.path.lexists(tmp):  # this pid's own leftover (pids are reused): no live process owns it
        _remove(tmp)
    done = False
    try:
        yield tmp
        check_target(path)  # created meanwhile by someone else: theirs is kept
        os.rename(os.path.join(tmp, inner) if inner else tmp, path)
        done = True
    finally:
        if os.path.lexists(tmp):
            _settle_writes()
            with contextlib.suppress(OSError):  # not removed: write_failed names it, the next run removes it
                _remove(tmp)
        for d in missing if not done else ():
            try:
                os.rmdir(d)
            except OSError:  # not empty: something else was put there meanwhile
                break


@contextlib.contextmanager
def new_store(path: str, capacity: int | None, **kwargs) -> Iterator[ZarrStorage]:
    """A new store for an import, built beside ``path`` and renamed to it once closed (see :func:`atomic_target`).

    If the import fails, or is killed, nothing is at ``path``. A store URL is
    written in place (an object store has no rename) and left as it is on failure.

    Args:
        path (str): the memory to create.
        capacity (int or None): its ``max_size`` (``None``: a memory without a declared capacity).
        **kwargs: passed to :class:`~torchrl_robotmem.ZarrStorage` (``ndim``, ``background``, ...).

    Example:
        >>> import os, tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem.cli._build import new_store
        >>> d = tempfile.mkdtemp()
        >>> with new_store(d + "/m.zarr", 10, background=False) as st:
        ...     st.set(slice(0, 2), TensorDict({"obs": torch.zeros(2)}, [2]))
        ...     os.path.exists(d + "/m.zarr")
        False
        >>> os.listdir(d)
        ['m.zarr']
    """
    from torchrl_robotmem.storage import ZarrStorage

    with atomic_target(path) if is_local(path) else contextlib.nullcontext(path) as target:
        storage = ZarrStorage(target, capacity, **kwargs)
        try:
            yield storage
        finally:
            storage.close()


def _chain(err: BaseException | None):
    seen = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        yield err
        err = err.__cause__ or err.__context__


def no_room(err: BaseException) -> BaseException | None:
    """The error under ``err`` (itself, or its causes) saying a write found no room or memory; ``None`` if none.

    No room: an ``OSError`` with an errno of :data:`NO_ROOM` (the background
    writer's ``RuntimeError`` carries it as its cause). No memory: a
    ``MemoryError``, or torch's allocator refusing (``RuntimeError: ... can't allocate memory``).

    Example:
        >>> import errno
        >>> from torchrl_robotmem.cli._build import no_room
        >>> try:
        ...     try:
        ...         raise OSError(errno.ENOSPC, "No space left on device")
        ...     except OSError as e:
        ...         raise RuntimeError("The background writer failed") from e
        ... except RuntimeError as err:
        ...     no_room(err).errno == errno.ENOSPC
        True
    """
    for e in _chain(err):
        if isinstance(e, OSError) and e.errno in NO_ROOM:
            return e
        if isinstance(e, MemoryError) or (isinstance(e, RuntimeError) and "can't allocate memory" in str(e)):
            return e
    return None


def write_failed(target: str | None, err: BaseException, *, what: str | None = None, built: bool = True,
                 url_cleaned: bool = False) -> CLIError:
    """The one line of a command whose write of ``target`` failed: the target, the cause, what is left there.

    Call it once the build was given up (the :func:`atomic_target` block left):
    a local ``target`` is then looked at, and the line says that nothing is at it,
    or names what is (the build of this process that could not be removed).

    Args:
        target (str, optional): what the command was writing (``None``: not known).
        err: what was raised; its cause (:func:`no_room`, or the first ``OSError`` under it) is named.

    Keyword Args:
        what (str, optional): the failed step, named first (default: ``"writing TARGET"``).
        built (bool): the command builds ``target`` beside it (import, export, copy); ``False`` for
            commands that change or add to an existing one (repair, plot): nothing is said of what is left.
        url_cleaned (bool): a store URL ``target`` (written in place) had what the command wrote removed.

    Example:
        >>> import errno, tempfile
        >>> from torchrl_robotmem.cli._build import write_failed
        >>> err = write_failed(tempfile.mkdtemp() + "/m.zarr", OSError(errno.ENOSPC, "No space left on device"))
        >>> print(str(err).replace("; ", ";\\n"))  # doctest: +ELLIPSIS
        writing '/.../m.zarr' failed (OSError: [Errno 28] No space left on device: no space left on the device);
        nothing was left at '/.../m.zarr';
        run it again once there is room
    """
    room = no_room(err)
    cause = room or next((e for e in _chain(err) if isinstance(e, OSError)), err)
    meaning = NO_ROOM.get(cause.errno) if isinstance(cause, OSError) else "out of memory" if room else None
    text = f"{type(cause).__name__}: {cause}" if str(cause) else type(cause).__name__
    text += f": {meaning}" if meaning else ""
    head = f"{what or ('writing ' + repr(target) if target else 'writing')} failed ({text})"
    again = "run it again once there is room" if room is not None else "run it again"
    if target is None or not built:
        return CLIError(head, code=1)
    if not is_local(target):
        left = "what the command wrote under it was removed" if url_cleaned else "remove what is under it"
        return CLIError(f"{head}; {target!r} is a store URL, written in place: {left}, then {again}", code=1)
    left = [p for p, pid in partial_builds(target) if pid == os.getpid()]
    if left:
        return CLIError(f"{head}; its incomplete build {left[0]!r} could not be removed: delete it, then {again}",
                        code=1)
    if os.path.lexists(target):
        return CLIError(f"{head}; {target!r} exists (made by another process meanwhile?)", code=1)
    return CLIError(f"{head}; nothing was left at {target!r}; {again}", code=1)
