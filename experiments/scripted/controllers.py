"""Phase-based scripted controllers for FetchPush, FetchSlide and FetchPickAndPlace.

Each controller is a small state machine over the Fetch observation
(``grip_pos = obs[0:3]``, ``object_pos = obs[3:6]``) and the desired goal, with
every choice that matters exposed as a named parameter:

* :class:`StrikeParams` (FetchPush, FetchSlide): rise to ``approach_height``,
  move ``approach_offset`` behind the object on the object->target line
  (turned by ``aim_angle``), descend to ``strike_height``, then stroke along
  that line at ``strike_speed`` until the gripper is ``strike_length`` short
  of (negative) or past (positive) the point where the object would sit on
  the target; then hold still (the puck of FetchSlide slides on by itself).
* :class:`GraspParams` (FetchPickAndPlace): open above the object, descend to
  ``grasp_height``, close for ``grasp_steps`` steps, lift by ``lift_height``,
  carry to the target at ``carry_speed`` and hold.

The core (:class:`StrikeController`, :class:`GraspController`) is plain numpy
over ``[N]`` envs with per-env phase state, so the same code drives a TorchRL
env through :class:`ScriptedPolicy` and a bare gymnasium env in the large
experiment arms.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

__all__ = [
    "GraspController",
    "GraspParams",
    "ScriptedPolicy",
    "StrikeController",
    "StrikeParams",
    "TASKS",
    "default_params",
    "make_controller",
    "params_class",
    "task_of",
]

# One action unit moves the Fetch mocap 5 cm (gymnasium-robotics scales by 0.05).
_ACTION_SCALE = 0.05
# Gripper centre to object centre at contact, along the stroke: the cube's
# (or puck's) half-width plus a finger's half-thickness.
_CONTACT = 0.035
_TOL = 0.01
# Pull back onto the stroke line (per step, fraction of the drift).
_LATERAL_GAIN = 0.5


@dataclasses.dataclass
class StrikeParams:
    """Parameters of the push / strike controller (metres, radians, action units)."""

    approach_offset: float = 0.06   # gripper start, behind the object along the line
    approach_height: float = 0.06   # transit height above the object's centre
    strike_height: float = 0.0      # gripper height above the object's centre during the stroke
    aim_angle: float = 0.0          # stroke direction, turned from the object->target line
    strike_speed: float = 0.5       # stroke speed, fraction of the max action (1 = 1.25 m/s)
    strike_length: float = 0.0      # stroke length added past ``strike_reach`` (m)
    strike_reach: float = 1.0       # fraction of the object->target distance the stroke covers


@dataclasses.dataclass
class GraspParams:
    """Parameters of the grasp-and-carry controller."""

    approach_height: float = 0.08   # transit height above the object's centre
    grasp_height: float = 0.0       # gripper height above the object's centre when closing
    grasp_steps: float = 4.0        # steps spent closing before lifting
    lift_height: float = 0.05       # lift above the object's start before carrying
    carry_speed: float = 0.6        # carry speed, fraction of the max action
    xy_tolerance: float = 0.008     # how well centred before descending (m)


ParamsT = StrikeParams | GraspParams

# Defaults per task. FetchSlide's strike_speed was tuned on held-out env seeds (docs/cross_env.md).
_DEFAULTS: dict[str, ParamsT] = {
    "push": StrikeParams(),
    "slide": StrikeParams(strike_speed=0.75, strike_length=0.05, strike_reach=0.0),
    "pick_and_place": GraspParams(),
}

#: task name -> gymnasium-robotics id
TASKS = {"push": "FetchPush-v4", "slide": "FetchSlide-v4", "pick_and_place": "FetchPickAndPlace-v4"}


def task_of(env_id: str) -> str:
    """``"FetchPush-v4"`` -> ``"push"`` (also accepts a task name)."""
    if env_id in TASKS:
        return env_id
    bare = env_id.split(":")[-1]
    for task, eid in TASKS.items():
        if bare.split("-")[0].replace("Dense", "") == eid.split("-")[0]:
            return task
    raise ValueError(f"no scripted controller for {env_id!r}; known: {sorted(TASKS.values())}.")


def params_class(task: str) -> type:
    return GraspParams if task_of(task) == "pick_and_place" else StrikeParams


def default_params(task: str) -> ParamsT:
    return dataclasses.replace(_DEFAULTS[task_of(task)])


def param_names(task: str) -> list[str]:
    return [f.name for f in dataclasses.fields(params_class(task))]


def _move(grip: np.ndarray, target: np.ndarray, speed: float) -> np.ndarray:
    """Action (3,) that moves toward ``target``, at most ``speed`` action units per axis-norm."""
    step = (target - grip) / _ACTION_SCALE
    norm = np.linalg.norm(step)
    return step if norm <= speed else step * (speed / norm)


# -- controllers ---------------------------------------------------------------------


class _Controller:
    """Per-env episode state; ``reset(i, obs, goal, params)`` at each episode start."""

    def __init__(self, num_envs: int = 1):
        self.num_envs = num_envs
        self.params: list[Any] = [None] * num_envs
        self.phase = np.zeros(num_envs, dtype=np.int64)
        self.t = np.zeros(num_envs, dtype=np.int64)
        self.obj0 = np.zeros((num_envs, 3))
        self.goal = np.zeros((num_envs, 3))
        self.grip0 = np.zeros((num_envs, 3))

    def reset(self, i: int, obs: np.ndarray, goal: np.ndarray, params) -> None:
        self.params[i] = params
        self.phase[i] = 0
        self.t[i] = 0
        self.grip0[i] = obs[0:3]
        self.obj0[i] = obs[3:6]
        self.goal[i] = goal

    #: phases of the state machine (the width of :meth:`features`' one-hot part)
    NUM_PHASES = 5

    def features(self) -> np.ndarray:
        """The controller's episode state, ``[N, NUM_PHASES + 1]`` float32: its phase one-hot and ``t / 50``.

        With the observation, what a learned residual on this controller needs to
        be Markov (:mod:`experiments.residual`): the phase is not in the env's state.
        """
        out = np.zeros((self.num_envs, self.NUM_PHASES + 1), dtype=np.float32)
        out[np.arange(self.num_envs), self.phase] = 1.0
        out[:, -1] = self.t / 50.0
        return out

    def act(self, obs: np.ndarray, goal: np.ndarray, rows=None) -> np.ndarray:
        """Actions ``[N, 4]`` for observations ``[N, 25]`` (float64 in, float32 out).

        ``rows``: step only these envs (their state advances); the others' actions are zeros.
        """
        out = np.zeros((self.num_envs, 4), dtype=np.float32)
        for i in range(self.num_envs) if rows is None else rows:
            out[i] = np.clip(self._act_one(i, obs[i], goal[i]), -1.0, 1.0)
            self.t[i] += 1
        return out


class StrikeController(_Controller):
    """FetchPush / FetchSlide: rise, get behind the object, descend, stroke, hold."""

    RISE, BEHIND, DESCEND, STRIKE, HOLD = range(5)

    def __init__(self, num_envs: int = 1):
        super().__init__(num_envs)
        self._dir = np.zeros((num_envs, 2))  # stroke direction (xy unit vector)
        self._dist = np.zeros(num_envs)  # object->target xy distance at the episode's start

    def reset(self, i, obs, goal, params: StrikeParams) -> None:
        super().reset(i, obs, goal, params)
        line = goal[:2] - obs[3:5]
        dist = float(np.linalg.norm(line))
        line = line / dist if dist > 1e-6 else np.array([1.0, 0.0])
        c, s = np.cos(params.aim_angle), np.sin(params.aim_angle)
        self._dir[i] = (c * line[0] - s * line[1], s * line[0] + c * line[1])
        self._dist[i] = dist

    def _act_one(self, i, obs, goal):
        p: StrikeParams = self.params[i]
        grip, u, obj0 = obs[0:3], self._dir[i], self.obj0[i]
        start = np.array([*(obj0[:2] - u * (p.approach_offset + _CONTACT)), obj0[2]])
        high = obj0[2] + p.approach_height
        a = np.zeros(4)
        a[3] = -1.0  # closed fingers: one solid pusher
        phase = self.phase[i]
        if phase == self.RISE:
            target = np.array([grip[0], grip[1], max(high, grip[2])])
            a[:3] = _move(grip, target, 1.0)
            if abs(grip[2] - target[2]) < _TOL:
                self.phase[i] = phase = self.BEHIND
        if phase == self.BEHIND:
            target = np.array([start[0], start[1], high])
            a[:3] = _move(grip, target, 1.0)
            if np.linalg.norm(grip[:2] - start[:2]) < _TOL:
                self.phase[i] = phase = self.DESCEND
        if phase == self.DESCEND:
            target = np.array([start[0], start[1], obj0[2] + p.strike_height])
            a[:3] = _move(grip, target, 1.0)
            if abs(grip[2] - target[2]) < _TOL and np.linalg.norm(grip[:2] - start[:2]) < _TOL:
                self.phase[i] = phase = self.STRIKE
        if phase == self.STRIKE:
            # travel from the start point to where the object's centre would be on the
            # target, plus strike_length; measured along the stroke direction
            travel = float(np.dot(grip[:2] - start[:2], u))
            end = p.approach_offset + p.strike_reach * self._dist[i] + p.strike_length
            if travel >= end:
                self.phase[i] = phase = self.HOLD
            else:
                off = (grip[:2] - start[:2]) - travel * u  # lateral drift off the line
                a[:2] = u * p.strike_speed - _LATERAL_GAIN * off / _ACTION_SCALE
                a[2] = (obj0[2] + p.strike_height - grip[2]) / _ACTION_SCALE
        if phase == self.HOLD:
            a[:3] = 0.0
        return a


class GraspController(_Controller):
    """FetchPickAndPlace: open above the object, descend, close, lift, carry, hold."""

    ABOVE, DESCEND, CLOSE, LIFT, CARRY = range(5)

    def __init__(self, num_envs: int = 1):
        super().__init__(num_envs)
        self._closing = np.zeros(num_envs, dtype=np.int64)  # steps spent closing the fingers

    def _act_one(self, i, obs, goal):
        p: GraspParams = self.params[i]
        grip, obj = obs[0:3], obs[3:6]
        a = np.zeros(4)
        phase = self.phase[i]
        if phase == self.ABOVE:
            a[3] = 1.0
            target = np.array([obj[0], obj[1], obj[2] + p.approach_height])
            a[:3] = _move(grip, target, 1.0)
            if np.linalg.norm(grip[:2] - obj[:2]) < p.xy_tolerance and abs(grip[2] - target[2]) < 2 * _TOL:
                self.phase[i] = phase = self.DESCEND
        if phase == self.DESCEND:
            a[3] = 1.0
            target = np.array([obj[0], obj[1], obj[2] + p.grasp_height])
            a[:3] = _move(grip, target, 1.0)
            if abs(grip[2] - target[2]) < 0.005:
                self.phase[i] = phase = self.CLOSE
                self._closing[i] = 0
        if phase == self.CLOSE:
            a[3] = -1.0
            self._closing[i] += 1
            if self._closing[i] > p.grasp_steps:
                self.phase[i] = phase = self.LIFT
        if phase == self.LIFT:
            a[3] = -1.0
            target = np.array([grip[0], grip[1], self.obj0[i][2] + p.lift_height])
            a[:3] = _move(grip, target, 1.0)
            if grip[2] >= target[2] - _TOL:
                self.phase[i] = phase = self.CARRY
        if phase == self.CARRY:
            a[3] = -1.0
            # carry the object (not the gripper) onto the target
            a[:3] = _move(obj, goal, p.carry_speed)
        return a


def make_controller(task: str, num_envs: int = 1) -> _Controller:
    return GraspController(num_envs) if task_of(task) == "pick_and_place" else StrikeController(num_envs)


# -- TorchRL policy ------------------------------------------------------------------

ParamSource = ParamsT | Callable[[np.ndarray, np.ndarray], ParamsT]


class ScriptedPolicy(TensorDictModuleBase):
    """A scripted controller as a TorchRL policy module (collectors, ``env.rollout``).

    Reads ``observation``, ``desired_goal`` and ``is_init`` (from
    :class:`~torchrl.envs.InitTracker`, which :func:`~torchrl_robotmem.make_env`
    adds) and writes ``action`` plus the episode's parameters as
    ``("params", name)`` float32 entries, so a buffer extended with the rollout
    stores them on every transition.

    Args:
        task (str): ``"push"``, ``"slide"``, ``"pick_and_place"`` or a Fetch id.
        params: the parameters of every episode, or a callable
            ``(observation, desired_goal) -> params`` called at each episode
            start (numpy arrays of one env), e.g. noisy or recalled parameters.
            Defaults to the task's defaults.
        num_envs (int): batch size of the env (``1`` for an unbatched env).
    """

    def __init__(self, task: str, params: ParamSource | None = None, num_envs: int = 1):
        super().__init__()
        self.task = task_of(task)
        self.source = params if params is not None else default_params(self.task)
        self.names = param_names(self.task)
        self.controller = make_controller(self.task, num_envs)
        self.in_keys = ["observation", "desired_goal", "is_init"]
        self.out_keys = ["action"] + [("params", n) for n in self.names]

    def _params_for(self, obs: np.ndarray, goal: np.ndarray) -> ParamsT:
        return self.source(obs, goal) if callable(self.source) else self.source

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get("observation").detach().cpu().double().numpy()
        goal = td.get("desired_goal").detach().cpu().double().numpy()
        init = td.get("is_init").detach().cpu().numpy()
        batch = obs.shape[:-1]
        obs, goal, init = obs.reshape(-1, obs.shape[-1]), goal.reshape(-1, goal.shape[-1]), init.reshape(-1)
        ctl = self.controller
        if obs.shape[0] != ctl.num_envs:
            raise ValueError(f"ScriptedPolicy was built for {ctl.num_envs} envs, got a batch of {obs.shape[0]}.")
        for i in np.flatnonzero(init):
            ctl.reset(i, obs[i], goal[i], self._params_for(obs[i], goal[i]))
        action = ctl.act(obs, goal)
        td.set("action", torch.from_numpy(action).reshape(*batch, 4))
        values = np.array([[getattr(p, n) for n in self.names] for p in ctl.params], dtype=np.float32)
        for j, n in enumerate(self.names):
            td.set(("params", n), torch.from_numpy(values[:, j].copy()).reshape(batch))
        return td
