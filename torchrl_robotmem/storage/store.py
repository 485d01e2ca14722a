"""``MemoryStore``: the parts of one open store, with the writer's position, for ``ZarrStorage``.

``ZarrStorage`` keeps what TorchRL's storage contract needs (``_len``, ``_storage``,
the last cursor, the mutation revision); this coordinator owns the rest: the handle,
the RAM mirror, the tags, the schema and the commit engine, the writer's cursor and
write count, durability (``flush``, ``close``) and closing the episodes a previous run
left open. ``docs/storage.md`` ("Map of storage/") says which part does what.
"""
from __future__ import annotations

import contextlib
import os
import secrets
import warnings
import weakref
from collections.abc import Callable
from typing import Any

import torch

from . import _backend, lifecycle, loader, writer_sync
from .commit import CommitEngine
from .context import missing_context, user_stacklevel
from .errors import IntegrityError
from .format import UNBOUNDED, dims, grown_size
from .handle import StoreHandle
from .layout import PackedLayout
from .mirror import RamMirror
from .planner import WritePlan, cursor_rows
from .rowfile import ROWS_DIR, RowFile, rows_layout, url_cache_dir
from .schema import StoreSchema, same_constants, with_constants
from .summary import summarize
from .tags import TAG_KEYS, TagRegistry

__all__ = ["GOAL_CONDITIONED", "MemoryStore"]

#: the optional attribute of the commit record that says the rows are not goal-conditioned (``false``);
#: a store without it (every store written before it existed) is goal-conditioned
GOAL_CONDITIONED = "goal_conditioned"


def _use_worker(handle, *, background: bool, commit_process: bool | None) -> bool:
    """Whether a writer's commits go through the commit worker process (local stores, background commits).

    ``commit_process=None``: yes unless the environment sets ``TORCHRL_ROBOTMEM_COMMIT_PROCESS=0``.
    """
    if handle.read_only or not background or handle.local_dir is None:
        return False
    if commit_process is not None:
        return bool(commit_process)
    return os.environ.get("TORCHRL_ROBOTMEM_COMMIT_PROCESS", "1") != "0"


