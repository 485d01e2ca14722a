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

import contextlib
import os
import shutil
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from . import CLIError
from ._memory import partial_builds, partial_path

if TYPE_CHECKING:
    from torchrl_robotmem.storage import ZarrStorage

__all__ = ["atomic_target", "check_target", "is_local", "new_store", "progress", "remove_stale_partials"]


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
            _remove(tmp)
        for d in missing if not done else ():
            try:
                os.rmdir(d)
            except OSError:  # not empty: something else was put there meanwhile
                break


@contextlib.contextmanager
def new_store(path: str, capacity: int, **kwargs) -> Iterator[ZarrStorage]:
    """A new store for an import, built beside ``path`` and renamed to it once closed (see :func:`atomic_target`).

    If the import fails, or is killed, nothing is at ``path``. A store URL is
    written in place (an object store has no rename) and left as it is on failure.

    Args:
        path (str): the memory to create.
        capacity (int): its ``max_size``.
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
