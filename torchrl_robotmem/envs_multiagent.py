"""MaMuJoCo (multi-agent MuJoCo, Gymnasium-Robotics) as a TorchRL multi-agent env.

:func:`make_mamujoco_env` builds ``gymnasium_robotics.mamujoco_v1.parallel_env``
(Peng et al., "FACMAC", 2021: one MuJoCo robot whose joints are split among
agents) through TorchRL's ``PettingZooWrapper``, with every agent in one
group, so a tensordict holds ``("agents", "observation")`` ``[..., n_agents,
obs_dim]``, ``("agents", "action")``, ``("next", "agents", "reward")`` and
per-agent ``("agents", "done" | "terminated" | "truncated")`` ``[..., n_agents, 1]``
beside the global ``"done"`` / ``"terminated"`` / ``"truncated"`` ``[..., 1]``
(any agent done ends the episode). Observations are float32.

Why a wrapper is needed (checked with gymnasium-robotics 1.4.2, pettingzoo
1.27.0, torchrl 0.14.1): ``PettingZooWrapper`` builds its ``("agents",
"info")`` spec from the info dicts of the *first reset*, but MaMuJoCo (as the
Gymnasium v5 MuJoCo envs it wraps) returns fewer info keys at reset
(HalfCheetah: ``x_position``) than at a step (``x_velocity``,
``reward_forward``, ``reward_ctrl`` too), so the first ``env.step`` fails with
``TypeError: 'NoneType' object does not support item assignment``
(``pettingzoo.py`` ``_step``, ``group_info.get(agent_info)[index] = ...``).
:class:`FixedInfoKeys` gives every reset and step the same info keys (none
by default), which makes the env pass ``check_env_specs``.

This module needs ``pettingzoo`` (not a dependency of the rest of the
package); :func:`make_mamujoco_env` is a plain function of plain values, so ``functools.partial(make_mamujoco_env, ...)`` is picklable for
spawned collector workers and buildable by hydra's ``_target_``.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

try:
    from pettingzoo.utils import BaseParallelWrapper
except ImportError as err:  # pragma: no cover - pettingzoo is an optional dependency
    raise ImportError(
        "torchrl_robotmem.envs_multiagent needs pettingzoo (MaMuJoCo's PettingZoo API): pip install 'pettingzoo>=1.23'"
    ) from err

__all__ = ["FixedInfoKeys", "agent_names", "make_mamujoco_env"]

#: The group every agent is put in (TorchRL's ``MarlGroupMapType.ALL_IN_ONE_GROUP`` name).
GROUP = "agents"


class FixedInfoKeys(BaseParallelWrapper):
    """A PettingZoo parallel-env wrapper whose infos hold the same keys at every reset and step.

    Keys in ``keys`` missing from an agent's info read ``0.0``; other keys are
    dropped; values become Python floats.

    Args:
        env: a PettingZoo ``ParallelEnv`` (e.g. ``mamujoco_v1.parallel_env(...)``).
        keys (sequence of str): the info keys to keep; empty (the default) keeps none.

    Example:
        >>> from gymnasium_robotics import mamujoco_v1
        >>> env = FixedInfoKeys(mamujoco_v1.parallel_env("HalfCheetah", "2x3"), keys=["x_velocity"])
        >>> _, info = env.reset(seed=0)
        >>> info["agent_0"]
        {'x_velocity': 0.0}
        >>> out = env.step({a: env.action_space(a).sample() for a in env.agents})
        >>> sorted(out[-1]["agent_1"])
        ['x_velocity']
    """

    def __init__(self, env, keys: Sequence[str] = ()) -> None:
        super().__init__(env)
        self.keys = tuple(str(k) for k in keys)

    def _infos(self, infos: dict) -> dict:
        return {agent: {k: float(info.get(k, 0.0)) for k in self.keys} for agent, info in infos.items()}

    def reset(self, seed=None, options=None):
        obs, infos = self.env.reset(seed=seed, options=options)
        return obs, self._infos(infos)

    def step(self, actions):
        obs, rewards, terminated, truncated, infos = self.env.step(actions)
        return obs, rewards, terminated, truncated, self._infos(infos)

    def state(self):
        return self.env.state()


def agent_names(env) -> list[str]:
    """The agents of the single group of a TorchRL multi-agent env built here, in their tensor order.

    Args:
        env: a TorchRL env (possibly a ``TransformedEnv``) wrapping a ``PettingZooWrapper``.

    Example:
        >>> env = make_mamujoco_env("HalfCheetah", "2x3")
        >>> agent_names(env)
        ['agent_0', 'agent_1']
    """
    base = getattr(env, "base_env", env)
    return list(base.group_map[GROUP])


def make_mamujoco_env(scenario: str = "HalfCheetah", agent_conf: str | None = "2x3", *,
                      max_episode_steps: int | None = None, seed: int | None = None,
                      info_keys: Sequence[str] = (), agent_obsk: int = 1, device: str = "cpu",
                      episode_reward: bool = True, step_counter: bool = True, **kwargs: Any):
    """A MaMuJoCo task as a TorchRL env: one group ``"agents"``, float32 observations.

    Args:
        scenario (str): the MuJoCo robot (``"HalfCheetah"``, ``"Ant"``, ``"Hopper"``, ``"Walker2d"``, ...).
        agent_conf (str, optional): how its joints are split (``"2x3"``: 2 agents of 3 joints).

    Keyword Args:
        max_episode_steps (int, optional): the episode length (the Gymnasium default, 1000, when ``None``).
        seed (int, optional): seeds the first reset (later resets continue its random stream).
        info_keys (sequence of str): info entries to read under ``("agents", "info", key)`` (none by default;
            see :class:`FixedInfoKeys`).
        agent_obsk (int): MaMuJoCo's observation depth (joints at graph distance <= k are seen; default 1).
        device (str): the env's device.
        episode_reward (bool): adds ``RewardSum`` writing ``("agents", "episode_reward")``.
        step_counter (bool): adds ``StepCounter`` writing ``"step_count"``.
        **kwargs: passed to ``mamujoco_v1.parallel_env``.

    Returns:
        a ``TransformedEnv`` over ``PettingZooWrapper`` (``DoubleToFloat`` first).

    Example:
        >>> from torchrl.envs.utils import check_env_specs
        >>> env = make_mamujoco_env("HalfCheetah", "2x3", max_episode_steps=20, seed=0)
        >>> check_env_specs(env)
        >>> td = env.rollout(25, break_when_any_done=False)
        >>> td["agents", "observation"].shape, td["next", "agents", "reward"].shape
        (torch.Size([25, 2, 12]), torch.Size([25, 2, 1]))
        >>> td["next", "done"].squeeze(-1).nonzero().flatten().tolist()
        [19]
    """
    from gymnasium_robotics import mamujoco_v1
    from torchrl.envs import Compose, DoubleToFloat, RewardSum, StepCounter, TransformedEnv
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper

    if max_episode_steps is not None:
        kwargs["max_episode_steps"] = int(max_episode_steps)
    raw = mamujoco_v1.parallel_env(scenario, agent_conf, agent_obsk=agent_obsk, **kwargs)
    raw = FixedInfoKeys(raw, keys=info_keys)
    base = PettingZooWrapper(raw, group_map={GROUP: list(raw.possible_agents)}, use_mask=False,
                             seed=seed, device=device)
    transforms = [DoubleToFloat()]
    if step_counter:
        transforms.append(StepCounter())
    if episode_reward:
        transforms.append(RewardSum(in_keys=[(GROUP, "reward")], out_keys=[(GROUP, "episode_reward")]))
    return TransformedEnv(base, Compose(*transforms))
