"""Which envs of a batch reset: what an env transform's ``_reset`` reads from the ``"_reset"`` flags.

Shared by :class:`~torchrl_robotmem.RecallTransform` and :class:`~torchrl_robotmem.GoalProposer`, which
both keep something per env (recalled goals, the goal pursued) and must redo it for the envs that reset only.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem.env_resets import reset_mask
    >>> td = TensorDict({"_reset": torch.tensor([[False], [True]])}, [2])
    >>> reset_mask(None, td, torch.Size([2])).tolist()
    [False, True]
    >>> reset_mask(None, None, torch.Size([2])) is None  # a first reset: every env
    True
"""
from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

__all__ = ["reset_mask"]


def reset_mask(parent: Any, tensordict: TensorDictBase | None, batch: torch.Size) -> torch.Tensor | None:
    """Rows that reset (``[*batch]`` bool), or ``None`` for all of them.

    Args:
        parent: the transformed env (its ``reset_keys``), or ``None`` (the key ``"_reset"``).
        tensordict: what ``reset`` was called with (``None``: a first reset).
        batch: the env's batch size.
    """
    if tensordict is None:
        return None
    reset_keys = parent.reset_keys if parent is not None else ["_reset"]
    masks = []
    for key in reset_keys:
        flag = tensordict.get(key, None)
        if flag is None:
            return None
        masks.append(flag.reshape(*batch, -1).any(-1) if len(batch) else flag.reshape(-1).any())
    if not masks:
        return None
    mask = masks[0]
    for other in masks[1:]:
        mask = mask | other
    return mask
