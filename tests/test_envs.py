"""Tests for torchrl_robotmem.envs on real Gymnasium-Robotics MuJoCo envs."""
from __future__ import annotations

import functools
import pickle

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.data import HERReplayBuffer, LazyTensorStorage
from torchrl.envs import CatTensors, ParallelEnv, SerialEnv
from torchrl.envs.utils import check_env_specs

from torchrl_robotmem.envs import env_family, goal_dim, make_env, make_reward_fn

torch.set_num_threads(1)

BASE_IDS = [
    "FetchReach-v4",
    "FetchPush-v4",
    "FetchSlide-v4",
    "FetchPickAndPlace-v4",
    "HandReach-v3",
    "HandManipulateBlock-v1",
    "HandManipulateEgg-v1",
    "HandManipulatePen-v1",
]


# -- specs ------------------------------------------------------------------


@pytest.mark.parametrize("env_id", BASE_IDS)
def test_check_env_specs_single(env_id):
    env = make_env(env_id, seed=0)
    try:
        check_env_specs(env, seed=0)
        assert env.batch_size == torch.Size([])
        assert env.env_id == env_id
        spec = env.observation_spec
        for key in ("observation", "achieved_goal", "desired_goal", "is_success", "step_count"):
            assert key in spec.keys(), key
        assert spec["desired_goal"].shape == (goal_dim(env_id),)
    finally:
        env.close()


def test_serial_batched_specs_seeding_and_outer_transforms():
    cat = CatTensors(["observation", "desired_goal"], out_key="obs_goal", del_keys=False)
    env = make_env("gymnasium_robotics:FetchReach-v4", num_envs=2, seed=3, transforms=[cat])
    try:
        assert isinstance(env.base_env, SerialEnv)
        assert env.env_id == "FetchReach-v4"
        # The extra transform sits after the standard ones and sees the [2] batch.
        assert env.transform[-1] is cat
        check_env_specs(env, seed=3)
        td = env.rollout(4)
        assert td.batch_size == (2, 4)
        assert td["obs_goal"].shape == (2, 4, 10 + 3)
        assert td["next", "is_success"].shape == (2, 4)
        # Workers get distinct seeds, hence distinct goals.
        assert not torch.equal(td["desired_goal"][0, 0], td["desired_goal"][1, 0])
    finally:
        env.close()


