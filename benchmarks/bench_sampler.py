"""Benchmark of GoalSimilaritySampler against RandomSampler (full ``rb.sample()``), plain and HER.

Prints a markdown table (medians) and writes ``bench_results/sampler.json``.

    python benchmarks/bench_sampler.py            # 1M rows, batch 256
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import torch
from torchrl.data import HERReplayBuffer, LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_recall import make_goals, make_rows  # noqa: E402

from torchrl_robotmem.sampler import GoalSimilaritySampler  # noqa: E402

torch.set_num_threads(1)


def median_ms(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def reward_fn(td):
    d = (td["next", "achieved_goal"] - td["desired_goal"]).norm(dim=-1, keepdim=True)
    return -(d > 0.05).float()


def fill(rb, n, gen):
    for start in range(0, n, 100_000):
        rb.extend(make_rows("fetch3", min(100_000, n - start), gen, start))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--repeat", type=int, default=41)
    parser.add_argument("--out", default="bench_results/sampler.json")
    args = parser.parse_args()
    gen = torch.Generator().manual_seed(0)
    bs, rep = args.batch, args.repeat

    storage = LazyTensorStorage(args.rows)
    sampler = GoalSimilaritySampler()
    rb = TensorDictReplayBuffer(storage=storage, sampler=sampler, batch_size=bs)
    fill(rb, args.rows, gen)
    rb_uniform = TensorDictReplayBuffer(storage=storage, sampler=RandomSampler(), batch_size=bs)
    queries = make_goals("fetch3", 64, gen)
    q1 = queries[0]

    t0 = time.perf_counter()
    with sampler.query(q1):
        rb.sample()
    first = time.perf_counter() - t0  # builds the GoalIndex

    res = {"rows": args.rows, "batch": bs, "first_sample_with_index_build_ms": 1e3 * first}
    res["uniform_RandomSampler_ms"] = median_ms(rb_uniform.sample, rep)
    res["goal_sampler_no_query_ms"] = median_ms(rb.sample, rep)


    # same query each call: candidates cached per (query, storage revision)
    sampler.set_query(q1)
    res["query_1_cached_ms"] = median_ms(rb.sample, rep)
    it = iter(range(10**9))
    res["query_1_new_each_call_ms"] = median_ms(
        lambda: (sampler.set_query(queries[next(it) % 64] + 1e-4), rb.sample()), rep
    )
    res["query_16_new_each_call_ms"] = median_ms(
        lambda: (sampler.set_query(queries[:16] + 1e-4 * (next(it) % 7)), rb.sample()), rep
    )
    sampler.uniform_ratio = 0.25
    res["query_1_uniform_ratio_0.25_new_each_call_ms"] = median_ms(
        lambda: (sampler.set_query(queries[next(it) % 64] + 1e-4), rb.sample()), rep
    )
    sampler.uniform_ratio = 0.0
    sampler.success_only = True
    sampler.set_query(q1)
    rb.sample()  # builds the success-only view
    res["query_1_success_only_new_each_call_ms"] = median_ms(
        lambda: (sampler.set_query(queries[next(it) % 64] + 1e-4), rb.sample()), rep
    )
    sampler.success_only = False
    sampler.set_query(q1)
    b = rb.sample()
    u = rb_uniform.sample()
    res["mean_goal_distance_query"] = b["goal_distance"].mean().item()
    res["mean_goal_distance_uniform"] = (u["next", "achieved_goal"] - q1).norm(dim=-1).mean().item()
    sampler.clear_query()

    # HER: same storage contents, HERReplayBuffer with both samplers
    her_storage = LazyTensorStorage(args.rows)
    gs = GoalSimilaritySampler()
    her = HERReplayBuffer(
        reward_fn, storage=her_storage, sampler=gs, batch_size=bs,
        achieved_goal_key=("next", "achieved_goal"),
    )
    fill(her, args.rows, torch.Generator().manual_seed(1))
    her_uniform = HERReplayBuffer(
        reward_fn, storage=her_storage, sampler=RandomSampler(), batch_size=bs,
        achieved_goal_key=("next", "achieved_goal"),
    )
    her_uniform.sample()  # episode-end cache
    gs.set_query(q1)
    her.sample()
    res["her_uniform_RandomSampler_ms"] = median_ms(her_uniform.sample, rep)
    res["her_query_1_cached_ms"] = median_ms(her.sample, rep)
    res["her_query_1_new_each_call_ms"] = median_ms(
        lambda: (gs.set_query(queries[next(it) % 64] + 1e-4), her.sample()), rep
    )

    base = res["uniform_RandomSampler_ms"]
    for key in list(res):
        if key.startswith("query_") or key == "goal_sampler_no_query_ms":
            res[f"ratio {key}"] = res[key] / base
    for key in ("her_query_1_cached_ms", "her_query_1_new_each_call_ms"):
        res[f"ratio {key}"] = res[key] / res["her_uniform_RandomSampler_ms"]

    print(f"\nGoalSimilaritySampler, {args.rows} rows, batch {bs}, torch threads=1, medians of {rep}\n")
    print("| measure | value |\n|---|---|")
    for key, value in res.items():
        print(f"| {key} | {value:.4g} |" if isinstance(value, float) else f"| {key} | {value} |")
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=2)
    print(f"\nwritten to {args.out}")


if __name__ == "__main__":
    main()
