"""The scripted controller as part of the env: its action and state written as observations.

A residual policy (``train.py``) acts ``base + residual``: with ``residual=True``
the env adds the controller's action to the policy's before it steps. Its critic bootstraps
from the next state, so the controller's action and phase at ``s_{t+1}`` must be
in the transition: :class:`ScriptedBase` runs the controller inside the env (one
call a step, a reset a new episode) and writes ``base_action`` and
``base_state`` at the root and under ``"next"``, as any observation. The
parameters of an episode's controller are recalled from a scripted memory by
goal geometry (:func:`recalled_params`), as docs/cross_env.md does.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import Transform

from experiments.scripted.controllers import default_params, make_controller, task_of
from experiments.scripted.recall_params import episode_index, recaller
from torchrl_robotmem import ZarrStorage

__all__ = ["ScriptedBase", "recalled_params"]


def recalled_params(task: str, memory: str | None, k: int = 5) -> Callable[[np.ndarray, np.ndarray], object]:
    """``(observation, desired_goal) -> params``: the mean parameters of the ``k`` successful episodes nearest in goal
    geometry in the scripted memory at ``memory`` (read-only); the task's defaults with ``memory=None`` or where the
    memory holds no successful episode.

    Example:
        >>> fn = recalled_params("push", None)
        >>> fn(np.zeros(25), np.zeros(3)).strike_speed
        0.5
    """
    if memory is None:
        base = default_params(task)
        return lambda obs, goal: base
    storage = ZarrStorage(memory, read_only=True)
    if len(storage) == 0:
        raise ValueError(f"the scripted memory {memory!r} is empty: collect one first "
                         "(python -m experiments.scripted.collect env=push episodes=500 noise=1 path=...).")
    return recaller(task, episode_index(storage), k)


class ScriptedBase(Transform):
    """Runs a scripted controller inside the env; writes its action and state as observations.

    Args:
        task (str): ``"push"``, ``"slide"`` (or their Fetch ids).
        memory (str, optional): a scripted memory (``experiments.scripted.collect``) to recall each episode's
            parameters from; ``None``: the task's default parameters.
        k (int): episodes recalled per episode. Default: ``5``.
        action_key (str): where the controller's action goes. Default: ``"base_action"``.
        state_key (str): where its state goes (phase one-hot and ``t / 50``). Default: ``"base_state"``.
        residual (bool): the policy's ``"action"`` is a residual: the env steps ``clip(base_action + action, -1, 1)``
            (the tensordict keeps the residual, as the policy wrote it). Default: ``False``.

    Example:
        >>> from torchrl_robotmem import make_env
        >>> env = make_env("FetchPush-v4", seed=0, transforms=[ScriptedBase("push")])
        >>> td = env.rollout(3, lambda td: td.set("action", td["base_action"]))
        >>> td["next", "base_state"].shape
        torch.Size([3, 6])
    """

    def __init__(self, task: str, memory: str | None = None, k: int = 5,
                 action_key: str = "base_action", state_key: str = "base_state", residual: bool = False):
        super().__init__(in_keys=["observation", "desired_goal"], out_keys=[action_key, state_key])
        self.residual = residual
        self.task = task_of(task)
        self.params_of = recalled_params(self.task, memory, k)
        self.controller = None  # built at the first reset, for the env's batch
        self._last = None  # the controller's last action, per env

    def _controller_for(self, n: int):
        if self.controller is None or self.controller.num_envs != n:
            self.controller = make_controller(self.task, n)
        return self.controller

    def _inputs(self, td: TensorDictBase) -> tuple[np.ndarray, np.ndarray]:
        obs, goal = (td.get(key).detach().cpu().double() for key in ("observation", "desired_goal"))
        return obs.reshape(-1, obs.shape[-1]).numpy(), goal.reshape(-1, goal.shape[-1]).numpy()

    def _write(self, td: TensorDictBase, action: np.ndarray) -> TensorDictBase:
        batch = td.batch_size
        td.set(self.out_keys[0], torch.from_numpy(action).reshape(*batch, -1))
        td.set(self.out_keys[1], torch.from_numpy(self.controller.features()).reshape(*batch, -1))
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        obs, goal = self._inputs(tensordict_reset)
        ctl = self._controller_for(obs.shape[0])
        mask = None if tensordict is None else tensordict.get("_reset", None)
        rows = np.arange(obs.shape[0]) if mask is None else np.flatnonzero(mask.reshape(obs.shape[0], -1).any(-1).numpy())
        for i in rows:
            ctl.reset(i, obs[i], goal[i], self.params_of(obs[i], goal[i]))
        first = ctl.act(obs, goal, rows)  # the first action of the reset rows; the running episodes are not stepped
        action = first if self._last is None or len(rows) == obs.shape[0] else self._last.copy()
        action[rows] = first[rows]
        self._last = action
        return self._write(tensordict_reset, action)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        obs, goal = self._inputs(next_tensordict)
        ctl = self._controller_for(obs.shape[0])
        self._last = ctl.act(obs, goal)
        return self._write(next_tensordict, self._last)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        if not self.residual:
            return tensordict
        action = tensordict.get("action")  # inv() hands a shallow copy: the caller's "action" stays the residual
        return tensordict.set("action", (action + tensordict.get(self.out_keys[0]).to(action)).clamp(-1.0, 1.0))

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        batch, device = observation_spec.shape, observation_spec.device
        width = make_controller(self.task, 1).features().shape[-1]
        observation_spec[self.out_keys[0]] = Unbounded((*batch, 4), dtype=torch.float32, device=device)
        observation_spec[self.out_keys[1]] = Unbounded((*batch, width), dtype=torch.float32, device=device)
        return observation_spec
