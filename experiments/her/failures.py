"""Why a trained Fetch push agent fails: its evaluation episodes, sorted by how they fail.

Loads the agent checkpoint a ``recipes/her/train.py`` run saved next to its
memory, replays the run's deterministic evaluation (same eval seeds, same
number of episodes) and sorts the failures by where the object ended::

    python -m experiments.her.failures bench_results/p60/own-push-s0.zarr-agent env=push seed=0

* untouched: the object moved less than 1 cm (the agent did not push);
* near miss: pushed, ended 5-10 cm from the goal (the success radius is 5 cm);
* far: pushed, ended more than 10 cm from the goal.

It also splits the success rate by where the goal is: on the table, or in the air
(FetchPickAndPlace puts half of its goals up to 45 cm above the table, where a
push cannot take the object).

The trailing arguments are hydra overrides of ``recipes/her/config.yaml``: give the ones the
run was trained with (env, seed, network, ``logger.eval_episodes``).
"""
from __future__ import annotations

import os
import sys

import torch
from hydra import compose, initialize_config_dir
from torchrl.checkpoint import Checkpoint

from recipes.her import utils

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# recipes/her's config with the prior-memory variants' keys (variants.yaml): the overrides of any run of
# recipes/her or experiments.prior_variants compose
CONFIG_DIR = os.path.join(ROOT, "experiments", "prior_variants")


def failures(checkpoint: str, overrides: list[str]) -> dict:
    """Success rate and failure categories of the deterministic evaluation of ``checkpoint``."""
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("variants", overrides=["logger.eval_episodes=100", *overrides])
    torch.set_num_threads(cfg.num_threads)
    train_env, eval_env = utils.make_environment(cfg)
    normalizer = utils.GoalNormalizer()
    model, _ = utils.make_agent(cfg, train_env, normalizer)
    loss = utils.make_loss_module(cfg, model)[0]
    Checkpoint(loss_module=loss, optimizer=utils.make_optimizer(cfg, loss), normalizer=normalizer).load(checkpoint)
    td = utils.eval_rollout(cfg, eval_env, model[0])  # the run's own evaluation episodes
    train_env.close()
    eval_env.close()
    success = td["next", "is_success"][:, -1].reshape(-1).bool()
    start, goal = td["achieved_goal"][:, 0], td["desired_goal"][:, 0]
    end = td["next", "achieved_goal"][:, -1]
    start_dist, end_dist = (goal - start).norm(dim=-1), (goal - end).norm(dim=-1)
    moved = (end - start).norm(dim=-1)
    fail = ~success
    in_air = (goal[:, 2] - start[:, 2]) > 0.01  # the object starts on the table; push goals are at its height
    untouched = fail & (moved < 0.01)
    near = fail & ~untouched & (end_dist < 0.10)
    far = fail & ~untouched & ~near
    return {
        "episodes": int(success.numel()),
        "success": success.float().mean().item(),
        "goals_on_table": int((~in_air).sum()),
        "success_on_table": success[~in_air].float().mean().item() if (~in_air).any() else float("nan"),
        "goals_in_air": int(in_air.sum()),
        "success_in_air": success[in_air].float().mean().item() if in_air.any() else float("nan"),
        "untouched": int(untouched.sum()),
        "untouched_start_dist": [round(x, 3) for x in start_dist[untouched].tolist()],
        "near_miss": int(near.sum()),
        "near_miss_end_dist": [round(x, 3) for x in end_dist[near].tolist()],
        "far": int(far.sum()),
        "start_dist_success_mean": start_dist[success].mean().item() if success.any() else float("nan"),
        "start_dist_failure_mean": start_dist[fail].mean().item() if fail.any() else float("nan"),
    }


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    if sys.argv[1] in ("-h", "--help"):  # not a checkpoint path
        print(__doc__)
        sys.exit(0)
    for key, value in failures(sys.argv[1], sys.argv[2:]).items():
        print(f"{key}: {value}")
