"""recipes/her (issue 25): prior memories' dtypes and summary, pretraining that stops when done, CPU-seconds.

Real parts: prior memories written from a raw Gymnasium-Robotics env through TorchRL's
GymEnv (float64 observations, as a Minari or SB3 import keeps them), real ZarrStores,
the recipe run as a subprocess with a budget of a few dozen frames.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from training.test_her_recipe import TINY  # the tiny budget every recipe test runs with

ROOT = Path(__file__).resolve().parents[2]
RECIPE_DIR = ROOT / "recipes" / "her"


def recipe(tmp_path: Path, *overrides: str, out: str = "out") -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(RECIPE_DIR / "train.py"), *TINY, *overrides, f"hydra.run.dir={tmp_path / out}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )


def summary_of(tmp_path: Path, proc: subprocess.CompletedProcess, out: str = "out") -> dict:
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads((tmp_path / out / "summary.json").read_text())


def raw_gym_rows(episodes: int = 2, seed: int = 0):
    """Episodes of FetchReach from TorchRL's GymEnv with no float32 transform: float64 observations and goals."""
    import gymnasium
    import gymnasium_robotics
    from torchrl.envs import GymEnv, StepCounter, TransformedEnv
    from torchrl.envs.libs.gym import default_info_dict_reader

    gymnasium.register_envs(gymnasium_robotics)
    env = GymEnv("FetchReach-v4")
    env.set_info_dict_reader(default_info_dict_reader(["is_success"]))
    env = TransformedEnv(env, StepCounter(50))
    env.set_seed(seed)
    torch.manual_seed(seed)
    try:
        return env.rollout(50 * episodes, break_when_any_done=False)
    finally:
        env.close()


def write_memory(path: Path, rows) -> Path:
    from torchrl_robotmem import ZarrStorage

    with ZarrStorage(path, max_size=1000, env="FetchReach-v4") as store:
        store.set(range(rows.shape[0]), rows)
    return path


def test_a_float64_prior_is_cast_summarised_and_trained_on(tmp_path):
    """prior=mix on a raw-gym (float64) memory: each float64 key is cast with one line, the run trains on it."""
    rows = raw_gym_rows()
    assert rows["observation"].dtype == torch.float64 and rows["next", "desired_goal"].dtype == torch.float64
    prior = write_memory(tmp_path / "raw-gym.zarr", rows)
    # (the rows cloned into the actor are cast too: tests/studies/test_prior_variants.py)
    proc = recipe(tmp_path, f"memory.path={tmp_path / 'own.zarr'}", "prior=mix", f"prior.paths=[{prior}]")
    s = summary_of(tmp_path, proc)
    assert s["frames"] == 50 and s["updates"] > 0
    casts = [line for line in proc.stdout.splitlines() if "cast to torch.float32" in line]
    keys = {"observation", "achieved_goal", "desired_goal", "next/observation", "next/achieved_goal",
            "next/desired_goal"}
    assert len(casts) == len(keys), casts
    for key in keys:
        assert any(f": {key} is stored as torch.float64, cast to torch.float32" in line and str(prior) in line
                   for line in casts), key
    # the prior's summary: printed, and in the run's summary and the memory's history
    expected = {"path": str(prior), "rows": 100, "episodes": 2, "success_column": True}
    assert len(s["priors"]) == 1 and {k: s["priors"][0][k] for k in expected} == expected
    assert 0.0 <= s["priors"][0]["success_rate"] <= 1.0
    assert f"prior memory {prior}: 100 rows, 2 episodes, success rate {s['priors'][0]['success_rate']:.2f}" \
        in proc.stdout
    history = [json.loads(line) for line in (tmp_path / "own.zarr-runs.jsonl").read_text().splitlines()]
    assert history[-1]["priors"] == s["priors"]
    # the prior is only read: still float64, still 100 rows
    from torchrl_robotmem import ZarrStorage

    with ZarrStorage(prior, read_only=True) as store:
        assert len(store) == 100 and store[0:1]["observation"].dtype == torch.float64