class MemoryStore:
    """The handle and parts of one open store, and the writer position it records.

    Args:
        path, read_only, storage_options: as ``ZarrStorage`` takes them (for the :class:`StoreHandle`).
        on_damage (str): what opening a damaged store does. commit_process (bool or None): as ``ZarrStorage``.
        goal_conditioned (bool or None): as ``ZarrStorage`` takes it (``None``: as the store records).
    """

    def __init__(self, path: Any, *, read_only: bool, storage_options: dict | None, on_damage: str,
                 commit_process: bool | None, goal_conditioned: bool | None = None) -> None:
        self.handle = StoreHandle(path, read_only=read_only, storage_options=storage_options)
        self.handle.flush = self.flush  # a newer writable handle in this process flushes this one first
        self.read_only = self.handle.read_only
        # names this writing session in each record it commits: two sessions that wrote different rows never
        # commit equal records (a row file sealed for one is never served for the other, see rowfile.py)
        self.session = secrets.token_hex(8)
        self.on_damage = on_damage
        self.commit_process = commit_process
        self.write_count = 0  # the writer's position: its count and its next row
        self.appended = 0  # rows this handle appended since its open (None: unknown, a reset or a loaded state)
        self.cursor = 0
        # the attached TorchRL writer's own (cursor, write_count), as last seen after a write, an empty or a load:
        # what a reopen hands the writer back (None: no writer seen; the store's own cursor and count are used)
        self.writer_at: tuple[int, int] | None = None
        self.unbounded = False  # a memory without a declared capacity (it grows; no ring)
        self.restored_writers: weakref.WeakSet | None = None  # set once the store is open
        self.context_checked = False  # a success column and an env name: checked at this handle's first write
        self.goal_conditioned_arg = goal_conditioned  # as given (None: as recorded)
        self.goal_conditioned = True if goal_conditioned is None else bool(goal_conditioned)
        self.recorded_goal_conditioned = True  # what the store's record says (no attribute: True)
        self.before_close: list[Callable[[], Any]] = []  # components' flushes (weak methods), run first on close
        self.rows: RowFile | None = None  # where the rows are mapped from (prepare_rows)
        self.rows_sealed = False  # the row file held the opened record's rows: no chunk was read

    def claim(self):
        """A writer takes the store's writer lock; returns the earlier handle of this process it took over, if any."""
        try:
            return self.handle.claim() if not self.read_only else None
        except BaseException:
            self.handle.closed = True  # never registered: the writer stays with the earlier handle
            raise

    def abandon(self, previous) -> None:
        """An open that failed: releases the store and gives the writer back to ``previous``.

        A row file this open made is deleted: a refused open leaves the store as it found it.
        """
        if self.rows is not None:
            self.rows.discard()
        self.release()
        if previous is not None:
            previous.take_back(self.handle)

    def build(self, max_size: int, *, ndim: int, device, length: Callable[[], int], record: Callable[[], dict],
              commit_interval: float, background: bool, codec: tuple, attrs: dict) -> None:
        """Makes the parts for a store of ``max_size`` rows and reads the record ``attrs`` into them."""
        handle = self.handle
        self.mirror = RamMirror(max_size, ndim=ndim, device=device, length=length)
        self.mirror.rows = self.rows
        self.tags = TagRegistry(read_only=self.read_only)
        self.engine = CommitEngine(
            self.mirror, handle.group, record=record, commit_interval=commit_interval,
            background=background, name=str(handle.path),
            worker_path=str(handle.local_dir) if _use_worker(handle, background=background,
                                                             commit_process=self.commit_process) else None,
        )
        self.engine.handle = handle  # the worker gets a copy of its writer lock's descriptor
        self.schema = StoreSchema(handle, self.mirror, self.engine.arrays, compressor=codec[0], level=codec[1])
        self.sync_attrs(attrs)
        self.restored_writers = weakref.WeakSet()  # this session's state

    def open_record(self, max_size: int | None, *, chunk_rows: int | None, ndim: int, device) -> dict:
        """Opens the store and its row file; returns the checked commit record (a new store's, written).

        Args:
            max_size (int or None): the capacity asked for (``None``: the stored one, or none for a new store).

        Keyword Args:
            chunk_rows (int or None), ndim (int): of a new store. device: where the rows live.
        """
        self.handle.open()
        self.prepare_rows(device)  # the rows' file: served without reading a chunk if sealed for the record
        return self.handle.open_record(max_size, chunk_rows=chunk_rows, ndim=ndim, on_damage=self.on_damage,
                                       served=self.open_rows, mapped=self.rows is not None)

    def settle_record(self, attrs: dict) -> tuple[dict, bool]:
        """The record whose rows are served: ``attrs`` with a pending journal applied; and whether one was."""
        pending = self.handle.pending_record(attrs)
        if pending is None:
            return attrs, False
        self.sync_attrs(pending)
        return pending, True

    def fill_rows(self, record: dict, attrs: dict, *, pending: bool) -> int:
        """Fills the allocated rows for the record ``attrs`` (``record``: as opened); returns the transitions.

        A row file sealed for the record holds them already; a large reader fills them in the background
        (:func:`.loader.fill_in_background`); any other open reads them now (:func:`.loader.load_rows`) and
        notes the episode ids and runs they use.
        """
        sealed = self.rows_sealed and not pending  # the row file holds the record's rows
        if sealed:
            return int(attrs.get("len", 0))
        if loader.fill_in_background(self.handle, self.mirror, record, attrs, on_damage=self.on_damage):
            if not self.read_only:  # the ids in use, from the columns read before the fill (a reader hands out none)
                self.note_stored(self.mirror.dim0(int(attrs.get("len", 0))))
            return int(attrs.get("len", 0))  # the rows are filled from the chunks as they are read
        n = loader.load_rows(self.handle, self.mirror, record, attrs, on_damage=self.on_damage)
        if n:  # a sealed file was closed cleanly: its record's counters are exact (and a reader filling in
            # the background hands out no id)
            self.note_stored(self.mirror.dim0(n))
        return n

    def prepare_rows(self, device) -> None:
        """Makes the row file: a local store's ``_rows/``; a URL store's in its local cache folder
        (:func:`.rowfile.url_cache_dir`); none (RAM) for in-memory stores and CUDA rows."""
        path = self.handle.path
        if torch.device(device).type != "cpu":
            self.rows = None  # a CUDA mirror lives in device memory
        elif self.handle.local_dir is not None:
            self.rows = RowFile(self.handle.local_dir, read_only=self.read_only)
        elif isinstance(path, str) and _backend.is_url(path) and not path.startswith("memory://"):
            folder = url_cache_dir(path, self.handle.storage_options)  # the same sealed file, in a local cache
            if not self.read_only:
                os.makedirs(folder, exist_ok=True)
            self.rows = RowFile(folder, read_only=self.read_only)
        else:
            self.rows = None

    def open_rows(self, attrs: dict) -> bool:
        """Picks the row file for the opened record ``attrs``; returns whether it holds its rows (no chunk to read).

        Called by the open's integrity check once ``attrs`` are sane (a served row file needs no chunk listing).
        """
        layout = None
        if attrs.get("schema"):
            max_dim0, _, inner = dims(attrs)
            layout = rows_layout(PackedLayout(attrs["schema"]), (max_dim0, *inner))
        self.rows_sealed = self.rows is not None and self.rows.open(attrs, layout=layout)
        if not self.rows_sealed and self.handle.local_dir is not None:
            _backend.refuse_links(self.handle.local_dir, self.handle.path, chunks=None)  # the chunks will be read
        return self.rows_sealed

    def seal_rows(self) -> None:
        """A writer's clean close: seals the row file for the committed record (see :mod:`.rowfile`)."""
        rows = self.mirror.rows
        if rows is None or self.read_only or self.mirror.schema is None:
            return
        try:
            self.mirror.finish_fill()
        except IntegrityError:
            return  # a chunk the writer's fill could not read: not sealed (the next open fills and names it)
        if self.mirror.packed is None:
            return
        n = int(self.mirror.length())
        # the open closed every episode it found open: only the rows appended since can end one (their
        # count, not the memory's size, is what this reads; a writer that appended nothing reads none)
        with self.scanning():
            ends = self.mirror.open_episode_ends(n, self.cursor, full=n >= self.mirror.max_size, newest=self.appended)
        record = _backend.open_group(self.handle.store, read_only=True).attrs.asdict()
        try:
            rows.seal(record, layout=self.mirror.file_layout(), open_ends=ends.tolist())
        except OSError as err:  # the rows are committed: an unsealed file is refilled from them at the next open
            warnings.warn(f"ZarrStorage at {self.handle.path!r}: the row file was not sealed ({type(err).__name__}: "
                          f"{err}); every row is committed, and the next open fills the row file from the chunks "
                          f"(remove what stands in the way under {ROWS_DIR}/ for the next close to seal it).",
                          RuntimeWarning, stacklevel=2)

    def open_arrays(self, attrs: dict) -> None:
        """A writer's handles on the stored arrays; starts its commit worker (after the open's reads).

        The partial files a writer killed mid-write left (``attrs``: the record the open found) are removed
        here, once every check of the open passed: an open refused for damage leaves every file as it was.
        A writer given ``goal_conditioned=`` first records it if the store says otherwise, so that a
        later ``ZarrStorage(path)`` remembers it (a store never told keeps no attribute).
        """
        if self.handle.local_dir is not None:
            _backend.remove_partial_files(self.handle.local_dir, attrs)
        if self.goal_conditioned != self.recorded_goal_conditioned:
            self.engine.update_attrs({GOAL_CONDITIONED: self.goal_conditioned})
            self.recorded_goal_conditioned = self.goal_conditioned
        # the row file is claimed (unsealed) by the mirror before its first write into it; the commit worker
        # starts with the first commit (which runs in-process until the worker is ready), and the writing
        # handles are opened by the first in-process commit that needs them (CommitEngine._array)

    def note_stored(self, n0: int) -> None:
        """Rows past the committed metadata may survive a crash (journal replays): never
        hand out an id that one of the first ``n0`` stored rows already uses."""
        if "episode" in self.mirror.schema:
            self.tags.note_stored(self.mirror.tag_view("episode")[:n0].max(), self.mirror.tag_view("run")[:n0].max())

    def sync_attrs(self, attrs: dict) -> None:
        """Persistent bookkeeping, mirrored from the group attributes."""
        self.schema.sync(attrs)
        self.tags.sync(attrs)
        self.write_count = int(attrs.get("write_count", 0))
        self.cursor = int(attrs.get("cursor", 0))
        self.writer_at = _writer_field(attrs.get("writer"), None if attrs.get(UNBOUNDED) else int(attrs["max_size"]))
        self.unbounded = self.mirror.unbounded = bool(attrs.get(UNBOUNDED))
        self.engine.set_committed(attrs)
        self.recorded_goal_conditioned = attrs.get(GOAL_CONDITIONED) is not False  # older stores lack it
        if self.goal_conditioned_arg is None:
            self.goal_conditioned = self.recorded_goal_conditioned

    def grow_for(self, need: int) -> bool:
        """A memory without a declared capacity: grows the arrays, the record and the rows to hold ``need`` rows.

        Called by the writer, with every earlier row committed, before a write that reaches past the rows
        allocated. The arrays grow first, then the record says so: a crash in between leaves arrays longer
        than the record, which opens as before. Returns whether it grew.
        """
        mirror = self.mirror
        if not self.unbounded or need <= mirror.max_dim0:
            return False
        new = grown_size(mirror.max_dim0, need, mirror.chunk_rows or 1)
        with self.engine.cv:
            self.grow(new, ring=False)
        return True

    def grow(self, new_max: int, *, ring: bool = True) -> None:
        """Grows a store that has not wrapped around to ``new_max`` transitions (arrays and record).

        Raises, saying what to pass instead, on a smaller size, a reader or a store that wrapped around.

        Args:
            new_max (int): the capacity asked for.

        Keyword Args:
            ring (bool): the store is a ring (a memory without a declared capacity never wraps around).
        """
        handle, mirror, engine = self.handle, self.mirror, self.engine
        old = mirror.max_size
        if new_max < old:
            raise ValueError(
                f"The store at {handle.path!r} holds up to {old} rows; max_size={new_max} would "
                f"shrink it. Shrinking is not supported: pass max_size={old} (or None)."
            )
        if handle.read_only:
            raise ValueError(f"Cannot grow a store opened read_only (max_size={old}).")
        if ring and (self.write_count > engine.committed_len or engine.committed_len > old):
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

    def env_code(self, name: str, *, create: bool = False) -> int:
        """The integer code of an environment name (``create``: register a new one, writers only)."""
        with self.engine.cv:
            code, added = self.tags.code(name, create=create)
            if added:
                self.engine.mark_meta_dirty()
        return code

    def check_writable(self) -> None:
        self.handle.check_writable()
        self.engine.raise_error()

    def register(self, plan: WritePlan):
        """Applies what a valid plan changes (env names, data kind, warnings, episode ids and run); returns its rows.

        The first TensorDict write of this handle without a success column (of a goal-conditioned
        store) or an env name warns once, naming the fix (:func:`.context.missing_context`).
        """
        for name in plan.new_env_names:
            self.env_code(name, create=True)
        self.schema.note(plan)
        if not self.context_checked and plan.env is not None:
            self.context_checked = True
            advice = missing_context(plan.data, plan.env, self.handle.path, goal_conditioned=self.goal_conditioned)
            if advice is not None:
                warnings.warn(advice, UserWarning, stacklevel=user_stacklevel())
        if plan.draw is not None and self.tags.tag_rows(plan):
            self.engine.mark_meta_dirty()  # this session's run was allocated
        return plan.rows()

    def advance(self, n: int, next_row: int) -> None:
        """The writer wrote ``n`` rows; its next row is ``next_row`` (wrapping around)."""
        self.write_count += n
        if self.appended is not None:
            self.appended += n
        self.cursor = next_row if self.unbounded else next_row % self.mirror.max_dim0
        self.writer_at = None  # taken again from the writer that wrote them (follow_writers); none: the store's own

    def follow_writers(self, storage: Any, *, record: bool = False) -> None:
        """Takes the position of the writer attached to ``storage`` (TorchRL's count) as the one to record.

        Called after each write (under the engine's lock: the commit that takes the rows takes the
        position with them); ``record``: commit the record even if no row changed (a flush, a close).
        A flush or close from inside a writer's method (a SIGTERM handler that interrupted
        ``writer.extend`` after its cursor moved and before its ``set``) keeps the position the last
        write took: the moved one names rows that were never written.
        """
        if self.read_only or self.handle.closed:
            return
        if record and writer_sync.writing_now(storage):
            return
        at = writer_sync.writer_position(storage)
        if at is None or at == self.writer_at:
            return
        self.writer_at = at
        if record:
            with self.engine.cv:
                self.engine.mark_meta_dirty()

    def reset(self) -> None:
        """An emptied store: the writer starts over (as TorchRL's writer restarts its count)."""
        self.cursor = 0
        self.write_count = 0
        self.writer_at = None
        self.appended = None
        self.tags.tagger.reset()
        self.engine.mark_meta_dirty()

    def meta_snapshot(self, length: int, last: int | None) -> dict:
        """The record a commit writes, for ``length`` rows and the last written row ``last``."""
        writer = {"writer": None if self.writer_at is None else list(self.writer_at)}  # None replaces a stale one
        # new constants with the rows that carry them (a rollback killed before its commit leaves neither);
        # a record that adds none leaves them out (the record's attributes are merged into the group's)
        constants = self.schema.constants
        constants = {} if same_constants(constants, self.engine.committed_constants) else {"constants": dict(constants)}
        return {"len": length, "cursor": self.cursor, "last_cursor": -1 if last is None else int(last),
                "write_count": self.write_count, "session": self.session, **writer, **self.tags.record(),
                **constants}

    def restore_writers(self, storage: Any, force: bool = False) -> None:
        """Puts the writers of the buffers on ``storage`` at this store's cursor and write count."""
        at = self.writer_at
        if at is None or at[0] > self.mirror.filled():  # a position never points past the rows stored
            at = (self.cursor, self.write_count)
        cursor, count = at
        writer_sync.restore_writers(storage, cursor, count, self.restored_writers, force=force)

    def rollback_writers(self, storage: Any, cursor: Any, size: int) -> None:
        """Undoes the cursor move the writers of ``storage`` made before a ``set`` at ``cursor`` that failed."""
        rows = cursor_rows(cursor, size)
        writer_sync.rollback_writers(storage, int(rows[0]) if len(rows) else 0, len(rows), size)

    # -- episodes --------------------------------------------------------------------------

    def mark_truncated(self, rows: torch.Tensor) -> None:
        """Sets ``("next", "done")`` and ``("next", "truncated")`` on flat ``rows`` (RAM, then disk).

        Committed with the next commit (nothing is kicked here); the caller bumps TorchRL's mutation
        revision (``ZarrStorage`` does, as for its own writes).
        """
        with lifecycle.critical(), self.engine.cv:
            self.engine.mark_dirty(self.mirror.mark_done(rows), self.mirror.chunk_rows)

    def close_episode_at(self, row: int) -> None:
        """Ends the open episode at ``row`` (see ``ZarrStorage.close_episode_at``)."""
        with self.engine.cv:
            self.tags.tagger.close_stream()
        self.mark_truncated(torch.tensor([row]))
        self.engine.kick()

    def scanning(self):
        """A context under which reads scan whole columns (readahead on: ``RowFile.scanning``)."""
        return self.rows.scanning() if self.rows is not None else contextlib.nullcontext()

    def note_in_place(self) -> None:
        """Stored rows were rewritten (a done flag may have been cleared): the close reads every row for the
        episodes left open, not only the rows this handle appended."""
        self.appended = None

    def mark_rows_dirty(self, n0: int) -> None:
        """Commits the first ``n0`` rows again (a write that did not say which rows it touched)."""
        self.note_in_place()
        if n0:
            with self.engine.cv:
                self.engine.mark_dirty(slice(0, n0), self.mirror.chunk_rows)
            self.engine.kick()

    def close_open_episodes(self, length: int, full: bool) -> bool:
        """Marks the last row of every episode the previous run left open as done/truncated; whether there was one."""
        if self.rows_sealed:  # the rows the writer that sealed them found open at its close
            rows = torch.tensor(self.mirror.rows.open_ends, dtype=torch.long)
        else:
            rows = self.mirror.open_episode_ends(length, self.cursor, full=full)
        if not rows.numel():
            return False
        self.mark_truncated(rows)
        return True

    # -- durability ------------------------------------------------------------------------

    def flush(self) -> None:
        """Blocks until every row written so far is durable and committed."""
        if self.read_only or self.handle.closed:
            return
        if self.handle.inherited:
            self.handle.check_writable()  # raises: the writer process flushes, not a forked child
        self.engine.flush()

    def close(self) -> None:
        """Flushes, stops the writer and releases the store. Idempotent.

        If the last rows cannot be written (a full disk), the handle is closed all the same and the
        error says which rows are lost; call ``flush`` first to keep them while the cause is fixed.
        """
        if self.handle.closed:
            return
        if self.handle.inherited:  # a forked child's copy: its rows, lock and commit thread are the parent's
            self.handle.closed = True
            return
        self.close_components()
        try:
            with lifecycle.critical():
                self.flush()
                self.seal_rows()
        except Exception:
            engine = getattr(self, "engine", None)
            if engine is not None:
                engine.raise_error(closing=True)  # says which rows are lost
            raise
        finally:
            self.release()

    def give_up_writes(self) -> None:
        """Closes the handle without committing what RAM holds since the last commit (a rewrite of the rows
        that failed half-way: ``ZarrStorage.load_state_dict``, which calls it inside its hold and critical
        section, so that neither the engine's own commits nor a signal's flush run first). The store stays as
        it is on disk; its row file, which no longer matches the commit record, is refilled from the chunks at
        the next open."""
        self.engine.discard_pending()
        if self.rows is not None:
            self.rows.discard()  # unsealed since the first write: never trusted again (its own file deleted)
        self.release()

    def close_components(self) -> None:
        """Runs the components' flushes registered in ``before_close`` (a sampler's priorities), each once.

        A component that fails is reported with a warning naming it: the rows are closed all the same.
        """
        hooks, self.before_close = self.before_close, []
        for ref in hooks:
            flush = ref()
            if flush is None:
                continue
            try:
                flush()
            except Exception as err:  # noqa: BLE001 - the rows still close; say what was not written
                warnings.warn(f"closing the store at {self.handle.path!r}: {flush!r} failed ({err!r}); the state it "
                              "kept since it was last written is lost, the rows are not.", RuntimeWarning,
                              stacklevel=user_stacklevel())

    def release(self) -> None:
        mirror = getattr(self, "mirror", None)
        if mirror is not None:
            mirror.stop_fill()  # before the file is let go
        self.handle.closed = True
        engine = getattr(self, "engine", None)
        if engine is not None:
            engine.close()
        if self.rows is not None:
            self.rows.release()
        self.handle.release()

    # -- reads -----------------------------------------------------------------------------

    def column(self, index, n0: int | None):
        """A column (or columns) of the first ``n0`` rows (``None``: all of them), as ``LazyTensorStorage`` gives it."""
        rows = self.mirror.views if n0 is None else self.mirror.views[:n0]
        if self.schema.constants:  # a non-tensor entry is a column too
            rows = with_constants(rows, self.schema.constants)
        return rows[index]

    def summary(self, initialized: bool, n: int, max_size: int) -> dict[str, Any]:
        """Rows, episodes, runs, success rates, env names and size on disk (see :func:`.summary.summarize`)."""
        return summarize(self.mirror if initialized else None, n=n, path=self.handle.path, max_size=max_size,
                         env_names=tuple(self.tags.env_names), constants=self.schema.constants,
                         local_dir=self.handle.local_dir)

    # -- a reader's refresh, a state dict --------------------------------------------------

    def snapshot(self) -> Callable[[], None]:
        """Saves what ``reopen`` changes; returns the function that puts it back."""
        saved = dict(vars(self))
        group = self.handle.group
        parts = [(part, dict(vars(part))) for part in (self.mirror, self.tags, self.schema)]
        engine = self.engine
        committed = {k: v for k, v in vars(engine).items() if k in ("group", "committed_len", "committed_write_count")}

        def restore() -> None:
            vars(self).update(saved)
            self.handle.group = group
            for part, state in parts:
                vars(part).update(state)
            vars(engine).update(committed)

        return restore

    def reopen(self, max_size: int) -> dict | None:
        """Re-reads the committed record (a reader's refresh); ``None`` while the store holds no schema."""
        group, attrs = self.handle.reopen_record(on_damage=self.on_damage, served=self.open_rows,
                                                 mapped=self.rows is not None)
        if attrs.get("schema") is None:
            return None
        self.handle.group = self.engine.group = group
        if int(attrs["max_size"]) != max_size:  # the writer grew the store
            self.mirror.max_size = int(attrs["max_size"])
        self.sync_attrs(attrs)
        return attrs

    def state(self, path: Any, ndim: int, initialized: bool) -> dict[str, Any]:
        """This store's bookkeeping in a ``state_dict`` (its ``"zarr"`` entry)."""
        tags = self.mirror.views.select(*TAG_KEYS, strict=False).state_dict() if initialized else {}
        return {"store": path if isinstance(path, str) else None, "write_count": self.write_count,
                "cursor": self.cursor, "env_names": list(self.tags.env_names), "ndim": ndim, "tags": tags,
                **self.schema.state()}

    def load_position(self, meta: dict, rows, n0: int, tagged: bool) -> None:
        """The writer position of ``n0`` loaded rows (``meta``: the source's bookkeeping, if any)."""
        cursor = int(meta.get("cursor", n0))
        self.cursor = cursor if self.unbounded else cursor % self.mirror.max_dim0  # unbounded: n0 may fill the rows
        self.write_count = int(meta.get("write_count", n0))
        self.appended = None
        if tagged:
            self.tags.note_stored(rows.get("episode").max(), rows.get("run").max())
        with self.engine.cv:
            self.engine.mark_meta_dirty()


def _writer_field(value: Any, max_size: int | None) -> tuple[int, int] | None:
    """The record's ``writer`` entry, ``[cursor, write_count]``; anything else (an older store has none, a forged
    one) is ``None``: the store's own cursor and count are handed to the writer instead."""
    if (isinstance(value, list) and len(value) == 2 and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
            and 0 <= value[0] and (max_size is None or value[0] < max_size) and value[1] >= 0):
        return value[0], value[1]
    return None
