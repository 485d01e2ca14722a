"""Smoke tests of experiments/scripted: controllers on the real MuJoCo envs, memories, recall."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torchrl.collectors import Collector

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

from experiments.scripted.collect import collect, main, noisy_params, open_memory  # noqa: E402
from experiments.scripted.controllers import TASKS, ScriptedPolicy, default_params, param_names  # noqa: E402
from experiments.scripted.recall_params import episode_index, mean_params, recall_episodes  # noqa: E402
from torchrl_robotmem import make_env  # noqa: E402

# experiments/ is reproduced in the full tier (make test-full, every landing): make test covers the product
pytestmark = pytest.mark.full

torch.set_num_threads(1)


@pytest.mark.parametrize("task", sorted(TASKS))
def test_controller_writes_memory_and_recall_returns_params(task, tmp_path):
    path = str(tmp_path / f"{task}.zarr")
    out = collect(task, 2, path, noise=1.0, seed=3)
    assert out["episodes"] == 2 and out["rows"] == 100
    rb = open_memory(path)  # reopened: what recall sees is what is on disk
    try:
        st = rb.storage
        assert len(st) == 100 and st.env_names == (TASKS[task],)
        index = episode_index(st, ("geometry", "distance"))
        for e in range(2):
            expected = noisy_params(task, 1.0, np.random.default_rng([3, e]))
            query = st[("geometry", "distance")][e * 50]
            rows = recall_episodes(index, query, 1, success_only=False, env=TASKS[task])
            assert rows.shape == (1,) and int(rows["episode"][0]) == int(st["episode"][e * 50])
            got = mean_params(rows, param_names(task))
            for name in param_names(task):
                assert got[name] == pytest.approx(getattr(expected, name), abs=1e-6)
            # every row of the episode carries the same parameters and outcome
            ep = st[e * 50 : (e + 1) * 50]
            assert torch.unique(ep["episode_success"]).numel() == 1
            assert float(ep["episode_success"][0]) == float(ep["next", "is_success"][-1])
            assert torch.unique(ep["params", param_names(task)[0]]).numel() == 1
        # success_only recall returns only episodes whose outcome was a success: add episodes with
        # the default parameters (seeded, so the same ones every run) until some succeeded
        def episode_success():
            return st["episode_success"][: len(st)].reshape(-1, 50)[:, 0] > 0.5

        for batch in range(6):  # (slide: 1 of the first 4 succeeds)
            if episode_success().any():
                break
            collect(task, 4, path, noise=0.0, seed=3 + batch, rb=rb)
        ep_success = episode_success()
        assert ep_success.any(), f"no {task} episode succeeded with the default parameters"
        rows = recall_episodes(index, [0.1], 2)
        assert rows.shape[0] == min(2, int(ep_success.sum())), rows.shape
        assert bool((rows["episode_success"] > 0.5).all())
        # the nearest successful episodes, by their geometry
        geometry = st[("geometry", "distance")][: len(st)].reshape(-1, 50, 1)[:, 0, 0].double()
        dist = torch.where(ep_success, (geometry - 0.1).abs(), torch.inf)
        nearest = torch.argsort(dist, stable=True)[: rows.shape[0]]
        assert sorted(rows["episode"].tolist()) == sorted(st["episode"][nearest * 50].tolist())
    finally:
        rb.storage.close()


def test_default_push_succeeds_and_slide_params_recorded(tmp_path):
    out = collect("push", 2, str(tmp_path / "p.zarr"), noise=0.0, seed=0)
    assert out["successes"] == 2  # the default push controller solves these two episodes


def test_policy_in_collector_with_per_episode_params():
    env = make_env("FetchPush-v4", seed=0)
    draws = []

    def source(obs, goal):
        draws.append(dataclasses.replace(default_params("push"), strike_speed=0.3 + 0.1 * len(draws)))
        return draws[-1]

    col = Collector(env, ScriptedPolicy("push", params=source), frames_per_batch=50, total_frames=100)
    try:
        batches = list(col)
    finally:
        col.shutdown()
    # (the collector may also call the policy once on its own, so draws can exceed episodes)
    speeds = []
    for b in batches:  # one batch = one episode; its parameters are drawn once, at is_init
        assert b["action"].shape == (50, 4)
        assert torch.unique(b["params", "strike_speed"]).numel() == 1
        speeds.append(round(float(b["params", "strike_speed"][0]), 4))
    assert len(set(speeds)) == 2 and set(speeds) <= {round(p.strike_speed, 4) for p in draws}


def test_gym_and_torchrl_episodes_share_one_memory(tmp_path):
    path = str(tmp_path / "mixed.zarr")
    rb = open_memory(path, 1000)
    try:
        collect("push", 1, path, noise=0.5, rb=rb)
        collect("slide", 1, path, noise=0.5, backend="gym", rb=rb)
        assert rb.storage.env_names == ("FetchPush-v4", "FetchSlide-v4")
        assert len(rb) == 100
        assert rb.sample()["params", "strike_speed"].shape == (256,)
    finally:
        rb.storage.close()


def test_command_line(tmp_path, capsys):
    out = main(["env=slide", "episodes=1", "noise=0", f"path={tmp_path / 's.zarr'}", "--backend", "gym"])
    assert out["env"] == "FetchSlide-v4" and out["rows"] == 50
    assert '"success_rate"' in capsys.readouterr().out


def test_batched_env_keeps_per_env_phase():
    env = make_env("FetchPush-v4", num_envs=2, seed=1)
    try:
        policy = ScriptedPolicy("push", num_envs=2)
        td = env.rollout(50, policy)
        assert td.batch_size == (2, 50)
        assert bool((td["next", "is_success"][:, -1] == 1).all())  # both envs solved, each on its own goal
    finally:
        env.close()
