"""``repair``: a damaged store made openable and writable again, every intact row kept bit-exact.

Rows after the first damaged chunk are dropped, never invented; records that
disagree are refused, never chosen between (see :func:`repair`).

Example:
    >>> import os, tempfile, torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity import repair
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100, chunk_rows=4) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> os.remove(os.path.join(path, "obs", "c.1.0"))  # rows 4-7
    >>> report = repair(path)
    >>> report.ok, report.after.rows
    (True, 4)
"""
from __future__ import annotations

import datetime
import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zarr

from .. import _backend
from ..errors import IntegrityError, LinkError, Problem
from ..format import BACKUP_DIR, FORMAT_MARKER, UNBOUNDED, dims, numel, writing_config
from ..journal import replay_journal
from ..rowfile import remove_rows
from .arrays import disagreement
from .attributes import bad_attributes, check_attributes, is_int, unsafe_path
from .capacity import capacity_problem
from .files import array_metas, delete_key, get_bytes, open_any, read_group_attrs, set_bytes
from .rebuild import data_problems, rebuild_array_meta, rebuild_attrs, ring_cursor, tag_maxima, written_extent
from .rows import row_file_problems
from .verify import IntegrityReport, verify

__all__ = ["RepairReport", "repair"]

#: the attributes that fix the arrays' layout: recomputed together from the arrays' own metadata
_STRUCTURAL = ("schema", "chunk_rows", "max_size", "inner_shape", "ndim")
#: the kinds of data damage (a chunk file missing or not decoding)
_DATA = ("missing_chunk", "checksum", "undecodable")


@dataclass
class RepairReport:
    """What :func:`repair` did: the reports before and after, the actions taken and where the backup is."""

    before: IntegrityReport
    after: IntegrityReport | None
    actions: list[str] = field(default_factory=list)
    backup: str | None = None

    @property
    def ok(self) -> bool:
        return self.after is not None and self.after.ok

    def __str__(self) -> str:
        done = "repaired" if self.after is not None else "would repair (dry run)"
        lines = [f"{self.before.path}: {done if self.actions else 'nothing to repair'}"
                 + (f" (backup of the metadata in {self.backup})" if self.backup else "")]
        lines += [f"  - {a}" for a in self.actions]
        if self.after is not None and not self.after.ok:
            lines.append(str(self.after))
        return "\n".join(lines)


