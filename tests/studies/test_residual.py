"""experiments/residual: the scripted controller inside the env, the residual policy, the recipe end to end.

Real FetchPush envs, a real scripted memory and the recipe as a subprocess."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

from experiments.residual.base import ScriptedBase, recalled_params  # noqa: E402
from experiments.scripted.collect import collect  # noqa: E402
from experiments.scripted.controllers import ScriptedPolicy  # noqa: E402
from torchrl_robotmem import ZarrStorage, make_env  # noqa: E402

# experiments/ is reproduced in the full tier (make test-full, every landing): make test covers the product
pytestmark = pytest.mark.full


def _controller_outcomes(memory: str, episodes: int = 2) -> list[int]:
    """Per-episode success of the controller recalled from ``memory`` on recipes/her's seed-0 evaluation goals."""
    env = make_env("FetchPush-v4", episodes, seed=10_000)
    try:
        env.set_seed(10_000)
        td = env.rollout(50, ScriptedPolicy("push", recalled_params("push", memory), num_envs=episodes),
                         break_when_any_done=False)
        return (td["next", "is_success"][:, -1] > 0.5).int().tolist()
    finally:
        env.close()


def _base_policy(td):
    return td.set("action", td["base_action"].clone())


def test_scripted_base_acts_as_the_scripted_policy():
    """Written as an observation, the controller's action is the one ScriptedPolicy takes, step for step."""
    env = make_env("FetchPush-v4", 2, seed=1)
    based = make_env("FetchPush-v4", 2, seed=1, transforms=[ScriptedBase("push")])
    try:
        want = env.rollout(50, ScriptedPolicy("push", num_envs=2))
        got = based.rollout(50, _base_policy)
        assert torch.equal(got["action"], want["action"])
        assert torch.equal(got["next", "observation"], want["next", "observation"])
        assert bool((got["next", "is_success"][:, -1] == 1).all())
        # the phase one-hot moves forward and is there for the next state too (the critic bootstraps from it)
        phase = got["next", "base_state"][..., :5].argmax(-1)
        assert bool((phase[:, 1:] >= phase[:, :-1]).all()) and int(phase[:, -1].min()) == 4
        assert torch.equal(got["base_state"][:, 1:], got["next", "base_state"][:, :-1])
    finally:
        env.close()
        based.close()


def test_residual_env_steps_base_plus_action_and_keeps_the_residual():
    zero = make_env("FetchPush-v4", 2, seed=1, transforms=[ScriptedBase("push", residual=True)])
    push = make_env("FetchPush-v4", 2, seed=1, transforms=[ScriptedBase("push", residual=True)])
    plain = make_env("FetchPush-v4", 2, seed=1)
    try:
        want = plain.rollout(50, ScriptedPolicy("push", num_envs=2))
        got = zero.rollout(50, lambda td: td.set("action", torch.zeros(2, 4)))
        assert torch.equal(got["next", "observation"], want["next", "observation"])  # residual 0: the controller
        assert torch.equal(got["action"], torch.zeros(2, 50, 4))  # the tensordict keeps the residual
        shift = torch.tensor([0.0, 0.0, 2.0, 0.0])  # up, whatever the controller says (the sum is clipped to 1)
        moved = push.rollout(50, lambda td: td.set("action", shift.expand(2, 4).clone()))
        assert torch.equal(moved["action"][0, 0], shift)
        height = moved["next", "observation"][..., 2]  # the gripper's z: it rises at full speed every step
        assert bool((height[:, -1] > want["next", "observation"][..., 2].max(-1).values + 0.1).all())
        assert bool((height[:, 1:] >= height[:, :-1] - 1e-3).all())
    finally:
        for e in (zero, push, plain):
            e.close()


def test_partial_reset_keeps_the_running_episodes_state():
    env = make_env("FetchPush-v4", 2, seed=2, transforms=[ScriptedBase("push")])
    try:
        td = env.reset()
        for _ in range(12):
            td = env.step(_base_policy(td))
            td = td["next"].clone()
        before = td["base_state"].clone()
        assert int(before[1, :5].argmax()) > 0  # env 1 is past its first phase
        td.set("_reset", torch.tensor([[True], [False]]))
        after = env.reset(td)
        assert int(after["base_state"][0, :5].argmax()) == 0  # env 0 starts over
        assert torch.equal(after["base_state"][1], before[1])  # env 1 is untouched
    finally:
        env.close()


def test_recalled_params_come_from_the_memory(tmp_path):
    path = str(tmp_path / "push.zarr")
    collect("push", 6, path, noise=1.0, seed=0)
    params = recalled_params("push", path, k=2)
    obs = torch.zeros(25).double().numpy()
    obs[3:6] = (1.3, 0.75, 0.42)
    p = params(obs, obs[3:6] + [0.1, 0.0, 0.0])
    assert p != recalled_params("push", None)(obs, obs[3:6])  # noisy episodes: not the defaults
    ZarrStorage(str(tmp_path / "empty.zarr"), max_size=10).close()
    with pytest.raises(ValueError, match="empty"):
        recalled_params("push", str(tmp_path / "empty.zarr"))


