"""Success rates of the scripted controllers (default and noisy parameters), with 95% Wilson CIs.

    python -m experiments.scripted.evaluate                  # 200 episodes per task and noise level
    python -m experiments.scripted.evaluate episodes=50 tasks=push noises=0,1

Episodes run on a bare gymnasium env (``gym_episodes``), reset with seeds
500000 + i, nothing is written. Success: the env's ``is_success`` at the last step.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from .collect import gym_episodes, kv_args, noisy_params
from .controllers import TASKS


def success_rate(task: str, noise: float, episodes: int, seed: int = 0) -> tuple[int, int]:
    def param_fn(e, obs, goal):
        return noisy_params(task, noise, np.random.default_rng([seed, 7, e]))

    outcomes = [float(td["episode_success"][0]) for td in gym_episodes(task, param_fn, range(500_000, 500_000 + episodes))]
    return int(sum(outcomes)), len(outcomes)


def main(argv: list[str] | None = None) -> list[dict]:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(prog="python -m experiments.scripted.evaluate")
    p.add_argument("--episodes", type=int, default=200)
    p.add_argument("--tasks", default=",".join(TASKS))
    p.add_argument("--noises", default="0,1")
    argv = sys.argv[1:] if argv is None else argv
    args = p.parse_args(kv_args(argv))
    from recipes.her.tools.stats import wilson  # the one home of the statistics

    rows = []
    print("| task | noise | success | 95% CI |\n|---|---|---|---|")
    for task in args.tasks.split(","):
        for noise in (float(x) for x in args.noises.split(",")):
            s, n = success_rate(task, noise, args.episodes)
            lo, hi = wilson(s, n)
            rows.append({"task": task, "noise": noise, "successes": s, "n": n, "ci95": [lo, hi]})
            print(f"| {TASKS[task]} | {noise:g} | {100 * s / n:.1f}% ({s}/{n}) | {100 * lo:.1f} - {100 * hi:.1f}% |", flush=True)
    return rows


if __name__ == "__main__":
    main()
