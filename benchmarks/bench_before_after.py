"""The storage, sampler and recall benchmarks on two revisions, in one run, interleaved.

For a change that must leave speed unchanged (a refactor), "within noise" needs
both sides measured on the same machine at the same time: this script checks
each revision out in a temporary ``git worktree``, then runs every benchmark on
both, alternating the order every round (A B, B A, ...), each revision with its
own copy of the benchmark scripts and its own package on ``PYTHONPATH``. It
prints, per metric, the median of each side and the after/before ratio of each
round (same-round ratios are what to quote on a noisy box).

    python benchmarks/bench_before_after.py --before 9f02009            # after = working tree
    python benchmarks/bench_before_after.py --before v1 --after v2 --rounds 3 --rows 200000

Writes ``bench_results/before_after.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]

# (benchmark, path in its JSON, higher is better)
METRICS = {
    "storage": [
        ("extend rows/s (foreground)", ("summary", "ZarrStorage", "extend_fg_rows_s"), True),
        ("extend vs LazyMemmapStorage", ("summary", "ZarrStorage", "fg_vs_memmap"), True),
        ("durable rows/s", ("summary", "ZarrStorage", "durable_rows_s"), True),
        ("sample(256) ms", ("summary", "ZarrStorage", "sample_ms"), False),
        ("sample speed vs LazyTensorStorage", ("summary", "ZarrStorage", "sample_speed_vs_lts"), True),
        ("HER sample(256) ms", ("summary", "ZarrStorage", "her_sample_ms"), False),
        ("HER sample speed vs LazyTensorStorage", ("summary", "ZarrStorage", "her_speed_vs_lts"), True),
        ("reopen s (writable)", ("reopen", "open_s"), False),
        ("reopen s (read-only)", ("reopen", "open_read_only_s"), False),
    ],
    "sampler": [
        ("RandomSampler sample ms", ("ZarrStorage", "uniform_RandomSampler_ms"), False),
        ("GoalSimilaritySampler 1 query ms", ("ZarrStorage", "query_1_new_each_call_ms"), False),
        ("HER + RandomSampler ms", ("ZarrStorage", "her_uniform_RandomSampler_ms"), False),
        ("HER + GoalSimilaritySampler ms", ("ZarrStorage", "her_query_1_new_each_call_ms"), False),
    ],
    "recall": [
        ("GoalIndex build ms", ("results", "fetch3 (euclidean)", "build_ms"), False),
        ("search 1 query top-5 ms", ("results", "fetch3 (euclidean)", "search_1q_top5_ms"), False),
        ("search 256 queries top-5 ms", ("results", "fetch3 (euclidean)", "search_256q_top5_ms"), False),
        ("recall() 1 query top-5 ms", ("results", "fetch3 (euclidean)", "recall_1q_top5_ms"), False),
        ("index update after extend(1000) ms", ("results", "fetch3 (euclidean)", "update_after_extend1000_ms"), False),
    ],
}


def commands(rows: int, out: Path) -> dict[str, list[str]]:
    return {
        "storage": ["benchmarks/bench_storage.py", "--rows", str(rows), "--repeats", "3", "--samples", "200",
                    "--no-variants", "--out", str(out / "storage.json")],
        "sampler": ["benchmarks/bench_sampler.py", "--rows", str(rows), "--repeat", "50",
                    "--out", str(out / "sampler.json")],
        "recall": ["benchmarks/bench_recall.py", "--rows", str(rows), "--quick", "--only", "fetch3",
                   "--out", str(out / "recall.json")],
    }


def checkout(rev: str, scratch: Path, side: str) -> Path:
    """The tree of ``rev``: the working tree for ``"."``, else a detached worktree under ``scratch``."""
    if rev == ".":
        return ROOT
    tree = scratch / f"{side}-tree"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--force", str(tree), rev],
                   check=True, capture_output=True)
    return tree


def run_one(tree: Path, argv: list[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    proc = subprocess.run([sys.executable, *argv], cwd=tree, env=env, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"{argv[0]} failed in {tree}:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
    return json.loads(Path(argv[argv.index("--out") + 1]).read_text())


def dig(d: dict, path: tuple) -> float | None:
    for key in path:
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return float(d) if isinstance(d, (int, float)) else None


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="git revision measured as 'before'")
    ap.add_argument("--after", default=".", help="git revision measured as 'after' ('.': the working tree)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--rows", type=int, default=200_000)
    ap.add_argument("--only", default="storage,sampler,recall")
    ap.add_argument("--out", default="bench_results/before_after.json")
    args = ap.parse_args(argv)
    only = args.only.split(",")
    results = {side: {b: [] for b in only} for side in ("before", "after")}
    with tempfile.TemporaryDirectory(prefix="before_after-") as tmp:
        scratch = Path(tmp)
        trees = {side: checkout(getattr(args, side), scratch, side) for side in ("before", "after")}
        try:
            steps = [(r, b, side) for r in range(args.rounds) for b in only
                     for side in (("before", "after") if r % 2 == 0 else ("after", "before"))]
            for r, bench, side in tqdm(steps, desc="benchmarks"):
                out = scratch / f"{side}-{bench}-{r}"
                out.mkdir()
                results[side][bench].append(run_one(trees[side], commands(args.rows, out)[bench]))
        finally:
            for tree in trees.values():
                if tree != ROOT:
                    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                                   capture_output=True)
    table = []
    for bench in only:
        for name, path, higher in METRICS[bench]:
            b = [dig(x, path) for x in results["before"][bench]]
            a = [dig(x, path) for x in results["after"][bench]]
            if None in a or None in b:
                continue
            ratios = [y / x for x, y in zip(b, a) if x]
            table.append({"benchmark": bench, "metric": name, "higher_is_better": higher,
                          "before": statistics.median(b), "after": statistics.median(a),
                          "round_ratios": ratios})
    print(f"\nbefore = {args.before}, after = {args.after}, {args.rows:,} rows, {args.rounds} rounds "
          f"(order alternated)\n")
    print("| benchmark | metric | before (median) | after (median) | after/before, each round |")
    print("|---|---|---|---|---|")
    for row in table:
        ratios = ", ".join(f"{x:.2f}" for x in row["round_ratios"])
        print(f"| {row['benchmark']} | {row['metric']} | {row['before']:.4g} | {row['after']:.4g} | {ratios} |")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"before": args.before, "after": args.after, "rows": args.rows,
                               "rounds": args.rounds, "table": table, "raw": results}, indent=1))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
