"""Column change tracking: what the index knows of its storage, and which rows changed since.

This is the one module of the recall package that reads a storage's state:
its columns (through :mod:`torchrl_robotmem.storage.columns`, the one column
reader), its length and TorchRL's ``_mutation_revision`` (the counter every
write through the storage bumps). Everything else (views, the index facade,
the sampler, the transform, :class:`~torchrl_robotmem.RobotMemory`) asks
:class:`ColumnTracker` or the functions below.

A :class:`ColumnTracker` keeps a snapshot of the columns an index depends on
(the goals, and the filter columns in use). When the storage's revision moved,
it compares them bitwise with the live columns: this finds appended rows and
rows overwritten in place (ring buffer, ``rb[idx] = ...``, ``loads``,
``ZarrStorage.refresh()``), at about 1 ms per million 3-D goals, whatever
wrote them. Each change gets a new :attr:`~ColumnTracker.revision` and is
logged with its rows; readers that fell behind the (bounded) log rebuild.
"""
from __future__ import annotations

import weakref
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data.replay_buffers.storages import Storage, TensorStorage

from torchrl_robotmem.storage.columns import has_rows, read_column, read_rows, scanning

__all__ = ["ColumnTracker", "as_tensor_storage", "live_column", "stored_rows"]


def as_tensor_storage(storage_or_rb: Any) -> TensorStorage:
    """The ``TensorStorage`` (``ndim=1``) of a storage or replay buffer; ``TypeError`` / ``ValueError`` otherwise."""
    storage = getattr(storage_or_rb, "storage", storage_or_rb)
    if not isinstance(storage, Storage):
        raise TypeError(
            f"expected a TorchRL Storage or ReplayBuffer, got {type(storage_or_rb).__name__}."
        )
    if not isinstance(storage, TensorStorage):
        raise TypeError(
            f"{type(storage).__name__} is not a TensorStorage; GoalIndex reads the columns "
            "of LazyTensorStorage, LazyMemmapStorage, ZarrStorage (or any TensorStorage)."
        )
    if storage.ndim != 1:
        raise ValueError(f"GoalIndex needs a storage with ndim=1, got ndim={storage.ndim}.")
    return storage


def storage_revision(storage: Storage) -> int | None:
    """TorchRL's mutation counter of ``storage`` (``None`` where this torchrl has none)."""
    try:
        return int(storage._mutation_revision)
    except AttributeError:  # older torchrl: resynchronise on every query
        return None


def live_column(storage: Storage, key: NestedKey) -> torch.Tensor | None:
    """The stored column ``key`` (``[max_size, *shape]``, no copy), or ``None`` before the first write.

    Raises a ``KeyError`` listing the stored keys when the storage has rows but
    no such column.
    """
    if not has_rows(storage):
        return None
    return read_column(storage, key)


def stored_rows(storage: Storage, rows: torch.Tensor) -> TensorDictBase | None:
    """Every stored entry of ``rows`` (int64, any shape; ``-1`` reads row 0), or ``None`` before the first write.

    Read with :func:`~torchrl_robotmem.storage.columns.read_rows`, not through
    ``storage.get``: a ``ZarrStorage`` keeps its ``episode`` / ``run`` / ``env``
    tags out of sampled batches unless ``sample_tags=True``, and a recall returns them.
    """
    if not has_rows(storage):
        return None
    return read_rows(storage, rows)


def _key_str(key: NestedKey) -> str:
    return repr(key) if isinstance(key, tuple) else repr(str(key))


def _missing(key: NestedKey, what: str, advice: str, err: KeyError) -> KeyError:
    """The error of a filter whose column the storage does not hold: the column, the fix, the stored keys."""
    fix = f" The rows were written without it. {advice}" if advice else ""
    return KeyError(f"{what} needs the column {_key_str(key)}, which this storage does not hold.{fix} "
                    f"({err.args[0]})")