def repair(path: Any, *, mode: str = "truncate", storage_options: dict | None = None,
           dry_run: bool = False) -> RepairReport:
    """Makes a damaged store openable and writable again, keeping every intact row bit-exact.

    What it does (``mode="truncate"``, the only mode), after copying every
    metadata file (the group's and each array's ``zarr.json``, damaged or not)
    to ``_repair_backup/<time>/`` inside the store:

    * an unreadable array ``zarr.json`` is rebuilt from the recorded schema and
      the codecs its chunks decode with (checksums tried first);
    * an unreadable group ``zarr.json`` (the commit record) is rebuilt from the
      arrays: schema, capacity and chunking from their metadata, the length from
      the last row holding any non-zero value, episode / run counters from the
      tag columns. Environment *names* cannot be recovered: codes keep their
      rows, named ``"unknown-env-<code>"``. A pytree store cannot be rebuilt (its
      tree structure lived only there);
    * insane attributes are recomputed the same way (a ``len`` past ``max_size``,
      a cursor out of range, malformed tag tables);
    * data damage (a missing, truncated or checksum-failing chunk below the
      committed length) truncates the committed length to the start of the first
      damaged chunk, then past trailing rows that are zero in every array (rows a
      too-large ``len`` would have served). Rows after the cut are dropped, never
      invented: for a ring that had wrapped, that includes the rows stored past
      the damaged chunk. The damaged chunk files move to the backup folder;
    * a pending journal whose chunks are damaged is dropped.

    It refuses, changing nothing, where fixing the store would mean trusting one
    record over another or leaving the store's folder: a path read from the store
    (a schema key, ``../other.zarr/observation``) that is not inside it, a
    symbolic link inside it, an array whose own ``zarr.json`` disagrees with the
    schema (dtype, shape, chunking: both records are named; restore the right one
    from a copy), a rebuilt ``zarr.json`` that decodes none of the array's
    chunks, or sizes no machine here can hold. A store of a newer format version
    is not touched (upgrade torchrl_robotmem).

    It takes the writer lock first (an error if a process is writing the store;
    for ``s3://`` stores, the lease; for other URL stores, stop the writer first).
    Readers may keep reading meanwhile: a chunk it moves away is an
    :class:`IntegrityError` naming it in a reader that was reading it, never zeros.

    Args:
        path: the store, as for ``ZarrStorage``.

    Keyword Args:
        mode (str): ``"truncate"``.
        storage_options (dict, optional): fsspec options for URL stores.
        dry_run (bool): report what would be done, write nothing.

    Returns:
        A :class:`RepairReport` (``before`` / ``after`` reports, ``actions``, ``backup``).

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.storage.integrity import repair
        >>> path = tempfile.mkdtemp() + "/memory.zarr"
        >>> with ZarrStorage(path, 100) as storage:
        ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
        >>> repair(path).actions
        []
    """
    if mode != "truncate":
        raise ValueError(f"mode must be 'truncate', got {mode!r}.")
    store, local_dir = open_any(path, storage_options, writable=not dry_run)
    lock = None if dry_run else _writer_lock(path, local_dir, storage_options)
    try:
        before = verify(path, storage_options=storage_options)  # under the lock: no writer changes it meanwhile
        if before.ok:
            actions = _remove_partials(local_dir, dry_run)
            if not dry_run and local_dir is not None and any(p.severity == "error" for p in row_file_problems(local_dir)) \
                    and remove_rows(local_dir):
                actions.append("deleted the row file (_rows/), which differs from the committed chunks: the next open "
                               "fills it from them")
            return RepairReport(before, before, actions)
        if any(p.kind == "format" for p in before.problems):
            raise IntegrityError(before.path, before.errors, action="repair does not touch a store of a newer format:")
        name = _backend.normalize_path(path)
        if not dry_run and isinstance(name, str) and name.endswith(".zip") and os.path.isfile(name):
            raise IntegrityError(before.path, before.errors, action=(
                "repair does not write into a *.zip memory (a zip is written once; nothing was changed): unzip it "
                f"into a directory (python -m zipfile -e {name} DIR.zarr), repair that, and zip it again if needed:"))
        metas = _refusals(before, store, local_dir)
        report = _repair(before, store, local_dir, path, storage_options, dry_run, metas)
        report.actions[:0] = _remove_partials(local_dir, dry_run)
        return report
    finally:
        if lock is not None:
            lock.release()


def _remove_partials(local_dir: Any, dry_run: bool) -> list[str]:
    """Removes every ``*.partial`` file of a killed write (a writer's open removes only those where it writes)."""
    if dry_run or local_dir is None:
        return []
    removed = _backend.remove_partial_files(local_dir, {})  # no schema: every folder is listed
    return [f"removed {removed} partial file(s) of writes a killed writer left"] if removed else []


def _writer_lock(path: Any, local_dir: Any, storage_options: dict | None):
    """The writer lock of the store, for as long as ``repair`` writes (``None`` where there is none)."""
    name = _backend.normalize_path(path)
    try:
        if local_dir is not None:
            return _backend.WriterLock(local_dir)
        if isinstance(name, str) and _backend.is_url(name):
            return _backend.url_writer_lock(name, storage_options)
    except RuntimeError as err:
        raise RuntimeError(f"robotmem repair needs the store to itself and did not change it: {err} "
                           f"Stop the writer (or let it finish), then run repair again.") from None
    return None


def _refuse(path: Any, problems: list[Problem], why: str) -> IntegrityError:
    return IntegrityError(path, problems, read_only=True, action=f"repair refuses this store: {why}; nothing was changed.",
                          hint=f"`robotmem verify {path}` lists everything found.")


