"""The packed RAM mirror of a store's rows: layout, allocation, growth, loading, chunk snapshots.

Every stored column of a row lives in one packed ``uint8`` buffer
(:class:`~torchrl_robotmem.storage.layout.PackedLayout`): a sampled batch is one
gather of whole rows, and a chunk the commit engine writes is one ``memcpy``
(:meth:`RamMirror.copy_chunk`, taken under the engine's lock, or after it for a
complete chunk no record covers yet: :meth:`RamMirror.copied`) split per array
later (:meth:`RamMirror.chunk_arrays`, outside it). The mirror also reads a
store's rows into RAM (:meth:`RamMirror.load`), including a reader's re-read
of chunks a writer overwrote during the load.

It knows nothing of TorchRL: the storage tells it how many transitions it
holds (``length``, a callable: the storage's ``len``).

Example:
    >>> import torch
    >>> from torchrl_robotmem.storage.mirror import RamMirror
    >>> m = RamMirror(8, length=lambda: 3)
    >>> m.chunk_rows = 4
    >>> m.configure({"x": {"dtype": "float32", "shape": [2]}})
    >>> m.allocate()
    >>> m.views.get("x")[:3] = 1.0
    >>> snap = m.copy_chunk(0)
    >>> m.chunk_arrays(snap)["x"].tolist()
    [[1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [0.0, 0.0]]
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from tensordict import LazyStackedTensorDict, TensorDict, TensorDictBase

from . import _backend
from .background_fill import RowFill
from .fast_read import ChunkReads, read_into
from .format import read_rows
from .journal import OVERWRITES, PREFIX, JournalArrayMissing, journal_chunks
from .layout import PackedLayout
from .rowfile import RowFile, rows_layout
from .tags import TAG_KEYS, open_episode_ends

__all__ = ["RamMirror", "DONE_KEY", "TRUNCATED_KEY"]

DONE_KEY = ("next", "done")
TRUNCATED_KEY = ("next", "truncated")


class RamMirror:
    """The rows of a store in RAM, packed, and the chunk snapshots the commit engine writes.

    Args:
        max_size (int): the store's capacity in transitions.

    Keyword Args:
        ndim (int): leading batch dimensions one stored item spans. Defaults to 1.
        device: device of the buffer. Defaults to ``"cpu"``.
        length: a callable returning how many transitions hold data (the storage's
            ``len``); rows past them reach the disk as zeros. Defaults to none.

    Example:
        >>> m = RamMirror(10, ndim=1)
        >>> m.max_dim0, m.dim0(7)
        (10, 7)
    """

    def __init__(self, max_size: int, *, ndim: int = 1, device: Any = "cpu",
                 length: Callable[[], int] = lambda: 0) -> None:
        self.max_size = int(max_size)
        self.ndim = int(ndim)
        self.device = device
        self.length = length
        self.schema: dict[str, dict] | None = None
        self.inner_shape: tuple[int, ...] = ()
        self.chunk_rows: int | None = None
        self.layout: PackedLayout | None = None
        self.key_specs: dict | None = None  # {key: (dtype, row shape)} without the tags: the hot validation path
        # the rows (read through ``packed`` / ``views`` / ``columns``, which wait for a fill under way)
        self._packed: torch.Tensor | None = None
        self._views: TensorDictBase | None = None
        self._columns: dict = {}
        self.fill: RowFill | None = None  # a reader's rows filled in the background (see ``start_fill``)
        self.rows: RowFile | None = None  # the file the packed rows are mapped from (None: RAM)
        self.unbounded = False  # a memory without a declared capacity: chunks sized for a large memory
        self.mapped_layout: dict | None = None  # the layout of the rows in that file
        self.read_early: dict = {}  # columns read before a writer's fill (``read_columns``), served during its open
        self.filled_in_background = False  # the open's rows were filled by a RowFill (``ZarrStorage.row_file``)

    # -- shapes along the first dimension --------------------------------------------

    @property
    def inner_numel(self) -> int:
        """Elements per first-dimension row that count in ``len`` (the dims up to ``ndim``)."""
        return math.prod(self.inner_shape[: self.ndim - 1]) if self.ndim > 1 else 1

    @property
    def max_dim0(self) -> int:
        """Rows along the first dimension."""
        return -(-self.max_size // self.inner_numel)

    def dim0(self, n: int) -> int:
        """First-dimension rows that ``n`` transitions span."""
        return -(-int(n) // self.inner_numel)

    def filled(self) -> int:
        """First-dimension rows that hold data."""
        return self.dim0(self.length())

    # -- schema and allocation -------------------------------------------------------

    def configure(self, schema: dict[str, dict] | None) -> None:
        """Sets the columns (``{path: {"dtype", "shape"}}``, tags included) and rebuilds the layout.

        ``inner_shape`` and ``chunk_rows`` are plain attributes, set before.
        """
        self.schema = schema
        self.layout = PackedLayout(schema) if schema is not None else None
        self.key_specs = None if schema is None else {
            _backend.path_to_key(p): (_backend.torch_dtype(spec["dtype"]), torch.Size(spec["shape"]))
            for p, spec in schema.items()
            if p not in TAG_KEYS
        }

    def file_layout(self) -> dict | None:
        """What a row file's seal binds the rows to: row bytes, each column's offset, dtype and shape, the rows."""
        return None if self.layout is None else rows_layout(self.layout, (self.max_dim0, *self.inner_shape))

    def allocate(self, *, keep: bool = True) -> None:
        """(Re)builds the packed buffer for the current schema, keeping the rows that hold data (unless not ``keep``).

        Rows mapped from a file (:attr:`rows`) that only grow (the same layout) stay where they are: the file
        is made longer and mapped again, no row is copied. A new layout (a column added) gets a file of its own.
        """
        old = self.views if keep else None
        shape = (self.max_dim0, *self.inner_shape)
        self.before_write()
        if self.rows is None:
            self._packed = self.layout.allocate(shape, self.device)
        else:
            layout = self.file_layout()
            same = old is not None and self.mapped_layout is not None and not self.rows.in_memory and \
                {**self.mapped_layout, "shape": None} == {**layout, "shape": None} and \
                self.mapped_layout["shape"][1:] == layout["shape"][1:]
            self._packed = self.rows.map(shape, self.layout.row_bytes, new_file=old is not None and not same)
            self.mapped_layout = layout
            if same and not self.rows.in_memory:
                old = None  # the rows are in the file already (unless there was no room for it: copied then)
        self._views = self.layout.views(self._packed)
        self._columns = dict(self._views.items(include_nested=True, leaves_only=True))
        if old is not None:
            n0 = self.filled()
            for path in self.schema:
                key = _backend.path_to_key(path)
                col = old.get(key, None)
                self._views.get(key)[:n0] = col[:n0] if col is not None else 0

    def column(self, path: str) -> torch.Tensor:
        """The column of an array path (all rows)."""
        return self.views.get(_backend.path_to_key(path))

    def _column(self, path: str) -> torch.Tensor:
        """The column of an array path, as the loads write it (no wait for a fill: they are the fill)."""
        return self._views.get(_backend.path_to_key(path))

    # -- the rows, and a fill under way ------------------------------------------------------

    @property
    def packed(self) -> torch.Tensor | None:
        """The packed rows ``[max_dim0, *inner, row_bytes]`` (filled: waits for a fill under way)."""
        self.finish_fill()
        return self._packed

    @property
    def views(self) -> TensorDictBase | None:
        """A TensorDict of views of the packed rows, one per column (filled: waits for a fill under way)."""
        self.finish_fill()
        return self._views

    @property
    def columns(self) -> dict:
        """``{key: view}`` of every column (filled: waits for a fill under way)."""
        self.finish_fill()
        return self._columns

    def start_fill(self, group: Any, n0: int, *, local_dir: Any, record_file: str | None,
                   fallback: Callable[[tuple | None], Any]) -> bool:
        """Fills the first ``n0`` rows from the chunk files in the background (:class:`.background_fill.RowFill`).

        ``record_file``: the commit record a reader looks at around each chunk read (``None``: the writer's
        fill). Returns ``False`` (nothing started) where a column cannot be read from its files: fill
        synchronously then.
        """
        self.finish_fill()
        arrays = {path: group[path] for path in self.schema}
        reads = ChunkReads(arrays, {path: self._column(path) for path in arrays}, self.chunk_rows, local_dir=local_dir)
        if reads.left or not reads.todo:
            return False
        self.fill = RowFill(reads, n0, record_file=record_file, max_size=self.max_size, fallback=fallback)
        self.filled_in_background = True
        return True

    def finish_fill(self) -> None:
        """Waits for a fill under way (raising the error that stopped it, at every call after it too)."""
        fill = self.fill
        if fill is not None:
            fill.wait()
            self.fill = None
            self.read_early = {}

    def read_columns(self, group: Any, paths: list[str], n0: int, *, local_dir: Any) -> bool:
        """Reads columns ``paths`` of the first ``n0`` rows from their chunk files now, before a writer's fill.

        What the writer's open reads before it returns (the episode tags and done flags: which episodes the
        previous writer left open, which ids are in use), into buffers of their own (written into the mapped
        rows, a byte a row would fault in every page of the file): :meth:`tag_view` serves them until
        :meth:`end_open`. Returns ``False`` where one cannot be read from its files (then fill synchronously).
        """
        early = {}
        for p in paths:
            col = self._column(p)
            early[p] = torch.empty((n0, *col.shape[1:]), dtype=col.dtype)
        if read_into({p: group[p] for p in paths}, early, n0, self.chunk_rows, local_dir=local_dir):
            return False
        self.read_early = {_backend.path_to_key(p): col for p, col in early.items()}
        return True

    def end_open(self) -> None:
        """The open is over: the columns read before the fill are dropped (reads of them wait for the fill)."""
        self.read_early = {}

    def tag_view(self, key) -> torch.Tensor:
        """The column ``key``: during the open, the rows read before a writer's fill (:meth:`read_columns`, the
        opened rows only); else all rows, filled."""
        early = self.read_early.get(key)
        if early is not None and self.fill is not None:
            return early
        return self.views.get(key)

    def keys(self) -> list:
        """The column keys (no wait for a fill: the layout is known before any row is read)."""
        return list(self._views.keys(True, True)) if self._views is not None else []

    def fill_before_write(self, index) -> None:
        """During a writer's fill, fills the chunks of the rows ``index`` (first dimension) below the filled
        length before they are written, so the fill never writes over a row written since the open (rows
        past that length are not filled at all: nothing to wait for). Raises the fill's damage error for a
        chunk it could not fill."""
        fill = self.fill
        if fill is None:
            return
        if fill.done and fill.error is None:
            self.finish_fill()  # every chunk filled: writes go straight in from now on
            return
        rows = _first_dim_rows(index, fill.n0, self.chunk_rows)
        if rows is None:
            self.finish_fill()
            return
        rows = rows[(rows >= 0) & (rows < fill.n0)]
        if rows.size and not fill.ready(rows):  # a chunk filled already is written (and committed) as it is,
            fill.ensure(rows)  # even after the fill met a damaged chunk elsewhere, which this raises

    def stop_fill(self) -> None:
        """Stops the background thread of a fill under way (reads after it fill what is left themselves)."""
        if self.fill is not None:
            self.fill.stop()

    def gather(self, index, n0: int | None) -> torch.Tensor:
        """The packed rows at ``index`` of the first ``n0`` first-dimension rows (``None``: all of them).

        One gather of whole rows. During a fill, the chunks of those rows are filled first (an index
        that is not an integer, a slice or an integer tensor waits for the whole fill).
        """
        fill = self.fill
        if fill is not None:
            n = self.max_dim0 if n0 is None else int(n0)
            rows = _first_dim_rows(index, n, self.chunk_rows)
            if rows is None:
                self.finish_fill()
            else:
                fill.ensure(rows)
                if fill.done:
                    self.finish_fill()
        packed = self._packed if n0 is None else self._packed[:n0]
        return packed[index]

    def lead(self, col: torch.Tensor) -> torch.Tensor:
        """A tag column without the item dims past ``ndim`` (tags are equal along them)."""
        extra = len(self.inner_shape) + 1 - self.ndim
        return col[(..., *([0] * extra))] if extra > 0 else col

    def flat_columns(self, keys, n: int) -> dict:
        """The first ``n`` transitions of columns ``keys``, flattened over the ``ndim`` leading dims."""
        out = {}
        n0 = self.dim0(n)
        for key in keys:
            col = self.tag_view(key)[:n0]
            if key in TAG_KEYS:
                col = self.lead(col)
            out[key] = col.reshape(-1, *col.shape[self.ndim:])[:n] if self.ndim > 1 else col[:n]
        return out

    def before_write(self) -> None:
        """Claims the row file (unsealing it, once) before the first write into the rows."""
        if self.rows is not None:
            self.rows.claim()

    def write(self, cursor, data: TensorDictBase) -> None:
        """Writes the prepared rows ``data`` at ``cursor`` (along the first dimension) into the views.

        During a writer's fill, the chunks written into are filled first (:meth:`fill_before_write`).
        """
        self.before_write()
        self.fill_before_write(cursor)
        if isinstance(data, LazyStackedTensorDict) and data.stack_dim == 0:
            self._views.update_at_(data, cursor)  # each stacked TensorDict written in place
        elif isinstance(cursor, slice) and isinstance(data, TensorDict):
            # hot path (appends): one copy per leaf into its column, no TensorDict machinery
            columns = self._columns
            for key, value in data.items(include_nested=True, leaves_only=True):
                columns[key][cursor].copy_(value)
            if self.rows is not None:  # the next pages mapped ahead (a user's slice may leave its stop out)
                self.rows.written(cursor.indices(self._packed.shape[0])[1] * self._packed.stride(0))
        else:
            self._views[cursor] = data

    # -- episode ends ----------------------------------------------------------------

    def mark_done(self, rows: torch.Tensor) -> torch.Tensor:
        """Sets ``("next", "done")`` and ``("next", "truncated")`` (if stored) on flat ``rows``.

        So does every other stored ``("next", ..., "done" | "truncated")`` leaf: a multi-agent
        env's per-agent flags (``("next", "agents", "done")`` ``[..., n_agents, 1]``) end with
        the episode, as TorchRL's envs set them.

        Returns the first-dimension rows written, for the commit engine to mark dirty.
        """
        self.before_write()
        first = torch.div(rows, self.inner_numel, rounding_mode="floor")
        self.fill_before_write(first)
        keys = self.keys()
        nested = [k for k in keys if isinstance(k, tuple) and len(k) > 2 and k[0] == "next"
                  and k[-1] in ("done", "truncated")]
        for key in (DONE_KEY, TRUNCATED_KEY, *nested):
            if key == DONE_KEY or key in keys:
                col = self._views.get(key)
                (col.reshape(-1, *col.shape[self.ndim:]) if self.ndim > 1 else col)[rows] = True
        return first

    def open_episode_ends(self, n: int, cursor: int, *, full: bool, newest: int | None = None) -> torch.Tensor:
        """The last row of every episode among the first ``n`` transitions that no done ends.

        ``cursor`` is the writer's position along the first dimension; ``full`` whether
        the buffer has wrapped around. Empty without rows, a done column or episode tags.
        ``newest``: only the ``newest`` rows written last (before ``cursor``) can end an open
        episode (a writer whose open closed every earlier one): only those are read (``ndim=1``).
        """
        if n == 0 or DONE_KEY not in self.keys() or "episode" not in self.schema or newest == 0:
            return torch.zeros(0, dtype=torch.long)
        if newest is not None and newest < n and self.ndim == 1:
            pos = torch.arange(cursor - newest, cursor, dtype=torch.long)
            pos = pos % self.max_dim0 if full else pos  # write order (a full ring wraps at its size)
            run, episode = (self.lead(self.tag_view(k)[pos]).reshape(newest).cpu() for k in ("run", "episode"))
            done = self.tag_view(DONE_KEY)[pos].reshape(newest, -1).any(-1).cpu()
            return pos[open_episode_ends(run, episode, done, cursor=0, full=False)]
        flat = {k: v.cpu() for k, v in self.flat_columns(("run", "episode", DONE_KEY), n).items()}
        done = flat[DONE_KEY].reshape(n, -1).any(-1)
        return open_episode_ends(flat["run"], flat["episode"], done, cursor=cursor * self.inner_numel, full=full)

    # -- what the commit engine reads ------------------------------------------------

    def copy_chunk(self, c: int, *, copy: bool = True) -> tuple[torch.Tensor, PackedLayout]:
        """A snapshot of chunk ``c``: ONE copy of its packed rows (taken under the engine's lock).

        The per-array split happens later, in :meth:`chunk_arrays`, outside the
        lock, so a foreground ``set`` waits for a memcpy, not for 30 column copies.

        ``copy=False`` (a chunk all of whose rows are written): the chunk's rows themselves, a view
        the caller copies with :meth:`copied` once it has released the lock. Only for a chunk no row of
        which a commit record covers yet, whose every later write marks it dirty again: a copy torn by
        such a write is written again before any record names its rows (``docs/storage.md``). The views stay
        readable however the rows move meanwhile (a growth or a new column maps a new file and keeps
        the old mapping alive; no row file shrinks while mapped).
        """
        lo = c * self.chunk_rows
        hi = min(lo + self.chunk_rows, self.max_dim0)
        valid = max(0, min(hi, self.filled()) - lo)
        self.fill_before_write(slice(lo, hi))  # a writer's fill: the chunk's rows read first (once)
        if not copy and valid == hi - lo:
            return self._packed[lo:hi], self.layout
        packed = self._packed[lo:hi].to("cpu", copy=True)  # a CUDA mirror (device="cuda") is written from host memory
        if valid < hi - lo:
            packed[valid:] = 0  # rows past len reach the disk as zeros
        return packed, self.layout

    @staticmethod
    def copied(snapshot: tuple[torch.Tensor, PackedLayout]) -> tuple[torch.Tensor, PackedLayout]:
        """The rows of a :meth:`copy_chunk` ``(copy=False)`` snapshot, copied (to host memory)."""
        packed, layout = snapshot
        return packed.to("cpu", copy=True), layout

    def chunk_arrays(self, snapshot: tuple[torch.Tensor, PackedLayout]) -> dict[str, np.ndarray]:
        """The per-array contents of a chunk snapshot (see :meth:`copy_chunk`)."""
        packed, layout = snapshot
        views = layout.views(packed)
        return {path: np.ascontiguousarray(views.get(_backend.path_to_key(path)).cpu().numpy())
                for path in self.schema}

    # -- loading ---------------------------------------------------------------------

    def load(self, group: Any, n0: int, *, store_path: Any, read_only: bool, local_dir: Any = None) -> set[str]:
        """Reads the first ``n0`` rows of every array of ``group`` (a damaged chunk raises, naming it).

        A local store's chunk files are read straight into the packed rows, in parallel
        (:func:`~.fast_read.read_into`); the rest through Zarr. Returns the paths read
        through Zarr (whose chunk files the caller lists again: Zarr reads a missing one as zeros).
        """
        if not n0:
            return set()
        self.before_write()
        arrays = {path: group[path] for path in self.schema}
        left = read_into(arrays, {path: self._column(path) for path in arrays}, n0, self.chunk_rows, local_dir=local_dir)
        for path in self.schema:
            if path in left:
                self._column(path)[:n0] = torch.from_numpy(
                    read_rows(arrays[path], path, n0, self.chunk_rows, store_path, read_only))
        return left

    def apply_journal(self, group: Any, journal: dict) -> JournalArrayMissing | None:
        """A reader applies a pending journal in RAM only.

        Returns ``None``, or the :class:`~.journal.JournalArrayMissing` of a journal array that is gone: the
        writer ended that commit during the load. The record has changed then, so :meth:`reread_overwritten`
        reads every chunk again; the caller reports the damage where it did not.
        """
        self.before_write()
        try:
            for path, rows, values in journal_chunks(group, journal):
                self._column(path)[rows] = torch.from_numpy(np.ascontiguousarray(values))
        except JournalArrayMissing as err:
            return err
        return None

    def reread_overwritten(self, store: Any, group: Any, record: dict, n0: int, *, store_path: Any) -> bool:
        """Reads again, chunk by chunk, the rows a writer may have overwritten during a reader's load.

        An overwrite (a ring wrapping around, a journalled in-place write)
        replaces one array's chunk at a time, so a read that overlapped it can
        return rows whose columns come from two writes. When the commit record
        changed during the load and an overwrite was possible (a wrapped ring, a
        journal pending before or after, or a journalled commit in between, which
        the record's ``overwrites`` count tells), each chunk is read
        until the record is the same before and after (from the journal while
        one names the chunk): every row is whole, possibly newer than ``len``.
        Returns whether it read anything.
        """
        def now() -> dict:
            return _backend.open_group(store, read_only=True).attrs.asdict()

        after = now()
        wrapped = int(after.get("write_count", 0)) > self.max_size
        in_place = after.get(OVERWRITES, 0) != record.get(OVERWRITES, 0)  # a journalled commit during the load
        if after == record or not (wrapped or in_place or record.get("journal") or after.get("journal")):
            return False
        rows = self.chunk_rows
        for lo in range(0, n0, rows):
            hi = min(lo + rows, n0)
            for _ in range(1000):
                before = now()
                journal = before.get("journal")
                prefix = PREFIX if journal and lo // rows in journal["chunks"] else ""
                try:
                    values = {path: group[prefix + path][lo:hi] for path in self.schema}
                except KeyError as err:  # that journal's arrays are gone: the writer ended its commit meanwhile
                    if not prefix:
                        raise
                    if now() == before:
                        raise JournalArrayMissing(err.args[0] if err.args else PREFIX) from err
                    continue
                if now() == before:
                    break
            else:
                raise RuntimeError(f"Could not read rows {lo}..{hi} of {store_path!r}: the writer commits too often.")
            for path, v in values.items():
                self._column(path)[lo:hi] = torch.from_numpy(np.ascontiguousarray(v))
        return True


def _first_dim_rows(index, n: int, every: int) -> np.ndarray | None:
    """First-dimension rows of every chunk (of ``every`` rows) an index of ``n`` rows reads (``None``: an index
    this does not resolve)."""
    if isinstance(index, (int, np.integer)) and not isinstance(index, bool):
        return np.array([int(index) + n if index < 0 else int(index)])
    if isinstance(index, slice):
        start, stop, step = index.indices(n)
        if step == 1:  # one row a chunk is enough
            return np.arange(start, stop, every) if stop <= start else np.r_[np.arange(start, stop, every), stop - 1]
        return np.arange(start, stop, step)
    if isinstance(index, torch.Tensor) and not index.dtype.is_floating_point and index.dtype != torch.bool:
        rows = index.reshape(-1).cpu().numpy().astype(np.int64)
        return np.where(rows < 0, rows + n, rows)
    return None
