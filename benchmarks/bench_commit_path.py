"""The commit path (issue 41): does the commit worker process still pay once chunks are written directly?

Writes ``--rows`` Fetch-shaped rows of noise (the row tier benchmark's rows and write
child, :mod:`bench_row_tier`: ``TensorDictReplayBuffer.extend`` in batches of 1000,
the noise made outside the timers) with:

* ``LazyMemmapStorage`` (TorchRL; the reference of every ratio);
* ``ZarrStorage(commit_process=True)`` (the commit worker; the child waits until the
  worker has started before its first extend, as in a run of any length) and
  ``ZarrStorage(commit_process=False)`` (in-process commits, the background thread);

each for two packages: **before** (``--rev``, the package as committed there: chunks
written through Zarr's ``setitem``) and **after** (``--after``, default the checkout:
chunks written by ``storage/fast_write.py``). Foreground rows/s counts the time inside
the extend calls; durable rows/s runs from the first extend until ``flush()`` returned
(``dumps`` for the memmap). Every run is a fresh process; the contestants are
interleaved and their order rotated every repetition; medians, and ratios taken within
a repetition.

    python benchmarks/bench_commit_path.py --rows 200000 --repeat 5 --rev fa75f7a
    python benchmarks/bench_commit_path.py --rows 1000000 --repeat 5 --rev fa75f7a

Prints a markdown table and writes ``--out`` (JSON, default
``bench_results/commit_path_<rows>.json``).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_row_tier import WRITE_CHILD, Runner, med  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

_MAKE = "    storage = ZarrStorage(path, rows)\n"
_WORKER = """    commit_process = os.environ["BENCH_COMMIT_PROCESS"] == "1"
    if commit_process:  # a run of any length: the worker has started before the first extend
        from torchrl_robotmem.storage._commit_worker import CommitWorker
        _w, _t = CommitWorker.get(), time.monotonic()
        while not _w.ready():
            assert time.monotonic() - _t < 120, "the commit worker did not start"
            time.sleep(0.01)
    storage = ZarrStorage(path, rows, commit_process=commit_process)
