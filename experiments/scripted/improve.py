"""The memory improves its controller: parameters recalled from a memory that the controller's own episodes join.

A scripted controller reads its parameters, per episode, from the ``k`` successful
episodes of a memory nearest in goal geometry (the recall of docs/cross_env.md).
This loop lets that memory learn from trial and error, as episodic control does:

1. the prior memory's rows are copied into the run's own memory (the prior is only read);
2. each training episode recalls its parameters, perturbs the recalled ones with
   ``noise`` times the spreads of :data:`~experiments.scripted.collect.NOISE`, runs, and is
   written to the run's memory with its parameters and outcome: a success joins what
   later episodes recall, a failure is kept but never recalled;
3. every ``eval_every`` frames the controller is evaluated without noise, on the fixed goals
   of ``recipes/her`` (``seed + 10000``, ``eval_episodes`` envs), and the per-episode
   outcomes are written to ``eval_episodes.jsonl``, so ``recipes.her.tools.compare`` and
   ``paired`` read these runs beside the learned ones.

The reward is the episode's success; the policy is the memory. Issue 27, goal 2
(docs/results.md): FetchPush from the noisy memory (66.8%) to >= 0.95 within 30k frames::

    python -m experiments.scripted.improve env=push seed=0 prior=bench_results/prior/scripted-push-500.zarr \\
        path=runs/improve-s0.zarr out=runs/improve-s0 frames=30000
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np
import torch
import tqdm

from torchrl_robotmem import ZarrStorage, make_env

from .collect import gym_episodes, kv_args, noisy_params, open_memory
from .controllers import TASKS, ScriptedPolicy, default_params, task_of
from .recall_params import STRIKE_RECALLED, episode_index, recaller

__all__ = ["evaluate", "improve", "main"]

_COPY_CHUNK = 5_000  # prior rows copied a write
_STEPS = 50  # Fetch episode length


def evaluate(task: str, recall, seed: int, episodes: int) -> list[int]:
    """Per-episode success (0 / 1) of the controller with ``recall``-ed parameters on ``recipes/her``'s fixed goals."""
    env = make_env(TASKS[task], episodes, seed=seed + 10_000, max_episode_steps=_STEPS)
    try:
        env.set_seed(seed + 10_000)
        with torch.no_grad():
            td = env.rollout(_STEPS, ScriptedPolicy(task, recall, num_envs=episodes), break_when_any_done=False)
        return (td["next", "is_success"].reshape(episodes, -1)[:, -1] > 0.5).int().tolist()
    finally:
        env.close()