def test_prior_columns_that_cannot_be_cast_are_refused_naming_path_key_and_dtypes(tmp_path):
    """An integer observation, a float done flag, another shape: refused before the run's memory is opened."""
    from recipes.her.prior_memory import TRANSITION_KEYS, check_prior_layout
    from torchrl_robotmem import ZarrStorage, make_env

    env = make_env("FetchReach-v4")
    example = env.fake_tensordict()
    env.close()
    rows = raw_gym_rows(episodes=1)
    cases = {
        "int-obs": (lambda td: td.set("observation", td["observation"].round().long()),
                    "observation: expected torch.float32 [10], found torch.int64 [10]"),
        "float-done": (lambda td: td.set(("next", "done"), td["next", "done"].float()),
                       "next/done: expected torch.bool [1], found torch.float32 [1]"),
        "short-goal": (lambda td: td.set("desired_goal", td["desired_goal"][..., :2]),
                       "desired_goal: expected torch.float32 [3], found torch.float64 [2]"),
    }
    for name, (edit, message) in cases.items():
        path = write_memory(tmp_path / f"{name}.zarr", edit(rows.clone()))
        with pytest.raises(ValueError) as err:
            check_prior_layout(ZarrStorage(path, read_only=True), example, TRANSITION_KEYS, "FetchReach-v4", log=None)
        assert str(path) in str(err.value) and message in str(err.value), str(err.value)
    # in the recipe: refused before training, and before its own memory is created
    bad = tmp_path / "float-done.zarr"
    proc = recipe(tmp_path, f"memory.path={tmp_path / 'own.zarr'}", "prior=mix", f"prior.paths=[{bad}]")
    assert proc.returncode != 0
    assert "cannot be cast safely" in proc.stderr and "next/done: expected torch.bool [1], found torch.float32 [1]" \
        in proc.stderr and str(bad) in proc.stderr
    assert not (tmp_path / "own.zarr").exists() and not (tmp_path / "out" / "summary.json").exists()


def test_a_prior_without_a_success_column_is_summarised_as_such(tmp_path):
    from recipes.her.prior_memory import describe_prior, prior_summary
    from torchrl_robotmem import ZarrStorage

    rows = raw_gym_rows(episodes=1).exclude(("next", "is_success"), "is_success")
    with pytest.warns(UserWarning, match="no \\('next', 'is_success'\\) column"):
        path = write_memory(tmp_path / "no-success.zarr", rows)
    s = prior_summary(ZarrStorage(path, read_only=True))
    assert s == {"path": str(path), "rows": 50, "episodes": 1, "success_rate": None, "success_column": False}
    assert describe_prior(s).endswith("50 rows, 1 episodes, success rate n/a (no next/is_success column)")


def test_pretrain_stops_at_the_target_or_a_plateau_of_its_checks():
    """recipes/her/pretrain.py: the checks decide (they run on held-out goals); nothing else is looked at."""
    from recipes.her.pretrain import pretrain

    steps = []
    checks = iter([0.5, 0.9, 1.0])
    out = pretrain(lambda: steps.append(1), lambda: {"eval/success_rate": next(checks)}, max_updates=3000,
                   eval_every=100, target=0.95, patience=5)
    assert out["stopped"] == "target" and out["updates"] == len(steps) == 300
    assert out["checks"] == [[100, 0.5], [200, 0.9], [300, 1.0]] and "metrics" not in out
    flat = iter([0.5, 0.6, 0.6, 0.55])
    out = pretrain(lambda: None, lambda: {"eval/success_rate": next(flat)}, 3000, 100, target=0.95, patience=2)
    assert out["stopped"] == "patience" and out["updates"] == 400
    # a critic-only pretraining (the actor does not move): one look before, and none in between
    looks = []
    fixed = pretrain(lambda: None, lambda: looks.append(1) or {"eval/success_rate": 0.3}, 3000, 100,
                     target=0.95, patience=1, actor_fixed=True)
    assert fixed["updates"] == 3000 and [u for u, _ in fixed["checks"]] == [0, 3000] and len(looks) == 2
    met = pretrain(lambda: None, lambda: {"eval/success_rate": 1.0}, 3000, 100, target=0.95, actor_fixed=True)
    assert met["updates"] == 0 and met["stopped"] == "target"


