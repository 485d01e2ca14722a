"""Where random row indices are drawn: on the CPU, whatever the device of the RAM mirror.

TorchRL's ``RandomSampler`` asks the storage for its indices
(``Storage._rand_given_ndim``), and a tensor storage draws them on its own
device. ``HERReplayBuffer`` (TorchRL 0.14.1) keeps its episode bounds on the
CPU and subtracts them from those indices, so over a CUDA storage it fails
with a device mismatch at the first sample. Drawn on the CPU, the indices
serve HER's bookkeeping as they are, and gathering the rows of a CUDA mirror
with them moves only the index (a few KiB) to the device.
"""
from __future__ import annotations

import torch

__all__ = ["HostIndices"]


class HostIndices:
    """Mixin for a TorchRL tensor storage: ``_rand_given_ndim`` draws one-dimensional indices on the CPU.

    Example:
        >>> import torch
        >>> from torchrl.data import LazyTensorStorage
        >>> from torchrl_robotmem.storage.indices import HostIndices
        >>> class Storage(HostIndices, LazyTensorStorage):
        ...     pass
        >>> s = Storage(10)
        >>> s.set(torch.arange(4), torch.zeros(4, 2))
        >>> s._rand_given_ndim(3).device
        device(type='cpu')
    """

    def _rand_given_ndim(self, batch_size: int):
        if self.ndim != 1:
            return super()._rand_given_ndim(batch_size)
        return torch.randint(0, len(self), (batch_size,), generator=self._rng)