def improve(task: str, prior: str, path: str, out: str, *, frames: int = 30_000, seed: int = 0,
            noise: float = 0.5, k: int = 5, eval_every: int = 5_000, eval_episodes: int = 100) -> dict:
    """Runs the loop above; returns the run's summary (also written to ``out/summary.json``).

    Args:
        task (str): ``"push"`` or ``"slide"`` (or their Fetch ids).
        prior (str): the scripted memory to start from (read-only).
        path (str): the run's own memory (must not exist): the prior's rows, then this run's episodes.
        out (str): where ``summary.json`` and ``eval_episodes.jsonl`` go.
        frames (int): env frames of training episodes (50 an episode).
        seed (int): seeds the exploration noise, the training episodes' resets and the evaluation goals.
        noise (float): exploration, times :data:`~experiments.scripted.collect.NOISE`, on the recalled parameters.
        k (int): successful episodes recalled per episode.
        eval_every (int): frames between evaluations.
        eval_episodes (int): episodes of an evaluation.
    """
    task = task_of(task)
    if os.path.exists(path):
        raise FileExistsError(f"{path} exists: the run's memory must be new (the prior {prior} is copied into it).")
    source = ZarrStorage(prior, read_only=True)
    episodes = frames // _STEPS
    rb = open_memory(path, len(source) + episodes * _STEPS, env=TASKS[task])
    for start in range(0, len(source), _COPY_CHUNK):
        rb.extend(source[start:min(start + _COPY_CHUNK, len(source))])
    rows_before = len(rb)
    index = episode_index(rb.storage)
    recall = recaller(task, index, k)
    os.makedirs(out, exist_ok=True)
    episodes_file = os.path.join(out, "eval_episodes.jsonl")
    curve, cpu0, successes = [], time.process_time(), 0
    eval_cpu = 0.0

    def log_eval(done_frames: int) -> None:
        nonlocal eval_cpu
        t0 = time.process_time()
        outcomes = evaluate(task, recall, seed, eval_episodes)
        eval_cpu += time.process_time() - t0
        with open(episodes_file, "a") as f:
            f.write(json.dumps({"frames": done_frames, "seed": seed, "success": outcomes}) + "\n")
        curve.append([done_frames, sum(outcomes) / len(outcomes)])

    log_eval(0)
    rng = np.random.default_rng([seed, 27])
    base = default_params(task)

    def explore(e, obs, goal):
        noisy = noisy_params(task, noise, rng, recall(obs, goal))
        return dataclasses.replace(noisy, **{f.name: getattr(base, f.name) for f in dataclasses.fields(base)
                                             if f.name not in STRIKE_RECALLED})

    seeds = [50_000_000 + seed * 100_000 + e for e in range(episodes)]
    done_frames = 0
    pbar = tqdm.tqdm(total=episodes * _STEPS, desc=f"improve {TASKS[task]}", leave=False)
    for td in gym_episodes(task, explore, seeds):
        rb.extend(td)
        successes += int(td["episode_success"][0] > 0.5)
        done_frames += td.shape[0]
        pbar.update(td.shape[0])
        if done_frames % eval_every < td.shape[0]:
            log_eval(done_frames)
            pbar.set_postfix(success=f"{curve[-1][1]:.2f}")
    pbar.close()
    if curve[-1][0] != done_frames:
        log_eval(done_frames)
    rb.storage.close()
    summary = {"env": TASKS[task], "algo": "recall + exploration (scripted)", "seed": seed, "frames": done_frames,
               "memory_rows_before": rows_before, "memory_rows_after": rows_before + done_frames,
               "train_success_rate": successes / max(episodes, 1), "noise": noise, "k": k,
               "cpu_s": round(time.process_time() - cpu0 - eval_cpu, 2), "eval_cpu_s": round(eval_cpu, 2),
               "process_cpu_s": round(time.process_time(), 2), "curve": curve, "frames_to_target": None,
               "prior": prior}
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump(summary, f)
    return summary


def main(argv: list[str] | None = None) -> dict:
    torch.set_num_threads(1)
    parser = argparse.ArgumentParser(prog="python -m experiments.scripted.improve", description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="push", help="push | slide (or a Fetch id)")
    parser.add_argument("--prior", required=True, help="the scripted memory to start from (read-only)")
    parser.add_argument("--path", required=True, help="the run's own memory (new)")
    parser.add_argument("--out", required=True, help="directory for summary.json and eval_episodes.jsonl")
    parser.add_argument("--frames", type=int, default=30_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--noise", type=float, default=0.5)
    parser.add_argument("--k", type=int, default=5)
    parser.add_argument("--eval_every", type=int, default=5_000)
    parser.add_argument("--eval_episodes", type=int, default=100)
    a = parser.parse_args(kv_args(sys.argv[1:] if argv is None else argv))
    out = improve(a.env, a.prior, a.path, a.out, frames=a.frames, seed=a.seed, noise=a.noise, k=a.k,
                  eval_every=a.eval_every, eval_episodes=a.eval_episodes)
    print(json.dumps({key: out[key] for key in ("env", "seed", "frames", "train_success_rate", "cpu_s", "curve")}))
    return out


if __name__ == "__main__":
    main()
