"""Prioritized replay in pure PyTorch, whose priorities persist in the memory's own Zarr store.

:class:`PersistentPrioritizedSampler` is TorchRL's proportional
:class:`~torchrl.data.PrioritizedSampler` (Schaul et al. 2015: ``P(i) ∝ (p_i + eps) ** alpha``,
importance weights ``(P(i) / min P) ** -beta`` under the key ``"priority_weight"``, new rows at the
largest priority seen) without TorchRL's C++ extension, which torchrl 0.14.1 builds against torch 2.14
only. Over a :class:`~torchrl_robotmem.ZarrStorage` the raw priorities are kept in the store, in the
reserved group ``_priority`` (chunks of priorities in an array's slots, and a record, the group's attributes,
naming the slot and crc32c of each chunk), so a resumed run samples with the priorities it had. A write is
all-or-nothing: new chunks into free slots, then the record in one ``zarr.json`` write. ``docs/samplers.md``
tells how and when they are written, and what a damaged chunk or record gives.
"""
from __future__ import annotations

import itertools
import json
import math
import os
import sys
import threading
import time
import warnings
import weakref
from pathlib import Path
from typing import Any, NamedTuple

import google_crc32c  # zarr's own crc32c (its Crc32cCodec)
import numpy as np
import torch
from torchrl.data.replay_buffers.samplers import PrioritizedSampler
from zarr.core.sync import sync as zarr_sync

from torchrl_robotmem.storage import lifecycle, make_compressors
from torchrl_robotmem.storage.format import RESERVED
from torchrl_robotmem.storage.zarr_storage import ZarrStorage, component_group, flush_before_close

__all__ = ["PersistentPrioritizedSampler", "PriorityTable"]

FORMAT = "torchrl_robotmem.PersistentPrioritizedSampler"
FORMAT_VERSION = 2  # 2: chunks in slots named by the record, with their crc32c (1: one array, read still)
CHUNK_ROWS = 1 << 16  # rows of a chunk of the stored priorities (256 KiB of float32)


