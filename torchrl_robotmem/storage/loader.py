"""Opening a store's commit record and loading its rows into the RAM mirror.

The steps of an open (and of a reader's ``refresh``), over the parts that own
the state: the :class:`~.handle.StoreHandle` (store, group, format check), the
:class:`~.mirror.RamMirror` (the rows) and the :class:`~.commit.CommitEngine`
(the arrays and the record it commits). ``ZarrStorage`` calls them in order and
keeps TorchRL's own bookkeeping (``_len``, ``initialized``, ``max_size``).

Example:
    >>> from torchrl_robotmem.storage.handle import StoreHandle
    >>> from torchrl_robotmem.storage.loader import open_record, pending_record
    >>> h = StoreHandle("memory://loader-doc", read_only=False)
    >>> attrs = open_record(h, 10, chunk_rows=None, ndim=1, on_damage="raise")
    >>> attrs["max_size"], pending_record(h, attrs) is None
    (10, True)
    >>> h.release()
"""
from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np

from . import _backend, integrity
from .format import FORMAT_MARKER, is_strict, writing_config
from .journal import replay_journal

__all__ = ["check_arguments", "fill_in_background", "grow_arrays", "load_rows", "open_record", "pending_record",
           "reopen_record", "snapshot", "use_worker"]


def use_worker(handle, *, background: bool, commit_process: bool | None) -> bool:
    """Whether a writer's commits go through the commit worker process (local stores, background commits).

    ``commit_process=None``: yes unless the environment sets ``TORCHRL_ROBOTMEM_COMMIT_PROCESS=0``.
    """
    if handle.read_only or not background or handle.local_dir is None:
        return False
    if commit_process is not None:
        return bool(commit_process)
    return os.environ.get("TORCHRL_ROBOTMEM_COMMIT_PROCESS", "1") != "0"


def open_record(handle, max_size: int | None, *, chunk_rows: int | None, ndim: int, on_damage: str,
                served: Callable[[dict], bool] | None = None, mapped: bool = False) -> dict:
    """Opens the store (writing a new store's record), checks its format and integrity; returns the record.

    Args:
        handle (StoreHandle): the store's handle (not opened yet).
        max_size (int or None): the capacity asked for (``None``: the stored one).

    Keyword Args:
        chunk_rows (int or None): rows per chunk of a new store.
        ndim (int): leading batch dimensions of a new store.
        on_damage (str): ``"raise"`` or ``"warn"`` (see ``ZarrStorage``).
        served (callable, optional): asked once the record is sane whether a sealed row file serves the
            rows (then no chunk is listed: none is read). mapped (bool): the rows are mapped from a file.

    Example:
        >>> from torchrl_robotmem.storage.handle import StoreHandle
        >>> h = StoreHandle("memory://open-record-doc", read_only=False)
        >>> open_record(h, 4, chunk_rows=2, ndim=1, on_damage="raise")["len"]
        0
        >>> h.release()
    """
    if handle.store is None:
        handle.open()
    attrs = handle.group.attrs.asdict() if handle.group is not None else {}  # None: a new store
    if attrs.get(FORMAT_MARKER) is None:
        handle.create(attrs, max_size, chunk_rows, ndim)
        attrs = handle.group.attrs.asdict()
    handle.check_format(attrs)
    if not handle.read_only and handle.local_dir is not None:
        _backend.remove_partial_files(handle.local_dir, attrs)  # left by a writer killed mid-write
    # before anything is read or written: a damaged store raises, naming the array and chunk
    grows = max_size is not None and int(max_size) != attrs.get("max_size")
    decode = not handle.read_only and (bool(attrs.get("journal")) or grows)
    if decode and handle.local_dir is not None:  # every chunk below the length is read: walk their folders first
        _backend.refuse_links(handle.local_dir, handle.path, chunks=None)
    return integrity.check_open(handle.group, attrs, store=handle.store, local_dir=handle.local_dir, path=handle.path,
                                read_only=handle.read_only, on_damage=on_damage, served=served, mapped=mapped,
                                decode=decode)


def reopen_record(handle, *, on_damage: str, served: Callable[[dict], bool] | None = None,
                  mapped: bool = False) -> tuple[Any, dict]:
    """A reader's fresh group on its store and the checked record (``refresh``); the handle is unchanged.

    Args:
        handle (StoreHandle): a read-only handle.

    Keyword Args:
        on_damage (str): ``"raise"`` or ``"warn"``. served, mapped: as :func:`open_record` takes them.
    """
    group = _backend.open_group(handle.store, read_only=True)
    attrs = group.attrs.asdict()
    handle.check_format(attrs)
    attrs = integrity.check_open(group, attrs, store=handle.store, local_dir=handle.local_dir, path=handle.path,
                                 read_only=True, on_damage=on_damage, served=served, mapped=mapped)
    return group, attrs


