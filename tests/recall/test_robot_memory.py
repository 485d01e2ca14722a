"""RobotMemory: the robotmem quick-start API over ZarrStorage + GoalIndex, on a real env."""
from __future__ import annotations

from functools import partial

import gymnasium as gym
import gymnasium_robotics  # noqa: F401
import numpy as np
import pytest
import torch
from torchrl.collectors import Collector
from torchrl.data import HERReplayBuffer, TensorDictReplayBuffer

from torchrl_robotmem import GoalIndex, RobotMemory, ZarrStorage, make_env, make_reward_fn

gym.register_envs(gymnasium_robotics)


def _play(mem, env_id="FetchPickAndPlace-v4", steps=120, seed=0):
    env = gym.make(env_id)
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    log = []
    for _ in range(steps):
        action = rng.uniform(-1, 1, 4).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        mem.save_perception(
            observation=obs["observation"], action=action, reward=reward,
            metadata={"achieved_goal": obs["achieved_goal"], "desired_goal": obs["desired_goal"],
                      "is_success": info["is_success"], "env": env_id,
                      "terminated": terminated, "truncated": truncated},
        )
        log.append((obs["achieved_goal"].copy(), action, info["is_success"]))
        if terminated or truncated:
            obs, _ = env.reset()
    env.close()
    return log


def test_save_perception_and_exact_recall(tmp_path):
    with RobotMemory(tmp_path / "m.zarr", max_size=1000) as mem:
        log = _play(mem, steps=120)
        assert len(mem) == 120
        goals = torch.tensor(np.stack([g for g, _, _ in log]), dtype=torch.float32)
        query = goals[57] + 0.01
        out = mem.recall(query.numpy(), top_k=5, one_per_episode=False)  # rows, whatever their episode
        dist = (goals - query).norm(dim=-1)
        # the object rarely moves under a random policy: many ties, so compare distances
        assert torch.allclose(out["distance"], dist.sort().values[:5], atol=1e-6)
        idx = out["index"]
        assert torch.allclose(dist[idx], out["distance"], atol=1e-6)
        assert torch.allclose(out["next", "achieved_goal"], goals[idx])
        assert torch.allclose(out["action"], torch.tensor(np.stack([log[i][1] for i in idx.tolist()])))
        assert out["mask"].all() and (out["distance"][1:] >= out["distance"][:-1]).all()
        # episodes: 50-step Fetch episodes, split at truncation, root obs = previous next obs
        s = mem.storage
        assert s["episode"][:120].tolist() == [0] * 50 + [1] * 50 + [2] * 20
        assert torch.equal(s["observation"][1:50], s["next", "observation"][0:49])
        assert s.env_names == ("FetchPickAndPlace-v4",)


def test_recall_filters_batch_and_robotmem_style_arguments(tmp_path):
    with RobotMemory(tmp_path / "m.zarr", max_size=1000) as mem:
        for t in range(30):
            mem.save_perception(
                np.zeros(25), np.zeros(4), -1.0,
                {"achieved_goal": [t * 0.01, 0, 0], "desired_goal": [1, 0, 0],
                 "is_success": t % 10 == 0, "env": "FetchPush-v4" if t < 20 else "FetchSlide-v4"},
            )
        q = np.array([0.155, 0, 0])
        # 30 rows of one episode: row-level recall (one_per_episode=False) ranks rows; the default, episodes
        assert mem.recall(q, top_k=2, one_per_episode=False)["index"].tolist() == [15, 16]
        assert mem.recall(q, top_k=2)["index"].tolist() == [15, -1]
        succ = mem.recall(q, top_k=5, success_only=True, one_per_episode=False)
        assert succ["index"][:3].tolist() == [20, 10, 0] and succ["mask"].tolist() == [True] * 3 + [False] * 2
        assert (succ["next", "is_success"][:3] == 1).all()
        same = mem.recall(None, top_k=5, context_filter={"task.success": True}, one_per_episode=False,
                          spatial_sort={"field": "spatial.target", "target": q})
        assert torch.equal(same["index"], succ["index"])
        slide = mem.recall(q, top_k=3, env="FetchSlide-v4", one_per_episode=False)
        assert slide["index"].tolist() == [20, 21, 22]
        batch = mem.recall(np.stack([q, q * 0]), top_k=2, one_per_episode=False)
        assert batch.shape == (2, 2) and batch["index"][1].tolist() == [0, 1]
        with pytest.raises(ValueError, match="FetchReach-v4"):
            mem.recall(q, env="FetchReach-v4")
        with pytest.raises(KeyError, match="context_filter"):
            mem.recall(q, context_filter={"task.reward": 1})


