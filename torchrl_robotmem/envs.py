"""Goal-conditioned robot environments from Gymnasium-Robotics as TorchRL envs.

:func:`make_env` builds the Fetch and Shadow-Hand tasks of Gymnasium-Robotics
(Plappert et al., "Multi-Goal Reinforcement Learning: Challenging Robotics
Environments and Request for Research," 2018, https://arxiv.org/abs/1802.09464)
with the keys the rest of ``torchrl_robotmem`` expects: ``observation``,
``achieved_goal``, ``desired_goal``, ``is_success`` and ``step_count`` at the
root of the tensordict, all float32 except the counter.

:func:`make_reward_fn` turns the environment's own vectorised
``compute_reward`` into a ``reward_fn`` for :class:`~torchrl.data.HERReplayBuffer`.
"""
from __future__ import annotations

import difflib
import functools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from tensordict.base import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvCreator,
    GymEnv,
    InitTracker,
    ParallelEnv,
    SerialEnv,
    StepCounter,
    Transform,
    TransformedEnv,
)
from torchrl.envs.libs.gym import default_info_dict_reader

__all__ = ["GoalRewardFn", "env_family", "goal_dim", "make_env", "make_reward_fn"]

_PREFIX = "gymnasium_robotics:"

# Longest prefix first: "HandReach" and "HandManipulate" share "Hand".
_FAMILY_PREFIXES: tuple[tuple[str, str], ...] = (
    ("HandManipulate", "hand_manipulate"),
    ("HandReach", "hand_reach"),
    ("Fetch", "fetch"),
)
# Fetch: object (or gripper) xyz; HandReach: 5 fingertips x xyz;
# HandManipulate: object xyz + quaternion.
_GOAL_DIMS: dict[str, int] = {"fetch": 3, "hand_reach": 15, "hand_manipulate": 7}

_SUPPORTED_HELP = (
    "Supported families: 'fetch' (FetchReach-v4, FetchPush-v4, FetchSlide-v4, "
    "FetchPickAndPlace-v4), 'hand_reach' (HandReach-v3) and 'hand_manipulate' "
    "(HandManipulateBlock-v1, HandManipulateEgg-v1, HandManipulatePen-v1 and their "
    "Rotate*/Full/_*TouchSensors variants), each also as a '...Dense-vN' id. "
    "The 'gymnasium_robotics:' prefix is optional."
)


# -- id resolution ---------------------------------------------------------


@functools.cache
def _registered_ids() -> dict[str, str]:
    """Supported Gymnasium-Robotics ids mapped to their family.

    Ids whose entry point uses the legacy ``mujoco-py`` bindings
    (``FetchPush-v1``, ``HandReach-v0``, ...) are left out: they need a
    package that no longer installs.
    """
    import gymnasium
    import gymnasium_robotics

    gymnasium.register_envs(gymnasium_robotics)
    out = {}
    for env_id, spec in gymnasium.registry.items():
        family = _family_from_name(env_id)
        if family is None or "MujocoPy" in str(spec.entry_point):
            continue
        out[env_id] = family
    return out


def _family_from_name(env_id: str) -> str | None:
    for prefix, family in _FAMILY_PREFIXES:
        if env_id.startswith(prefix):
            return family
    return None


def _resolve(env_id: str) -> tuple[str, str]:
    """Returns ``(bare_id, family)`` or raises a :class:`ValueError`."""
    if not isinstance(env_id, str):
        raise ValueError(f"env_id must be a str, got {type(env_id).__name__}.")
    bare = env_id[len(_PREFIX) :] if env_id.startswith(_PREFIX) else env_id
    supported = _registered_ids()
    if bare in supported:
        return bare, supported[bare]
    hint = difflib.get_close_matches(bare, list(supported), n=3, cutoff=0.6)
    hint_msg = f" Did you mean {', '.join(map(repr, hint))}?" if hint else ""
    raise ValueError(
        f"Unknown or unsupported environment id {env_id!r}.{hint_msg} {_SUPPORTED_HELP}"
    )


