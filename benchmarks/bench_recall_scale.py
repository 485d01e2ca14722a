"""Recall at scale (issue 41): GoalIndex top-5 over 1M-10M stored goals against scipy's cKDTree.

For each row count, on Fetch-shaped achieved goals (3-D float32, spread as a
pushed object's positions are) held by a ``LazyTensorStorage`` (the index
reads a ``ZarrStorage``'s goal column the same way, through
``storage._storage``), in one run.
Each side runs in a fresh child process (so neither reuses memory the other
freed). For each row count:

* the index build (the first ``refresh()``: snapshot of the goal column, the
  KD-tree), its resident memory (RSS after minus before, and the peak during
  the build), and the bytes it says it holds (``GoalIndex.nbytes()``);
* top-5 ``search`` time, one query at a time and in batches of 256;
* the same for ``scipy.spatial.cKDTree`` built over the same goals (scipy's
  defaults, ``query(k=5, workers=1)``), with the ratios;
* exactness: every query's top-5 rows (or, on a tie, distances) equal the
  cKDTree's.

Prints a markdown table and writes ``bench_results/recall_scale.json``.

    python benchmarks/bench_recall_scale.py --rows 1000000 10000000
    python benchmarks/bench_recall_scale.py --quick        # 100k rows, a few seconds
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import statistics
import subprocess
import sys
import time

import numpy as np
import torch
from scipy.spatial import cKDTree

torch.set_num_threads(1)
_PAGE = os.sysconf("SC_PAGE_SIZE")


def rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * _PAGE


def reset_peak() -> bool:
    """Resets the kernel's peak-RSS counter (VmHWM); False where it cannot."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    return 0


def fetch_goals(rows: int, seed: int = 0) -> torch.Tensor:
    """``rows`` Fetch-shaped achieved goals ``[rows, 3]`` float32."""
    g = torch.Generator().manual_seed(seed)
    return torch.tensor([1.3, 0.75, 0.42]) + torch.randn(rows, 3, generator=g) * torch.tensor([0.08, 0.08, 0.01])


def memory(rows: int, seed: int = 0):
    """A ``LazyTensorStorage`` of ``rows`` Fetch-shaped achieved goals (and success flags)."""
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage

    g = torch.Generator().manual_seed(seed + 2)
    goals = fetch_goals(rows, seed)
    storage = LazyTensorStorage(rows)
    storage.set(torch.arange(rows), TensorDict({
        ("next", "achieved_goal"): goals,
        ("next", "is_success"): (torch.rand(rows, generator=g) < 0.1).float(),
    }, [rows]))
    return storage


def timed(fn, repeat: int) -> tuple[float, float]:
    """Median wall and CPU seconds of ``repeat`` calls ``fn(i)`` (CPU time: this process, all threads)."""
    wall, cpu = [], []
    for i in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        fn(i)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def exact_rows(idx_d, idx_p, ref_d, ref_p) -> np.ndarray:
    """Per query: the index's top-k equals the reference (same rows, or the same distances on a tie)."""
    same_rows = (idx_p == ref_p).all(1)
    same_dist = np.isclose(idx_d, ref_d.astype(np.float32), rtol=1e-6, atol=0).all(1)
    return same_rows | same_dist


def _queries(goals: np.ndarray, seed: int) -> np.ndarray:
    """256 query goals near stored ones (as a proposer's or a transform's goals are)."""
    rng = np.random.default_rng(seed + 1)
    rows = goals.shape[0]
    return goals[rng.integers(0, rows, 256)].astype(np.float64) + rng.normal(size=(256, 3)) * [0.01, 0.01, 0.002]


def part(which: str, rows: int, singles: int, batches: int, k: int, seed: int) -> dict:
    """One side (``"index"`` or ``"tree"``) measured in this process, which holds nothing else."""
    if which == "index":
        from torchrl_robotmem.goal_index import GoalIndex

        storage = memory(rows, seed)
        goals = storage._storage["next", "achieved_goal"].numpy()
    else:  # the same goals, without importing torchrl
        goals = fetch_goals(rows, seed).numpy()
    queries = _queries(goals, seed)
    gc.collect()
    before = rss()
    has_peak = reset_peak()
    out = {}
    if which == "index":
        index = GoalIndex(storage)
        c0, t0 = time.process_time(), time.perf_counter()
        index.refresh()
        build_s, build_cpu = time.perf_counter() - t0, time.process_time() - c0
        out["nbytes"] = index.nbytes() if hasattr(index, "nbytes") else None
        q1 = [torch.from_numpy(queries[i]) for i in range(singles)]
        qb = torch.from_numpy(queries)

        def one(i):
            index.search(q1[i % singles], k)

        def batch(i):
            index.search(qb, k)

        def result():
            d, p, _ = index.search(qb, k)
            return d.numpy().astype(np.float64), p.numpy()
    else:
        c0, t0 = time.process_time(), time.perf_counter()
        tree = cKDTree(goals)
        build_s, build_cpu = time.perf_counter() - t0, time.process_time() - c0
        out["nbytes"] = None

        def one(i):
            tree.query(queries[i % singles][None], k=k, workers=1)

        def batch(i):
            tree.query(queries, k=k, workers=1)

        def result():
            return tree.query(queries, k=k, workers=1)
    gc.collect()
    out.update(build_s=build_s, build_cpu_s=build_cpu, rss_bytes=rss() - before,
               peak_bytes=peak() - before if has_peak else None)
    wall, cpu = timed(one, singles)
    out["query1_ms"], out["query1_cpu_ms"] = 1e3 * wall, 1e3 * cpu
    wall, cpu = timed(batch, batches)
    out["query256_ms"], out["query256_cpu_ms"] = 1e3 * wall, 1e3 * cpu
    d, p = result()
    out["d"], out["p"] = d.tolist(), p.tolist()
    return out