def test_bad_input_leaves_memory_unchanged(tmp_path):
    with RobotMemory(tmp_path / "m.zarr", max_size=100) as mem:
        ok = {"achieved_goal": [0, 0, 0], "desired_goal": [1, 0, 0], "is_success": 0}
        mem.save_perception(np.zeros(25), np.zeros(4), -1.0, ok)
        with pytest.raises(KeyError, match="achieved_goal"):
            mem.save_perception(np.zeros(25), np.zeros(4), -1.0, {"desired_goal": [1, 0, 0]})
        with pytest.raises(ValueError, match="NaN"):
            mem.save_perception(np.full(25, np.nan), np.zeros(4), -1.0, ok)
        with pytest.raises(ValueError, match="'observation'.*shape"):
            mem.save_perception(np.zeros(24), np.zeros(4), -1.0, ok)
        with pytest.raises(KeyError, match="Unknown metadata"):
            mem.save_perception(np.zeros(25), np.zeros(4), -1.0, {**ok, "colour": "red"})
        with pytest.raises(ValueError, match="dim"):
            mem.recall([0.0, 0.0], top_k=1)
        with pytest.raises(ValueError, match="NaN or infinite"):
            mem.recall([np.nan, 0.0, 0.0], top_k=1)
        with pytest.raises(ValueError, match="k must be"):
            mem.recall([0.0, 0.0, 0.0], top_k=0)
        assert len(mem) == 1 and mem.buffer.writer._cursor == 1


def test_goal_change_starts_a_new_episode(tmp_path):
    with RobotMemory(tmp_path / "m.zarr", max_size=100) as mem:
        for goal in ([1, 0, 0], [1, 0, 0], [0, 1, 0]):  # no done flag between goals
            mem.save_perception(np.zeros(25), np.zeros(4), -1.0, {"achieved_goal": [0, 0, 0], "desired_goal": goal})
        s = mem.storage
        assert s["episode"][:3].tolist() == [0, 0, 1]
        assert s["next", "done"][:3].squeeze(-1).tolist() == [False, True, False]


def test_collector_store_is_readable_by_robotmemory_and_back(tmp_path):
    path = tmp_path / "m.zarr"
    storage = ZarrStorage(path, 10_000, env="FetchPush-v4")
    rb = TensorDictReplayBuffer(storage=storage, batch_size=32)
    collector = Collector(partial(make_env, "FetchPush-v4", seed=1), policy=None, frames_per_batch=100, total_frames=200)
    for data in collector:
        rb.extend(data.reshape(-1))
    collector.shutdown()
    goals = storage["next", "achieved_goal"][:200].clone()
    storage.close()

    with RobotMemory(path) as mem:  # read a collector-written store
        assert len(mem) == 200
        q = goals[123]
        got = int(mem.recall(q.numpy(), top_k=1)["index"][0])
        assert torch.equal(goals[got], q)  # ties: the object sits still for many steps
        # and write into it: keys the facade does not know are zero-filled
        mem.save_perception(np.zeros(25), np.zeros(4), -1.0,
                            {"achieved_goal": [9, 9, 9], "desired_goal": [1, 1, 1], "is_success": 1.0})
        assert len(mem) == 201
    storage = ZarrStorage(path)  # ... and back: TorchRL buffers sample it, HER relabels it
    her = HERReplayBuffer(reward_fn=make_reward_fn("FetchPush-v4"), storage=storage, batch_size=64,
                          achieved_goal_key=("next", "achieved_goal"))
    batch = her.sample()
    assert batch.shape == (64,) and (batch["next", "reward"] == 0).any()
    assert int(GoalIndex(storage).search([9.0, 9.0, 9.0], 1)[1][0]) == 200
    storage.close()


def test_save_episode_from_a_rollout(tmp_path):
    env = make_env("FetchReach-v4", seed=0)
    with RobotMemory(tmp_path / "m.zarr", max_size=1000) as mem:
        rows = mem.save_episode(env.rollout(20))
        assert rows.tolist() == list(range(20))
        assert bool(mem.storage["next", "done"][19])  # closed although the rollout was cut
        rows = mem.save_episode(env.rollout(10))
        assert mem.storage["episode"][20:30].unique().tolist() == [1]
        with pytest.raises(TypeError, match="batch size"):
            mem.save_episode(env.rollout(4).reshape(2, 2))


def test_save_episode_ends_the_episode_save_perception_left_open(tmp_path):
    """Found by a review: three save_perception steps (no done) then save_episode gave the stored episode the
    same id as the open one, so recall(one_per_episode=True) and HER took the two for one episode."""
    env = make_env("FetchReach-v4", seed=0)
    meta = {"achieved_goal": [0.1, 0, 0], "desired_goal": [1, 0, 0], "is_success": 0.0}
    with RobotMemory(tmp_path / "m.zarr", max_size=100) as mem:
        for _ in range(3):
            mem.save_perception(np.zeros(10), np.zeros(4), -1.0, meta)
        with pytest.raises(TypeError, match="batch size"):  # refused: the open episode stays open
            mem.save_episode(env.rollout(4).reshape(2, 2))
        assert not bool(mem.storage["next", "done"][2])
        mem.save_episode(env.rollout(5))
        assert mem.storage["episode"][:8].tolist() == [0, 0, 0, 1, 1, 1, 1, 1]
        assert mem.storage["next", "done"][:8].reshape(-1).tolist() == [False, False, True] + [False] * 4 + [True]


