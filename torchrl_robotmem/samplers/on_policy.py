"""On-policy batch replay over a persistent storage: minibatches of the newest collected batch only.

SLM Lab's ``OnPolicyBatchReplay`` trains on the batch just collected and then
forgets it. :class:`OnPolicyBatchSampler` keeps the first half and drops the
second: the buffer's storage (a :class:`~torchrl_robotmem.ZarrStorage`) keeps
every row ever written, so an on-policy run (PPO, A2C) leaves its experience
behind for off-policy runs, recall and later runs, while the sampler hands the
learner only the rows of the newest batch, in shuffled minibatches without
replacement, for a fixed number of epochs, as TorchRL's sota PPO does with a
``SamplerWithoutReplacement`` over a storage of one batch.
"""
from __future__ import annotations

from typing import Any

import torch
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from torchrl_robotmem.samplers.json_state import JsonStateDumps

__all__ = ["OnPolicyBatchSampler"]

_STATE_KEYS = ("epochs", "drop_last", "shuffle", "accumulate", "position_key", "batch", "valid", "order", "epoch", "drawn", "ran_out")


def _as_index(index, what: str) -> torch.Tensor:
    """A write's storage indices as a flat CPU LongTensor (1-D storages only)."""
    if isinstance(index, tuple):
        raise ValueError(
            f"OnPolicyBatchSampler.{what}: got a tuple of index tensors (a storage with ndim > 1). It draws "
            "rows of 1-D storages: flatten the collected batch before extending (data.reshape(-1))."
        )
    index = torch.as_tensor(index).reshape(-1)
    if index.is_floating_point() or index.dtype == torch.bool:
        raise ValueError(f"OnPolicyBatchSampler.{what}: storage indices must be integers, got {index.dtype}.")
    return index.to("cpu", torch.long)