def snapshot(handle, mirror, tags, schema, engine) -> Callable[[], None]:
    """Saves what a reader's ``refresh`` changes in the parts; returns the function that puts it back.

    Args:
        handle (StoreHandle): its ``group``.
        mirror (RamMirror), tags (TagRegistry), schema (StoreSchema): their whole state.
        engine (CommitEngine): its ``group`` and committed length and write count.
    """
    group = handle.group
    states = [(part, dict(vars(part))) for part in (mirror, tags, schema)]
    engine_state = {k: v for k, v in vars(engine).items() if k in ("group", "committed_len", "committed_write_count")}

    def restore() -> None:
        handle.group = group
        for part, state in states:
            vars(part).update(state)
        vars(engine).update(engine_state)

    return restore


def grow_arrays(handle, mirror, engine, new_max: int, *, write_count: int, ring: bool = True) -> None:
    """Grows a store that has not wrapped around to ``new_max`` transitions (arrays and record).

    Raises, saying what to pass instead, on a smaller size, a reader or a store that wrapped around.

    Args:
        handle (StoreHandle): the store's handle.
        mirror (RamMirror): its RAM rows (``max_size`` is updated).
        engine (CommitEngine): its commit engine (the new size is recorded).
        new_max (int): the capacity asked for.

    Keyword Args:
        write_count (int): transitions written to the store so far.
        ring (bool): the store is a ring (a memory without a declared capacity never wraps around).
    """
    old = mirror.max_size
    if new_max < old:
        raise ValueError(
            f"The store at {handle.path!r} holds up to {old} rows; max_size={new_max} would "
            f"shrink it. Shrinking is not supported: pass max_size={old} (or None)."
        )
    if handle.read_only:
        raise ValueError(f"Cannot grow a store opened read_only (max_size={old}).")
    if ring and (write_count > engine.committed_len or engine.committed_len > old):
        raise ValueError(
            f"The store at {handle.path!r} has wrapped around its max_size={old}; it cannot "
            f"grow to {new_max} without reordering rows. Pass max_size={old} (or None)."
        )
    mirror.max_size = new_max
    if mirror.schema is not None:
        for path in mirror.schema:
            arr = handle.group[path]
            arr.resize((mirror.max_dim0, *arr.shape[1:]))
    engine.reset_arrays()
    engine.update_attrs({"max_size": new_max})


def pending_record(handle, attrs: dict) -> dict | None:
    """The record once a pending journal is applied, or ``None`` if none is pending.

    A writer replays the journal on disk; a reader applies its record in RAM only
    (its rows with :meth:`RamMirror.apply_journal <.mirror.RamMirror.apply_journal>`).
    """
    journal = attrs.get("journal")
    if not journal:
        return None
    if not handle.read_only:
        with writing_config():
            return replay_journal(handle.group, journal)
    return {**attrs, **journal["meta"]}


#: rows (bytes) from which a reader fills in the background (below it, the open's read is a few
#: tens of milliseconds); ``$TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES`` sets another threshold
BACKGROUND_FILL_BYTES = 64 << 20
BACKGROUND_FILL_ENV = "TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES"


def fill_in_background(handle, mirror, record: dict, attrs: dict, *, on_damage: str) -> bool:
    """Starts a background fill of a reader's rows (:mod:`.background_fill`) where it serves what a
    synchronous load would; returns whether it started (``False``: call :func:`load_rows`).

    Only a reader of a local store on the CPU, with one batch dimension, that raises on damage, whose
    record has no pending journal and whose ring has not wrapped, with at least
    :data:`BACKGROUND_FILL_BYTES` of rows, every column read from its chunk files.
    """
    n0 = mirror.dim0(int(attrs.get("len", 0)))
    threshold = int(os.environ.get(BACKGROUND_FILL_ENV, BACKGROUND_FILL_BYTES))
    if not (handle.read_only and handle.local_dir is not None and on_damage == "raise" and mirror.ndim == 1
            and str(mirror.device).startswith("cpu") and not record.get("journal")
            and int(attrs.get("write_count", 0)) <= mirror.max_size and n0
            and n0 * mirror.layout.row_bytes >= threshold):
        return False
    return mirror.start_fill(handle.group, n0, local_dir=handle.local_dir,
                             record_file=os.path.join(handle.local_dir, "zarr.json"),
                             fallback=lambda: load_rows(handle, mirror, record, attrs, on_damage=on_damage))


