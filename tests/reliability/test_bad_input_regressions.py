"""Regression tests for the faults a 74-case probe of bad inputs found (issue 7).

Each refused call must raise the library's own error and leave the memory, the
buffer's write position and the open episode exactly as they were.
"""
from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
import torch
from _rows import fetch_rows
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import GoalSimilaritySampler, RobotMemory, ZarrStorage


def _two_env_store(path, gen):
    storage = ZarrStorage(path, 2000)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=256)
    storage.env = "FetchPush-v4"
    rb.extend(fetch_rows(500, gen, success_rate=0.3))
    storage.env = "FetchSlide-v4"
    rb.extend(fetch_rows(500, gen, success_rate=0.3))
    return rb


def test_sampler_filters_hold_without_a_query(tmp_path):
    gen = torch.Generator().manual_seed(0)
    rb = _two_env_store(tmp_path / "m.zarr", gen)
    sampler = GoalSimilaritySampler(success_only=True, env="FetchSlide-v4")
    rb2 = TensorDictReplayBuffer(storage=rb.storage, sampler=sampler, batch_size=512)
    batch = rb2.sample()  # no query set
    assert (batch["next", "is_success"] == 1).all()
    slide = rb.storage.env_code("FetchSlide-v4")
    assert (rb.storage["env"][batch["index"]] == slide).all()
    # every matching row can come out, and nothing else
    matching = ((rb.storage["env"][:1000] == slide) & (rb.storage["next", "is_success"][:1000] == 1))
    assert set(batch["index"].tolist()) <= set(matching.nonzero().squeeze(-1).tolist())
    rb.storage.close()


def test_sampler_unknown_env_is_an_error_with_or_without_query(tmp_path):
    gen = torch.Generator().manual_seed(1)
    rb = _two_env_store(tmp_path / "m.zarr", gen)
    sampler = GoalSimilaritySampler(env="FetchPickAndPlace-v4")
    rb2 = TensorDictReplayBuffer(storage=rb.storage, sampler=sampler, batch_size=8)
    with pytest.raises(ValueError, match="unknown env 'FetchPickAndPlace-v4'.*FetchPush-v4"):
        rb2.sample()
    with pytest.raises(ValueError, match="unknown env 'FetchPickAndPlace-v4'"):
        with sampler.query(torch.zeros(3)):
            rb2.sample()
    rb.storage.close()


def test_empty_extend_is_refused_by_the_library(tmp_path, transitions):
    rb = TensorDictReplayBuffer(storage=ZarrStorage(tmp_path / "m.zarr", 100), batch_size=4)
    rb.extend(transitions(5))
    with pytest.raises(ValueError, match="Cannot write an empty TensorDict"):
        rb.extend(transitions(5)[:0])
    assert len(rb) == 5 and rb.writer._cursor == 5 and rb.writer._write_count == 5
    rb.storage.close()


@pytest.mark.parametrize("how", ["read_only", "closed"])
def test_refused_extend_does_not_move_the_write_position(tmp_path, transitions, how):
    path = tmp_path / "m.zarr"
    with ZarrStorage(path, 100) as s:
        TensorDictReplayBuffer(storage=s).extend(transitions(5))
    storage = ZarrStorage(path, read_only=how == "read_only")
    rb = TensorDictReplayBuffer(storage=storage, batch_size=4)
    if how == "closed":
        storage.close()
    assert rb.writer._cursor == 5
    with pytest.raises(RuntimeError, match="opened read_only" if how == "read_only" else "is closed"):
        rb.extend(transitions(3, 5))
    assert rb.writer._cursor == 5 and rb.writer._write_count == 5 and len(rb) == 5


