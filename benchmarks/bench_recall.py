"""Benchmark of GoalIndex / recall on FetchPush-, HandManipulate- and HandReach-shaped storages.

Prints a markdown table (medians) and writes ``bench_results/recall.json``.

    python benchmarks/bench_recall.py            # 1M rows
    python benchmarks/bench_recall.py --rows 200000 --quick
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_robotmem.goal_index import GoalIndex

torch.set_num_threads(1)


def median_ms(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def unit_quat(n, gen):
    q = torch.randn(n, 4, generator=gen)
    return q / q.norm(dim=1, keepdim=True)


def make_goals(kind, n, gen):
    if kind == "fetch3":  # object positions on a table
        return torch.rand(n, 3, generator=gen) * torch.tensor([0.3, 0.3, 0.1]) + torch.tensor([1.2, 0.6, 0.42])
    if kind == "pose7":  # block pose in the hand: position jitter + any orientation
        pos = torch.rand(n, 3, generator=gen) * 0.04 + torch.tensor([1.0, 0.87, 0.2])
        return torch.cat([pos, unit_quat(n, gen)], 1)
    if kind == "reach15":  # 5 fingertips driven by a 6-D latent hand posture (smooth map)
        z = torch.rand(n, 6, generator=gen)
        w = torch.randn(6, 15, generator=torch.Generator().manual_seed(7)) * 0.03
        return torch.tanh(z @ w * 3) * 0.05 + torch.linspace(0.9, 1.1, 15)
    if kind == "uniform15":
        return torch.rand(n, 15, generator=gen)
    raise ValueError(kind)


def make_rows(kind, n, gen, start=0):
    """FetchPush-shaped transitions (HandManipulate shapes for pose goals)."""
    goals = make_goals(kind, n, gen)
    gd = goals.shape[1]
    obs_dim, act_dim = (61, 20) if gd == 7 else ((63, 20) if gd == 15 else (25, 4))
    step = torch.arange(start, start + n) % 50
    done = (step == 49).unsqueeze(-1)
    success = (torch.rand(n, generator=gen) < 0.1).float()
    return TensorDict(
        {
            "observation": torch.randn(n, obs_dim, generator=gen),
            "achieved_goal": goals,
            "desired_goal": make_goals(kind, n, gen),
            "action": torch.rand(n, act_dim, generator=gen) * 2 - 1,
            "done": torch.zeros(n, 1, dtype=torch.bool),
            "terminated": torch.zeros(n, 1, dtype=torch.bool),
            "truncated": torch.zeros(n, 1, dtype=torch.bool),
            "is_success": torch.zeros(n),
            "episode": (torch.arange(start, start + n) // 50),
            "run": torch.zeros(n, dtype=torch.int64),
            "env": torch.randint(0, 2, (n,), generator=gen),
            ("next", "observation"): torch.randn(n, obs_dim, generator=gen),
            ("next", "achieved_goal"): goals,
            ("next", "desired_goal"): make_goals(kind, n, gen),
            ("next", "reward"): success.unsqueeze(-1) - 1,
            ("next", "done"): done,
            ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
            ("next", "truncated"): done,
            ("next", "is_success"): success,
        },
        batch_size=[n],
    )


def build_buffer(kind, n, capacity=None, seed=0):
    gen = torch.Generator().manual_seed(seed)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity or n))
    for start in range(0, n, 100_000):
        rb.extend(make_rows(kind, min(100_000, n - start), gen, start))
    return rb, gen


def brute_force(storage, queries, k, metric, chunk=8):
    goals = storage._storage.get(("next", "achieved_goal"))[: len(storage)].double()
    ds, ids = [], []
    for i in range(0, queries.shape[0], chunk):
        dist = metric.pairwise(queries[i : i + chunk].double(), goals)
        d, j = torch.topk(dist, k, dim=1, largest=False)
        ds.append(d)
        ids.append(j)
    return torch.cat(ds).float(), torch.cat(ids)


def exactness(index, storage, queries, k, metric):
    d, i, _ = index.search(queries, k)
    bd, bi = brute_force(storage, queries, k, metric)
    same_index = (i == bi).float().mean().item()
    same_dist = torch.isclose(d, bd, rtol=1e-5, atol=1e-6).float().mean().item()
    return same_index, same_dist


def bench_kind(kind, n, metric, quick, extra=None):
    rep = 5 if quick else 21
    rb, gen = build_buffer(kind, n)
    st = rb.storage
    index = GoalIndex(rb, metric=metric)
    t0 = time.perf_counter()
    index.refresh()
    build = time.perf_counter() - t0
    m = index.metric
    queries = make_goals(kind, 256, gen) + 0.001 * torch.randn(256, make_goals(kind, 1, gen).shape[1], generator=gen)
    q1 = queries[:1]
    res = {
        "rows": n,
        "goal_dim": q1.shape[1],
        "metric": m.name,
        "backend": index.backend_in_use,
        "build_ms": 1e3 * build,
        "search_1q_top5_ms": median_ms(lambda: index.search(q1[0], 5), 10 * rep),
        "search_256q_top5_ms": median_ms(lambda: index.search(queries, 5), rep),
        "recall_1q_top5_ms": median_ms(lambda: index.recall(q1[0], 5), 10 * rep),
        "recall_256q_top5_ms": median_ms(lambda: index.recall(queries, 5), rep),
    }
    idx_eq, dist_eq = exactness(index, st, queries[: 64 if quick else 256], 5, m)
    res["exact_index_match"] = idx_eq
    res["exact_distance_match"] = dist_eq
    if extra:
        res.update(extra(rb, index, gen, queries, rep))
    return res


def incremental(rb, index, gen, queries, rep):
    """Cost of bringing the index up to date after extend(1000), growing and (ring) full."""
    out = {}
    q1 = queries[:1]
    st = rb.storage
    start = len(st)
    # success_only and env views exist, so their upkeep is included
    index.refresh(success_only=True)
    out["search_1q_success_only_ms"] = median_ms(lambda: index.search(q1[0], 5, success_only=True), 10 * rep)
    env_names = ("FetchPush-v4", "FetchSlide-v4")
    index._env_names = env_names
    index.refresh(env="FetchSlide-v4")
    out["search_1q_env_ms"] = median_ms(lambda: index.search(q1[0], 5, env="FetchSlide-v4"), 10 * rep)
    ext, upd, q_after = [], [], []
    for i in range(3 * rep):
        td = make_rows("fetch3", 1000, gen, start + 1000 * i)
        t0 = time.perf_counter()
        rb.extend(td)
        t1 = time.perf_counter()
        index.refresh()
        index.refresh(success_only=True)
        t2 = time.perf_counter()
        index.search(q1[0], 5)
        t3 = time.perf_counter()
        ext.append(t1 - t0)
        upd.append(t2 - t1)
        q_after.append(t3 - t2)
    out["extend1000_ms"] = 1e3 * statistics.median(ext)
    out["update_after_extend1000_ms"] = 1e3 * statistics.median(upd)
    out["update_after_extend1000_mean_ms"] = 1e3 * statistics.mean(upd)
    out["search_1q_first_after_update_ms"] = 1e3 * statistics.median(q_after)
    view = index._views[(False, None, None)]
    out["tail_state"] = (
        f"main stale {view.main.n_stale}, mid {view.mid.size if view.mid else 0}, "
        f"live {view.live.size if view.live else 0}"
    )
    out["search_1q_with_tail_ms"] = median_ms(lambda: index.search(q1[0], 5), 10 * rep)
    out["search_256q_with_tail_ms"] = median_ms(lambda: index.search(queries, 5), rep)
    out["full_before_ring"] = st._is_full
    return out


def ring(n, quick):
    """A full ring buffer overwritten by extend(1000): update cost and exactness afterwards."""
    rep = 5 if quick else 21
    rb, gen = build_buffer("fetch3", n)
    index = GoalIndex(rb)
    index.refresh()
    upd = []
    for i in range(3 * rep):
        rb.extend(make_rows("fetch3", 1000, gen, n + 1000 * i))
        t0 = time.perf_counter()
        index.refresh()
        upd.append(time.perf_counter() - t0)
    queries = make_goals("fetch3", 64, gen)
    idx_eq, dist_eq = exactness(index, rb.storage, queries, 5, index.metric)
    return {
        "ring_update_after_extend1000_ms": 1e3 * statistics.median(upd),
        "ring_update_mean_ms": 1e3 * statistics.mean(upd),
        "ring_search_1q_ms": median_ms(lambda: index.search(queries[0], 5), 10 * rep),
        "ring_exact_index_match": idx_eq,
        "ring_exact_distance_match": dist_eq,
    }


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default="bench_results/recall.json")
    parser.add_argument("--only", default="fetch3,pose7,reach15,uniform15,ring")
    args = parser.parse_args()
    only = args.only.split(",")
    results = {}
    if "fetch3" in only:
        results["fetch3 (euclidean)"] = bench_kind("fetch3", args.rows, "euclidean", args.quick, incremental)
    if "ring" in only:
        results["fetch3 ring"] = ring(args.rows, args.quick)
    if "pose7" in only:
        results["pose7 (pose)"] = bench_kind("pose7", args.rows, "pose", args.quick)
    if "reach15" in only:
        results["reach15 (euclidean)"] = bench_kind("reach15", args.rows, "euclidean", args.quick)
    if "uniform15" in only:
        results["uniform15 (euclidean)"] = bench_kind("uniform15", args.rows, "euclidean", args.quick)

    keys = sorted({k for r in results.values() for k in r})
    print(f"\nGoalIndex benchmark, torch threads=1, {platform.processor() or platform.machine()}, medians\n")
    print("| metric | " + " | ".join(results) + " |")
    print("|---|" + "---|" * len(results))
    for key in keys:
        cells = []
        for r in results.values():
            v = r.get(key, "")
            cells.append(f"{v:.4g}" if isinstance(v, float) else str(v))
        print(f"| {key} | " + " | ".join(cells) + " |")
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"rows": args.rows, "torch_threads": 1, "results": results}, f, indent=2)
    print(f"\nwritten to {args.out}")


if __name__ == "__main__":
    main()
