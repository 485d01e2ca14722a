"""Synthetic FetchPush-v4 transitions, shaped like a TorchRL collector's output.

Values are realistic enough for compression to behave as with real data: the
gripper and the object follow smooth random walks inside the workspace, actions
are smooth, rewards are sparse (-1 / 0), episodes last 50 steps (``truncated``
at the last step), goals are fixed per episode.

Keys (``bytes_per_row`` gives the total; 307 bytes):

* root: ``observation`` f32[25], ``achieved_goal`` f32[3], ``desired_goal`` f32[3],
  ``action`` f32[4], ``done`` / ``terminated`` / ``truncated`` bool[1],
  ``is_success`` f32[], ``step_count`` int64[1], ``is_init`` bool[1],
  ``("collector", "traj_ids")`` int64[]
* ``next``: ``observation``, ``achieved_goal``, ``desired_goal``, ``reward`` f32[1],
  ``done`` / ``terminated`` / ``truncated`` bool[1], ``is_success`` f32[],
  ``step_count`` int64[1]
"""
from __future__ import annotations

import torch
from tensordict import TensorDict

EPISODE_LEN = 50
_TABLE_LO = torch.tensor([1.05, 0.40, 0.42])
_TABLE_HI = torch.tensor([1.55, 1.10, 0.42])


def fetch_push_transitions(n: int, *, seed: int = 0, start: int = 0) -> TensorDict:
    """``n`` FetchPush-v4 transitions (whole 50-step episodes; ``n`` is rounded up)."""
    gen = torch.Generator().manual_seed(seed)
    n_ep = -(-n // EPISODE_LEN)
    T = EPISODE_LEN

    def walk(start_pos, scale, lo, hi):
        steps = torch.randn(n_ep, T + 1, 3, generator=gen) * scale
        steps[:, 0] = 0
        pos = start_pos.unsqueeze(1) + steps.cumsum(1)
        return pos.clamp(lo, hi)

    def rand_in(lo, hi, k):
        return lo + (hi - lo) * torch.rand(k, 3, generator=gen)

    obj0 = rand_in(_TABLE_LO, _TABLE_HI, n_ep)
    grip0 = obj0 + torch.randn(n_ep, 3, generator=gen) * 0.05 + torch.tensor([0.0, 0.0, 0.05])
    grip = walk(grip0, 0.01, _TABLE_LO - 0.1, _TABLE_HI + 0.3)  # [E, T+1, 3]
    # the object moves only now and then (when pushed)
    pushed = (torch.rand(n_ep, T + 1, 1, generator=gen) < 0.3).float()
    obj_steps = torch.randn(n_ep, T + 1, 3, generator=gen) * 0.004 * pushed
    obj_steps[..., 2] = 0
    obj_steps[:, 0] = 0
    obj = (obj0.unsqueeze(1) + obj_steps.cumsum(1)).clamp(_TABLE_LO, _TABLE_HI)
    goal = rand_in(_TABLE_LO, _TABLE_HI, n_ep).unsqueeze(1).expand(n_ep, T + 1, 3)

    rot = (torch.randn(n_ep, T + 1, 3, generator=gen) * 0.02).cumsum(1)
    velp = torch.diff(obj, dim=1, prepend=obj[:, :1]) / 0.04
    velr = torch.diff(rot, dim=1, prepend=rot[:, :1]) / 0.04
    grip_velp = torch.diff(grip, dim=1, prepend=grip[:, :1]) / 0.04
    finger = (0.025 + 0.02 * torch.sin(torch.arange(T + 1) * 0.2 + torch.rand(n_ep, 1, generator=gen) * 6)).unsqueeze(-1)
    gripper_state = torch.cat([finger, finger], -1)
    gripper_vel = torch.diff(gripper_state, dim=1, prepend=gripper_state[:, :1]) / 0.04
    obs = torch.cat(
        [grip, obj, obj - grip, gripper_state, rot, velp, velr, grip_velp, gripper_vel], -1
    ).float()  # [E, T+1, 25]
    action = torch.tanh((torch.randn(n_ep, T, 4, generator=gen) * 0.3).cumsum(1) * 0.5).float()

    dist = (obj - goal).norm(dim=-1)  # [E, T+1]
    success = (dist < 0.05).float()
    step = torch.arange(T + 1).expand(n_ep, T + 1)
    last = (step[:, 1:] == T).unsqueeze(-1)  # next is the 50th step: truncated
    false = torch.zeros(n_ep, T, 1, dtype=torch.bool)
    traj = (torch.arange(n_ep) + start // T).unsqueeze(1).expand(n_ep, T)

    td = TensorDict(
        {
            "observation": obs[:, :-1],
            "achieved_goal": obj[:, :-1].float(),
            "desired_goal": goal[:, :-1].float(),
            "action": action,
            "done": false.clone(),
            "terminated": false.clone(),
            "truncated": false.clone(),
            "is_success": success[:, :-1],
            "step_count": step[:, :-1].unsqueeze(-1).long(),
            "is_init": (step[:, :-1] == 0).unsqueeze(-1),
            "collector": {"traj_ids": traj.long()},
            "next": {
                "observation": obs[:, 1:],
                "achieved_goal": obj[:, 1:].float(),
                "desired_goal": goal[:, 1:].float(),
                "reward": (success[:, 1:] - 1).unsqueeze(-1),
                "done": last.clone(),
                "terminated": false.clone(),
                "truncated": last.clone(),
                "is_success": success[:, 1:],
                "step_count": step[:, 1:].unsqueeze(-1).long(),
            },
        },
        [n_ep, T],
    )
    return td.reshape(-1)[:n].contiguous()


def bytes_per_row(td: TensorDict) -> int:
    return sum(v[0].numel() * v.element_size() for v in td.values(True, True))


def fetch_reward_fn(td: TensorDict) -> torch.Tensor:
    """FetchPush's ``compute_reward`` (sparse, 5 cm threshold) as a HER ``reward_fn``."""
    d = (td.get(("next", "achieved_goal")) - td.get("desired_goal")).norm(dim=-1, keepdim=True)
    return -(d > 0.05).float()
