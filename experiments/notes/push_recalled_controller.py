"""What the noisy FetchPush memory is worth to the controller that wrote it (issue 27, goal 2).

Runs the scripted push controller (``experiments/scripted``) on FetchPush-v4 with, per
episode, the mean parameters of the ``k`` successful memory episodes nearest in
goal geometry (``experiments.scripted.recall_params``, the recall of
docs/cross_env.md), against the controller's default parameters, on the same
env seeds (20,000,000 onward: disjoint from the memory's and the recipe's).

    python -m experiments.notes.push_recalled_controller --episodes 200 --k 5   # default 0.99, recalled 0.955 (results.md)

Needs ``bench_results/prior/scripted-push-500.zarr``
(``python -m experiments.scripted.collect env=push episodes=500 noise=1 seed=0 backend=gym path=...``).
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from experiments.cross_env.run import PREREGISTERED
from experiments.scripted.collect import gym_episodes
from experiments.scripted.controllers import default_params
from experiments.scripted.recall_params import episode_index, recaller
from torchrl_robotmem import ZarrStorage


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--memory", default="bench_results/prior/scripted-push-500.zarr")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--k", type=int, default=5)
    args = parser.parse_args()
    storage = ZarrStorage(args.memory, read_only=True)
    names = PREREGISTERED["supplied"]  # the parameters the cross-env experiment recalls
    index = episode_index(storage, tuple(PREREGISTERED["key"].split("/")))
    base = default_params("push")
    params = recaller("push", index, args.k, names)

    def recalled(e, obs, goal):
        return params(obs, goal)

    seeds = [20_000_000 + i for i in range(args.episodes)]
    out = {}
    for arm, fn in (("default parameters", lambda e, o, g: base), (f"recalled, k={args.k}", recalled)):
        out[arm] = float(np.mean([float(td["episode_success"][0]) for td in gym_episodes("push", fn, seeds)]))
    print(json.dumps({"episodes": args.episodes, "success": out}))
    return out


if __name__ == "__main__":
    main()