def test_failed_save_perception_with_a_new_goal_keeps_the_open_episode(tmp_path):
    with RobotMemory(tmp_path / "m.zarr", max_size=100, env="FetchPush-v4") as mem:
        meta = {"achieved_goal": [0, 0, 0], "desired_goal": [1, 0, 0], "is_success": 0.0}
        mem.save_perception(np.zeros(25), np.zeros(4), -1.0, meta)
        row = mem.save_perception(np.zeros(25), np.zeros(4), -1.0, meta)
        before = mem.storage[: len(mem)].clone()
        new_goal = {**meta, "desired_goal": [0, 1, 0], "env": "FetchSlide-v4"}
        with pytest.raises(ValueError, match="'next', 'observation'|observation"):
            mem.save_perception(np.zeros(24), np.zeros(4), -1.0, new_goal)  # wrong size
        assert len(mem) == 2
        assert not bool(mem.storage["next", "done"][row].any())  # the episode is still open
        assert mem.storage.env_names == ("FetchPush-v4",)  # the refused env name was not registered
        assert (mem.storage[: len(mem)] == before).all()
        # and the episode continues with the next good transition of the same goal
        mem.save_perception(np.zeros(25), np.zeros(4), -1.0, meta)
        assert mem.storage["episode"][:3].unique().numel() == 1


def test_background_writer_failure_names_its_cause(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    s = ZarrStorage(path, 10_000, chunk_rows=64)
    rb = TensorDictReplayBuffer(storage=s, batch_size=4)
    rb.extend(transitions(10))
    s.flush()
    rb.extend(transitions(10, 10))
    # the array's directory is replaced by a file: the next chunk write fails
    target = path / "observation"
    shutil.rmtree(target)
    target.write_text("in the way")
    with pytest.raises(RuntimeError, match=r"background writer of .* failed: \w+Error: .*observation") as info:
        s.flush()
    assert info.value.__cause__ is not None
    assert "not durable" in str(info.value) and "10 rows" in str(info.value)
    # and later writes say the same, not a bare "failed"
    with pytest.raises(RuntimeError, match=r"failed: \w+Error"):
        rb.extend(transitions(1, 20))
    os.remove(target)
    s._store.release()


def test_quick_start_as_pasted_with_only_the_import_line_changed(tmp_path, monkeypatch):
    """The seed's quick start (reindented) with `from torchrl_robotmem import RobotMemory`.

    Two things come from outside the seed text: ``policy`` (the user's own
    agent) and the env id: ``FetchPickAndPlace-v3`` was removed from
    gymnasium-robotics 1.4 (``gym.make`` raises ``DeprecatedEnv: use v4``), so
    the test pastes the seed with ``-v4``.
    """
    import gymnasium_robotics  # noqa: F401  (registers the Fetch envs, as the seed's setup did)

    seed = '''
import gymnasium as gym
from torchrl_robotmem import RobotMemory
mem = RobotMemory(db="gym_robotics.db")
env = gym.make("FetchPickAndPlace-v4")
obs, info = env.reset()
for step in range(1000):
    # Recall past trajectories where similar goals were achieved
    prior = mem.recall(obs["desired_goal"], top_k=5)
    action = policy.predict(obs, prior_goals=prior)
    obs, reward, terminated, truncated, info = env.step(action)
    # Save every achieved goal with full observation context
    mem.save_perception(
        observation=obs["observation"],
        action=action,
        reward=reward,
        metadata={
            "achieved_goal": obs["achieved_goal"].tolist(),
            "desired_goal": obs["desired_goal"].tolist(),
            "is_success": info["is_success"],
            "env": "FetchPickAndPlace-v3"
        }
    )
'''

    class Policy:
        rng = np.random.default_rng(0)

        def predict(self, obs, prior_goals=None):
            assert prior_goals.batch_size == (5,)
            return self.rng.uniform(-1, 1, 4).astype(np.float32)

    monkeypatch.chdir(tmp_path)
    namespace = {"policy": Policy()}
    exec(compile(seed.replace("range(1000)", "range(120)"), "seed-quick-start", "exec"), namespace)
    mem = namespace["mem"]
    assert len(mem) == 120 and (tmp_path / "gym_robotics.db" / "zarr.json").exists()
    # the seed's loop never resets the env: one episode, so one past episode to recall (its nearest step),
    # and the five nearest steps one argument away
    prior = mem.recall(namespace["obs"]["desired_goal"], top_k=5)
    assert prior["mask"].tolist() == [True, False, False, False, False]
    assert mem.recall(namespace["obs"]["desired_goal"], top_k=5, one_per_episode=False)["mask"].all()
    assert mem.storage.env_names == ("FetchPickAndPlace-v3",)
    mem.close()
    with pytest.raises(TypeError, match="db="):
        RobotMemory()
