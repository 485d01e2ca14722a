from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

torch.set_num_threads(1)


def make_transitions(n: int, start: int = 0, *, episode_len: int = 10, goal_dim: int = 3) -> TensorDict:
    """Deterministic FetchPush-shaped transitions; row i is a function of ``start + i``."""
    i = torch.arange(start, start + n)
    done = ((i + 1) % episode_len == 0).unsqueeze(-1)
    step = (i % episode_len).unsqueeze(-1)
    goal = torch.stack([torch.sin(i * 0.1), torch.cos(i * 0.1), i * 1e-3] + [i * 0.0] * (goal_dim - 3), -1).float()
    return TensorDict(
        {
            "observation": (i.unsqueeze(-1) + torch.arange(25)).float(),
            "achieved_goal": goal,
            "desired_goal": torch.zeros(n, goal_dim),
            "action": -i.float().unsqueeze(-1).expand(n, 4).clone(),
            "done": torch.zeros(n, 1, dtype=torch.bool),
            "step_count": step,
            "next": {
                "observation": (i.unsqueeze(-1) + torch.arange(25) + 1).float(),
                "achieved_goal": goal + 0.01,
                "desired_goal": torch.zeros(n, goal_dim),
                "reward": -torch.ones(n, 1),
                "done": done,
                "truncated": done.clone(),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
                "is_success": (i % 7 == 0).float(),
                "step_count": step + 1,
            },
        },
        [n],
    )


@pytest.fixture
def transitions():
    return make_transitions
