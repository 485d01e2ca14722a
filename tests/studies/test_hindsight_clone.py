"""prior.clone_goals=hindsight (issue 27; experiments/prior_variants): cloning every prior row towards what its
episode achieved.

Real parts: FetchReach episodes from TorchRL's GymEnv written to real ZarrStorages, load_demos /
HindsightGoals on them, and ``python -m experiments.prior_variants.train`` run as a subprocess.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from training.test_her_priors_and_pretraining import raw_gym_rows, summary_of, write_memory

from studies.test_prior_variants import VARIANTS_DIR
from studies.test_prior_variants import variants as recipe

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from experiments.prior_variants.hindsight import (  # noqa: E402
    ACHIEVED_KEY,
    EPISODE_KEY,
    HindsightGoals,
    episode_ids,
    numbered_episodes,
)

# the prior-memory variants are experiments (experiments/prior_variants): their tests run in the full tier
pytestmark = pytest.mark.full

SEED = int(os.environ.get("ROBOTMEM_TEST_SEED", "0"))


def test_episode_ids_from_done_flags_and_from_trajectory_ids():
    done = torch.tensor([False, True, False, False, True, False]).unsqueeze(-1)
    truncated = torch.tensor([False, False, True, False, False, False]).unsqueeze(-1)
    rows = TensorDict({("next", "done"): done, ("next", "truncated"): truncated}, batch_size=[6])
    assert episode_ids(rows).tolist() == [0, 0, 1, 2, 2, 3]  # truncated ends an episode as done does
    rows.set(("collector", "traj_ids"), torch.tensor([7, 7, 7, 9, 9, 9]))
    assert episode_ids(rows).tolist() == [7, 7, 7, 9, 9, 9]  # the collector's own ids win
    with pytest.raises(KeyError, match="episode boundaries"):
        episode_ids(TensorDict({"observation": torch.zeros(3, 2)}, batch_size=[3]))


def test_numbered_episodes_are_unique_across_memories():
    first = TensorDict({("collector", "traj_ids"): torch.tensor([7, 7, 9, 12])}, batch_size=[4])
    second = TensorDict({("collector", "traj_ids"): torch.tensor([0, 0, 1])}, batch_size=[3])  # another run's collector
    a = numbered_episodes(first)
    b = numbered_episodes(second, first=int(a.max()) + 1)
    assert a.tolist() == [0, 0, 1, 2] and b.tolist() == [3, 3, 4]


def hindsight_rows(n_episodes: int = 3, length: int = 5) -> TensorDict:
    """Achieved goal of row i = [episode, step]: every relabelled goal tells which row it came from."""
    ep = torch.arange(n_episodes).repeat_interleave(length)
    step = torch.arange(length).repeat(n_episodes)
    achieved = torch.stack([ep, step], -1).float()
    return TensorDict({"desired_goal": torch.full((n_episodes * length, 2), -1.0), ACHIEVED_KEY: achieved,
                       EPISODE_KEY: ep}, batch_size=[n_episodes * length])


@pytest.mark.parametrize("horizon", [1, 3, 10])
def test_relabelled_goals_are_achieved_later_in_the_same_episode(horizon):
    print(f"seed {SEED} (ROBOTMEM_TEST_SEED overrides)")
    rows = hindsight_rows()
    relabel = HindsightGoals(rows, horizon, generator=torch.Generator().manual_seed(SEED))
    index = torch.arange(rows.shape[0]).repeat(200)
    goals = relabel(index).get("desired_goal")
    ep, step = rows[EPISODE_KEY][index], rows[ACHIEVED_KEY][index][:, 1]
    assert (goals[:, 0] == ep).all()  # never another episode's goal
    ahead = goals[:, 1] - step
    assert (ahead >= 0).all() and (ahead < horizon).all()  # the row's own next achieved goal, or at most horizon-1 on
    if horizon == 1:
        assert torch.equal(goals, rows[ACHIEVED_KEY][index])
    else:  # every offset the horizon allows is drawn, where the episode has room for it
        first = step == 0
        assert set(ahead[first].long().tolist()) == set(range(min(horizon, 5)))
    assert (rows["desired_goal"] == -1).all()  # the rows themselves are untouched


def test_relabelling_refuses_a_bad_horizon_and_rows_without_episodes():
    rows = hindsight_rows()
    with pytest.raises(ValueError, match="clone_horizon must be >= 1"):
        HindsightGoals(rows, 0)
    with pytest.raises(KeyError, match="hindsight_episode"):
        HindsightGoals(rows.exclude(EPISODE_KEY), 3)


def test_load_demos_keeps_every_row_with_episodes_unique_across_memories(tmp_path):
    """Two real memories: all their rows (not only successful episodes), episode numbers that do not collide."""
    from hydra import compose, initialize_config_dir

    from experiments.prior_variants.bc import load_demos
    from recipes.her import utils
    from torchrl_robotmem import ZarrStorage

    a = write_memory(tmp_path / "a.zarr", raw_gym_rows(episodes=2, seed=0))
    b = write_memory(tmp_path / "b.zarr", raw_gym_rows(episodes=3, seed=1))
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "her"), version_base="1.3"):
        cfg = compose("config", overrides=["algo=td3", "network.hidden_sizes=[8]"])
    train_env, eval_env = utils.make_environment(cfg)
    try:  # the recipe's own actor and TorchRL loss module
        loss_module = utils.make_loss_module(cfg, utils.make_agent(cfg, train_env, utils.GoalNormalizer())[0])[0]
    finally:
        train_env.close()
        eval_env.close()
    storages = [ZarrStorage(a, read_only=True), ZarrStorage(b, read_only=True)]
    try:
        demos = load_demos(loss_module, storages, hindsight=True)
    finally:
        for s in storages:
            s.close()
    assert demos.shape[0] == 250
    assert demos[EPISODE_KEY].unique().tolist() == [0, 1, 2, 3, 4]
    assert (demos[EPISODE_KEY].reshape(5, 50) == torch.arange(5).unsqueeze(-1)).all()  # whole 50-step episodes
    assert ACHIEVED_KEY in demos.keys(True)


def test_the_recipe_clones_a_prior_with_hindsight_goals(tmp_path):
    prior = write_memory(tmp_path / "raw-gym.zarr", raw_gym_rows())
    proc = recipe(tmp_path, f"memory.path={tmp_path / 'own.zarr'}", "prior=clone", f"prior.paths=[{prior}]",
                  "prior.clone_steps=5", "prior.clone_goals=hindsight", "prior.clone_horizon=2", "algo=td3")
    summary_of(tmp_path, proc)
    assert "cloned the prior's actions into the actor: 5 steps (hindsight goals, horizon 2)" in proc.stdout


@pytest.mark.parametrize("overrides, message", [
    (["prior.clone_goals=future"], "prior.clone_goals must be original or hindsight"),
    (["prior.clone_goals=hindsight", "prior.clone_horizon=0"], "clone_horizon must be >= 1"),
    (["prior.clone_goals=hindsight", "memory.recall.enabled=true"], "set memory.recall.enabled=false"),
    (["prior.clone_goals=hindsight", "prior.bc=0.4", "prior.bc_original_goals=true"], "Set one of them"),
])
def test_hindsight_settings_that_do_not_go_together_are_refused(overrides, message):
    from hydra import compose, initialize_config_dir

    from experiments.prior_variants import check_prior_config

    with initialize_config_dir(config_dir=str(VARIANTS_DIR), version_base="1.3"):
        cfg = compose("variants", overrides=["prior=clone", "prior.paths=[prior.zarr]", *overrides])
    with pytest.raises(ValueError, match=message):
        check_prior_config(cfg)


def test_the_recipe_refuses_them_before_writing_anything(tmp_path):
    prior = write_memory(tmp_path / "raw-gym.zarr", raw_gym_rows(episodes=1))
    own = tmp_path / "own.zarr"
    proc = recipe(tmp_path, f"memory.path={own}", "prior=clone", f"prior.paths=[{prior}]",
                  "prior.clone_goals=hindsight", "memory.recall.enabled=true")
    assert proc.returncode != 0 and "set memory.recall.enabled=false" in proc.stderr, proc.stderr[-2000:]
    assert not own.exists()  # check_prior_config runs before the run's memory is opened
