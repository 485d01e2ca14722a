"""What GoalProposer costs a training loop: one proposal (per reset) over memories of 10k to 10M rows.

A proposal draws ``num_candidates`` stored achieved goals and asks the storage's
GoalIndex for each one's ``k``-th nearest neighbour (exact). This measures, on
Fetch-shaped goals (3-D, spread as a pushed object's positions are), the index
build (once, then kept in step with appends), a proposal, and the same
proposal done by a brute-force scan (``torch.cdist`` over every row, what the
index avoids), and puts a proposal beside a training loop's cost per episode
(50 frames at the recipe's ~20 ms a frame on this machine: about 1 s).

    python benchmarks/bench_proposer.py                     # 10k, 100k, 1M rows
    python benchmarks/bench_proposer.py --rows 10000000     # 10M (about 1 GB of RAM)
    python benchmarks/bench_proposer.py --reached-in 0 2    # with MEGA's filter counted in the memory, beside none

Each figure is the median of ``--repeats`` proposals in this process; the
storage is a ``LazyTensorStorage`` (the index reads any TorchRL tensor storage
the same way as a ``ZarrStorage``'s rows, so no disk write is timed here).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage

from torchrl_robotmem import GoalProposer

LOOP_S_PER_EPISODE = 50 * 0.020  # 50 frames at ~20 ms a frame (docs/speed.md: SAC+HER on FetchPush, CPU)


def memory(rows: int, seed: int = 0) -> LazyTensorStorage:
    g = torch.Generator().manual_seed(seed)
    goals = torch.tensor([1.3, 0.75, 0.42]) + torch.randn(rows, 3, generator=g) * torch.tensor([0.08, 0.08, 0.01])
    storage = LazyTensorStorage(rows)
    episodes = torch.arange(rows) // 50  # 50-step episodes, as Fetch's (what reached_in counts)
    storage.set(torch.arange(rows), TensorDict({("next", "achieved_goal"): goals, "episode": episodes}, [rows]))
    return storage


def bench(rows: int, repeats: int, num_candidates: int, k: int, reached_in: int = 0) -> dict:
    storage = memory(rows)
    proposer = GoalProposer(storage, "FetchPush-v4", num_candidates=num_candidates, k=k, warmup_rows=1, seed=0,
                            reached_in=reached_in)
    t0 = time.perf_counter()
    proposer.propose(1)  # builds the index
    build = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        proposer.propose(1)
        times.append(time.perf_counter() - t0)
    goals = storage[:]["next", "achieved_goal"]
    scans = []
    for _ in range(max(1, min(repeats, 3))):
        cand = goals[torch.randint(rows, (num_candidates,))]
        t0 = time.perf_counter()
        d = torch.cdist(cand, goals)  # [candidates, rows]
        d.topk(k + 1, largest=False).values[:, -1].argmax()
        scans.append(time.perf_counter() - t0)
    return {"rows": rows, "build_s": build, "propose_ms": 1e3 * statistics.median(times),
            "scan_ms": 1e3 * statistics.median(scans)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--num-candidates", type=int, default=100)
    parser.add_argument("--k", type=int, default=10)
    parser.add_argument("--reached-in", type=int, nargs="+", default=[0],
                        help="GoalProposer's reached_in (0: no filter), each measured")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"GoalProposer: one proposal ({args.num_candidates} candidates, k={args.k}), median of {args.repeats}; "
          f"a training loop spends ~{LOOP_S_PER_EPISODE:.1f} s an episode")
    print("| rows | reached_in | index build (s) | proposal (ms) | brute-force scan (ms) | scan / index | "
          "proposal / episode of training |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for rows in args.rows:
        for reached_in in args.reached_in:
            r = bench(rows, args.repeats, args.num_candidates, args.k, reached_in)
            print(f"| {rows:,} | {reached_in} | {r['build_s']:.2f} | {r['propose_ms']:.2f} | {r['scan_ms']:.1f} | "
                  f"{r['scan_ms'] / r['propose_ms']:.0f}x | {r['propose_ms'] / 1e3 / LOOP_S_PER_EPISODE:.2%} |",
                  flush=True)


if __name__ == "__main__":
    main()