"""
_RESULT = 'res["package"] = torchrl_robotmem.__file__\n'
assert WRITE_CHILD.count(_MAKE) == 1 and WRITE_CHILD.count(_RESULT) == 1, "bench_row_tier's write child changed"
CHILD = WRITE_CHILD.replace(_MAKE, _WORKER).replace(
    _RESULT, _RESULT + 'res["via_worker"] = bool(getattr(getattr(storage, "_engine", None), "_via_worker", False))\n'
                       'res["cpu_s"] = time.process_time()\n')

KINDS = ("memmap", "worker@before", "inproc@before", "worker@after", "inproc@after")
LABELS = {"memmap": "`LazyMemmapStorage`",
          "worker@before": "`ZarrStorage(commit_process=True)`, before (Zarr setitem)",
          "inproc@before": "`ZarrStorage(commit_process=False)`, before (Zarr setitem)",
          "worker@after": "`ZarrStorage(commit_process=True)`, after (direct writes)",
          "inproc@after": "`ZarrStorage(commit_process=False)`, after (direct writes)"}


def unpack(rev: str, scratch: Path) -> tuple[str, str]:
    package = scratch / f"pkg_{rev}"
    shutil.rmtree(package, ignore_errors=True)
    package.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "torchrl_robotmem"], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(package)], input=archive.stdout, check=True)
    short = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", rev], capture_output=True, text=True).stdout
    return str(package), short.strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rev", required=True, help="the 'before' package: as committed at this git revision")
    ap.add_argument("--after", default=None, help="the 'after' package: a git revision (default: the checkout)")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--scratch", default=None)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    scratch = Path(args.scratch or tempfile.mkdtemp(prefix="bench_commit_"))
    scratch.mkdir(parents=True, exist_ok=True)
    before, before_label = unpack(args.rev, scratch)
    if args.after:
        after, after_label = unpack(args.after, scratch)
    else:
        after, after_label = str(ROOT), "checkout"
    runners = {"before": Runner(scratch, before), "after": Runner(scratch, after)}
    kinds = args.kinds.split(",")
    runs: dict[str, list] = {k: [] for k in kinds}
    for rep in range(args.repeat):
        order = kinds[rep % len(kinds):] + kinds[: rep % len(kinds)]
        for kind in order:
            mode, _, which = kind.partition("@")
            runner = runners[which or "after"]
            runner.env["BENCH_COMMIT_PROCESS"] = "1" if mode == "worker" else "0"
            path = scratch / f"store_{kind.replace('@', '_')}"
            res = runner.run(CHILD, "memmap" if mode == "memmap" else "zarr", path, args.rows, rep)
            shutil.rmtree(path, ignore_errors=True)
            if mode == "worker" and not res["via_worker"]:
                raise RuntimeError(f"{kind}: the commits did not go through the worker")
            res["rep"] = rep
            runs[kind].append(res)
            print(f"rep {rep} {kind:14s} extend {res['extend_fg_rows_s']:>12,.0f} rows/s  durable "
                  f"{res['durable_rows_s']:>12,.0f} rows/s  after last extend {res['after_last_extend_s']:.2f} s",
                  flush=True)
    ref = runs.get("memmap")
    summary = {}
    for kind, rs in runs.items():
        s = {k: med([r[k] for r in rs]) for k in ("extend_fg_rows_s", "durable_rows_s", "after_last_extend_s", "cpu_s")}
        if ref:
            s["extend_vs_memmap"] = med([r["extend_fg_rows_s"] / m["extend_fg_rows_s"] for r, m in zip(rs, ref)])
            s["durable_vs_memmap"] = med([r["durable_rows_s"] / m["durable_rows_s"] for r, m in zip(rs, ref)])
        summary[kind] = s
    pairs = {}
    for which in ("before", "after"):
        w, i = runs.get(f"worker@{which}"), runs.get(f"inproc@{which}")
        if w and i:
            pairs[which] = {"extend_worker_vs_inproc": med([a["extend_fg_rows_s"] / b["extend_fg_rows_s"] for a, b in zip(w, i)]),
                            "durable_worker_vs_inproc": med([a["durable_rows_s"] / b["durable_rows_s"] for a, b in zip(w, i)])}
    bpr = next(iter(runs.values()))[0]["bytes_per_row"]
    print(f"\n{args.rows:,} Fetch-shaped rows of noise ({bpr} B each), before = as committed at {before_label}, "
          f"after = {after_label}; {len(os.sched_getaffinity(0))} CPUs, load average {os.getloadavg()[0]:.1f}; "
          f"median of {args.repeat} interleaved repetitions, each in a fresh process; ratios are medians of "
          f"same-repetition ratios.\n")
    print("| write | extend rows/s (foreground) | x memmap | durable rows/s (until flush returns) | x memmap | "
          "after the last extend, s |")
    print("|---|---|---|---|---|---|")
    for kind, s in summary.items():
        xm = f"{s['extend_vs_memmap']:.2f}x" if "extend_vs_memmap" in s else ""
        dm = f"{s['durable_vs_memmap']:.2f}x" if "durable_vs_memmap" in s else ""
        print(f"| {LABELS.get(kind, kind)} | {s['extend_fg_rows_s']:,.0f} | {xm} | {s['durable_rows_s']:,.0f} | {dm} | "
              f"{s['after_last_extend_s']:.2f} |")
    for which, p in pairs.items():
        print(f"\n{which}: worker / in-process, same repetition: extend {p['extend_worker_vs_inproc']:.2f}x, "
              f"durable {p['durable_worker_vs_inproc']:.2f}x")
    out = Path(args.out or ROOT / "bench_results" / f"commit_path_{args.rows}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"meta": {"rows": args.rows, "repeat": args.repeat, "before": before_label,
                                        "after": after_label, "cpus": len(os.sched_getaffinity(0)),
                                        "time": time.strftime("%Y-%m-%d %H:%M:%S")},
                               "summary": summary, "worker_vs_inproc": pairs, "runs": runs}, indent=1))
    print(f"\nwrote {out}")
    if not args.scratch:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
