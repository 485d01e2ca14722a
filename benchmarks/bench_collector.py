"""Collector throughput with and without RecallTransform over a 100k-transition memory.

Two single-process TorchRL ``Collector`` objects on ``FetchPush-v4`` (random
policy) live side by side: one plain, one whose env carries
``RecallTransform(path, k)`` over a synthetic 100k-row FetchPush memory in a
``ZarrStorage`` (opened read-only from its path, as a user would). Batches are
pulled from the two alternately (the order flips every repetition) so that
both see the same machine noise; the table reports medians and the ratio of
the medians. Memory open and index build happen once, before the timed
batches, and are reported separately.

    python benchmarks/bench_collector.py                 # 100k rows, 12 x 500 frames each
    python benchmarks/bench_collector.py --rows 1000000  # a bigger memory

Writes ``bench_results/collector.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from functools import partial
from pathlib import Path

import torch
import torchrl
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import RecallTransform, ZarrStorage, make_env

ENV_ID = "FetchPush-v4"
EPISODE_LEN = 50


def synthetic_memory(path: str, rows: int, seed: int = 0) -> float:
    """Writes ``rows`` FetchPush-shaped transitions to a new store; returns seconds taken.

    Keys, shapes and dtypes are those of a real ``make_env("FetchPush-v4")``
    rollout. Goals are plausible: the object rests on the table
    (x in [1.05, 1.55], y in [0.40, 1.10], z = 0.42); in one episode out of
    five it is pushed along a straight line; ``is_success`` is the env's 5 cm
    test.
    """
    template = make_env(ENV_ID, seed=seed).rollout(1)[0]
    gen = torch.Generator().manual_seed(seed)
    storage = ZarrStorage(path, rows, env=ENV_ID)
    rb = TensorDictReplayBuffer(storage=storage)
    t0 = time.perf_counter()
    chunk_episodes = 200
    episodes = rows // EPISODE_LEN
    for e0 in range(0, episodes, chunk_episodes):
        ne = min(chunk_episodes, episodes - e0)
        n = ne * EPISODE_LEN
        step = torch.arange(EPISODE_LEN).repeat(ne)

        def table(count):
            lo, hi = torch.tensor([1.05, 0.40, 0.42]), torch.tensor([1.55, 1.10, 0.42])
            return lo + (hi - lo) * torch.rand(count, 3, generator=gen)

        start, desired = table(ne), table(ne)
        pushed = torch.rand(ne, generator=gen) < 0.2
        direction = torch.nn.functional.normalize(torch.randn(ne, 3, generator=gen) * torch.tensor([1.0, 1.0, 0.0]), dim=-1)
        speed = torch.where(pushed, 0.1 / EPISODE_LEN, 0.0)
        achieved = (start.repeat_interleave(EPISODE_LEN, 0)
                    + (direction * speed[:, None]).repeat_interleave(EPISODE_LEN, 0) * (step[:, None] + 1))
        prev = achieved - (direction * speed[:, None]).repeat_interleave(EPISODE_LEN, 0)
        desired = desired.repeat_interleave(EPISODE_LEN, 0)
        success = (torch.linalg.vector_norm(achieved - desired, dim=-1) < 0.05).float()
        last = (step == EPISODE_LEN - 1).unsqueeze(-1)
        td = template.expand(n).clone()
        td["observation"] = torch.randn(n, 25, generator=gen)
        td["achieved_goal"], td["desired_goal"] = prev, desired
        td["action"] = torch.rand(n, 4, generator=gen) * 2 - 1
        td["step_count"] = step.unsqueeze(-1)
        td["is_init"] = (step == 0).unsqueeze(-1)
        td["next", "observation"] = torch.randn(n, 25, generator=gen)
        td["next", "achieved_goal"], td["next", "desired_goal"] = achieved, desired
        td["next", "is_success"] = success
        td["next", "reward"] = (success - 1).unsqueeze(-1)
        td["next", "done"], td["next", "truncated"] = last, last.clone()
        td["next", "terminated"] = torch.zeros_like(last)
        td["next", "step_count"] = (step + 1).unsqueeze(-1)
        td["next", "is_init"] = torch.zeros_like(last)
        rb.extend(td)
    storage.close()
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=100_000)
    parser.add_argument("--k", type=int, default=5)
    parser.add_argument("--frames-per-batch", type=int, default=500)
    parser.add_argument("--reps", type=int, default=12)
    parser.add_argument("--out", default="bench_results/collector.json")
    args = parser.parse_args()
    torch.set_num_threads(1)

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "push.zarr")
        write_s = synthetic_memory(path, args.rows)

        # One-off costs, measured on their own transform.
        probe = RecallTransform(path, args.k)
        t0 = time.perf_counter()
        _ = probe.storage
        open_s = time.perf_counter() - t0
        goal = torch.tensor([[1.3, 0.75, 0.42]])
        t0 = time.perf_counter()
        probe.forward(TensorDict({"desired_goal": goal}, [1]))
        first_query_s = time.perf_counter() - t0
        query_times = []
        for _ in range(200):
            g = goal + 0.05 * torch.randn(1, 3)
            t0 = time.perf_counter()
            probe.forward(TensorDict({"desired_goal": g}, [1]))
            query_times.append(time.perf_counter() - t0)
        query_ms = 1e3 * statistics.median(query_times)
        del probe

        transform = RecallTransform(path, args.k)
        variants = {
            "plain": Collector(partial(make_env, ENV_ID, seed=0), None,
                               frames_per_batch=args.frames_per_batch, total_frames=-1),
            "recall": Collector(partial(make_env, ENV_ID, seed=0, transforms=[transform]), None,
                                frames_per_batch=args.frames_per_batch, total_frames=-1),
        }
        iters = {name: iter(col) for name, col in variants.items()}
        for it in iters.values():  # warm-up: env start, memory open, index build
            next(it)
        fps: dict[str, list[float]] = {name: [] for name in variants}
        for rep in range(args.reps):
            order = list(variants) if rep % 2 == 0 else list(variants)[::-1]
            for name in order:
                t0 = time.perf_counter()
                data = next(iters[name])
                fps[name].append(data.numel() / (time.perf_counter() - t0))
        for col in variants.values():
            col.shutdown()

    med = {name: statistics.median(v) for name, v in fps.items()}
    ratio = med["recall"] / med["plain"]
    pair_ratios = [r / p for r, p in zip(fps["recall"], fps["plain"])]
    result = {
        "env": ENV_ID,
        "memory_rows": args.rows,
        "k": args.k,
        "frames_per_batch": args.frames_per_batch,
        "reps": args.reps,
        "fps": fps,
        "median_fps": med,
        "ratio_of_medians": ratio,
        "median_paired_ratio": statistics.median(pair_ratios),
        "memory_write_s": write_s,
        "memory_open_s": open_s,
        "first_query_s": first_query_s,
        "query_ms_median": query_ms,
        "episodes_per_batch": args.frames_per_batch / EPISODE_LEN,
        "machine": {
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "torchrl": torchrl.__version__,
        },
    }
    print(f"\nCollector on {ENV_ID}, random policy, {args.frames_per_batch} frames/batch, "
          f"{args.reps} interleaved reps; memory: {args.rows:,} rows, k={args.k}\n")
    print("| collector | median frames/s | min | max |")
    print("|---|---:|---:|---:|")
    for name in variants:
        label = "plain" if name == "plain" else f"+ RecallTransform (k={args.k})"
        print(f"| {label} | {med[name]:.0f} | {min(fps[name]):.0f} | {max(fps[name]):.0f} |")
    print(f"\nratio of medians: {ratio:.3f}x   (median of paired ratios {result['median_paired_ratio']:.3f}x)")
    print(f"one recall query (1 goal, {args.rows:,} rows): {query_ms:.2f} ms median; "
          f"first query incl. index build {first_query_s * 1e3:.0f} ms; "
          f"opening the store read-only {open_s:.2f} s")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
