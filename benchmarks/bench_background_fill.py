"""An open that must fill its rows (no seal: a writer beside it, a crash): the open, the first sample, the whole fill.

Issue 41: a row file that is missing, stale or torn is refilled from the chunks in the background, the
chunks a sample needs first. ``--rows`` Fetch-shaped rows of noise (as ``bench_row_tier.py``: 274 bytes a
row) are written once into ``ZarrStorage(path, rows)`` and closed; before every measurement the row file is
deleted (``remove_rows``: what a reader beside an active writer, or after a crash, finds) and the page
cache of the store dropped, so each open reads the chunks from disk. Each measurement in a fresh process,
the two kinds interleaved:

* ``sync``: the open fills every row before it returns (``TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES`` set
  above the rows' size: what every open did before);
* ``background``: the open returns at once and a thread fills (the default from 64 MiB of rows).

Recorded: the open's seconds; the first ``sample(256)`` (uniform: a batch touches most chunks of a small
memory, a few of a large one); the first ``get`` of 256 rows of one chunk (a sampler reading recent rows);
and the time until every row is filled (``storage._storage`` returns). Medians over ``--repeat``.
``--writer``: the same opens as the store's writer (what a run restarted after a crash does), with one
more figure, the first append of 256 rows after the sample (a writer's first ``extend``).

    python benchmarks/bench_background_fill.py --rows 1000000 --repeat 3
    python benchmarks/bench_background_fill.py --rows 10000000 --repeat 3 --scratch /tmp/bgfill
    python benchmarks/bench_background_fill.py --rows 10000000 --repeat 3 --scratch /tmp/bgfill --keep --writer
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_row_tier import drop_cache  # noqa: E402

WRITE = r"""
import sys, torch
from tensordict import TensorDict
from torchrl_robotmem import ZarrStorage
path, rows = sys.argv[1], int(sys.argv[2])
gen = torch.Generator().manual_seed(0)
def noise(n):
    f = lambda *s: torch.rand(n, *s, generator=gen)
    b = lambda: torch.rand(n, 1, generator=gen) < 0.5
    return TensorDict({"observation": f(25), "achieved_goal": f(3), "desired_goal": f(3), "action": f(4),
        "done": b(), "terminated": b(), "truncated": b(),
        "next": {"observation": f(25), "achieved_goal": f(3), "desired_goal": f(3), "reward": f(1),
                 "done": b(), "terminated": b(), "truncated": b()}}, [n])
with ZarrStorage(path, rows + 65536, env="FetchReach-v4", goal_conditioned=False) as st:  # room for --writer appends
    for lo in range(0, rows, 10_000):
        n = min(10_000, rows - lo)
        st.set(torch.arange(lo, lo + n), noise(n))
"""

OPEN = r"""
import json, sys, time, torch
torch.set_num_threads(1)
from torchrl.data import RandomSampler, TensorDictReplayBuffer
from torchrl_robotmem import ZarrStorage
path, writer = sys.argv[1], sys.argv[2] == "writer"
t0 = time.perf_counter()
st = ZarrStorage(path) if writer else ZarrStorage(path, read_only=True)
t1 = time.perf_counter()
n = len(st)
rb = TensorDictReplayBuffer(storage=st, sampler=RandomSampler(), batch_size=256)
rb.sample()
t2 = time.perf_counter()
lo = (n // 2) // 1000 * 1000
rows = st.get(torch.arange(lo, lo + 256))
t3 = time.perf_counter()
res = {"open_s": t1 - t0, "first_sample_s": t2 - t1, "one_chunk_get_s": t3 - t2}
if writer:
    st.set(torch.arange(n, n + 256), rows)
    res["first_append_s"] = time.perf_counter() - t3
_ = st._storage
res["whole_fill_s"] = time.perf_counter() - t0
res["background"] = bool(st.row_file and st.row_file["background"])
st.close()
print(json.dumps(res))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--scratch", default=None, help="where the store goes (default: a temporary directory)")
    parser.add_argument("--keep", action="store_true", help="keep the store written by an earlier run")
    parser.add_argument("--writer", action="store_true", help="open as the store's writer (each run appends 256 rows)")
    parser.add_argument("--out", default=None, help="JSON results (default bench_results/background_fill_<rows>[_writer].json)")
    args = parser.parse_args()
    scratch = Path(args.scratch or tempfile.mkdtemp(prefix="bgfill-"))
    scratch.mkdir(parents=True, exist_ok=True)
    path = scratch / "store.zarr"
    py = [sys.executable, "-c"]
    if not (args.keep and path.exists()):
        shutil.rmtree(path, ignore_errors=True)
        subprocess.run([*py, WRITE, str(path), str(args.rows)], check=True, cwd=ROOT)
    from torchrl_robotmem.storage.rowfile import remove_rows

    runs: dict[str, list[dict]] = {"sync": [], "background": []}
    for rep in range(args.repeat):
        kinds = ["sync", "background"] if rep % 2 == 0 else ["background", "sync"]
        for kind in kinds:
            remove_rows(path)
            drop_cache(path)
            env = dict(os.environ)
            if kind == "sync":
                env["TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES"] = str(1 << 50)
            else:
                env.pop("TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES", None)
            out = subprocess.run([*py, OPEN, str(path), "writer" if args.writer else "reader"], check=True, cwd=ROOT,
                                 env=env, capture_output=True, text=True)
            runs[kind].append(json.loads(out.stdout.strip().splitlines()[-1]))
    summary = {kind: {k: statistics.median(r[k] for r in rs) for k in rs[0] if k != "background"}
               for kind, rs in runs.items()}
    who = "the writer" if args.writer else "a reader"
    print(f"{args.rows:,} rows, no row file (filled from the chunks, page cache dropped), opened by {who}, "
          f"medians of {args.repeat}:\n")
    extra = " then an append of 256 rows s |" if args.writer else ""
    print(f"| open | open s | first `sample(256)` s | then `get` of 256 rows of one chunk s |{extra} every row filled, from the open s |")
    print("|---|---|---|---|---|" + ("---|" if args.writer else ""))
    for kind, s in summary.items():
        append = f" {s['first_append_s']:.4f} |" if args.writer else ""
        print(f"| {kind} | {s['open_s']:.4f} | {s['first_sample_s']:.4f} | {s['one_chunk_get_s']:.4f} |{append} {s['whole_fill_s']:.3f} |")
    if not all(r["background"] for r in runs["background"]) or any(r["background"] for r in runs["sync"]):
        raise SystemExit("an open did not fill the way its kind says (see row_file['background'] in the runs)")
    name = f"background_fill_{args.rows}" + ("_writer" if args.writer else "")
    out = Path(args.out or ROOT / "bench_results" / f"{name}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rows": args.rows, "repeat": args.repeat, "runs": runs, "median": summary}, indent=1))
    if not args.scratch:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