class OnPolicyBatchSampler(JsonStateDumps, Sampler):
    """Draws minibatches, without replacement, from the rows of the newest write only, for ``epochs`` epochs.

    The sampler learns the newest rows from the buffer's ``extend`` / ``add``
    hooks (storage indices only; the rows stay in the storage, which keeps
    every row ever written): each write replaces the batch. With
    ``accumulate=True``, writes that follow each other with no draw in between
    make one batch (a collector that writes trajectory by trajectory,
    ``Collector(replay_buffer=rb)``, still gives one batch a collection) and
    the first write after a draw starts a new one.

    Each epoch is one pass over the batch in a fresh random order (``shuffle``),
    cut into minibatches of the requested size: no row is drawn twice in an
    epoch. The last minibatch of an epoch holds what is left (fewer rows) or,
    with ``drop_last``, is skipped. When an epoch's rows are used up
    :attr:`ran_out` turns ``True``, which ends ``for batch in rb:`` (TorchRL's
    iteration protocol, as with :class:`~torchrl.data.SamplerWithoutReplacement`);
    the next draw starts the next epoch. After ``epochs`` epochs the batch is
    stale for an on-policy learner and :meth:`sample` raises until new rows
    are written. Nothing written since the sampler was built (a reopened
    memory's old rows) is an error too, never a silent draw of old rows.

    Every sampled TensorDict also gets ``position_key``: each row's position
    in the batch, in write order (the order of the data that was extended).
    It joins values the learner computed on the collected batch but did not
    store (advantages, value targets, log-probabilities) to the drawn rows:
    ``batch.update(extra[batch["batch_position"]])``.

    Args:
        epochs (int): passes over each batch before it is stale. Defaults to 1.

    Keyword Args:
        drop_last (bool): skip an epoch's last minibatch when it is smaller than
            the batch size. Defaults to ``False``.
        shuffle (bool): a fresh random order each epoch (the buffer's generator);
            ``False``: write order. Defaults to ``True``.
        accumulate (bool): writes with no draw in between make one batch;
            ``False``: the newest write alone. Defaults to ``False``.
        position_key (str, optional): the key of the rows' batch positions in
            sampled TensorDicts; ``None`` leaves it out. Defaults to ``"batch_position"``.

    Raises:
        ValueError: on ``epochs < 1``, or when ``drop_last`` leaves no full minibatch.
        RuntimeError: on :meth:`sample` with no new rows, with all epochs drawn,
            or after the storage lost rows of the batch (emptied).

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import TensorDictReplayBuffer
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.samplers.on_policy import OnPolicyBatchSampler
        >>> path = tempfile.mkdtemp() + "/onpolicy.zarr"
        >>> rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 1000, env="FetchReach-v4"),
        ...                             sampler=OnPolicyBatchSampler(epochs=2), batch_size=4)
        >>> def rows(a, b):  # transitions a..b-1 (with the success flag the memory keeps)
        ...     return TensorDict({"obs": torch.arange(a, b).float(), ("next", "is_success"): torch.zeros(b - a)}, [b - a])
        >>> _ = rb.extend(rows(0, 10))                    # an older batch
        >>> _ = rb.extend(rows(10, 16))                   # the newest
        >>> epoch = [b["obs"] for b in rb]                # one pass: minibatches of 4 and 2
        >>> [len(x) for x in epoch], sorted(torch.cat(epoch).tolist())
        ([4, 2], [10.0, 11.0, 12.0, 13.0, 14.0, 15.0])
        >>> sorted(torch.cat([b["batch_position"] for b in rb]).tolist())  # second epoch
        [0, 1, 2, 3, 4, 5]
        >>> rb.sample()
        Traceback (most recent call last):
        ...
        RuntimeError: OnPolicyBatchSampler: all 2 epochs over the newest batch (6 rows) have been drawn...
        >>> len(rb.storage)                               # every row stays in the memory
        16
        >>> rb.storage.close()
    """

    def __init__(self, epochs: int = 1, *, drop_last: bool = False, shuffle: bool = True, accumulate: bool = False,
                 position_key: str | None = "batch_position"):
        self.epochs = int(epochs)
        self.drop_last = bool(drop_last)
        self.shuffle = bool(shuffle)
        self.accumulate = bool(accumulate)
        self.position_key = position_key
        self._check_config()
        self._empty()

    def _check_config(self) -> None:
        if self.epochs < 1:
            raise ValueError(f"OnPolicyBatchSampler: epochs must be >= 1, got {self.epochs}.")
        if self.position_key is not None and not isinstance(self.position_key, str):
            raise ValueError(f"OnPolicyBatchSampler: position_key must be a str or None, got {self.position_key!r}.")

    # -- the newest batch, from the buffer's write hooks ------------------------
    def extend(self, index) -> None:
        index = _as_index(index, "extend")
        if self._batch is None or self._drawn or not self.accumulate:
            self._batch = index
        else:  # writes with no draw in between: one batch
            self._batch = torch.cat([self._batch, index])
        # a storage smaller than the batch wraps around: a later write over the same slot wins
        slots, inverse = torch.unique(self._batch, return_inverse=True)
        positions = torch.arange(len(self._batch))
        if len(slots) == len(self._batch):
            self._valid = positions
        else:  # each slot's last position in the batch
            last = torch.full((len(slots),), -1, dtype=torch.long).scatter_reduce(0, inverse, positions, reduce="amax")
            self._valid = last.sort().values
        self._order, self._epoch, self._drawn, self._ran_out = None, 0, False, False
        self._remaining_batches = int(torch.iinfo(torch.int64).max)

    def add(self, index: int) -> None:
        self.extend(torch.as_tensor([index]))

    # -- drawing ------------------------------------------------------------------
    @property
    def batch_rows(self) -> int:
        """Rows of the newest batch (0 before any write)."""
        return 0 if self._valid is None else len(self._valid)

    @property
    def epochs_left(self) -> int:
        """Epochs not yet started over the newest batch (the one under way not counted)."""
        return 0 if self._batch is None else self.epochs - self._epoch

    def _epoch_has(self, batch_size: int) -> bool:
        """Whether the epoch under way still has a minibatch of ``batch_size`` to give."""
        if self._order is None or not len(self._order):
            return False
        return len(self._order) >= batch_size or not self.drop_last

    def _check_batch(self, storage: Storage, batch_size: int) -> None:
        if self._batch is None:
            raise RuntimeError(
                f"OnPolicyBatchSampler: nothing to sample: no rows were written since the sampler was built "
                f"or emptied (the storage holds {len(storage)} rows, all older: an on-policy sampler draws only "
                "the newest batch). Extend the buffer with a newly collected batch first."
            )
        if len(self._batch) and int(self._batch.max()) >= len(storage):
            raise RuntimeError(
                f"OnPolicyBatchSampler: the newest batch has rows up to index {int(self._batch.max())}, but the "
                f"storage now holds {len(storage)} rows (emptied or replaced since the write?). Extend it again."
            )
        if batch_size < 1:
            raise ValueError(f"OnPolicyBatchSampler: batch_size must be >= 1, got {batch_size}.")
        if self.drop_last and self.batch_rows < batch_size:
            raise ValueError(
                f"OnPolicyBatchSampler(drop_last=True): the newest batch has {self.batch_rows} rows, fewer than "
                f"one minibatch of {batch_size}. Use a smaller batch size or drop_last=False."
            )

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        self._check_batch(storage, batch_size)
        if not self._epoch_has(batch_size):
            if self._epoch >= self.epochs:
                raise RuntimeError(
                    f"OnPolicyBatchSampler: all {self.epochs} epochs over the newest batch ({self.batch_rows} "
                    "rows) have been drawn: the batch is stale for an on-policy learner. Extend the buffer with "
                    "a newly collected batch, or build the sampler with more epochs (OnPolicyBatchSampler(epochs=N))."
                )
            n = len(self._valid)
            order = torch.randperm(n, generator=self._rng) if self.shuffle else torch.arange(n)
            self._order = self._valid[order]
            self._epoch += 1
        positions, self._order = self._order[:batch_size], self._order[batch_size:]
        self._drawn = True
        self._ran_out = not self._epoch_has(batch_size)
        left = len(self._order)
        self._remaining_batches = left // batch_size if self.drop_last else -(-left // batch_size)
        device = getattr(storage, "device", None)
        index = self._batch[positions]
        if isinstance(device, torch.device) and device.type != "cpu":
            index, positions = index.to(device), positions.to(device)
        info = {} if self.position_key is None else {self.position_key: positions}
        return index, info

    def can_sample(self, storage: Storage, batch_size: int) -> bool:
        if self._batch is None or not self.batch_rows or (self.drop_last and self.batch_rows < batch_size):
            return False
        return self._epoch_has(batch_size) or self._epoch < self.epochs

    def _sampleable_count(self, storage: Storage, batch_size: int) -> int:
        return self.batch_rows if self.can_sample(storage, batch_size) else 0

    @property
    def ran_out(self) -> bool:
        return self._ran_out

    @ran_out.setter
    def ran_out(self, value: bool) -> None:
        self._ran_out = bool(value)

    # -- buffer hooks and persistence -------------------------------------------
    def _empty(self) -> None:
        self._batch: torch.Tensor | None = None
        self._valid: torch.Tensor | None = None
        self._order: torch.Tensor | None = None
        self._epoch, self._drawn, self._ran_out = 0, False, False
        self._remaining_batches = int(torch.iinfo(torch.int64).max)

    def state_dict(self) -> dict[str, Any]:
        def listed(t):
            return None if t is None else t.tolist()

        return {
            "epochs": self.epochs, "drop_last": self.drop_last, "shuffle": self.shuffle, "accumulate": self.accumulate,
            "position_key": self.position_key, "batch": listed(self._batch), "valid": listed(self._valid),
            "order": listed(self._order), "epoch": self._epoch, "drawn": self._drawn, "ran_out": self._ran_out,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        missing = [k for k in _STATE_KEYS if k not in state_dict]
        if missing:
            raise KeyError(f"OnPolicyBatchSampler.load_state_dict: the state has no {missing} (not the state of an "
                           "OnPolicyBatchSampler?). Nothing was changed.")

        def tensor(value):
            return None if value is None else torch.as_tensor(value, dtype=torch.long).reshape(-1).clone()

        epochs, epoch = int(state_dict["epochs"]), int(state_dict["epoch"])
        if not 0 <= epoch <= epochs:
            raise ValueError(f"OnPolicyBatchSampler.load_state_dict: epoch {epoch} is outside [0, epochs={epochs}]. "
                             "Nothing was changed.")
        batch, valid, order = tensor(state_dict["batch"]), tensor(state_dict["valid"]), tensor(state_dict["order"])
        if (batch is None) != (valid is None):
            raise ValueError("OnPolicyBatchSampler.load_state_dict: 'batch' and 'valid' must both be set or both "
                             "None. Nothing was changed.")
        self.epochs, self.drop_last, self.shuffle = epochs, bool(state_dict["drop_last"]), bool(state_dict["shuffle"])
        self.accumulate, self.position_key = bool(state_dict["accumulate"]), state_dict["position_key"]
        self._check_config()
        self._batch, self._valid, self._order = batch, valid, order
        self._epoch, self._drawn, self._ran_out = epoch, bool(state_dict["drawn"]), bool(state_dict["ran_out"])

    def __repr__(self) -> str:
        left = 0 if self._order is None else len(self._order)
        return (f"{type(self).__name__}(epochs={self.epochs}, drop_last={self.drop_last}, batch_rows={self.batch_rows}, "
                f"epoch={self._epoch}, rows_left_in_epoch={left})")