def _bits(a: np.ndarray) -> np.ndarray:
    """Flat integer view of a contiguous array, for bitwise comparison (NaN == NaN)."""
    flat = a.reshape(-1)
    return flat.view(np.dtype(f"i{flat.dtype.itemsize}")) if flat.dtype.kind != "b" else flat


def _numpy(col: torch.Tensor) -> np.ndarray:
    if col.device.type != "cpu":
        col = col.cpu()
    return torch.Tensor.numpy(col.as_subclass(torch.Tensor) if type(col) is not torch.Tensor else col)


_DIFF_CHUNK = 1 << 20  # rows compared at a time: bounds the comparison's temporaries


def _grow(snap: np.ndarray | None, live: np.ndarray, n: int, cap: int, dtype=None) -> np.ndarray:
    """Snapshot buffer with room for ``n`` rows (capacity doubles, up to ``cap``); new rows left for the caller.

    A new buffer (``snap is None``) has ``dtype`` (default: ``live``'s) and holds ``live[:n]``.
    """
    if snap is None:
        out = np.empty((max(n, 1), *live.shape[1:]), dtype=dtype or live.dtype)
        out[:n] = live[:n]
        return out
    if snap.shape[0] >= n:
        return snap
    out = np.empty((max(n, min(2 * snap.shape[0], cap)), *snap.shape[1:]), dtype=snap.dtype)
    out[: snap.shape[0]] = snap
    return out


class _StrongRef:
    """``weakref.ref``-like holder that keeps its object alive (and pickles)."""

    __slots__ = ("obj",)

    def __init__(self, obj):
        self.obj = obj

    def __call__(self):
        return self.obj


_DERIVED_STATE = ("_rev", "n", "_snap", "_log", "_log_rows", "_floor", "goal_shape")