def _refusals(before: IntegrityReport, store: Any, local_dir: Any) -> dict[str, bytes]:
    """What makes ``repair`` refuse, checked before it writes anything; returns the array metadata to rebuild.

    Raises :class:`IntegrityError` naming the records at fault (a path leaving
    the store, a symbolic link, two records that disagree, a rebuilt
    ``zarr.json`` that decodes none of the chunks) or the size no machine here
    can hold.
    """
    name = before.path
    if local_dir is not None:
        links = _backend.links_below(local_dir)
        if links:
            raise _refuse(name, LinkError(name, links).problems, "repair writes only inside the store's folder "
                          "(remove each link, then run repair again: its rows are then mended as missing)")
    attrs, _ = read_group_attrs(store)
    if attrs is None:
        attrs = rebuild_attrs(store, local_dir)
    schema = attrs.get("schema")
    if isinstance(schema, dict):
        unsafe = [(k, unsafe_path(k)) for k in schema if unsafe_path(k) is not None]
        if unsafe:
            raise _refuse(name, [Problem("attribute", f"schema key {k!r} is not a path inside the store ({why})",
                                         key="zarr.json") for k, why in unsafe], "it names paths outside it")
    if bad_attributes(attrs) & {*_STRUCTURAL, FORMAT_MARKER}:
        return {}  # the structure is recomputed from the arrays' own metadata: nothing to disagree with
    capacity = capacity_problem(attrs)
    if capacity is not None:
        raise _refuse(name, [capacity], "its sizes are more than this machine can hold")
    found, metas = [], {}
    for p, spec in schema.items():
        try:
            arr = zarr.open_array(store, path=p, mode="r", zarr_format=3)
        except Exception:  # noqa: BLE001 - missing or unreadable: rebuilt, if the chunks agree
            arr = None
        if arr is not None:
            problem = disagreement(arr, p, spec, attrs)
            if problem is not None:
                found.append(problem)
            continue
        try:
            jarr = zarr.open_array(store, path=f"_journal/{p}", mode="r", zarr_format=3)
        except Exception:  # noqa: BLE001 - no journal array to compare with
            jarr = None
        if jarr is not None and (np.dtype(jarr.dtype) != _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"]))
                                 or tuple(jarr.shape[1 + len(dims(attrs)[2]):]) != tuple(spec["shape"])):
            found.append(Problem("metadata", f"array metadata missing, and the journal's copy (_journal/{p}/zarr.json) "
                                 f"records {np.dtype(jarr.dtype)} {list(jarr.shape)} where the schema records "
                                 f"{spec['dtype']} {spec['shape']}", array=p, key=f"{p}/zarr.json"))
            continue
        meta = rebuild_array_meta(store, local_dir, p, attrs)
        if meta is None:
            found.append(Problem("metadata", f"array metadata missing, and none of its chunk files decodes as the "
                                 f"schema records it ({spec['dtype']} {spec['shape']} in chunks of "
                                 f"{attrs['chunk_rows']} rows)", array=p, key=f"{p}/zarr.json"))
            continue
        metas[p] = meta
    if found:
        raise _refuse(name, found, "its records disagree, and repair does not choose between them (restore the "
                      "right one from a copy of the store)")
    return metas


def _repair(before, store, local_dir, path, storage_options, dry_run, metas) -> RepairReport:
    mend = _Mend(before, store, local_dir, dry_run)
    if not dry_run and local_dir is not None and remove_rows(local_dir):
        # the row file is a cache of the chunks being mended: the next open fills it from the mended ones
        mend.actions.append("deleted the row file (_rows/): the next open fills it from the mended chunks")
    mend.run(metas)
    after = None if dry_run else verify(path, storage_options=storage_options)
    return RepairReport(before, after, mend.actions, mend.backup)