def _run_part(which: str, rows: int, args) -> dict:
    cmd = [sys.executable, __file__, "--part", which, "--rows", str(rows), "--k", str(args.k),
           "--seed", str(args.seed), "--singles", str(args.singles), "--batches", str(args.batches)]
    done = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def bench(rows: int, args) -> dict:
    """Both sides, each in a fresh process (so neither inherits the other's freed memory)."""
    idx, ref = _run_part("index", rows, args), _run_part("tree", rows, args)
    exact = exact_rows(np.array(idx["d"], dtype=np.float32), np.array(idx["p"]),
                       np.array(ref["d"]), np.array(ref["p"]))
    nb = idx["nbytes"]
    return {
        "rows": rows, "k": args.k,
        "index_build_s": idx["build_s"], "index_build_cpu_s": idx["build_cpu_s"],
        "index_rss_bytes": idx["rss_bytes"], "index_peak_bytes": idx["peak_bytes"],
        "index_nbytes": nb, "index_rss_bytes_per_row": idx["rss_bytes"] / rows,
        "index_nbytes_per_row": None if nb is None else nb / rows,
        "index_query1_ms": idx["query1_ms"], "index_query256_ms": idx["query256_ms"],
        "index_query1_cpu_ms": idx["query1_cpu_ms"], "index_query256_cpu_ms": idx["query256_cpu_ms"],
        "tree_build_s": ref["build_s"], "tree_build_cpu_s": ref["build_cpu_s"],
        "tree_rss_bytes": ref["rss_bytes"], "tree_peak_bytes": ref["peak_bytes"],
        "tree_query1_ms": ref["query1_ms"], "tree_query256_ms": ref["query256_ms"],
        "tree_query1_cpu_ms": ref["query1_cpu_ms"], "tree_query256_cpu_ms": ref["query256_cpu_ms"],
        # ratios of CPU time (this box is shared: wall time measures the neighbours too)
        "build_ratio": idx["build_cpu_s"] / ref["build_cpu_s"],
        "query1_ratio": idx["query1_cpu_ms"] / ref["query1_cpu_ms"],
        "query256_ratio": idx["query256_cpu_ms"] / ref["query256_cpu_ms"],
        "exact_fraction": float(exact.mean()),
    }


def _mb(b):
    return "-" if b is None else f"{b / 1e6:,.0f}"


def table(results: list[dict]) -> str:
    """Markdown table; times are CPU time of the process (wall time in the JSON)."""
    head = ("| rows | build s: index / cKDTree | index RSS MB (B/row) | index peak MB | index `nbytes()` B/row "
            "| cKDTree RSS MB (B/row) | top-5, 1 query, ms: index / cKDTree | top-5, 256 queries, ms: index / cKDTree "
            "| exact |")
    lines = [head, "|" + "---:|" * 9]
    for r in results:
        n = r["rows"]
        npr = "-" if r["index_nbytes_per_row"] is None else f"{r['index_nbytes_per_row']:.1f}"
        lines.append(
            f"| {n:,} | {r['index_build_cpu_s']:.2f} / {r['tree_build_cpu_s']:.2f} ({r['build_ratio']:.2f}x) "
            f"| {_mb(r['index_rss_bytes'])} ({r['index_rss_bytes_per_row']:.1f}) | {_mb(r['index_peak_bytes'])} "
            f"| {npr} | {_mb(r['tree_rss_bytes'])} ({r['tree_rss_bytes'] / n:.1f}) "
            f"| {r['index_query1_cpu_ms']:.3f} / {r['tree_query1_cpu_ms']:.3f} ({r['query1_ratio']:.2f}x) "
            f"| {r['index_query256_cpu_ms']:.2f} / {r['tree_query256_cpu_ms']:.2f} ({r['query256_ratio']:.2f}x) "
            f"| {r['exact_fraction']:.3f} |"
        )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, nargs="+", default=[1_000_000])
    ap.add_argument("--quick", action="store_true", help="100k rows and fewer repeats (a smoke run)")
    ap.add_argument("--singles", type=int, default=200, help="single queries timed (median)")
    ap.add_argument("--batches", type=int, default=5, help="256-query batches timed (median)")
    ap.add_argument("--k", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench_results/recall_scale.json")
    ap.add_argument("--part", choices=["index", "tree"], help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.part:  # one side, in a child process: its figures as one JSON line
        print(json.dumps(part(args.part, args.rows[0], args.singles, args.batches, args.k, args.seed)))
        return None
    rows = [100_000] if args.quick else args.rows
    if args.quick:
        args.singles, args.batches = 50, 3
    results = []
    for n in rows:
        results.append(bench(n, args))
        print(json.dumps(results[-1]), flush=True)
    print()
    print(table(results))
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"machine": platform.platform(), "cpus": os.cpu_count(), "torch_threads": 1,
                   "args": vars(args), "results": results}, f, indent=2)
    return results


if __name__ == "__main__":
    main()