@pytest.mark.parametrize("threads", [1, 2])
def test_closing_a_batched_env_keeps_the_thread_count(threads):
    """A run on N torch threads that closes an evaluation SerialEnv mid-run goes on with N threads."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        env = make_env("FetchReach-v4", num_envs=5, seed=0)
        env.rollout(2)
        env.close()
        assert torch.get_num_threads() == threads
        with pytest.raises(RuntimeError, match="closed"):  # still TorchRL's close: a second one is refused
            env.close()
        env.close(raise_if_closed=False)
        assert torch.get_num_threads() == threads
    finally:
        torch.set_num_threads(before)


def test_seed_reproducible():
    goals = []
    for _ in range(2):
        env = make_env("FetchPush-v4", seed=7)
        goals.append(env.reset()["desired_goal"])
        env.close()
    assert torch.equal(goals[0], goals[1])


@pytest.mark.timeout(600)  # a hang guard, not a speed limit
def test_parallel_spawn_specs():
    env = make_env("FetchReach-v4", num_envs=2, parallel=True, seed=0)
    try:
        assert isinstance(env.base_env, ParallelEnv)
        check_env_specs(env, seed=0)
        td = env.rollout(3)
        assert td["achieved_goal"].shape == (2, 3, 3)
        assert td["achieved_goal"].dtype == torch.float32
    finally:
        env.close()


# -- rollouts ---------------------------------------------------------------


@pytest.mark.parametrize(
    "env_id, obs_dim, goal, act_dim",
    [("FetchPush-v4", 25, 3, 4), ("HandManipulateBlock-v1", 61, 7, 20)],
)
def test_rollout_shapes_and_dtypes(env_id, obs_dim, goal, act_dim):
    env = make_env(env_id, seed=0)
    try:
        td = env.rollout(5)
    finally:
        env.close()
    assert td["observation"].shape == (5, obs_dim)
    assert td["action"].shape == (5, act_dim)
    for key in ("observation", "achieved_goal", "desired_goal", "is_success"):
        for k in (key, ("next", key)):
            assert td[k].dtype == torch.float32, k
    for k in ("achieved_goal", "desired_goal"):
        assert td[k].shape == td["next", k].shape == (5, goal)
    assert td["action"].dtype == td["next", "reward"].dtype == torch.float32
    assert td["is_success"].shape == td["next", "is_success"].shape == (5,)


def test_max_episode_steps_truncates_and_counts():
    env = make_env("FetchReach-v4", max_episode_steps=5, seed=0)
    try:
        td = env.rollout(12, break_when_any_done=False)
    finally:
        env.close()
    assert env.max_episode_steps == 5
    truncated = td["next", "truncated"].squeeze(-1).nonzero().squeeze(-1)
    assert truncated.tolist() == [4, 9]
    assert td["step_count"].squeeze(-1).tolist() == [0, 1, 2, 3, 4] * 2 + [0, 1]
    assert td["is_init"].squeeze(-1).nonzero().squeeze(-1).tolist() == [0, 5, 10]


# -- reward fn --------------------------------------------------------------


def test_reward_fn_sparse_matches_env_and_relabels():
    env = make_env("FetchReach-v4", seed=1)
    try:
        td = env.rollout(20)
    finally:
        env.close()
    reward_fn = make_reward_fn("FetchReach-v4")
    reward = reward_fn(td)
    assert reward.dtype == torch.float32
    assert reward.shape == (20, 1)
    assert torch.equal(reward, td["next", "reward"])
    assert torch.equal(reward_fn.success(td), td["next", "is_success"])
    # Any batch shape, e.g. [2, 10] rows.
    assert torch.equal(reward_fn(td.reshape(2, 10)), reward.reshape(2, 10, 1))
    # Hindsight: the reached goal as desired goal is a success.
    relabelled = td.clone()
    relabelled["desired_goal"] = td["next", "achieved_goal"]
    assert torch.equal(reward_fn(relabelled), torch.zeros(20, 1))
    assert torch.equal(reward_fn.success(relabelled), torch.ones(20))
    # Survives pickling (spawned workers) without carrying the MuJoCo env.
    clone = pickle.loads(pickle.dumps(reward_fn))
    assert clone._env is None
    assert torch.equal(clone(td), reward)


@pytest.mark.parametrize("env_id", ["FetchPushDense-v4", "HandManipulatePenDense-v1"])
def test_reward_fn_dense_matches_env(env_id):
    # Pen exercises the row-wise path: gymnasium-robotics' batched
    # compute_reward is wrong for envs with ignore_z_target_rotation.
    env = make_env(env_id, seed=0)
    try:
        td = env.rollout(20)
    finally:
        env.close()
    reward_fn = make_reward_fn(env_id)
    reward = reward_fn(td)
    assert reward.shape == (20, 1) and reward.dtype == torch.float32
    assert td["next", "reward"].abs().min() > 0  # dense: informative values
    torch.testing.assert_close(reward, td["next", "reward"], atol=1e-4, rtol=1e-4)
    relabelled = td.clone()
    relabelled["desired_goal"] = td["next", "achieved_goal"]
    # Not exactly 0 for Hand: 2 * arccos(|q|^2) of a float32 quaternion is ~1e-3.
    torch.testing.assert_close(reward_fn(relabelled), torch.zeros(20, 1), atol=2e-3, rtol=0)
    assert torch.equal(reward_fn.success(relabelled), torch.ones(20))


def test_reward_fn_in_her_buffer():
    env = make_env("FetchReach-v4", seed=0)
    try:
        data = env.rollout(100, break_when_any_done=False)
    finally:
        env.close()
    reward_fn = make_reward_fn("FetchReach-v4")
    rb = HERReplayBuffer(
        reward_fn,
        her_ratio=1.0,
        strategy="future",
        achieved_goal_key=("next", "achieved_goal"),
        storage=LazyTensorStorage(200),
        batch_size=64,
    )
    rb.extend(data)
    torch.manual_seed(0)
    batch = rb.sample()
    assert batch["next", "reward"].shape == (64, 1)
    # Relabelled rewards agree with the goals now in the batch, and "future"
    # goals include the reached ones (reward 0) that random play never hits.
    assert torch.equal(batch["next", "reward"], reward_fn(batch))
    assert (batch["next", "reward"] == 0).any()


# -- collector --------------------------------------------------------------


def test_collector_random_policy():
    collector = Collector(
        functools.partial(make_env, "FetchReach-v4", seed=0),
        policy=None,
        frames_per_batch=50,
        total_frames=100,
    )
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch.batch_size == (50,)
        assert batch["next", "is_success"].shape == (50,)
        assert batch["desired_goal"].dtype == torch.float32
        assert batch["action"].abs().max() <= 1.0
    # 50 frames = one 50-step episode each: the first truncates at its end.
    assert batches[0]["next", "truncated"].squeeze(-1).nonzero().squeeze(-1).tolist() == [49]


# -- ids --------------------------------------------------------------------


@pytest.mark.parametrize(
    "env_id, family, dim",
    [
        ("FetchPushDense-v4", "fetch", 3),
        ("gymnasium_robotics:HandReach-v3", "hand_reach", 15),
        ("HandManipulateBlockRotateZ-v1", "hand_manipulate", 7),
        ("HandManipulatePen_ContinuousTouchSensorsDense-v1", "hand_manipulate", 7),
    ],
)
def test_family_and_goal_dim(env_id, family, dim):
    assert env_family(env_id) == family
    assert goal_dim(env_id) == dim


def test_unknown_id_message():
    with pytest.raises(ValueError, match="Supported families") as err:
        make_env("FetchJump-v4")
    assert "FetchPush-v4" in str(err.value)  # close-match hint
    with pytest.raises(ValueError, match="Unknown or unsupported"):
        env_family("CartPole-v1")
    # Legacy mujoco-py ids are registered but cannot be built.
    with pytest.raises(ValueError, match="Unknown or unsupported"):
        make_reward_fn("FetchPush-v1")
