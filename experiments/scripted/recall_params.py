"""Recall the parameters of remembered scripted episodes by goal geometry.

Every row of an episode carries the same geometry; ``one_per_episode=True``
makes the ``k`` results ``k`` different episodes.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import torch
from tensordict import TensorDictBase

from torchrl_robotmem import GoalIndex

__all__ = ["GEOMETRY_KEY", "STRIKE_RECALLED", "SUCCESS_KEY", "episode_index", "mean_params", "recall_episodes",
           "recaller"]

#: goal column of the geometry index (distance over the task's typical distance)
GEOMETRY_KEY = ("geometry", "scaled_distance")
#: success column: the episode's outcome, on every one of its rows
SUCCESS_KEY = "episode_success"
#: what recall supplies to the push / slide controller (how to strike); where the stroke ends stays at the
#: task's default: the names of ``experiments.cross_env.run.PREREGISTERED["supplied"]``
STRIKE_RECALLED = ("approach_offset", "approach_height", "strike_height", "aim_angle", "strike_speed")


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


def recaller(task: str, index: GoalIndex, k: int = 5, names: Sequence[str] = STRIKE_RECALLED):
    """``(observation, desired_goal) -> params``: the task's defaults with ``names`` replaced by their mean over the
    ``k`` successful episodes of ``index`` nearest in scaled goal geometry (the defaults where there are none).

    Example:
        >>> params = recaller("push", episode_index(storage))
        >>> params(obs, goal).strike_speed     # the mean of the 5 nearest successes
    """
    from .collect import episode_geometry
    from .controllers import default_params

    base = default_params(task)

    def params(obs: np.ndarray, goal: np.ndarray):
        query = float(episode_geometry(task, obs, goal)["scaled_distance"][0])
        means = mean_params(recall_episodes(index, query, k), names)
        return base if means is None else dataclasses.replace(base, **means)

    return params
