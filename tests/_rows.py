"""Random FetchPush-shaped transitions for the recall, sampler and Zarr-memory tests.

``conftest.make_transitions`` (the ``transitions`` fixture) is the deterministic
builder of the storage tests; ``fetch_rows`` draws from a ``torch.Generator`` so
that goals are spread out, which the nearest-neighbour tests need. Imported as
``from _rows import fetch_rows`` (pytest puts ``tests/`` on ``sys.path``).
"""
from __future__ import annotations

import torch
from tensordict import TensorDict

EP_LEN = 50


def unit_quat(n, gen):
    q = torch.randn(n, 4, generator=gen)
    return q / q.norm(dim=1, keepdim=True)


def fetch_rows(n, gen, start=0, *, goal_dim=3, success_rate=0.2, envs=0, tags=False):
    """``n`` transitions: observation 25, action 4, goals ``goal_dim``, an episode every 50 steps.

    ``goal_dim`` 7 gives pose goals (position, unit quaternion), any other value
    uniform goals (15: HandReach). Row ``i``'s root ``achieved_goal`` is row
    ``i - 1``'s next one. ``envs > 0`` adds an ``env`` column with codes drawn
    from ``range(envs)``; ``tags`` adds ``run`` (0 or 1), ``episode`` and root
    ``done`` / ``is_success``, the columns a ZarrStorage would write itself, for
    tests over in-memory storages. ``start`` is the step count of row 0.
    """
    if goal_dim == 7:
        goals = torch.cat([torch.rand(n, 3, generator=gen) * 0.05, unit_quat(n, gen)], 1)
    else:
        goals = torch.rand(n, goal_dim, generator=gen)
    step = torch.arange(start, start + n) % EP_LEN
    done = (step == EP_LEN - 1).unsqueeze(-1)
    success = (torch.rand(n, generator=gen) < success_rate).float()
    # the dict is filled in this order so that each draw from gen stays in place
    root = {
        "observation": torch.randn(n, 25, generator=gen),
        "achieved_goal": goals.roll(1, 0),
        "desired_goal": torch.rand(n, goal_dim, generator=gen),
        "action": torch.rand(n, 4, generator=gen) * 2 - 1,
    }
    if tags:
        root["is_success"] = success.roll(1, 0)
        root["done"] = torch.zeros(n, 1, dtype=torch.bool)
    if envs:
        root["env"] = torch.randint(0, envs, (n,), generator=gen)
    if tags:
        root["run"] = torch.randint(0, 2, (n,), generator=gen)
        root["episode"] = torch.arange(start, start + n) // EP_LEN
    return TensorDict(
        {
            **root,
            ("next", "observation"): torch.randn(n, 25, generator=gen),
            ("next", "achieved_goal"): goals,
            ("next", "desired_goal"): torch.rand(n, goal_dim, generator=gen),
            ("next", "reward"): success.unsqueeze(-1) - 1,
            ("next", "done"): done,
            ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
            ("next", "truncated"): done,
            ("next", "is_success"): success,
        },
        batch_size=[n],
    )