def test_pretraining_checks_look_at_held_out_goals_never_at_the_evaluation_goals():
    """The goals a check sees and the goals the run is evaluated on share none (issue 42: selection on held-out goals)."""
    from omegaconf import OmegaConf

    from recipes.her.utils import eval_seed, make_eval_env

    cfg = OmegaConf.create({"seed": 3, "env": {"name": "FetchReach-v4", "max_episode_steps": 50}})
    goals = {}
    for held_out in (False, True):
        env = make_eval_env(cfg, 20, held_out=held_out)
        env.set_seed(eval_seed(cfg, held_out))
        goals[held_out] = env.reset()["desired_goal"]
        env.close()
    assert goals[False].shape == goals[True].shape == (20, 3)
    distances = torch.cdist(goals[False], goals[True])
    assert distances.min() > 1e-6  # not one evaluation goal among the held-out ones
    # and the evaluation goals are what they were: the same seeds as before the held-out split
    env = make_eval_env(cfg, 20)
    env.set_seed(cfg.seed + 10_000)
    assert torch.equal(env.reset()["desired_goal"], goals[False])
    env.close()


@pytest.mark.full  # a second test of what the default tier covers (make test stays under 15 minutes)
def test_pretraining_stops_once_the_memory_meets_the_target_and_the_run_reports_its_cpu(tmp_path):
    """A second run whose target the memory already meets: a few pretraining updates, no new frame, CPU-s reported."""
    mem = tmp_path / "mem.zarr"
    first = summary_of(tmp_path, recipe(tmp_path, f"memory.path={mem}", out="run1"), out="run1")
    assert first["memory_rows_after"] == 50 and first["pretrain_updates"] == 0 and first["priors"] == []
    proc = recipe(tmp_path, f"memory.path={mem}", "logger.target_success=0.0", "memory.pretrain_updates=3000",
                  "memory.pretrain_eval_every=5", "logger.eval_episodes=2", "memory.pretrain_eval_episodes=1",
                  out="run2")
    s = summary_of(tmp_path, proc, out="run2")
    assert s["pretrain_stopped"] == "target" and s["pretrain_updates"] == 5 < 3000 and s["updates"] == 5
    assert [u for u, _ in s["pretrain_checks"]] == [5]  # one check, on held-out goals; then the evaluation
    assert s["frames"] == 0 and s["frames_to_target"] == 0 and s["memory_rows_after"] == 50
    assert "pretraining on the memory: 5 of at most 3000 updates, stopped at the target 0.0" in proc.stdout
    # CPU-seconds: the whole process, and its training and evaluation parts, printed and recorded
    for run in (first, s):
        assert run["process_cpu_s"] >= run["cpu_s"] + run["eval_cpu_s"] - 0.05 and run["eval_cpu_s"] > 0
    line = next(line for line in proc.stdout.splitlines() if line.startswith("frames to target 0.0"))
    assert line.startswith(f"frames to target 0.0: 0 new (50 total), CPU-s: {s['process_cpu_s']:.1f} "
                           f"(training {s['cpu_s']:.1f}, evaluation {s['eval_cpu_s']:.1f}, the rest ")
    history = [json.loads(x) for x in (tmp_path / "mem.zarr-runs.jsonl").read_text().splitlines()]
    assert [h["pretrain_updates"] for h in history] == [0, 5] and history[-1]["process_cpu_s"] == s["process_cpu_s"]
