"""HER over a memory that fills and wraps: TorchRL's ``HERReplayBuffer`` with two fixes.

A persistent memory fills: across runs a ring of any capacity is full sooner or
later, and from then on every ``extend`` overwrites the oldest rows. TorchRL
0.14.1's :class:`~torchrl.data.HERReplayBuffer` has two faults there (with
``LazyTensorStorage`` as with :class:`~torchrl_robotmem.ZarrStorage`), which
:class:`PersistentHERReplayBuffer` mends and nothing else:

* **The first sample after an extend of a full ring raises** ``RuntimeError:
  Boolean value of Tensor with more than one value is ambiguous``. Its episode
  cache is keyed by ``(len, storage._last_cursor, is_full)``; once full, ``len``
  no longer changes, so the comparison of two keys reaches ``_last_cursor``,
  the tensor of the rows last written. Here the key holds plain ints, and the
  storage's mutation counter, so a write of exactly ``max_size`` rows between
  two samples also rebuilds the cache.
* **A full ring relabels rows with another episode's goals.** The rows after its
  last episode end, up to the ring's physical end, belong to the episode that
  goes on at row 0; TorchRL gives them the range of the episode before, so
  ``"final"`` and ``"episode"`` draw that episode's goals (about 7% of the rows
  relabelled in a ring of 130 rows holding 50-step episodes), and ``"future"``
  draws only the row's own goal. Here the ring's last row ends an episode too:
  those rows relabel among themselves.
"""
from __future__ import annotations

import torch
from torchrl.data import HERReplayBuffer
from torchrl.data.replay_buffers.storages import Storage

__all__ = ["PersistentHERReplayBuffer"]


class PersistentHERReplayBuffer(HERReplayBuffer):
    """:class:`torchrl.data.HERReplayBuffer` that samples a full, wrapping memory (see the module docstring).

    Takes exactly TorchRL's arguments, and relabels exactly as it does wherever the ring is not full.

    Args:
        reward_fn (callable): the reward of a relabelled transition (e.g.
            :func:`~torchrl_robotmem.make_reward_fn`).

    Keyword Args:
        her_ratio, strategy, end_key, goal_key, achieved_goal_key, reward_key, storage, sampler, batch_size,
            ...: as :class:`torchrl.data.HERReplayBuffer`.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage
        >>> from torchrl_robotmem import make_reward_fn
        >>> from torchrl_robotmem.her import PersistentHERReplayBuffer
        >>> rb = PersistentHERReplayBuffer(make_reward_fn("FetchReach-v4"), her_ratio=1.0, strategy="final",
        ...                                achieved_goal_key=("next", "achieved_goal"),
        ...                                storage=LazyTensorStorage(8), batch_size=8)
        >>> def episode(i):  # 5 steps; every achieved goal of episode i is (i, i, i)
        ...     done = torch.tensor([[False]] * 4 + [[True]])
        ...     return TensorDict({"desired_goal": torch.zeros(5, 3), ("next", "achieved_goal"): torch.full((5, 3), float(i)),
        ...                        ("next", "done"): done, ("next", "reward"): torch.zeros(5, 1)}, [5])
        >>> for i in range(3):  # 15 steps into 8 rows: the ring is full and wraps
        ...     _ = rb.extend(episode(i))
        >>> batch = rb.sample()  # TorchRL 0.14.1's buffer raises here
        >>> bool((batch["desired_goal"] == batch["next", "achieved_goal"]).all())  # each row: its own episode's goal
        True
    """

    def _storage_cache_key(self, storage: Storage) -> tuple:
        revision = getattr(storage, "_mutation_revision", None)
        return (len(storage), None if revision is None else int(revision), self._last_written(storage),
                bool(getattr(storage, "_is_full", False)))

    def _last_written(self, storage: Storage) -> int | None:
        """The row written last: the storage's record of it, else (after TorchRL's ``load_state_dict`` /
        ``loads``, which restore no storage's last cursor) the row before the writer's cursor."""
        last = getattr(storage, "_last_cursor_index", None)  # TorchRL's own reading of the last cursor: an int
        if last is not None:
            last = int(last)
        else:
            cursor = getattr(getattr(self, "_writer", None), "_cursor", None)
            if isinstance(cursor, int) and len(storage):
                last = (cursor - 1) % len(storage)
        return last

    def _build_episode_cache(self, storage: Storage) -> torch.Tensor:
        ends = super()._build_episode_cache(storage)
        n = len(storage)
        if n and bool(getattr(storage, "_is_full", False)):
            # the newest episode ends at the row written last (an episode still open there too), and the
            # wrapping episode's rows before the wrap end at the ring's last row
            last = self._last_written(storage)
            extra = sorted({r for r in (None if last is None else last % n, n - 1) if r is not None} - set(ends.tolist()))
            if extra:
                ends = torch.sort(torch.cat([ends, ends.new_tensor(extra)])).values
        return ends

    def load_state_dict(self, state_dict: dict) -> None:
        super().load_state_dict(state_dict)
        self._restored()

    def loads(self, path) -> None:
        super().loads(path)
        self._restored()

    def _restored(self) -> None:
        """After a restore: the storage's record of its last written row (TorchRL's storages keep the one of
        before the restore, in a buffer that wrote since) is dropped, so the restored writer's cursor says it;
        the episode cache is rebuilt at the next sample."""
        forget = getattr(self._storage, "_set_last_cursor", None)  # TorchRL's own setter (None: not recorded)
        if forget is not None:
            forget(None)
        self._episode_ends_cache, self._last_cache_key = None, (-1,)
