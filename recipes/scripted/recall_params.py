"""Recall the parameters of remembered scripted episodes by goal geometry.

Every row of an episode carries the same geometry; ``one_per_episode=True``
makes the ``k`` results ``k`` different episodes.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from tensordict import TensorDictBase

from torchrl_robotmem import GoalIndex

__all__ = ["GEOMETRY_KEY", "SUCCESS_KEY", "episode_index", "mean_params", "recall_episodes"]

#: goal column of the geometry index (distance over the task's typical distance)
GEOMETRY_KEY = ("geometry", "scaled_distance")
#: success column: the episode's outcome, on every one of its rows
SUCCESS_KEY = "episode_success"


def episode_index(storage, goal_key=GEOMETRY_KEY) -> GoalIndex:
    """A :class:`GoalIndex` over a scripted memory, keyed by episode geometry."""
    return GoalIndex(storage, goal_key=goal_key, success_key=SUCCESS_KEY)


def recall_episodes(
    index: GoalIndex,
    query: float | Sequence[float],
    k: int,
    *,
    env: str | Sequence[str] | None = None,
    success_only: bool = True,
) -> TensorDictBase:
    """One row (the nearest) of each of the ``k`` episodes nearest to ``query``.

    Returns a TensorDict of batch ``[m]``, ``m <= k`` (fewer when the memory
    holds fewer matching episodes), nearest first, with every stored column
    (``("params", name)``, ``episode``, ``env``, ...) and ``distance``.
    """
    q = torch.as_tensor(np.atleast_1d(np.asarray(query, dtype=np.float32)))
    out = index.recall(q, k, success_only=success_only, env=env, one_per_episode=True)
    return out[out["mask"]]


def mean_params(rows: TensorDictBase, names: Sequence[str]) -> dict[str, float] | None:
    """Mean of ``("params", name)`` over ``rows`` (``None`` when there are none)."""
    if rows.shape[0] == 0:
        return None
    return {n: float(rows["params", n].double().mean()) for n in names}