def env_family(env_id: str) -> str:
    """Returns the task family of a Gymnasium-Robotics id.

    The family decides how goals compare: Euclidean distance for ``"fetch"``
    and ``"hand_reach"``, position plus rotation for ``"hand_manipulate"``.
    No environment is built.

    Args:
        env_id (str): a supported id, with or without the
            ``"gymnasium_robotics:"`` prefix.

    Returns:
        ``"fetch"``, ``"hand_reach"`` or ``"hand_manipulate"``.

    Raises:
        ValueError: if ``env_id`` is not a supported Gymnasium-Robotics id.

    Example:
        >>> from torchrl_robotmem.envs import env_family
        >>> env_family("FetchPushDense-v4")
        'fetch'
        >>> env_family("gymnasium_robotics:HandManipulateBlockRotateZ-v1")
        'hand_manipulate'
    """
    return _resolve(env_id)[1]


def goal_dim(env_id: str) -> int:
    """Returns the size of ``achieved_goal`` / ``desired_goal`` for an id.

    Read from the family (3 for Fetch, 15 for HandReach, 7 for
    HandManipulate); no environment is built.

    Args:
        env_id (str): a supported id, with or without the
            ``"gymnasium_robotics:"`` prefix.

    Raises:
        ValueError: if ``env_id`` is not a supported Gymnasium-Robotics id.

    Example:
        >>> from torchrl_robotmem.envs import goal_dim
        >>> goal_dim("FetchReach-v4"), goal_dim("HandReach-v3"), goal_dim("HandManipulatePen-v1")
        (3, 15, 7)
    """
    return _GOAL_DIMS[env_family(env_id)]


# -- env construction ------------------------------------------------------


def _make_base_env(
    full_id: str, device: str, gym_kwargs: dict[str, Any]
) -> GymEnv:
    # Module-level (not a closure) so ParallelEnv can pickle it for spawned
    # workers; the prefixed id makes gymnasium import gymnasium_robotics there.
    env = GymEnv(full_id, device=device, **gym_kwargs)
    env.set_info_dict_reader(default_info_dict_reader(["is_success"]))
    return env


def _episode_steps(bare_id: str, max_episode_steps: int | None) -> int:
    """The episode length: ``max_episode_steps`` checked, or the id's registered one."""
    if max_episode_steps is None:
        import gymnasium

        return gymnasium.spec(bare_id).max_episode_steps
    if max_episode_steps < 1:
        raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}.")
    return max_episode_steps


def _base_env(bare_id: str, num_envs: int, parallel: bool, device: str, gym_kwargs: dict[str, Any]):
    """The untransformed env: one :class:`~torchrl.envs.GymEnv` reading ``is_success``
    from the step info, or ``num_envs`` of them batched in a
    :class:`~torchrl.envs.SerialEnv` (a :class:`~torchrl.envs.ParallelEnv`
    with ``parallel``, one spawned process per env).
    """
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}.")
    create = functools.partial(_make_base_env, _PREFIX + bare_id, device, gym_kwargs)
    if num_envs == 1:
        return create()
    if parallel:
        return ParallelEnv(num_envs, EnvCreator(create), device=device)
    return ThreadKeepingSerialEnv(num_envs, create, device=device)


class ThreadKeepingSerialEnv(SerialEnv):
    """A :class:`~torchrl.envs.SerialEnv` whose ``close()`` leaves torch's thread count as it found it.

    TorchRL 0.14.1's ``BatchedEnvBase.close`` sets ``torch.set_num_threads(min(initial pool,
    current + num_workers))``, undoing what a ``ParallelEnv`` took at start. A ``SerialEnv`` took
    nothing, so a process that runs on one torch thread (``torch.set_num_threads(1)``, as the
    recipes do) and closes a 5-env evaluation ``SerialEnv`` goes on with 2 OpenMP threads. On a
    busy 2-core machine that made a FetchSlide SAC run spend 3x the CPU per frame (the second
    thread spins at an OpenMP barrier) and slowed the run beside it (docs/results.md, "FetchSlide").

    Example:
        >>> import torch
        >>> from torchrl_robotmem.envs import make_env
        >>> threads = torch.get_num_threads()
        >>> torch.set_num_threads(1)
        >>> env = make_env("FetchReach-v4", num_envs=2)
        >>> _ = env.rollout(2)              # a SerialEnv starts its workers on first use
        >>> env.close()
        >>> torch.get_num_threads()
        1
        >>> torch.set_num_threads(threads)
    """

    def close(self, *, raise_if_closed: bool = True) -> None:
        threads = torch.get_num_threads()
        try:
            super().close(raise_if_closed=raise_if_closed)
        finally:
            if torch.get_num_threads() != threads:
                torch.set_num_threads(threads)


