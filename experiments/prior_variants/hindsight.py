"""Hindsight goals for cloning: each stored row aimed at what its own episode achieved a few steps later.

``prior.clone_goals=hindsight`` clones *every* row of the prior memories, not
only their successful episodes, by relabelling: the row's ``desired_goal``
becomes ``("next", "achieved_goal")`` of a row ``k`` steps later in the same
episode, ``k`` drawn uniformly from ``[0, prior.clone_horizon)`` at each draw.
The stored action then did move the system towards that goal, so regressing
the actor onto it is hindsight inverse dynamics (PCHID, Sun et al. 2019) or,
with longer horizons, goal-conditioned supervised learning (GCSL, Ghosh et al.
2019). It turns a memory whose own goals were mostly missed (a failed run, a
random controller) into a policy: on HandReach-v3 the 64,650 rows of a
SAC+HER run that scored 0.10 clone into 0.41-0.43 (horizon 1-3; 0.25 at 10;
docs/results.md, "Shadow Hand").
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

__all__ = ["ACHIEVED_KEY", "EPISODE_KEY", "HindsightGoals", "episode_ids", "numbered_episodes"]

ACHIEVED_KEY = ("next", "achieved_goal")
EPISODE_KEY = "hindsight_episode"  # the column load_demos adds: one number an episode, unique across memories
TRAJ_KEY = ("collector", "traj_ids")  # what the recipe's collector writes


def episode_ids(rows: TensorDictBase) -> torch.Tensor:
    """An episode number per row (int64, ``[N]``), in storage order.

    From ``("collector", "traj_ids")`` where the memory has it (the recipe's
    own runs), else counted from the ``("next", "done")`` / ``("next",
    "truncated")`` flags (scripted and imported memories): a row follows an
    episode's last row starts the next one.

    Example:
        >>> from tensordict import TensorDict
        >>> done = torch.tensor([False, True, False, False, True]).unsqueeze(-1)
        >>> episode_ids(TensorDict({("next", "done"): done}, batch_size=[5]))
        tensor([0, 0, 1, 1, 1])
    """
    keys = rows.keys(True)
    if TRAJ_KEY in keys:
        return rows.get(TRAJ_KEY).reshape(rows.shape[0]).long()
    if ("next", "done") not in keys:
        raise KeyError("prior.clone_goals=hindsight needs episode boundaries: a prior memory holds neither "
                       f"{TRAJ_KEY} nor ('next', 'done').")
    ends = rows.get(("next", "done")).reshape(rows.shape[0]).bool()
    if ("next", "truncated") in keys:
        ends = ends | rows.get(("next", "truncated")).reshape(rows.shape[0]).bool()
    starts = torch.zeros_like(ends)
    starts[1:] = ends[:-1]
    return starts.long().cumsum(0)


def numbered_episodes(rows: TensorDictBase, first: int = 0) -> torch.Tensor:
    """:func:`episode_ids` renumbered ``first, first + 1, ...`` in order of the ids (int64, ``[N]``).

    Numbering each memory from where the previous one stopped makes episode
    numbers unique across several memories (two runs' collectors both start
    their ``traj_ids`` at 0); the next memory starts at ``int(ids.max()) + 1``.

    Example:
        >>> from tensordict import TensorDict
        >>> rows = TensorDict({("collector", "traj_ids"): torch.tensor([7, 7, 9])}, batch_size=[3])
        >>> numbered_episodes(rows, first=4)
        tensor([4, 4, 5])
    """
    return torch.unique(episode_ids(rows), return_inverse=True)[1] + int(first)


class HindsightGoals:
    """Rows with their goal replaced by what their episode achieved ``k`` steps later, ``0 <= k < horizon``.

    Args:
        rows (TensorDictBase): the rows, with ``goal_key``, ``("next", "achieved_goal")``
            and :data:`EPISODE_KEY` (``load_demos(..., hindsight=True)``).
        horizon (int): the relabelled goal is drawn from the next ``horizon`` achieved goals
            (1: the very next one; the row's own transition).
        goal_key (str): the goal the actor reads.
        generator (torch.Generator, optional): the draws of ``k``.

    Example:
        >>> relabel = HindsightGoals(demos, horizon=3)
        >>> batch = relabel(torch.randint(len(demos), (256,)))   # batch["desired_goal"]: achieved 1-3 steps on
    """

    def __init__(self, rows: TensorDictBase, horizon: int, goal_key: str = "desired_goal",
                 generator: torch.Generator | None = None) -> None:
        if int(horizon) < 1:
            raise ValueError(f"prior.clone_horizon must be >= 1 (1: the next achieved goal), got {horizon}.")
        missing = [k for k in (goal_key, ACHIEVED_KEY, EPISODE_KEY) if k not in rows.keys(True)]
        if missing:
            raise KeyError(f"hindsight cloning needs {missing} in the rows (load_demos(..., hindsight=True)).")
        self.rows, self.horizon, self.goal_key, self.generator = rows, int(horizon), goal_key, generator
        self.episodes = rows.get(EPISODE_KEY)
        self.achieved = rows.get(ACHIEVED_KEY)

    def __call__(self, index: torch.Tensor) -> TensorDictBase:
        index = index.to(self.episodes.device)
        ahead = torch.randint(self.horizon, index.shape, generator=self.generator).to(index.device)
        later = (index + ahead).clamp(max=self.rows.shape[0] - 1)
        later = torch.where(self.episodes[later] == self.episodes[index], later, index)  # never past the episode
        batch = self.rows[index]
        batch.set(self.goal_key, self.achieved[later].to(batch.get(self.goal_key).dtype))
        return batch
