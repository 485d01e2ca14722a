"""Uniform replay over the newest ``window`` transitions of a storage (a sliding window).

On a memory that keeps growing (a ring larger than a run needs, or a memory without a declared
capacity) uniform sampling over every row makes the replay ratio of new experience fall as the memory
grows; sampling the newest ``window`` rows keeps it fixed, whatever the memory's size.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torchrl.data.replay_buffers.samplers import Sampler

from .json_state import JsonStateDumps

__all__ = ["WindowSampler"]


def _check_window(window) -> int:
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window <= 0:
        raise ValueError(f"window must be a positive integer (how many of the newest rows are sampled), got "
                         f"{window!r}.")
    return int(window)


class WindowSampler(JsonStateDumps, Sampler):
    """Samples uniformly, with replacement, among the newest ``window`` transitions of the storage.

    - A storage that has not wrapped (``len(storage) < max_size``, or a memory without a capacity):
      the rows ``[len - window, len)``.
    - A full ring (``len(storage) == max_size``): the ``window`` rows that end at the last written row,
      across the wrap. The last written row is read, in this order, from TorchRL's
      ``Storage._last_cursor_index`` (set by every ``TensorStorage.set``, e.g.
      :class:`~torchrl.data.LazyTensorStorage`, and shared with the processes that write; what TorchRL's
      own ``SliceSampler`` reads; a :class:`~torchrl_robotmem.ZarrStorage` keeps it in its commit
      record, so it holds after a reopen and a reader's ``refresh``), from the storage's public
      ``write_count`` (a ``ZarrStorage`` reopened where no write followed a load: row
      ``(write_count - 1) % max_size``), else from the last write this sampler saw through its buffer
      (``extend`` / ``add``). That record is kept in the sampler's ``state_dict``: TorchRL's
      ``rb.load_state_dict`` / ``rb.loads`` restore the rows and the writer's cursor but leave
      ``_last_cursor_index`` unset or stale, so after a restore and until the next write through the
      buffer the restored record places the window first.
      A full ring none of these describe is refused with a ``RuntimeError``, never sampled at random.
    - ``window >= len(storage)``: every stored row.

    The storage must have ``ndim=1`` (``RuntimeError`` otherwise, naming the storage and its ``ndim``):
    flatten the collector's ``[num_envs, T]`` batches with ``reshape(-1)`` before ``rb.extend``.
    It subclasses TorchRL's ``Sampler``, not ``RandomSampler``, so ``ReplayBuffer(consume_after_n_samples=)``
    refuses it instead of replacing it. Over a :class:`~torchrl_robotmem.GoalSimilaritySampler` use
    the composition in ``docs/samplers.md``; as the base of a
    :class:`~torchrl_robotmem.samplers.combined.CombinedExperienceSampler` it gives combined replay over
    the window.

    Args:
        window (int): how many of the newest transitions are sampled (``> 0``). A plain value, so a
            Hydra config builds it with ``_target_: torchrl_robotmem.samplers.WindowSampler``.

    ``state_dict()`` is ``{"window": ..., "last_written": ...}``; ``load_state_dict`` restores both, and
    ``rb.dumps`` / ``rb.loads`` write them as JSON (``sampler_metadata.json``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_robotmem.samplers import WindowSampler
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), sampler=WindowSampler(10),
        ...                             batch_size=256)
        >>> _ = rb.extend(TensorDict({"step": torch.arange(60)}, [60]))
        >>> sorted(set(rb.sample()["index"].tolist())) == list(range(50, 60))
        True
        >>> _ = rb.extend(TensorDict({"step": torch.arange(60, 105)}, [45]))  # the ring wrapped: 100..104 in rows 0..4
        >>> rb.sampler.window_rows(rb.storage).tolist()
        [95, 96, 97, 98, 99, 0, 1, 2, 3, 4]
        >>> set(rb.sample()["step"].tolist()) <= set(range(95, 105))
        True
    """

    def __init__(self, window: int) -> None:
        self.window = _check_window(window)
        self._last_written: int | None = None  # the last row written through the buffer (extend / add)
        self._restored = False  # _last_written came from load_state_dict and no write followed

    # -- where the window is --------------------------------------------------------------------

    def _last_row(self, storage, n: int, size: int) -> int:
        # TorchRL: every TensorStorage.set records it (shared with processes that write, e.g. a collector's;
        # ZarrStorage keeps it in its record); TorchRL's rb.load_state_dict / loads do not restore it: until
        # the next write, the restored record wins (a store's write_count counts the rows a load wrote, not
        # where the loaded writer goes on)
        last = self._last_written if self._restored else getattr(storage, "_last_cursor_index", None)
        if last is None:
            write_count = getattr(storage, "write_count", None)  # ZarrStorage: public, kept in the store
            if isinstance(write_count, (int, np.integer)) and not isinstance(write_count, bool) and write_count >= n:
                return (int(write_count) - 1) % size
            last = self._last_written
        if last is None:
            raise RuntimeError(
                f"WindowSampler cannot tell where the newest rows of the full ring {type(storage).__name__} "
                f"(len={n}) end: the storage records no last written row (no write_count, no "
                f"_last_cursor_index) and no write went through this sampler's buffer. Write through the "
                f"buffer (rb.extend / rb.add) before sampling."
            )
        last = int(last.reshape(-1)[-1]) if isinstance(last, torch.Tensor) else int(last)
        return last % size

    def _bounds(self, storage) -> tuple[int, int, int]:
        """``(start, k, size)``: the window is rows ``(start + arange(k)) % size``."""
        ndim = getattr(storage, "ndim", 1)
        if ndim != 1:
            raise RuntimeError(
                f"WindowSampler samples storages with ndim=1; {type(storage).__name__} has ndim={ndim}, whose "
                f"rows have no single write order. Build the storage with ndim=1 and flatten the "
                f"collector's batch (reshape(-1)) before rb.extend."
            )
        n = len(storage)
        if n == 0:
            raise RuntimeError("Cannot sample from an empty storage.")
        k = min(self.window, n)
        max_size = getattr(storage, "max_size", None)
        if max_size is None or n < int(max_size):  # not wrapped (or no capacity): the rows written last
            return n - k, k, n
        size = int(max_size)
        last = self._last_row(storage, n, size)
        return (last - k + 1) % size, k, size

    def window_rows(self, storage) -> torch.Tensor:
        """The rows sampled now, oldest first (``min(window, len(storage))`` of them)."""
        start, k, size = self._bounds(storage)
        return (start + torch.arange(k)) % size

    # -- sampling -------------------------------------------------------------------------------

    def sample(self, storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        start, k, size = self._bounds(storage)
        index = (start + torch.randint(k, (batch_size,), generator=self._rng)) % size
        device = getattr(storage, "device", None)
        if isinstance(device, (str, torch.device)) and str(device) not in ("cpu", "auto"):
            index = index.to(device)
        return index, {}

    def _note_written(self, index) -> None:
        if isinstance(index, tuple):  # an ndim > 1 write: sample() names the problem
            return
        index = torch.as_tensor(index).reshape(-1)
        if index.numel():
            self._last_written = int(index[-1])
            self._restored = False

    def extend(self, index) -> None:
        self._note_written(index)

    def add(self, index) -> None:
        self._note_written(index)

    # -- state ----------------------------------------------------------------------------------

    def _empty(self) -> None:
        self._last_written = None
        self._restored = False

    def state_dict(self) -> dict[str, Any]:
        return {"window": self.window, "last_written": self._last_written}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.window = _check_window(state_dict["window"])
        last = state_dict.get("last_written")
        self._last_written = None if last is None else int(last)
        self._restored = last is not None

    def __repr__(self) -> str:
        return f"{type(self).__name__}(window={self.window})"