def make_env(
    env_id: str,
    num_envs: int = 1,
    *,
    seed: int | None = None,
    max_episode_steps: int | None = None,
    parallel: bool = False,
    device: str = "cpu",
    transforms: Sequence[Transform] | None = None,
    **gym_kwargs: Any,
) -> TransformedEnv:
    """Builds a Gymnasium-Robotics goal-conditioned task as a TorchRL env.

    The base env (:func:`_base_env`) is wrapped in ``Compose(DoubleToFloat(),
    StepCounter(max_steps), InitTracker(), *transforms)``, outside a batched
    env. The dict observation stays flat: ``observation``, ``achieved_goal``,
    ``desired_goal``, ``is_success`` (float32, shape ``(*B,)``) and
    ``step_count`` live at the root and under ``"next"``.

    Args:
        env_id (str): a Fetch (``-v4``), HandReach (``-v3``) or HandManipulate
            (``-v1``) id, dense and touch-sensor variants included, with or
            without the ``"gymnasium_robotics:"`` prefix. The env is always
            built from the prefixed id so that spawned workers register the
            robotics envs.
        num_envs (int, optional): number of envs, batched in one env whose
            transforms run once on the ``[num_envs]`` batch in the main
            process. ``1`` returns an unbatched env (batch size ``[]``).
            Default: ``1``.

    Keyword Args:
        seed (int, optional): passed to ``env.set_seed`` (batched envs seed
            worker ``i`` with a seed derived from it). Default: ``None``.
        max_episode_steps (int, optional): episode length. Sets both the
            gymnasium ``TimeLimit`` and the ``StepCounter``. Defaults to the
            registered value (50 for Fetch and HandReach, 100 for
            HandManipulate).
        parallel (bool, optional): use a :class:`~torchrl.envs.ParallelEnv`
            (one spawned process per env) instead of a
            :class:`~torchrl.envs.SerialEnv` when ``num_envs > 1``.
            Default: ``False``.
        device (str, optional): device of the env. Default: ``"cpu"``.
        transforms (sequence of Transform, optional): extra transforms appended
            after the standard ones, e.g. a recall transform. Default: none.
        **gym_kwargs: forwarded to ``gymnasium.make`` through
            :class:`~torchrl.envs.GymEnv` (e.g. ``reward_type="dense"``; the Fetch
            and Hand ids set their own ``distance_threshold`` and refuse it here).

    Returns:
        A :class:`~torchrl.envs.TransformedEnv`. Its ``env_id`` attribute
        holds the bare id (e.g. ``"FetchPush-v4"``) and ``max_episode_steps``
        the episode length.

    Raises:
        ValueError: for an unknown id or ``num_envs < 1``.

    Example:
        >>> import torch
        >>> from torchrl_robotmem.envs import make_env
        >>> env = make_env("FetchPush-v4", seed=0)
        >>> td = env.rollout(5)
        >>> td["observation"].shape, td["desired_goal"].shape, td["next", "is_success"].shape
        (torch.Size([5, 25]), torch.Size([5, 3]), torch.Size([5]))
        >>> env.env_id
        'FetchPush-v4'
        >>> batched = make_env("FetchReach-v4", num_envs=2, seed=0)
        >>> batched.rollout(3)["achieved_goal"].shape
        torch.Size([2, 3, 3])
        >>> batched.close()
    """
    bare_id, _ = _resolve(env_id)
    max_episode_steps = _episode_steps(bare_id, max_episode_steps)
    base = _base_env(bare_id, num_envs, parallel, device, {**gym_kwargs, "max_episode_steps": max_episode_steps})
    standard = (DoubleToFloat(), StepCounter(max_steps=max_episode_steps), InitTracker())
    env = TransformedEnv(base, Compose(*standard, *(transforms or ())))
    env.env_id = bare_id
    env.max_episode_steps = max_episode_steps
    if seed is not None:
        env.set_seed(seed)
    return env


