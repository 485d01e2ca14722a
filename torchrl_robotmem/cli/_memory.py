"""Reading a memory for the command line: open it read-only, read its columns in write order.

Shared by the ``inspect``, ``plot`` and ``export`` commands. A memory is opened
with ``ZarrStorage(path, read_only=True)``: no writer lock is taken, a pending
commit journal is applied in RAM only, and a writer process may keep appending
meanwhile (what it commits later is not seen).

Commands that create a store build it in a hidden sibling
``.NAME.partial-PID`` and rename it into place when complete
(:func:`partial_path`). Such a sibling is an interrupted build: opening it, or
the missing target beside it, is an error that says so (:func:`incomplete_build_error`).
"""
from __future__ import annotations

import json
import os
import re
import zipfile
from typing import Any

import numpy as np

from .errors import CLIError

DONE_KEY = ("next", "done")
TAGS = ("episode", "run", "env")  # the tag columns, in the order the commands read them
SUCCESS_KEY = ("next", "is_success")
GOAL_KEYS = (("next", "achieved_goal"), "achieved_goal")


def not_a_memory(path: Any, why: str) -> CLIError:
    return CLIError(f"{os.fspath(path)!r} is not a torchrl_robotmem memory ({why}).")


# -- partial builds -----------------------------------------------------------------------------------

_PARTIAL = re.compile(r"^\.(?P<target>.+)\.partial-(?P<pid>\d+)(?:\.zip|\.npz)?$")


def partial_path(path: str, pid: int | None = None) -> str:
    """The hidden sibling a command builds ``path`` in: ``PARENT/.NAME.partial-PID`` (``.zip`` / ``.npz`` kept).

    Example:
        >>> partial_path("/data/fetch.zarr", pid=42)
        '/data/.fetch.zarr.partial-42'
        >>> partial_path("/data/fetch.npz", pid=42)
        '/data/.fetch.npz.partial-42.npz'
    """
    parent, base = os.path.split(os.path.abspath(path))
    suffix = next((s for s in (".zip", ".npz") if base.endswith(s)), "")
    return os.path.join(parent, f".{base}.partial-{os.getpid() if pid is None else pid}{suffix}")


def partial_builds(path: str) -> list[tuple[str, int]]:
    """``[(partial path, pid)]``: the builds of ``path`` beside it (finished ones were renamed to ``path``)."""
    parent, base = os.path.split(os.path.abspath(path))
    try:
        names = sorted(os.listdir(parent))
    except (FileNotFoundError, NotADirectoryError, PermissionError):
        return []
    out = []
    for name in names:
        m = _PARTIAL.match(name)
        if m is not None and m.group("target") == base:
            out.append((os.path.join(parent, name), int(m.group("pid"))))
    return out


def incomplete_build_error(path: Any, code: int = 2) -> CLIError | None:
    """A :class:`CLIError` when ``path`` is an interrupted build, or a missing target with one beside it."""
    from torchrl_robotmem.storage import is_url, normalize_path

    name = normalize_path(path)
    if not isinstance(name, str) or is_url(name):
        return None
    m = _PARTIAL.match(os.path.basename(os.path.abspath(name)))
    if m is not None and os.path.lexists(name):
        target = os.path.join(os.path.dirname(os.path.abspath(name)), m.group("target"))
        return CLIError(
            f"{os.fspath(path)!r} is the incomplete build of {target!r} left by an interrupted command (process "
            f"{m.group('pid')}): not a memory to use. Run that command again (it removes this), or delete it.",
            code=code,
        )
    if not os.path.lexists(name):
        beside = partial_builds(name)
        if beside:
            return not_a_memory(path, f"no such file or directory; {beside[0][0]!r} beside it is the incomplete "
                                      f"build of an interrupted command (process {beside[0][1]}): run it again")
    return None


def open_memory(path: Any):
    """A read-only :class:`~torchrl_robotmem.ZarrStorage` on ``path``, or a :class:`CLIError` saying why not."""
    from torchrl_robotmem.storage import ZarrStorage, is_url, normalize_path
    from torchrl_robotmem.storage.errors import LinkError
    from torchrl_robotmem.storage.format import FORMAT_MARKER

    incomplete = incomplete_build_error(path)
    if incomplete is not None:
        raise incomplete
    name = normalize_path(path)
    if isinstance(name, str) and not is_url(name):
        if not os.path.exists(name):
            raise not_a_memory(path, "no such file or directory")
        record = os.path.join(name, "zarr.json")
        if os.path.isdir(name):
            if not os.path.lexists(record):
                raise not_a_memory(path, "a directory without zarr.json: not a Zarr store")
            if not os.path.islink(record):  # a link is never read: the open below refuses the store, naming it
                if not os.path.isfile(record):  # a named pipe would block the read for ever
                    raise not_a_memory(path, "zarr.json is not a regular file")
                try:
                    with open(record) as f:
                        meta = json.load(f)
                except (OSError, ValueError, RecursionError) as err:
                    raise not_a_memory(path, f"unreadable zarr.json: {type(err).__name__}: {err}"[:300]) from None
                if not isinstance(meta, dict):
                    raise not_a_memory(path, f"zarr.json holds {json.dumps(meta)[:40]}, not a Zarr node's metadata")
                attributes = meta.get("attributes")
                if meta.get("node_type") != "group" or not isinstance(attributes, dict) or FORMAT_MARKER not in attributes:
                    raise not_a_memory(path, f"a Zarr {meta.get('node_type', 'node')} without the {FORMAT_MARKER!r} "
                                             "attribute")
        elif not name.endswith(".zip"):
            raise not_a_memory(path, "a file, not a Zarr store directory or *.zip")
    try:
        return ZarrStorage(path, read_only=True)
    except LinkError as err:
        raise CLIError(str(err), code=1) from None
    except (FileNotFoundError, ValueError, OSError, zipfile.BadZipFile) as err:
        raise not_a_memory(path, str(err)) from None
    except (TypeError, AttributeError, KeyError, RecursionError) as err:  # a record that is not a memory's
        raise not_a_memory(path, f"its metadata is not a memory's ({type(err).__name__}: {err})"[:300]) from None


