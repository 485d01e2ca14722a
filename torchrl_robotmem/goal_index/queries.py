"""What a caller asks of an index, checked: the query goals and ``k``.

Pure functions over arrays: no storage, no index state.
"""
from __future__ import annotations

import numpy as np
import torch
from tensordict.utils import NestedKey

__all__ = ["check_k", "parse_goals"]


def check_k(k) -> int:
    """``k`` as an int, or a ``ValueError`` unless it is a positive integer."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k must be a positive integer, got {k!r}.")
    return int(k)


def parse_goals(goal, goal_dim: int | None, goal_key: NestedKey) -> tuple[np.ndarray, bool]:
    """Query goals as a contiguous float64 ``[Q, goal_dim]`` array, and whether they came batched.

    Args:
        goal: ``[goal_dim]`` or ``[B, goal_dim]`` (tensor, array or list).
        goal_dim (int or None): the stored goals' dimension (``None``: not known yet).
        goal_key (NestedKey): the stored goal column, named in the error.

    Example:
        >>> from torchrl_robotmem.goal_index.queries import parse_goals
        >>> q, batched = parse_goals([0.1, 0.2, 0.3], 3, ("next", "achieved_goal"))
        >>> q.shape, q.dtype, batched
        ((1, 3), dtype('float64'), False)
    """
    if isinstance(goal, torch.Tensor):
        q = goal.detach()
        q = (q if q.device.type == "cpu" else q.cpu()).double().numpy()
    else:
        try:
            q = np.asarray(goal, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"goal must be numeric, got {type(goal).__name__}: {err}") from None
    if q.ndim not in (1, 2):
        raise ValueError(
            f"goal must have shape [goal_dim] or [B, goal_dim], got {tuple(q.shape)}."
        )
    batched = q.ndim == 2
    q = np.ascontiguousarray(q.reshape(-1, q.shape[-1]))
    if goal_dim is not None and q.shape[1] != goal_dim:
        key = repr(goal_key) if isinstance(goal_key, tuple) else repr(str(goal_key))
        raise ValueError(
            f"goal has dimension {q.shape[1]} but the stored goals {key} have dimension {goal_dim}."
        )
    if not np.isfinite(q).all():
        raise ValueError("goal contains NaN or infinite values.")
    return q, batched