class _Mend:
    """One run of ``repair``'s truncate mode: the store, what ``verify`` found, the actions taken so far.

    Each step appends what it did to ``actions`` (in a dry run, what it would do)
    and writes nothing when ``dry_run``.
    """

    def __init__(self, before: IntegrityReport, store: Any, local_dir: Any, dry_run: bool) -> None:
        self.before = before
        self.store = store
        self.local_dir = local_dir
        self.dry_run = dry_run
        self.actions: list[str] = []
        self.backup: str | None = None

    def run(self, metas: dict[str, bytes]) -> None:
        """Every step, in order; ``metas``: the array metadata :func:`_refusals` rebuilt."""
        self.backup_metadata()
        attrs, rebuilt = self.commit_record()
        journal = attrs.get("journal")
        journal_bad = any(p.kind == "journal" for p in self.before.problems)
        if journal and not rebuilt and not journal_bad and not check_attributes(attrs) and not self.dry_run:
            # an interrupted overwrite: redo it first (as a writable open would), so no row stays torn
            attrs = self.replay(journal)
            journal = None
        new = dict(attrs)
        bad = self.recompute_structure(new, bad_attributes(attrs))
        self.restore_array_metadata(new, metas)
        # a damaged journal's overwrite may have reached some arrays' chunks and not others: those rows may be torn
        torn = journal["chunks"] if journal and journal_bad and isinstance(journal, dict) and journal.get("chunks") else ()
        n_dim0, data = self.committed_rows(new, bad, rebuilt, torn)
        changes = self.counters(attrs, new, bad, rebuilt, n_dim0)
        if journal is not None and ("journal" in bad or journal_bad or data):
            changes["journal"] = None
            self.actions.append("dropped the pending journal (damaged, or superseded by the truncation)")
        for key in sorted(bad - set(changes) - {"len"}):
            self.actions.append(f"attribute {key!r} could not be recomputed")
        changes = {k: v for k, v in changes.items() if new.get(k, object()) != v or rebuilt}
        if changes and not any(a.startswith(("truncated", "set the committed")) for a in self.actions):
            self.actions.append(f"rewrote attributes {sorted(changes)}")
        if not self.dry_run:
            self.write(attrs, new, changes, rebuilt)

    def backup_metadata(self) -> None:
        """Copies every metadata file (the group's and each array's ``zarr.json``) to ``_repair_backup/<time>/``."""
        if self.dry_run:
            return
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S-%f")
        self.backup = f"{BACKUP_DIR}/{stamp}"
        for key in ["zarr.json"] + [f"{p}/zarr.json" for p in array_metas(self.store, self.local_dir)]:
            raw = get_bytes(self.store, key)
            if raw is not None:
                set_bytes(self.store, f"{self.backup}/{key}", raw, self.local_dir)
        self.actions.append(f"backed up the metadata files to {self.backup}/")

    def commit_record(self) -> tuple[dict, bool]:
        """``(attributes, rebuilt)``: the group's, or rebuilt from the arrays if its ``zarr.json`` is unreadable."""
        attrs, problem = read_group_attrs(self.store)
        if attrs is not None:
            return attrs, False
        attrs = rebuild_attrs(self.store, self.local_dir)
        if attrs.get(UNBOUNDED):
            shape = (f"as a memory without a declared capacity (its arrays say so), {attrs['max_size']:,} rows "
                     f"allocated: it grows again as rows arrive")
        else:
            shape = (f"as a ring of {attrs['max_size']:,} rows, the arrays' length (a memory without a declared "
                     f"capacity written before its arrays recorded it now wraps at that length)")
        self.actions.append(f"rebuilt the commit record (group zarr.json) from the arrays: {problem.what}; {shape}")
        return attrs, True

    def replay(self, journal: dict) -> dict:
        """Redoes the pending journal's overwrite; the attributes it led to."""
        with writing_config():
            attrs = replay_journal(zarr.open_group(self.store, mode="r+", zarr_format=3), journal)
        self.actions.append(f"replayed the pending journal (chunks {journal['chunks']})")
        return attrs

    def recompute_structure(self, new: dict, bad: set[str]) -> set[str]:
        """Insane structural attributes recomputed (in ``new``) from the arrays' metadata; the rest of ``bad``."""
        if not set(_STRUCTURAL) & bad:
            return bad
        rebuilt = rebuild_attrs(self.store, self.local_dir)
        for key in (*_STRUCTURAL, "kind"):
            if key in bad or key in ("schema", "chunk_rows", "max_size"):
                new[key] = rebuilt[key]
        self.actions.append(f"recomputed {sorted(bad)} from the arrays' metadata")
        return bad - {*_STRUCTURAL, "kind"}

    def restore_array_metadata(self, new: dict, metas: dict[str, bytes]) -> None:
        """Writes the ``zarr.json`` of every array of the schema that has none (or an unreadable one)."""
        for path in new.get("schema") or {}:
            try:
                arr = zarr.open_array(self.store, path=path, mode="r", zarr_format=3)
            except Exception:  # noqa: BLE001 - missing or unreadable: rebuilt below
                arr = None
            if arr is not None:
                disagree = disagreement(arr, path, new["schema"][path], new)
                if disagree is not None:  # (the schema was recomputed from these very arrays: never here)
                    raise _refuse(self.before.path, [disagree], "its records disagree")
                continue
            meta = metas.get(path) or rebuild_array_meta(self.store, self.local_dir, path, new)
            if meta is None:
                raise _refuse(self.before.path, [Problem("metadata", "array metadata missing, and none of its chunk "
                                                         "files decodes as the schema records it", array=path)],
                              "its records disagree")
            self.actions.append(f"rebuilt the metadata of array {path!r} ({path}/zarr.json)")
            if not self.dry_run:
                set_bytes(self.store, f"{path}/zarr.json", meta, self.local_dir)

    def committed_rows(self, new: dict, bad: set[str], rebuilt: bool, torn: Any) -> tuple[int, list[Problem]]:
        """``(rows along dim 0 to commit, the data damage that cut them)``: the length, truncated before any damage."""
        max_dim0, n_dim0, _ = dims(new)
        if "len" in bad or rebuilt:
            n_dim0 = written_extent(self.store, new, limit=max_dim0)
        if not self.dry_run:
            data = data_problems(self.store, self.local_dir, {**new, "len": n_dim0 * numel(new)})
        else:
            data = [p for p in self.before.problems if p.kind in _DATA and p.severity == "error"]
        if torn:
            rows = int(new["chunk_rows"])
            data += [Problem("journal", "overwritten by an interrupted commit whose journal is damaged", chunk=c,
                             rows=(c * rows, (c + 1) * rows)) for c in torn if c * rows < n_dim0]
        if data:
            n_dim0 = self.truncate(new, n_dim0, data)
        elif "len" in bad:
            self.actions.append(f"set the committed length to {n_dim0 * numel(new)} rows (the written rows)")
        return n_dim0, data

    def truncate(self, new: dict, n_dim0: int, data: list[Problem]) -> int:
        """Cuts the length before the first damaged chunk and past trailing zero rows; moves damaged chunks away."""
        cut = min(p.rows[0] for p in data)
        trimmed = written_extent(self.store, new, limit=cut)
        self.actions.append(f"truncated the committed length from {n_dim0 * numel(new)} to {trimmed * numel(new)} "
                            "rows: " + "; ".join(str(p) for p in data[:4]) + (" ..." if len(data) > 4 else ""))
        for p in data:
            if p.kind != "missing_chunk" and p.key and not self.dry_run:
                raw = get_bytes(self.store, p.key)
                if raw is not None:
                    set_bytes(self.store, f"{self.backup}/{p.key}", raw, self.local_dir)
                delete_key(self.store, p.key, self.local_dir)
                self.actions.append(f"moved the damaged chunk {p.key} to {self.backup}/{p.key}")
        return trimmed

    def counters(self, attrs: dict, new: dict, bad: set[str], rebuilt: bool, n_dim0: int) -> dict[str, Any]:
        """The length, cursors, counters and tag tables to commit with ``n_dim0`` rows along dim 0."""
        max_dim0 = dims(new)[0]
        length = n_dim0 * numel(new)
        unbounded = bool(new.get(UNBOUNDED))  # never wraps: its cursor is its length, even at the rows allocated
        full = n_dim0 >= max_dim0 and not unbounded
        old_count = attrs.get("write_count") if is_int(attrs.get("write_count")) and "write_count" not in bad else None
        changes: dict[str, Any] = {}
        if length != attrs.get("len") or rebuilt or {"cursor", "last_cursor"} & bad:
            cursor = ring_cursor(self.store, new, max_dim0) if full else n_dim0
            wrap = (lambda i: i) if unbounded else (lambda i: i % max_dim0)
            changes.update(len=length, cursor=wrap(cursor), last_cursor=wrap(cursor - 1) if length else -1)
        if length != attrs.get("len") or rebuilt or old_count is None:
            # a ring that stays full keeps its count (it has wrapped); otherwise the count is the length
            changes["write_count"] = max(length, old_count or 0) if full else length
        tags = tag_maxima(self.store, new, n_dim0)
        for key in ("episode_next", "runs"):
            if key in bad or rebuilt:
                changes[key] = tags.get(key, 0)
        if "env_names" in bad or rebuilt:
            changes["env_names"] = [f"unknown-env-{i}" for i in range(tags.get("env_codes", 0))]
            changes["env"] = None
            if changes["env_names"]:
                self.actions.append(f"environment names lost: codes 0..{len(changes['env_names']) - 1} named "
                                    "'unknown-env-<code>'")
        if "env" in bad:
            changes["env"] = None
        if "overwrites" in bad:  # only compared for a change (a reader's load): any count readers saw is left behind
            changes["overwrites"] = 0
        if "kind" in bad:
            changes["kind"] = rebuild_attrs(self.store, self.local_dir)["kind"]
        return changes

    def write(self, attrs: dict, new: dict, changes: dict, rebuilt: bool) -> None:
        """Commits the mended record: the whole group ``zarr.json`` if it was rebuilt or restructured."""
        if rebuilt or new != attrs:
            doc = {"attributes": {**new, **changes}, "zarr_format": 3, "consolidated_metadata": None,
                   "node_type": "group"}
            set_bytes(self.store, "zarr.json", json.dumps(doc, indent=2).encode(), self.local_dir)
        elif changes:
            zarr.open_group(self.store, mode="r+", zarr_format=3).update_attributes(changes)