# -- reward function -------------------------------------------------------


class GoalRewardFn:
    """Reward and success from a Gymnasium-Robotics env, for relabelled goals.

    Calls the ``compute_reward`` of an unwrapped ``gymnasium.make(env_id)``
    on ``td[achieved_goal_key]`` and ``td[desired_goal_key]``, so the
    relabelled rewards match what the env would have returned (sparse
    ``-1 / 0`` or dense, as the id says). Pass it as ``reward_fn`` to
    :class:`~torchrl.data.HERReplayBuffer`.

    The env is created on first use and dropped when pickled, so the object
    can be sent to spawned workers. Goals are evaluated in float64, as the
    env does.

    .. note::
        Gymnasium-Robotics 1.4.2 mis-handles batched goals for envs with
        ``ignore_z_target_rotation`` (all ``HandManipulatePen*`` ids): its
        ``euler_a[2] = euler_b[2]`` overwrites row 2 instead of the z angle.
        Those envs are evaluated one row at a time.

    Args:
        env_id (str): a supported id, with or without the
            ``"gymnasium_robotics:"`` prefix.

    Keyword Args:
        achieved_goal_key (NestedKey): goal reached by the transition.
            Default: ``("next", "achieved_goal")``.
        desired_goal_key (NestedKey): goal being pursued (the one HER
            relabels). Default: ``"desired_goal"``.
        **gym_kwargs: forwarded to ``gymnasium.make``; use the same ones as
            for :func:`make_env` (e.g. ``reward_type="dense"``).

    Example:
        >>> import torch
        >>> from torchrl_robotmem.envs import GoalRewardFn, make_env
        >>> env = make_env("FetchReach-v4", seed=0)
        >>> td = env.rollout(10)
        >>> reward_fn = GoalRewardFn("FetchReach-v4")
        >>> torch.equal(reward_fn(td), td["next", "reward"])
        True
        >>> reward_fn.success(td).shape
        torch.Size([10])
    """

    def __init__(
        self,
        env_id: str,
        *,
        achieved_goal_key: NestedKey = ("next", "achieved_goal"),
        desired_goal_key: NestedKey = "desired_goal",
        **gym_kwargs: Any,
    ) -> None:
        self.env_id, family = _resolve(env_id)
        self.distance_based = family in ("fetch", "hand_reach")  # compute_reward is a norm against a threshold
        self.achieved_goal_key = achieved_goal_key
        self.desired_goal_key = desired_goal_key
        self.gym_kwargs = gym_kwargs
        self._env = None
        self._rowwise = False

    def __call__(self, td: TensorDictBase) -> torch.Tensor:
        """Returns the float32 reward, shape ``(*B, 1)``.

        Goals on an accelerator (a CUDA memory) of a Fetch or HandReach task are
        rewarded where they are (:meth:`torch_reward`): no copy to the host and
        back on every HER sample. On the CPU the env's own ``compute_reward`` is
        called.
        """
        if self.distance_based and td.get(self.achieved_goal_key).device.type != "cpu":
            return self.torch_reward(td).unsqueeze(-1)
        env = self._unwrapped()
        return self._evaluate(td, lambda a, g: env.compute_reward(a, g, None)).unsqueeze(-1)

    def torch_reward(self, td: TensorDictBase) -> torch.Tensor:
        """The env's ``compute_reward`` in torch, on the goals' device: float32, shape ``(*B,)``.

        Fetch and HandReach only (their reward is the goal distance, or minus one
        beyond ``distance_threshold``), in float64 as the env computes it. It
        agrees with the env's reward except for distances within float64
        rounding of the threshold.

        Example:
            >>> import torch
            >>> from torchrl_robotmem.envs import GoalRewardFn, make_env
            >>> td = make_env("FetchReach-v4", seed=0).rollout(10)
            >>> fn = GoalRewardFn("FetchReach-v4")
            >>> torch.equal(fn.torch_reward(td), td["next", "reward"].squeeze(-1))
            True
        """
        if not self.distance_based:
            raise ValueError(f"torch_reward covers Fetch and HandReach goals; {self.env_id} compares rotations: "
                             "call the reward function itself (it uses the env's compute_reward).")
        env = self._unwrapped()
        achieved, desired = td.get(self.achieved_goal_key), td.get(self.desired_goal_key)
        distance = torch.linalg.vector_norm(achieved.double() - desired.double(), dim=-1)
        if env.reward_type == "sparse":
            return -(distance > env.distance_threshold).float()
        return (-distance).float()

    @property
    def distance_threshold(self) -> float | None:
        """The task's success distance between goals (Fetch, HandReach), or ``None`` (a task comparing rotations)."""
        return float(self._unwrapped().distance_threshold) if self.distance_based else None

    def success(self, td: TensorDictBase) -> torch.Tensor:
        """Returns ``is_success`` (float32 ``0./1.``, shape ``(*B,)``, like the env's)."""
        env = self._unwrapped()
        if env.reward_type == "sparse":
            return self._evaluate(td, lambda a, g: env.compute_reward(a, g, None) == 0)
        return self._evaluate(td, env._is_success)

    # -- helpers ------------------------------------------------------------

    def _unwrapped(self):
        if self._env is None:
            import gymnasium

            self._env = gymnasium.make(_PREFIX + self.env_id, **self.gym_kwargs).unwrapped
            self._rowwise = bool(getattr(self._env, "ignore_z_target_rotation", False))
        return self._env

    def _evaluate(
        self, td: TensorDictBase, fn: Callable[[np.ndarray, np.ndarray], np.ndarray]
    ) -> torch.Tensor:
        achieved = td.get(self.achieved_goal_key)
        desired = td.get(self.desired_goal_key)
        batch = achieved.shape[:-1]
        a = achieved.detach().reshape(-1, achieved.shape[-1]).cpu().double().numpy()
        g = desired.detach().reshape(-1, desired.shape[-1]).cpu().double().numpy()
        if self._rowwise:
            out = np.array([fn(ai, gi) for ai, gi in zip(a, g)], dtype=np.float32)
        else:
            out = np.asarray(fn(a, g), dtype=np.float32)
        return torch.as_tensor(out, device=achieved.device).reshape(batch)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_env"] = None  # MuJoCo handles do not pickle; rebuilt lazily
        return state

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(env_id={self.env_id!r}, "
            f"achieved_goal_key={self.achieved_goal_key!r}, "
            f"desired_goal_key={self.desired_goal_key!r})"
        )