@pytest.mark.parametrize("actor_update", ["sac", "crr"])
def test_recipe_starts_as_the_recalled_controller_and_keeps_its_transitions(tmp_path, actor_update):
    memory = str(tmp_path / "scripted.zarr")
    collect("push", 6, memory, noise=1.0, seed=0)
    run = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.residual.train", f"base.memory={memory}", "collector.total_frames=200",
         "collector.warmup_frames=100", "collector.actor_freeze_frames=150", "optim.batch_size=8",
         "network.hidden_sizes=[16,16]", "logger.eval_iter=100", "logger.eval_episodes=2",
         f"algo.actor_update={actor_update}",
         f"memory.path={tmp_path / 'run.zarr'}", f"hydra.run.dir={run}"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["frames"] == 200 and summary["updates"] == 200 and summary["memory_rows_after"] == 200
    evals = [json.loads(line) for line in (run / "eval_episodes.jsonl").read_text().splitlines()]
    assert [e["frames"] for e in evals] == [0, 100, 200]
    assert evals[0]["success"] == _controller_outcomes(memory)  # the first policy is the recalled controller
    stored = ZarrStorage(str(tmp_path / "run.zarr"), read_only=True)[:]
    assert {"base_action", "base_state"} <= set(stored.keys()) and ("next", "base_action") in stored.keys(True)
    assert float(stored["action"].abs().max()) < 1.0  # the residual, inside its range, not the env's action
    assert "loc" not in stored.keys()
    logged = {p.stem for p in run.glob("her_logging/*/scalars/train/*.csv")}
    assert {"loss_actor", "loss_qvalue", "residual_sq"} <= logged  # the actor moved after actor_freeze_frames
    assert ("crr_kept" in logged) == (actor_update == "crr")


def test_recipe_refuses_a_memory_that_already_holds_transitions(tmp_path):
    path = tmp_path / "run.zarr"
    st = ZarrStorage(str(path), max_size=10, env="FetchPush-v4")
    st.set(torch.arange(1), TensorDict({"x": torch.zeros(1, 1), "next": {"is_success": torch.zeros(1)}}, [1]))
    st.close()
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.residual.train", f"memory.path={path}", f"hydra.run.dir={tmp_path / 'r'}"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode != 0 and "already holds 1 transitions" in proc.stderr
    bad = tmp_path / "bad.zarr"
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.residual.train", "algo.actor_update=ppo", f"memory.path={bad}",
         f"hydra.run.dir={tmp_path / 'b'}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0 and "algo.actor_update must be sac or crr" in proc.stderr and not bad.exists()


def test_improve_grows_the_memory_and_starts_as_the_recalled_controller(tmp_path):
    """experiments.scripted.improve: the prior is copied, never written; new episodes join the run's memory with their
    (explored) parameters; the first evaluation is the controller recalled from the prior."""
    from experiments.scripted.controllers import default_params
    from experiments.scripted.improve import improve
    from experiments.scripted.recall_params import STRIKE_RECALLED

    prior = str(tmp_path / "prior.zarr")
    collect("push", 6, prior, noise=1.0, seed=0)
    before = ZarrStorage(prior, read_only=True)[:]
    out = improve("push", prior, str(tmp_path / "run.zarr"), str(tmp_path / "run"), frames=200, seed=0,
                  eval_every=100, eval_episodes=2)
    assert out["frames"] == 200 and out["memory_rows_after"] == 500
    after = ZarrStorage(prior, read_only=True)[:]
    assert after.shape == before.shape and torch.equal(after["action"], before["action"])  # the prior: unchanged
    run = ZarrStorage(str(tmp_path / "run.zarr"), read_only=True)[:]
    assert torch.equal(run[:300]["action"], before["action"])  # copied first
    new = run[300:]
    defaults = default_params("push")
    for name in ("strike_length", "strike_reach"):  # not recalled: the defaults, unexplored
        assert bool((new["params", name] == getattr(defaults, name)).all())
    aims = new["params", "aim_angle"][::50]
    assert "aim_angle" in STRIKE_RECALLED and torch.unique(aims).numel() == 4  # explored: one draw an episode
    evals = [json.loads(line) for line in (tmp_path / "run" / "eval_episodes.jsonl").read_text().splitlines()]
    assert [e["frames"] for e in evals] == [0, 100, 200]
    assert evals[0]["success"] == _controller_outcomes(prior)
    with pytest.raises(FileExistsError, match="must be new"):
        improve("push", prior, str(tmp_path / "run.zarr"), str(tmp_path / "again"), frames=100)