#: times :func:`open_settled` opens a full ring again when a writer committed while it was read
SETTLE_TRIES = 5


def open_settled(path: Any):
    """:func:`open_memory`, with rows that are one commit's: a full ring that a writer overwrote while it was
    read (its record changed) is opened again, up to :data:`SETTLE_TRIES` times, then refused.

    A reader reads each chunk whole, but chunks read at different commits of a wrapping ring are not in any
    one write order: an export or a plot in write order needs the rows of one commit. A memory that is not
    full is only appended to, and its rows up to the committed length do not change.
    """
    for _ in range(SETTLE_TRIES):
        storage = open_memory(path)
        if not is_full(storage) or storage.record(now=True) == storage.record():
            return storage
        storage.close()
    raise CLIError(
        f"{path}: a writer overwrote rows of this full ring while it was read, {SETTLE_TRIES} times in a row: rows "
        f"of different commits cannot be put in write order. Export it while the writer is stopped or paused, or "
        f"from a copy made then (robotmem copy).", code=1)


def root_attrs(storage) -> dict:
    """The store's group attributes (the commit record), as plain JSON values."""
    return storage.record()


def is_full(storage) -> bool:
    """Whether every slot of the ring holds an item (the next write overwrites the oldest).

    Args:
        storage: a :class:`~torchrl_robotmem.ZarrStorage` (or any TorchRL storage with ``max_size``).

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.cli._memory import is_full, stored_along_dim0
        >>> st = ZarrStorage(tempfile.mkdtemp() + "/m.zarr", 4, background=False)
        >>> st.set(slice(0, 3), TensorDict({"obs": torch.zeros(3)}, [3]))
        >>> is_full(st), stored_along_dim0(st)
        (False, 3)
        >>> st.close()
    """
    return storage.initialized and len(storage) == storage.max_size


def stored_along_dim0(storage) -> int:
    """How many positions along the first dimension hold items (TorchRL's ``storage.shape[0]``); 0 before any write.

    Args:
        storage: an initialized or empty TorchRL ``TensorStorage``; example in :func:`is_full`.
    """
    return int(storage.shape[0]) if storage.initialized else 0


def write_order(storage) -> np.ndarray:
    """Positions along the first dimension of the stored items, oldest first (a full ring starts at the cursor)."""
    n0 = stored_along_dim0(storage)
    order = np.arange(n0)
    if is_full(storage):
        record = root_attrs(storage)
        journal = record.get("journal")
        if isinstance(journal, dict) and isinstance(journal.get("meta"), dict):
            record = {**record, **journal["meta"]}  # a reader serves the rows of a pending journal (applied in RAM)
        cursor = int(record.get("cursor", 0)) % max(n0, 1)
        order = np.roll(order, -cursor)
    return order


def has_key(storage, key) -> bool:
    return storage.initialized and key in storage.view().keys(True, True)


def column(storage, key, order: np.ndarray | None = None) -> np.ndarray:
    """Column ``key`` (tags included) as numpy, items in ``order`` (default: write order)."""
    order = write_order(storage) if order is None else order
    col = storage.view().get(key)
    return col[:stored_along_dim0(storage)].numpy()[order] if len(order) else col[:0].numpy()


def flat_column(storage, key, order: np.ndarray | None = None) -> np.ndarray:
    """Column ``key`` with every batch dimension (items, time, ...) flattened into one: ``[transitions, *row_shape]``."""
    batch_dims = storage.view().get("episode").ndim if has_key(storage, "episode") else storage.ndim
    col = column(storage, key, order)
    return col.reshape(-1, *col.shape[batch_dims:])


def goal_key(storage, requested=None):
    """The achieved-goal column to report on: ``requested`` or the first of :data:`GOAL_KEYS` stored."""
    if requested is not None:
        key = tuple(requested.split("/")) if isinstance(requested, str) and "/" in requested else requested
        path = "/".join(key) if isinstance(key, tuple) else key
        if not has_key(storage, key) or path not in {*schema_paths(storage), "episode", "run", "env"}:  # not a group
            raise CLIError(f"the memory has no column {requested!r}; stored keys: {', '.join(schema_paths(storage))}")
        return key
    return next((k for k in GOAL_KEYS if has_key(storage, k)), None)


def schema_paths(storage) -> list[str]:
    return sorted((root_attrs(storage).get("schema") or {}).keys())