class PriorityTable:
    """Proportional sampling over ``capacity`` weights: blocks of ``block`` rows with their sums and minima.

    Updating ``k`` rows re-sums the blocks they fall in; a draw picks blocks by a cumulative sum over the
    block sums, then rows within the block (``O(capacity / block + k * block)``, no C++ extension).

    Args:
        capacity (int): rows. block (int, optional): rows per block. Defaults to 1024.

    Example:
        >>> t = PriorityTable(10, block=4)
        >>> t.set(torch.arange(3), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
        >>> t.draw(torch.tensor([0.3, 0.9], dtype=torch.float64)).tolist(), t.total(), t.minimum()
        ([1, 1], 1.0, 1.0)
    """

    def __init__(self, capacity: int, block: int = 1024) -> None:
        self.capacity, self.block = int(capacity), int(block)
        nblocks = max(1, -(-self.capacity // self.block))
        self.weights = torch.zeros(nblocks * self.block, dtype=torch.float64)
        self.sums = torch.zeros(nblocks, dtype=torch.float64)
        self.mins = torch.full((nblocks,), math.inf, dtype=torch.float64)

    def set(self, index: torch.Tensor, weights: torch.Tensor) -> None:
        """Sets the weights of rows ``index`` (a later duplicate wins, as in a tensor assignment)."""
        self.weights[index] = weights
        self._refresh(torch.unique(torch.div(index, self.block, rounding_mode="floor")))

    def set_all(self, weights: torch.Tensor) -> None:
        self.weights.zero_()
        self.weights[: weights.numel()] = weights
        self._refresh(None)

    def _refresh(self, blocks: torch.Tensor | None) -> None:
        rows = self.weights.view(-1, self.block)
        if blocks is not None:
            rows = rows[blocks]
        sums = rows.sum(1)
        mins = torch.where(rows > 0, rows, math.inf).amin(1)
        if blocks is None:
            self.sums, self.mins = sums, mins
        else:
            self.sums[blocks], self.mins[blocks] = sums, mins

    def total(self) -> float:
        return float(self.sums.sum())

    def minimum(self) -> float:
        """The smallest positive weight (``inf`` when none is)."""
        return float(self.mins.min())

    def draw(self, mass: torch.Tensor) -> torch.Tensor:
        """Rows whose cumulative weight first exceeds each of ``mass`` (float64 in ``[0, total)``)."""
        cum = self.sums.cumsum(0)
        last = _last_positive(cum.unsqueeze(0))
        block = torch.searchsorted(cum, mass, right=True).clamp_max_(int(last))
        rest = mass - (cum[block] - self.sums[block])
        within = self.weights.view(-1, self.block)[block].cumsum(1)
        offset = torch.searchsorted(within, rest.unsqueeze(1), right=True).squeeze(1)
        offset = torch.minimum(offset, _last_positive(within))  # rounding past the block's last row
        return block * self.block + offset


def _last_positive(cum: torch.Tensor) -> torch.Tensor:
    """Per row of cumulative sums, the position of the last positive term (where the final value is reached)."""
    return torch.searchsorted(cum, cum[:, -1:].contiguous(), right=False).squeeze(1)


# -- persistence in the store ---------------------------------------------------------------------
#
# The group ``_priority/`` holds one array (``priority``, or ``priority_b`` after a re-creation) of
# CHUNK_ROWS-row chunk slots, and its own record: the group's attributes, written as ONE ``zarr.json``
# (replaced atomically on a local store, one PUT on an object store). The record names, for each chunk of
# priorities, the slot that holds it and the crc32c of its values. A write never touches a slot the
# committed record (or the one before it) names: its chunks go to free slots, then the record is replaced.
# A write killed at any step leaves the committed record and every slot it names as they were.


class _Record(NamedTuple):
    """A checked record: which slots hold the priorities, and the store's position when they were written."""

    version: int
    dtype: np.dtype
    length: int  # the store's len at the write
    cursor: int
    write_count: int
    max_priority: float | None
    array: str
    chunk_rows: int
    slots: list[int] | None  # slot of each chunk (format 1: None, chunk c in slot c)
    crc: list[int] | None  # crc32c of each chunk's values (format 1: none)
    previous: list[int]  # the slots of the record before (kept one write longer, for a reader in flight)


class _Stored(NamedTuple):
    """What :func:`_read_state` gives the sampler: the record and the raw priorities of rows ``[0, len)``."""

    record: _Record
    values: np.ndarray
    damaged: list[tuple[str, int, int, str]]  # (store key, first row, end row, what is wrong) of unusable chunks


_ARRAYS = ("priority", "priority_b")  # a re-created array takes the name the committed record does not use
_DTYPES = ("float32", "float64")


def _crc(values: np.ndarray) -> int:
    return int(google_crc32c.value(np.ascontiguousarray(values, dtype=values.dtype.newbyteorder("<")).tobytes()))


def _is_int(v: Any) -> bool:
    return type(v) is int


def _check_record(attrs: dict, capacity: int) -> tuple[_Record | None, list[str]]:
    """``(record, [])`` if every field of ``attrs`` is sound for a store of ``capacity`` rows, else ``(None, why)``.

    Each problem names its field: a value of the wrong type, outside the range the store's extent allows,
    or inconsistent with another field.
    """
    problems: list[str] = []

    def field(key: str, ok, what: str) -> Any:
        if key not in attrs:
            problems.append(f"field {key!r} is missing")
            return None
        value = attrs[key]
        if not ok(value):
            problems.append(f"field {key!r} = {value!r} is not {what}")
            return None
        return value

    if attrs.get("format") != FORMAT:
        return None, [f"field 'format' = {attrs.get('format')!r} is not {FORMAT!r}"]
    version = field("format_version", lambda v: v in (1, 2) and _is_int(v), "1 or 2 (this version reads 1 and 2)")
    if version is None:
        return None, problems
    dtype = field("dtype", lambda v: v in _DTYPES, f"one of {_DTYPES}")
    slots = crc = None
    previous: list[int] = []
    array, rows_per_chunk = "priority", CHUNK_ROWS
    if version == 2:
        array = field("array", lambda v: v in _ARRAYS, f"one of {_ARRAYS}")
        rows_per_chunk = field("chunk_rows", lambda v: _is_int(v) and 1 <= v <= 1 << 30, "an integer in [1, 2**30]")
        nchunks_max = -(-capacity // rows_per_chunk) if rows_per_chunk else 0
        is_slots = lambda v: isinstance(v, list) and all(_is_int(s) and 0 <= s < 1 << 40 for s in v)  # noqa: E731
        slots = field("chunks", lambda v: is_slots(v) and len(set(v)) == len(v) and len(v) <= nchunks_max,
                      f"a list of distinct slot numbers, at most {nchunks_max} (the store's {capacity} rows "
                      f"make {nchunks_max} chunks of {rows_per_chunk})")
        crc = field("crc32c", lambda v: isinstance(v, list) and all(_is_int(s) and 0 <= s < 1 << 32 for s in v)
                    and (slots is None or len(v) == len(slots)), "one crc32c (an integer < 2**32) a chunk")
        previous = field("previous", is_slots, "a list of slot numbers") or []
    extent = capacity if slots is None else min(capacity, len(slots) * (rows_per_chunk or 0))
    length = field("len", lambda v: _is_int(v) and 0 <= v <= extent, f"an integer in [0, {extent}] (the rows the "
                   f"store and the record's chunks hold)")
    field("cursor", lambda v: _is_int(v) and 0 <= v <= max(extent - 1, 0), f"an integer in [0, {max(extent - 1, 0)}]")
    field("write_count", lambda v: _is_int(v) and 0 <= v < 1 << 63, "an integer >= 0")
    top = field("max_priority", lambda v: v is None or type(v) in (int, float) and math.isfinite(v) and v >= 0,
                "null or a finite number >= 0")
    if problems or length is None:
        return None, problems
    return _Record(version, np.dtype(dtype), length, attrs["cursor"], attrs["write_count"],
                   None if top is None else float(top), array, rows_per_chunk, slots, crc, previous), []


def _warn(msg: str) -> None:
    warnings.warn(msg, stacklevel=5)


def _read_state(storage: ZarrStorage, name: str, capacity: int) -> _Stored | None:
    """The stored priorities of ``storage`` (``None``: nothing stored, or a record refused: warns naming the field).

    Every field of the record is checked against ``capacity`` (the store's rows) before use; every chunk
    holding rows below the recorded ``len`` is read and checked against its crc32c. A chunk that is
    missing, damaged or unreadable is listed in ``damaged`` (its rows are zeros in ``values``).
    """
    try:
        group = component_group(storage, name)
        if group is None:
            return None
        attrs = group.attrs.asdict()
    except Exception as err:  # noqa: BLE001 - derived state: the rows are intact, the priorities start over
        _warn(f"{storage.path!r}: the record of the stored priorities ({name}/zarr.json) cannot be read "
              f"({type(err).__name__}: {str(err)[:200]}); every row restarts at priority 1.0, as in a new buffer "
              f"(the rows are intact). The next priority write replaces it.")
        return None
    record, problems = _check_record(attrs, capacity)
    if record is None:
        _warn(f"{storage.path!r}: the record of the stored priorities ({name}/zarr.json) is refused: "
              f"{'; '.join(problems)}. Every row restarts at priority 1.0, as in a new buffer (the priorities are "
              f"derived state: the rows are intact). The next priority write replaces the record.")
        return None
    rows = record.chunk_rows
    values = np.zeros(record.length, dtype=record.dtype)
    damaged: list[tuple[str, int, int, str]] = []
    nread = -(-record.length // rows)
    path = f"{name}/{record.array}"
    try:
        array = group[record.array]
        if not hasattr(array, "shape") or array.ndim != 1 or array.chunks != (rows,) or array.dtype != record.dtype:
            raise ValueError(f"its metadata ({getattr(array, 'shape', None)}, chunks "
                             f"{getattr(array, 'chunks', None)}, {getattr(array, 'dtype', None)}) is not the "
                             f"record's (chunks of {rows}, {record.dtype})")
    except Exception as err:  # noqa: BLE001 - every chunk of the array is lost
        if nread:
            damaged.append((f"{path}/zarr.json", 0, record.length, f"unreadable ({type(err).__name__}: "
                                                                    f"{str(err)[:160]})"))
        return _Stored(record, values, damaged)
    store = array.store
    for c in range(nread):
        slot = c if record.slots is None else record.slots[c]
        lo, hi = c * rows, min((c + 1) * rows, record.length)
        key = f"{array.path}/{array.metadata.encode_chunk_key((slot,))}"
        try:
            if record.slots is not None and (slot + 1) * rows > array.shape[0]:
                raise ValueError(f"slot {slot} is beyond the array's {array.shape[0]} rows")
            chunk = np.asarray(array[slot * rows: (slot + 1) * rows])
            if chunk.size < hi - lo:
                raise ValueError(f"the array's {array.shape[0]} rows end before the record's len {record.length}")
        except Exception as err:  # noqa: BLE001 - a chunk that fails to decode (a crc32c codec mismatch, a torn file)
            damaged.append((key, lo, hi, f"unreadable ({type(err).__name__}: {str(err)[:160]})"))
            continue
        if record.crc is not None:
            bad = "" if _crc(chunk) == record.crc[c] else "checksum"
        else:  # format 1: no checksum, but every chunk was written (a missing one reads as Zarr's fill value)
            bad = "" if zarr_sync(store.exists(key)) else "missing"
        if not bad and (not np.all(np.isfinite(chunk[: hi - lo])) or np.any(chunk[: hi - lo] < 0)):
            bad = "values"
        if bad:
            if bad == "checksum":
                bad = "missing" if not zarr_sync(store.exists(key)) else "damaged (its crc32c does not match)"
            elif bad == "values":
                bad = "damaged (negative or non-finite values)"
            damaged.append((key, lo, hi, bad))
            continue
        values[lo:hi] = chunk[: hi - lo]
    return _Stored(record, values, damaged)


# Each step of a write is one of the functions below: a write killed between any two leaves the committed
# record and the slots it names untouched (tests/reliability/test_priority_faults.py kills at each).


def _create_array(group, name: str, size: int, rows: int, dtype: np.dtype):
    """A new, empty array of ``size`` rows (no record names it: ``overwrite`` drops only unreferenced slots)."""
    return group.create_array(name, shape=(size,), chunks=(rows,), dtype=dtype, fill_value=0, overwrite=True,
                              compressors=make_compressors("zstd", 3, dtype.itemsize),
                              config={"write_empty_chunks": True})


def _resize_array(array, size: int) -> None:
    """More slots at the end (the array's ``zarr.json``, replaced in one write; no slot is moved or dropped)."""
    array.resize((size,))


def _write_chunk(array, slot: int, values: np.ndarray) -> None:
    """Writes one chunk of priorities into a free slot (one chunk file: no record names it yet)."""
    rows = values.size
    array[slot * rows: (slot + 1) * rows] = values


def _write_record(group, record: dict) -> None:
    """The commit: the group's attributes, replaced in ONE ``zarr.json`` write."""
    group.attrs.put(record)


def _delete_array(group, name: str) -> None:
    """Drops an array no record names any more (after a re-creation, or one left by a killed write)."""
    del group[name]


def _group_for_write(storage: ZarrStorage, name: str):
    try:
        return component_group(storage, name, write=True)
    except (ValueError, TypeError, KeyError):  # its zarr.json does not parse: no record to keep (the read warned)
        return component_group(storage, name, write=True, fresh=True)


def _write_state(storage: ZarrStorage, name: str, raw: torch.Tensor, chunks: set[int], attrs: dict) -> None:
    """Writes the ``chunks`` of ``raw`` that changed into free slots, then the record that names them.

    A chunk the committed record names but ``chunks`` leaves out keeps its slot. The committed array is kept
    when the record is sound and of the same dtype and chunking; otherwise every chunk is written into a new
    array under the other name, which the new record names (the old array is dropped after the record).
    """
    group = _group_for_write(storage, name)
    rows = CHUNK_ROWS
    values = raw.numpy()
    dtype = values.dtype
    nchunks = max(1, -(-values.size // rows))
    padded = np.zeros(nchunks * rows, dtype=dtype)
    padded[: values.size] = values
    current = group.attrs.asdict()
    record, _ = _check_record(current, values.size)
    array = None
    if record is not None and record.version == 2 and record.dtype == dtype and record.chunk_rows == rows:
        try:
            array = group[record.array]
            if array.ndim != 1 or array.chunks != (rows,) or array.dtype != dtype or array.shape[0] % rows:
                array = None
        except KeyError:
            array = None
    if array is not None:
        name_used, slots, crc = record.array, list(record.slots), list(record.crc)
        protected = set(record.slots) | set(record.previous)
        write = {c for c in chunks if c < nchunks} | set(range(len(slots), nchunks))
        previous = list(record.slots) if write else list(record.previous)  # one record back stays readable
    else:  # a first write, a format-1 group, a refused record, a new dtype: every chunk into a new array
        used = current.get("array") if current.get("array") in _ARRAYS else (
            "priority" if current.get("format_version") == 1 else None)
        name_used = "priority_b" if used == "priority" else "priority"
        array = _create_array(group, name_used, nchunks * rows, rows, dtype)
        slots, crc, protected, previous = [], [], set(), []
        write = set(range(nchunks))
    slots += [-1] * (nchunks - len(slots))
    crc += [0] * (nchunks - len(crc))
    free = (s for s in itertools.count() if s not in protected)
    for c in sorted(write):
        slots[c] = next(free)
    size = (max(slots) + 1) * rows
    if array.shape[0] < size:
        _resize_array(array, size)
    for c in sorted(write):
        chunk = padded[c * rows: (c + 1) * rows]
        _write_chunk(array, slots[c], chunk)
        crc[c] = _crc(chunk)
    _write_record(group, {**attrs, "format": FORMAT, "format_version": FORMAT_VERSION, "dtype": str(dtype),
                          "array": name_used, "chunk_rows": rows, "chunks": slots[:nchunks], "crc32c": crc[:nchunks],
                          "previous": previous})
    other = _ARRAYS[1 - _ARRAYS.index(name_used)]
    if other in group:
        _delete_array(group, other)


_LIVE: weakref.WeakSet = weakref.WeakSet()
os.register_at_fork(after_in_child=_LIVE.clear)  # a forked child writes no priority of its parent's samplers at exit
_HOOKED = False
_EXITING = False


def _persist_all_at_exit() -> None:
    global _EXITING
    _EXITING = True
    for sampler in list(_LIVE):
        try:
            sampler.flush()
        except Exception as err:  # noqa: BLE001 - report, never raise at exit
            _report(f"the priorities of {sampler!r} changed since they were last written are lost "
                             f"({err}). Call sampler.flush() before closing its storage.")


def _report(msg: str) -> None:
    try:
        sys.stderr.write(f"torchrl_robotmem: {msg}\n")
    except Exception:  # noqa: BLE001 - stderr may be gone at exit
        pass


def _hook_exit(sampler: PersistentPrioritizedSampler) -> None:
    """Priorities are written at interpreter exit, before the storages close (a later threading hook runs first)."""
    global _HOOKED
    _LIVE.add(sampler)
    lifecycle.register_writer(sampler)  # SIGTERM: flushed with the storages
    if not _HOOKED:
        _HOOKED = True
        try:
            threading._register_atexit(_persist_all_at_exit)  # type: ignore[attr-defined]
        except (AttributeError, RuntimeError):
            pass


class PersistentPrioritizedSampler(PrioritizedSampler):
    """Proportional prioritized replay in pure PyTorch, with its priorities kept in a ``ZarrStorage``'s store.

    Same semantics, arguments and keys as TorchRL's :class:`~torchrl.data.PrioritizedSampler`: rows are drawn
    with probability ``(p + eps) ** alpha / sum``, each sample carries the importance weight
    ``(w_i / min w) ** -beta`` under ``"priority_weight"``, new rows get the largest priority given so far
    (1.0 at first), and ``update_priority(index, priority)`` / ``TensorDictReplayBuffer(priority_key=...)``
    update them. It subclasses ``PrioritizedSampler`` (without running its ``__init__``, which builds the
    C++ trees) because TorchRL's buffers route ``update_tensordict_priority`` to ``isinstance(sampler,
    PrioritizedSampler)`` only; every method that touches the trees is replaced.

    Over a :class:`~torchrl_robotmem.ZarrStorage` opened for writing, the raw priorities are written into
    the store's reserved group ``name`` (dirty chunks only, after the store's own rows are flushed) on
    :meth:`flush`, ``state_dict`` / ``dumps`` (checkpoints), every ``persist_interval`` seconds of updates,
    on SIGTERM and at interpreter exit; the first contact with the storage reads them back. Rows written
    after the last priority write get the max priority. A read-only storage samples with the stored
    priorities and writes none. Over any other storage the priorities live in RAM (and in
    ``state_dict`` / ``dumps``). A buffer built over a store that holds rows gives every row the default
    priority (TorchRL's ``ReplayBuffer._initialize_prioritized_sampler``); the sampler skips that fill
    when it read the priorities from the store. ``storage.close()`` writes them first.

    Args:
        max_capacity (int, optional): rows; defaults to the storage's ``max_size`` at first contact.
        alpha (float): priority exponent (0: uniform). beta (float): importance-weight exponent.
        eps (float, optional): added to every priority. Defaults to ``1e-8``.
        dtype (torch.dtype or str, optional): of the stored priorities, float32 (default) or float64.
        reduction (str, optional): how a multi-valued priority is reduced, as in TorchRL. Defaults to ``"max"``.
        max_priority_within_buffer (bool, optional): new rows get the max priority of the rows held now,
            rather than the largest ever given. Defaults to ``False``.

    Keyword Args:
        name (str, optional): the store's group holding the priorities. Defaults to ``"_priority"``.
        persist_interval (float, optional): seconds between writes made by updates (``None``: only on
            flush, checkpoints and exit). Defaults to 60.
        block (int, optional): rows per block of the sampling table. Defaults to 1024.

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import TensorDictReplayBuffer
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.samplers.prioritized import PersistentPrioritizedSampler
        >>> path = tempfile.mkdtemp() + "/memory.zarr"
        >>> rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 1000),
        ...                             sampler=PersistentPrioritizedSampler(alpha=0.7, beta=0.5), batch_size=8)
        >>> _ = rb.extend(TensorDict({"obs": torch.randn(10, 3)}, [10]))
        >>> batch = rb.sample()
        >>> rb.update_tensordict_priority(batch.set("td_error", torch.rand(8)))
        >>> before = rb.sampler.priority.clone()
        >>> rb.sampler.flush(); rb.storage.close()
        >>> rb = TensorDictReplayBuffer(storage=ZarrStorage(path),
        ...                             sampler=PersistentPrioritizedSampler(alpha=0.7, beta=0.5), batch_size=8)
        >>> "priority_weight" in rb.sample().keys(), torch.equal(rb.sampler.priority, before)
        (True, True)
        >>> rb.storage.close()
    """

    def __init__(self, max_capacity: int | None = None, alpha: float = 0.6, beta: float = 0.4, eps: float = 1e-8,
                 dtype: torch.dtype | str = torch.float32, reduction: str = "max",
                 max_priority_within_buffer: bool = False, *, name: str = "_priority",
                 persist_interval: float | None = 60.0, block: int = 1024) -> None:
        # PrioritizedSampler.__init__ is not called: it builds the C++ trees this class replaces.
        if alpha < 0 or beta < 0:
            raise ValueError(f"alpha and beta must be >= 0, got alpha={alpha}, beta={beta}.")
        if not (isinstance(eps, (int, float)) and math.isfinite(eps) and eps >= 0):
            raise ValueError(f"eps must be a finite number >= 0, got {eps!r}.")
        if not isinstance(name, str) or not name.startswith("_") or "/" in name or name in RESERVED:
            raise ValueError(f"name must be one top-level name starting with '_' (not one of {RESERVED}), got {name!r}.")
        dtype = getattr(torch, dtype) if isinstance(dtype, str) else dtype
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}.")
        self._max_capacity = None if max_capacity is None else int(max_capacity)
        self._alpha, self._beta, self._eps = float(alpha), float(beta), float(eps)
        self.dtype, self.reduction = dtype, reduction
        self._max_priority_within_buffer = bool(max_priority_within_buffer)
        self._device = torch.device("cpu")
        self.name, self.persist_interval, self.block = name, persist_interval, int(block)
        self._storage_ref = None  # the storage met first (weakly: the sampler never keeps a store open)
        self._persistent = False
        self._skip_fill = False
        self._table: PriorityTable | None = None
        self._raw: torch.Tensor | None = None  # raw priorities, in self.dtype
        self._top = None
        self._dirty: set[int] = set()
        self._last_persist = 0.0
        if self._max_capacity is not None:
            self._allocate(self._max_capacity)

    # -- the table -------------------------------------------------------------------------------

    def _allocate(self, capacity: int) -> None:
        self._max_capacity = int(capacity)
        self._table = PriorityTable(capacity, self.block)
        self._raw = torch.zeros(capacity, dtype=self.dtype)
        self._dirty = set(range(-(-capacity // CHUNK_ROWS)))

    def _weights(self, raw: torch.Tensor) -> torch.Tensor:
        return (raw.double() + self._eps) ** self._alpha

    def _set(self, index: torch.Tensor, raw: torch.Tensor) -> None:
        self._raw[index] = raw
        self._table.set(index, self._weights(self._raw[index]))
        self._dirty.update(torch.unique(torch.div(index, CHUNK_ROWS, rounding_mode="floor")).tolist())

    @property
    def priority(self) -> torch.Tensor:
        """The raw priorities of the rows held (a view: read, do not write)."""
        storage = self._storage()
        n = len(storage) if storage is not None else (0 if self._raw is None else self._raw.numel())
        return self._raw[:n] if self._raw is not None else torch.zeros(0, dtype=self.dtype)

    @property
    def max_size(self):
        return self._max_capacity

    @property
    def device(self) -> torch.device:
        return self._device

    @property
    def alpha(self):
        return self._alpha

    @alpha.setter
    def alpha(self, value):
        if value < 0:
            raise ValueError(f"alpha must be greater or equal than 0, got alpha={value}")
        self._alpha = float(value)
        if self._raw is not None:  # the raw priorities are kept: exact for any change of alpha
            n = self._filled()
            self._table.set_all(self._weights(self._raw[:n]))

    @property
    def default_priority(self) -> float:
        """The priority of a new row: the largest given so far (or held now), 1.0 before any."""
        if self._max_priority_within_buffer and self._raw is not None and self._filled():
            return float(self._raw[: self._filled()].max())
        return 1.0 if self._top is None else float(self._top)

    def _filled(self) -> int:
        storage = self._storage()
        return min(len(storage), self._max_capacity) if storage is not None else int(self._max_capacity or 0)

    # -- the storage -----------------------------------------------------------------------------

    def _storage(self):
        return None if self._storage_ref is None else self._storage_ref()

    def _attach(self, storage) -> None:
        """First contact with ``storage``: size the table, read the store's priorities, hook the writes."""
        if storage is None or self._storage() is storage:
            return
        if self._storage_ref is not None:
            raise RuntimeError(f"{type(self).__name__} serves one storage; it met a second one ({storage!r}). "
                               "Build one sampler per replay buffer.")
        if getattr(storage, "ndim", 1) != 1:
            raise ValueError(f"{type(self).__name__} supports storages with ndim=1, got ndim={storage.ndim}.")
        if getattr(storage, "bounded", True) is False:
            raise ValueError(
                f"{type(self).__name__} keeps one priority a row, in a table the size of the storage's capacity, "
                f"and {storage!r} has none (a memory without max_size grows without bound). Build the memory "
                f"with a capacity (ZarrStorage(path, max_size)); to replay the newest rows of a growing memory, "
                f"use WindowSampler."
            )
        capacity = int(storage.max_size)
        if self._max_capacity is not None and self._max_capacity != capacity:
            raise ValueError(f"max_capacity={self._max_capacity} but the storage holds {capacity} rows; "
                             "leave max_capacity out to use the storage's.")
        if self._raw is None or self._raw.numel() != capacity:
            self._allocate(capacity)
        self._storage_ref = weakref.ref(storage)
        if isinstance(storage, ZarrStorage):
            self._load(storage)
            self._persistent = not storage.read_only
            if self._persistent:
                self._last_persist = time.monotonic()  # the first periodic write persist_interval from now
                _hook_exit(self)
                flush_before_close(storage, self.flush)  # storage.close() writes the priorities first

    def _load(self, storage: ZarrStorage) -> None:
        n, cap = min(len(storage), self._max_capacity), self._max_capacity
        stored = _read_state(storage, self.name, cap)
        raw = torch.zeros(cap, dtype=self.dtype)
        fresh = torch.ones(n, dtype=torch.bool)  # rows with no usable stored priority: the max priority
        if stored is not None:
            record = stored.record
            m = min(stored.values.size, n)
            raw[:m] = torch.from_numpy(stored.values[:m].copy()).to(self.dtype)
            self._top = record.max_priority
            since = storage.write_count - record.write_count
            if since >= 0:  # (negative: the store was emptied since, and every row is new)
                fresh[:m] = False
                rows = (record.cursor + torch.arange(min(since, cap))) % cap
                fresh[rows[rows < n]] = True  # rows committed after the last priority write
            for _, lo, hi, _ in stored.damaged:
                fresh[lo:min(hi, n)] = True
            self._skip_fill = True
        raw[n:] = 0
        restart = self._restart_priority(raw[:n], fresh)
        raw[:n][fresh] = restart
        if stored is not None:
            for key, lo, hi, why in stored.damaged:
                _warn(f"{storage.path!r}: the priority chunk {key} (rows {lo}-{hi - 1}) is {why}: those rows restart "
                      f"at the max priority, {restart:g} (the largest recorded, as new rows get; 1.0 if none is), the "
                      f"other rows keep theirs. The next priority write replaces the chunk.")
        self._raw = raw
        self._table.set_all(self._weights(raw[:n]))
        if stored is None:
            self._dirty = set(range(-(-cap // CHUNK_ROWS)))
        else:  # the chunks whose rows differ from the stored ones (the others keep their slots)
            self._dirty = set(torch.unique(torch.div(torch.nonzero(fresh).reshape(-1), CHUNK_ROWS,
                                                     rounding_mode="floor")).tolist())

    def _restart_priority(self, raw: torch.Tensor, fresh: torch.Tensor) -> float:
        """The priority of rows with none stored: the max priority (of the kept rows with ``max_priority_within_buffer``)."""
        if self._max_priority_within_buffer and bool((~fresh).any()):
            return float(raw[~fresh].max())
        return 1.0 if self._top is None else float(self._top)

    # -- TorchRL's sampler API ----------------------------------------------------------------

    def sample(self, storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        self._attach(storage)
        if len(storage) == 0:
            raise RuntimeError("Cannot sample from an empty storage.")
        total, p_min = self._table.total(), self._table.minimum()
        if not total > 0 or not math.isfinite(p_min):
            raise RuntimeError("every stored row has priority 0 (with eps=0): there is nothing to draw.")
        mass = torch.rand(batch_size, generator=self._rng, dtype=torch.float64) * total
        index = self._table.draw(mass).clamp_max_(len(storage) - 1)
        return index, {"priority_weight": self.importance_weight(index)}

    def importance_weight(self, index) -> torch.Tensor:
        """The importance weights ``(w_i / min w) ** -beta`` of rows ``index``, as :meth:`sample` gives them."""
        index = torch.as_tensor(index, dtype=torch.long).cpu()
        return ((self._table.weights[index] / self._table.minimum()) ** (-self._beta)).to(self.dtype)

    def extend(self, index) -> None:
        return None

    def add(self, index) -> None:
        return None

    def mark_update(self, index, *, storage=None) -> None:
        self._attach(storage)
        index = torch.as_tensor(index, dtype=torch.long).reshape(-1)
        self._skip_fill = False
        self.update_priority(index, self.default_priority, storage=storage)

    @torch.no_grad()
    def update_priority(self, index, priority, *, storage=None) -> None:  # noqa: D417
        """Sets the priority of the rows ``index``; bad input raises and changes nothing.

        Args:
            index (int or tensor): rows (``-1`` entries are skipped, as TorchRL's max-value writer marks them).
            priority (float or tensor): one value, or one per row; finite and ``>= 0``.

        Keyword Args:
            storage (Storage, optional): the buffer's storage (met first here, or at the first sample).
        """
        self._attach(storage)
        if self._raw is None:
            raise RuntimeError(f"{type(self).__name__} has no capacity yet: pass max_capacity or sample first.")
        index, priority = self._check_update(index, priority)
        if self._skip_fill and self._is_fill(index, priority):
            self._skip_fill = False  # the buffer's initial fill (ReplayBuffer._initialize_prioritized_sampler)
            return
        self._skip_fill = False
        if index.numel() == 0:
            return
        self._set(index, priority.to(self.dtype))
        top = float(priority.max())
        if self._top is None or top > self._top:
            self._top = top
        self._maybe_persist()

    def _check_update(self, index, priority) -> tuple[torch.Tensor, torch.Tensor]:
        index = torch.as_tensor(index)
        if index.dtype.is_floating_point or index.dtype == torch.bool or index.is_complex():
            raise TypeError(f"update_priority: index must be integers, got dtype {index.dtype}.")
        index = index.to(torch.long).cpu()
        if index.ndim > 1:
            raise ValueError(f"update_priority: index must be 1-D (rows of a ndim=1 storage), got {tuple(index.shape)}.")
        index = index.reshape(-1)
        priority = torch.as_tensor(priority).detach().cpu()
        if priority.dtype == torch.bool or priority.is_complex():
            raise TypeError(f"update_priority: priority must be real numbers, got dtype {priority.dtype}.")
        if priority.numel() == 1:
            priority = priority.reshape(1).expand(index.numel())
        elif priority.numel() != index.numel():
            raise ValueError(f"update_priority: {priority.numel()} priorities (shape {tuple(priority.shape)}) for "
                             f"{index.numel()} rows (index shape {tuple(index.shape)}): give one value or one a row.")
        priority = priority.reshape(-1).double()
        keep = index >= 0
        index, priority = index[keep], priority[keep]
        if not bool(torch.isfinite(priority).all()) or bool((priority < 0).any()):
            bad = priority[~torch.isfinite(priority) | (priority < 0)][:3].tolist()
            raise ValueError(f"update_priority: priorities must be finite and >= 0, got {bad} (e.g. a TD error "
                             "that diverged: take its absolute value and check the loss). Nothing was changed.")
        storage = self._storage()
        limit = len(storage) if storage is not None else self._raw.numel()
        if index.numel() and int(index.max()) >= limit:
            raise IndexError(f"update_priority: row {int(index.max())} is not held (the storage holds {limit} rows). "
                             "Nothing was changed.")
        return index, priority

    def _is_fill(self, index: torch.Tensor, priority: torch.Tensor) -> bool:
        n = self._filled()
        return (index.numel() == n and bool((index == torch.arange(n)).all())
                and bool((priority == priority[0]).all()) if n else False)

    def _empty(self) -> None:
        if self._raw is not None:
            self._raw.zero_()
            self._table.set_all(self._raw[:0].double())
            self._dirty = set(range(-(-self._max_capacity // CHUNK_ROWS)))
        self._top = None

    # -- persistence -----------------------------------------------------------------------------

    def _maybe_persist(self) -> None:
        if self._persistent and self.persist_interval is not None:
            now = time.monotonic()
            if now - self._last_persist >= self.persist_interval:
                self.flush()
                self._last_persist = now

    def flush(self) -> None:
        """Writes the changed priorities into the store (after flushing its rows); a no-op off a writable store."""
        storage = self._storage()
        if not self._persistent or storage is None or not (self._dirty or self._meta_dirty(storage)):
            return
        storage.flush()  # the rows first: the priorities then describe committed rows
        last = getattr(storage, "_last_cursor_index", None)  # TorchRL's last written row (the writer's next: +1)
        cursor = 0 if last is None or int(last) < 0 else (int(last) + 1) % self._max_capacity
        attrs = {"len": len(storage), "cursor": cursor, "write_count": int(storage.write_count),
                 "max_priority": self._top, "alpha": self._alpha, "beta": self._beta, "eps": self._eps}
        _write_state(storage, self.name, self._raw, self._dirty, attrs)
        self._dirty = set()
        self._written = (attrs["write_count"], self._top)

    def _meta_dirty(self, storage) -> bool:
        return getattr(self, "_written", None) != (storage.write_count, self._top)

    def close(self) -> None:
        """Writes the priorities (as :meth:`flush`) if the storage is still open; the sampler stays usable.

        (At interpreter exit this runs after the exit hook, which already warned about a storage closed first.)
        """
        try:
            self.flush()
        except RuntimeError:
            if not _EXITING:
                raise

    def state_dict(self) -> dict[str, Any]:
        """The priorities and parameters (the store gets them too, when attached to one)."""
        self.flush()
        return {"_schema_version": 1, "_alpha": self._alpha, "_beta": self._beta, "_eps": self._eps,
                "_max_priority": self._top, "priority": None if self._raw is None else self._raw.clone()}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        raw = state_dict.get("priority")
        if raw is not None:
            raw = torch.as_tensor(raw)
            if raw.ndim != 1 or (self._raw is not None and raw.numel() != self._raw.numel()):
                raise ValueError(f"load_state_dict: 'priority' has shape {tuple(raw.shape)}, expected "
                                 f"({None if self._raw is None else self._raw.numel()},).")
            if not bool(torch.isfinite(raw).all()) or bool((raw < 0).any()):
                raise ValueError("load_state_dict: 'priority' holds negative or non-finite values.")
        self._alpha, self._beta, self._eps = state_dict["_alpha"], state_dict["_beta"], state_dict["_eps"]
        mp = state_dict.get("_max_priority")
        self._top = None if mp is None or isinstance(mp, tuple) and mp[0] is None else float(
            mp[0] if isinstance(mp, tuple) else mp)
        if raw is not None:
            if self._raw is None:
                self._allocate(raw.numel())
            self._raw.copy_(raw.to(self.dtype))
            self._table.set_all(self._weights(self._raw[: self._filled()]))
            self._dirty = set(range(-(-self._max_capacity // CHUNK_ROWS)))
        self._skip_fill = False

    def dumps(self, path) -> None:
        """Writes ``sampler_metadata.json`` and ``priority.npy`` under ``path`` (and the store's copy)."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        state = self.state_dict()
        raw = state.pop("priority")
        with open(path / "sampler_metadata.json", "w") as f:
            json.dump({**state, "dtype": str(self.dtype).split(".")[-1]}, f)
        if raw is not None:
            np.save(path / "priority.npy", raw.numpy(), allow_pickle=False)

    def loads(self, path) -> None:
        path = Path(path)
        with open(path / "sampler_metadata.json") as f:
            state = json.load(f)
        file = path / "priority.npy"
        state["priority"] = torch.from_numpy(np.load(file, allow_pickle=False)) if file.exists() else None
        self.load_state_dict(state)

    def __getstate__(self):
        state = super().__getstate__()
        state["_storage_ref"] = None
        state["_persistent"] = False
        return state

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(alpha={self._alpha}, beta={self._beta}, eps={self._eps}, "
                f"reduction={self.reduction}, persistent={self._persistent})")