class ColumnTracker:
    """Snapshots of a storage's goal column and the filter columns in use, and a log of changed rows.

    Args:
        storage (TensorStorage): the storage followed.
        goal_key (NestedKey): the goal column (always tracked).

    Keyword Args:
        weak (bool): hold the storage weakly (a shared index must not keep its
            storage alive). Defaults to ``False``.
        float64_goals (bool): keep the snapshot of a floating-point goal
            column in float64 (the values are the same: float16/32 convert
            exactly), so that a Euclidean KD-tree searches it in place
            instead of holding its own float64 copy. Defaults to ``False``.
        tail_size (int), rebuild_fraction (float): the change log keeps about
            ``2 * max(tail_size, rebuild_fraction * n)`` rows; readers further
            behind rebuild. Defaults to 4096 and 0.05 (those of ``GoalIndex``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage
        >>> from torchrl_robotmem.goal_index.tracking import ColumnTracker
        >>> st = LazyTensorStorage(10)
        >>> st.set(range(4), TensorDict({"g": torch.rand(4, 3)}, [4]))
        >>> tracker = ColumnTracker(st, "g")
        >>> tracker.sync(); tracker.n, tracker.goal_dim
        (4, 3)
        >>> seen = tracker.revision
        >>> st.set([1], TensorDict({"g": torch.zeros(1, 3)}, [1]), set_cursor=False)
        >>> tracker.sync(); tracker.changed_since(seen).tolist()
        [1]
    """

    def __init__(
        self,
        storage: TensorStorage,
        goal_key: NestedKey,
        *,
        weak: bool = False,
        tail_size: int = 4096,
        rebuild_fraction: float = 0.05,
        float64_goals: bool = False,
    ):
        self._ref = weakref.ref(storage) if weak else _StrongRef(storage)
        self.goal_key = goal_key
        self.float64_goals = float64_goals
        self.tail_size = tail_size
        self.rebuild_fraction = rebuild_fraction
        self._tracked: dict[NestedKey, str] = {}  # filter columns: key -> what needs it
        self._advice: dict[NestedKey, str] = {}  # filter columns: key -> how to record it (for errors)
        self.revision = 0
        self._reset()

    def _reset(self) -> None:
        self._rev = None  # the storage revision last synchronised
        self.n = 0
        self._snap: dict[NestedKey, np.ndarray] = {}
        self._log: list[tuple[int, np.ndarray]] = []
        self._log_rows = 0
        self._floor = self.revision  # readers older than this rebuild
        self.goal_shape = None

    @property
    def storage(self) -> TensorStorage:
        """The storage followed."""
        st = self._ref()
        if st is None:
            raise RuntimeError("the storage of this GoalIndex was garbage-collected.")
        return st

    @property
    def goal_dim(self) -> int | None:
        """Size of a stored goal (``None`` before the first write)."""
        return None if self.goal_shape is None else int(np.prod(self.goal_shape))

    @property
    def floor(self) -> int:
        """Oldest revision :meth:`changed_since` can answer from; older readers rebuild."""
        return self._floor

    @property
    def capacity(self) -> int:
        """Rows the snapshots can grow to without reallocating past the storage: its ``max_size`` (or unbounded)."""
        try:
            cap = int(self.storage.max_size)
        except (AttributeError, TypeError, ValueError, OverflowError):  # an unbounded storage
            return 2**62
        return max(cap, self.n, 1)

    def nbytes(self) -> int:
        """Bytes the tracker holds: its column snapshots (their allocated rows) and the change log."""
        return int(sum(a.nbytes for a in self._snap.values()) + sum(rows.nbytes for _, rows in self._log))

    def _snap_dtype(self, key: NestedKey, live: np.ndarray) -> np.dtype:
        """The dtype the snapshot of ``key`` has for live values ``live``."""
        if key == self.goal_key and self.float64_goals and live.dtype.kind == "f":
            return np.dtype(np.float64)
        return live.dtype

    def column(self, key: NestedKey) -> np.ndarray:
        """Snapshot of a tracked column (``[>= n, *shape]``; rows ``[:n]`` are current)."""
        return self._snap[key]

    def flat(self, key: NestedKey, rows: np.ndarray | slice) -> np.ndarray:
        """Snapshot values ``[len(rows), numel]`` of a tracked column at ``rows``."""
        c = self._snap[key][rows]
        return c.reshape(c.shape[0], int(np.prod(c.shape[1:], dtype=np.int64)))

    def changed_since(self, revision: int) -> np.ndarray | None:
        """Rows changed after ``revision`` (sorted, unique), or ``None`` when the log no longer reaches back."""
        if revision < self._floor:
            return None
        logged = [rows for rev, rows in self._log if rev > revision]
        if not logged:
            return np.zeros(0, dtype=np.int64)
        return logged[0] if len(logged) == 1 else np.unique(np.concatenate(logged))

    def track(self, key: NestedKey, what: str, advice: str = "") -> None:
        """Snapshots one more column (one value per row), named ``what`` in errors; kept from then on.

        ``advice``: how to get the column, added to the error when the storage has no such column.
        """
        if key in self._snap or self.goal_shape is None:
            self._tracked.setdefault(key, what)
            self._advice[key] = advice
            return
        with scanning(self.storage):  # every row's value is read: readahead on
            try:
                col = _numpy(read_column(self.storage, key, self.n))
            except KeyError as err:
                raise _missing(key, what, advice, err) from None
            if int(np.prod(col.shape[1:], dtype=np.int64)) != 1:
                raise ValueError(
                    f"{what} needs one value per row in {_key_str(key)}, got shape {tuple(col.shape)}."
                )
            self._snap[key] = _grow(None, col, self.n, self.capacity)
        self._tracked[key] = what
        self._advice[key] = advice

    def sync(self, check_goal_dim=None) -> None:
        """Brings the snapshots up to date with the storage (free when its revision did not move).

        ``check_goal_dim(goal_dim)`` is called when goals are first seen or
        change shape; it raises to refuse them.
        """
        st = self.storage
        rev = storage_revision(st)
        if rev is not None and rev == self._rev:
            return
        if not has_rows(st):
            if self.n or self.goal_shape is not None:
                self.revision += 1
                self._reset()
            self._rev = rev
            return
        with scanning(st):  # the snapshot reads (and compares) every row's columns: readahead on
            self._sync_rows(st, len(st), rev, check_goal_dim)

    def _sync_rows(self, st, n: int, rev, check_goal_dim) -> None:
        """``sync`` of a storage that holds rows: the snapshots brought to its first ``n`` rows."""
        cols = {self.goal_key: _numpy(read_column(st, self.goal_key, n))}
        for key, what in list(self._tracked.items()):
            try:
                cols[key] = _numpy(read_column(st, key, n))
            except KeyError as err:
                raise _missing(key, what, self._advice.get(key, ""), err) from None
        goals = cols[self.goal_key]
        if goals.ndim < 2 or goals.dtype.kind not in "fiu":
            raise ValueError(
                f"goal column {_key_str(self.goal_key)} must be numeric with shape [N, goal_dim], "
                f"got dtype {goals.dtype} and shape {tuple(goals.shape)}."
            )
        shapes_changed = any(
            key in self._snap and (cols[key].shape[1:] != self._snap[key].shape[1:]
                                   or self._snap_dtype(key, cols[key]) != self._snap[key].dtype)
            for key in cols
        )
        if self.goal_shape is None or n < self.n or shapes_changed:
            if check_goal_dim is not None:
                check_goal_dim(int(np.prod(goals.shape[1:])))
            self.revision += 1
            self._reset()
            self.goal_shape = goals.shape[1:]
            for key, live in cols.items():
                self._snap[key] = _grow(None, live, n, n, self._snap_dtype(key, live))
            self.n = n
            self._rev = rev
            return
        m = self.n
        changed = np.zeros(m, dtype=bool)
        for key, live in cols.items():
            snap = self._snap[key]
            width = int(np.prod(live.shape[1:], dtype=np.int64)) or 1
            for c0 in range(0, m, _DIFF_CHUNK):
                c1 = min(c0 + _DIFF_CHUNK, m)
                # a float64 snapshot of float32 goals: the conversion is exact and deterministic,
                # so equal bits after it mean equal stored bits
                now = live[c0:c1] if live.dtype == snap.dtype else live[c0:c1].astype(snap.dtype)
                diff = np.flatnonzero(_bits(now) != _bits(snap[c0:c1]))
                if diff.size:
                    changed[c0 + diff // width] = True
        rows = np.flatnonzero(changed)
        del changed
        cap = self.capacity
        for key, live in cols.items():
            snap = self._snap[key] = _grow(self._snap[key], live, n, cap)
            if rows.size:
                snap[rows] = live[rows]
            if n > m:
                snap[m:n] = live[m:n]
        if n > m:
            rows = np.concatenate([rows, np.arange(m, n)])
        if n < 2**31 - 1:
            rows = rows.astype(np.int32)  # the log holds int32 row ids where they fit
        if rows.size:
            self.revision += 1
            self._log.append((self.revision, rows))
            self._log_rows += rows.size
            limit = 2 * max(self.tail_size, int(self.rebuild_fraction * n)) + rows.size
            while self._log_rows > limit and len(self._log) > 1:
                rev_old, old = self._log.pop(0)
                self._log_rows -= old.size
                self._floor = rev_old
        self.n = n
        self._rev = rev

    def __getstate__(self):
        # Snapshots are derived data, rebuilt at the first sync after unpickling.
        state = {k: v for k, v in self.__dict__.items() if k not in _DERIVED_STATE}
        state["_ref"] = _StrongRef(self.storage)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self.__dict__.setdefault("_advice", {})
        self.__dict__.setdefault("float64_goals", False)
        self._reset()