def load_rows(handle, mirror, record: dict, attrs: dict, *, on_damage: str) -> int:
    """Reads the rows of ``attrs`` into the allocated ``mirror``; returns the transitions kept.

    ``record`` is the record as opened (before a pending journal); a reader applies
    that journal and re-reads chunks a writer overwrote meanwhile. The chunk
    files of the arrays read through Zarr (a missing file reads as zeros there) are
    listed again after the read (:meth:`StoreHandle.check_read <.handle.StoreHandle.check_read>`);
    those read from their files (:mod:`.fast_read`) need no listing.

    Args:
        handle (StoreHandle): the store's handle.
        mirror (RamMirror): the RAM rows, allocated for the record's schema.
        record (dict): the record as opened.
        attrs (dict): the record to load (``record`` with a pending journal applied).

    Keyword Args:
        on_damage (str): ``"raise"`` or ``"warn"``.
    """
    journal = record.get("journal")
    read_only = handle.read_only
    n = int(attrs.get("len", 0))
    n0 = mirror.dim0(n)
    left = mirror.load(handle.group, n0, store_path=handle.path, read_only=read_only, local_dir=handle.local_dir)
    if journal and read_only:
        mirror.apply_journal(handle.group, journal)
    reread = bool(read_only and n0 and mirror.reread_overwritten(handle.store, handle.group, record, n0,
                                                                  store_path=handle.path))
    if n0 and (left or reread):
        # Zarr reads a chunk file that is gone as zeros: one moved away since the open's
        # listing (by `robotmem repair`) is an error here, never zero rows served. The
        # arrays read from their chunk files (fast_read) need no listing: each file was read.
        listed = attrs if not read_only else {**record, "len": min(n, int(record.get("len", 0)))}
        if not reread and is_strict(listed):
            listed = {**listed, "schema": {p: spec for p, spec in listed["schema"].items() if p in left}}
        n = handle.check_read(listed, n, on_damage=on_damage, inner_numel=mirror.inner_numel)
    return n


def check_arguments(path, max_size, *, chunk_rows, commit_interval, ndim, shared_init, compressor,
                    compression_level, on_damage, read_only, goal_conditioned=None) -> None:
    """Raises, saying what to pass instead, on constructor arguments ``ZarrStorage`` refuses.

    Args:
        path: the store's path (a number is refused: the first argument is no ``max_size``).
        max_size (int or None): the capacity.

    Keyword Args:
        chunk_rows, commit_interval, ndim, shared_init, compressor, compression_level, on_damage, read_only,
            goal_conditioned: ``ZarrStorage``'s arguments of those names.

    Example:
        >>> check_arguments("memory://a", 10, chunk_rows=None, commit_interval=1.0, ndim=1, shared_init=False,
        ...                 compressor="blosc", compression_level=1, on_damage="raise", read_only=False)
    """
    if isinstance(path, (int, np.integer)) and not isinstance(path, bool):
        raise TypeError(
            f"ZarrStorage's first argument is the store's path; got the number {path}. "
            f"Use ZarrStorage(path, max_size), e.g. functools.partial(ZarrStorage, 'memory/run.zarr')."
        )
    if max_size is not None and int(max_size) <= 0:
        raise ValueError(f"max_size must be a positive integer, got {max_size}.")
    if chunk_rows is not None and int(chunk_rows) <= 0:
        raise ValueError(f"chunk_rows must be a positive integer, got {chunk_rows}.")
    if commit_interval <= 0:
        raise ValueError(f"commit_interval must be > 0 seconds, got {commit_interval}.")
    if int(ndim) < 1:
        raise ValueError(f"ndim must be >= 1, got {ndim}.")
    if shared_init:
        raise ValueError(
            "ZarrStorage(shared_init=True) is not supported: a store has one writer process. "
            "Write from the main process (iterate the collector there and call rb.extend), and "
            "give other processes read-only handles: pickle the storage (it arrives read_only) "
            "or open ZarrStorage(path, read_only=True) there."
        )
    _backend.make_compressors(compressor, compression_level, 4)  # validates the name
    if on_damage not in ("raise", "warn") or (on_damage == "warn" and not read_only):
        raise ValueError(
            f"on_damage must be 'raise', or 'warn' with read_only=True (a damaged store is not "
            f"opened for writing: run `robotmem repair PATH`), got {on_damage!r} with read_only={read_only}."
        )
    if goal_conditioned is not None and not isinstance(goal_conditioned, (bool, np.bool_)):
        raise TypeError(f"goal_conditioned must be True, False or None (as the store records), got {goal_conditioned!r}.")