def make_reward_fn(
    env_id: str,
    *,
    achieved_goal_key: NestedKey = ("next", "achieved_goal"),
    desired_goal_key: NestedKey = "desired_goal",
    **gym_kwargs: Any,
) -> GoalRewardFn:
    """Builds a picklable ``reward_fn`` for :class:`~torchrl.data.HERReplayBuffer`.

    See :class:`GoalRewardFn`; its ``success(td)`` method recomputes
    ``is_success`` for relabelled rows (HER itself does not).

    Args:
        env_id (str): a supported id, with or without the
            ``"gymnasium_robotics:"`` prefix.

    Keyword Args:
        achieved_goal_key (NestedKey): Default: ``("next", "achieved_goal")``.
        desired_goal_key (NestedKey): Default: ``"desired_goal"``.
        **gym_kwargs: forwarded to ``gymnasium.make``.

    Returns:
        A callable mapping a tensordict of rows to float32 rewards of shape
        ``(*B, 1)``.

    Example:
        >>> import torch
        >>> from torchrl.data import HERReplayBuffer, LazyTensorStorage
        >>> from torchrl_robotmem.envs import make_env, make_reward_fn
        >>> env = make_env("FetchReach-v4", seed=0)
        >>> rb = HERReplayBuffer(
        ...     make_reward_fn("FetchReach-v4"),
        ...     achieved_goal_key=("next", "achieved_goal"),
        ...     storage=LazyTensorStorage(1000),
        ...     batch_size=32,
        ... )
        >>> _ = rb.extend(env.rollout(50))
        >>> rb.sample()["next", "reward"].shape
        torch.Size([32, 1])
    """
    return GoalRewardFn(
        env_id,
        achieved_goal_key=achieved_goal_key,
        desired_goal_key=desired_goal_key,
        **gym_kwargs,
    )