def test_notebook_cell_run_twice(tmp_path):
    """`mem = RobotMemory(path)` run again while the first memory (and its index) is alive."""
    meta = {"achieved_goal": [0.1, 0, 0], "desired_goal": [1, 0, 0], "is_success": 0.0}
    mem = RobotMemory(tmp_path / "x.db", max_size=100)
    mem.save_perception(np.zeros(25), np.zeros(4), -1.0, meta)
    first, index = mem.storage, mem.index  # something still refers to the first handle
    mem = RobotMemory(tmp_path / "x.db")
    assert len(mem) == 1
    mem.save_perception(np.zeros(25), np.zeros(4), -1.0, meta)
    assert len(mem) == 2 and len(first) == 1 and index.storage is first  # the old handle is a snapshot
    # run the cell a third time: the second handle (never closed) hands over its rows
    mem = RobotMemory(tmp_path / "x.db")
    assert len(mem) == 2 and len(RobotMemory(tmp_path / "x.db", read_only=True)) == 2
    mem.close()


def _files(path):
    import hashlib

    return {p.relative_to(path).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("bad", [
    ("reward", float("nan"), ValueError, r"'reward' is nan"),
    ("reward", float("inf"), ValueError, r"'reward' is inf"),
    ("reward", [1.0, 2.0], ValueError, r"'reward' must be one number \(shape \[\] or \[1\]\), got shape \[2\]"),
    ("reward", np.zeros((1, 1)), ValueError, r"'reward' must be one number"),
    ("reward", "high", TypeError, r"'reward' must be one number"),
    ("is_success", float("nan"), ValueError, r"'is_success' is nan"),
    ("is_success", -float("inf"), ValueError, r"'is_success' is -inf"),
    ("is_success", [1, 0], ValueError, r"'is_success' must be one number .*shape \[2\]"),
], ids=["reward-nan", "reward-inf", "reward-pair", "reward-2d", "reward-str", "success-nan", "success-inf",
        "success-pair"])
def test_reward_and_success_are_checked_like_the_observation(tmp_path, bad):
    """A NaN / inf / wrongly shaped reward or success is refused, naming it; the memory is unchanged."""
    name, value, error, match = bad
    path = tmp_path / "m.zarr"
    ok = {"achieved_goal": [0, 0, 0], "desired_goal": [1, 0, 0], "is_success": 0}
    with RobotMemory(path, max_size=100, background=False) as mem:
        mem.save_perception(np.zeros(25), np.zeros(4), -1.0, ok)
        mem.flush()
        before = _files(path)
        reward, meta = (value, ok) if name == "reward" else (-1.0, {**ok, "is_success": value})
        with pytest.raises(error, match=match):
            mem.save_perception(np.ones(25), np.zeros(4), reward, {**meta, "env": "FetchPush-v4"})
        mem.flush()
        assert _files(path) == before, "a refused transition changed the store"
        assert len(mem) == 1 and mem.buffer.writer._cursor == 1 and mem.storage.env_names == ()
        # the open episode continues: the refused call left no trace in it
        mem.save_perception(np.full(25, 2.0), np.zeros(4), np.float32(0.5), {**ok, "is_success": np.array([True])})
        s = mem.storage
        assert s["episode"][:2].tolist() == [0, 0]
        assert s["observation"][1].tolist() == [0.0] * 25  # the root values are the previous step's
        assert s["next", "reward"][:2].squeeze(-1).tolist() == [-1.0, 0.5]
        assert s["next", "is_success"][:2].tolist() == [0.0, 1.0]


def test_recall_top_k_far_above_the_rows(tmp_path):
    """top_k = 10**12 on a memory of 3 rows (capacity 100): 100 slots, the 3 rows first; nothing allocated for k."""
    with RobotMemory(tmp_path / "m.zarr", max_size=100, background=False) as mem:
        assert mem.recall([0.0, 0.0, 0.0], top_k=10**12)["mask"].shape == (100,)  # empty: the same shape
        for t in range(3):
            mem.save_perception(np.zeros(25), np.zeros(4), -1.0, {"achieved_goal": [0.1 * t, 0, 0],
                                                                  "desired_goal": [1, 0, 0], "is_success": t == 2})
        out = mem.recall([0.0, 0.0, 0.0], top_k=10**12, one_per_episode=False)
        assert out.batch_size == (100,) and out["index"][:4].tolist() == [0, 1, 2, -1]
        assert out["mask"].sum() == 3 and out["mask"][:3].all()
        succ = mem.recall([0.0, 0.0, 0.0], top_k=10**12, success_only=True)
        assert succ["mask"].sum() == 1 and succ["index"][:2].tolist() == [2, -1]
        assert mem.recall(np.zeros((2, 3)), top_k=10**12).batch_size == (2, 100)
        assert mem.recall(np.zeros(3), top_k=5).batch_size == (5,)  # below the capacity: top_k slots, as always


def _episode_reference(mem, goal, k, keep=None, max_distance=None):
    """Brute force: the k episodes whose nearest (kept) row is closest to ``goal``, as (distance, episode) pairs."""
    s, n = mem.storage, len(mem)
    d = (s["next", "achieved_goal"][:n].double() - torch.as_tensor(goal, dtype=torch.float64)).norm(dim=-1)
    best = {}
    for e, dist, ok in zip(s["episode"][:n].tolist(), d.tolist(), (keep if keep is not None else [True] * n)):
        if ok and (max_distance is None or dist <= max_distance) and dist < best.get(e, float("inf")):
            best[e] = dist
    return sorted(best.items(), key=lambda item: item[1])[:k]


def _assert_episodes(out, ref):
    mask = out["mask"]
    assert int(mask.sum()) == len(ref)
    episodes = out["episode"][mask].tolist()
    assert len(set(episodes)) == len(episodes), "two results from one episode"
    assert np.allclose(out["distance"][mask].numpy(), [d for _, d in ref], atol=1e-6)
    # the same episodes, except where two episodes tie to float precision
    for got, (e, dist) in zip(episodes, ref):
        assert got == e or any(abs(d2 - dist) < 1e-6 for e2, d2 in ref if e2 == got)


def test_seed_quick_start_recall_returns_distinct_episodes(tmp_path):
    """The seed's `prior = mem.recall(obs["desired_goal"], top_k=5)`: five past episodes, not five steps of one."""
    with RobotMemory(tmp_path / "m.zarr", max_size=1000) as mem:
        _play(mem, steps=300)  # six 50-step FetchPickAndPlace episodes, saved as the quick start saves them
        env = gym.make("FetchPickAndPlace-v4")
        obs, _ = env.reset(seed=7)
        env.close()
        prior = mem.recall(obs["desired_goal"], top_k=5)
        assert prior["mask"].all() and prior["episode"].unique().numel() == 5
        assert (prior["distance"][1:] >= prior["distance"][:-1]).all()
        _assert_episodes(prior, _episode_reference(mem, obs["desired_goal"], 5))
        # the row-level answer is one argument away: the 5 nearest steps (a random policy rarely moves the
        # object, so they tie and come from fewer episodes than 5)
        rows = mem.recall(obs["desired_goal"], top_k=5, one_per_episode=False)
        d = (mem.storage["next", "achieved_goal"][:300] - torch.as_tensor(obs["desired_goal"]).float()).norm(dim=-1)
        assert torch.allclose(rows["distance"], d.sort().values[:5], atol=1e-6)


def test_recall_episodes_exact_with_filters(tmp_path):
    """Distinct-episode recall is exact (the k nearest episodes by their nearest row) under every filter."""
    rng = np.random.default_rng(0)
    with RobotMemory(tmp_path / "m.zarr", max_size=1000) as mem:
        envs = ["FetchPush-v4", "FetchSlide-v4"]
        for episode in range(24):
            for t in range(10):
                mem.save_perception(np.zeros(25), np.zeros(4), -1.0, {
                    "achieved_goal": rng.uniform(0, 1, 3), "desired_goal": [episode, 0, 0],
                    "is_success": rng.uniform() < 0.3, "env": envs[episode % 2], "truncated": t == 9})
        s, n = mem.storage, len(mem)
        success = (s["next", "is_success"][:n] > 0.5).tolist()
        slide = (s["env"][:n] == s.env_code("FetchSlide-v4")).tolist()
        for goal in rng.uniform(0, 1, (4, 3)):
            _assert_episodes(mem.recall(goal, top_k=6), _episode_reference(mem, goal, 6))
            _assert_episodes(mem.recall(goal, top_k=6, success_only=True),
                             _episode_reference(mem, goal, 6, keep=success))
            _assert_episodes(mem.recall(goal, top_k=5, env="FetchSlide-v4"), _episode_reference(mem, goal, 5, keep=slide))
            both = [a and b for a, b in zip(success, slide)]
            _assert_episodes(mem.recall(goal, top_k=30, success_only=True, env="FetchSlide-v4", max_distance=0.4),
                             _episode_reference(mem, goal, 30, keep=both, max_distance=0.4))
