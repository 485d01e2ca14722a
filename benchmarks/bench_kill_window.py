"""How much a SIGKILL loses while a process writes as fast as it can.

A child process extends a ``ZarrStorage`` buffer in a tight loop (1000
FetchPush-v4 transitions per ``extend``, pre-built, so nothing but the storage
runs) and records, in a memory-mapped array, when each ``extend`` returned.
After ``--warmup`` seconds of sustained writing plus a random delay, the parent
SIGKILLs it, reopens the store, and reports:

* rows lost: rows whose ``extend`` had returned but that are not in the store;
* the loss window: how long before the kill the last surviving row's
  ``extend`` returned (what "at most ``commit_interval`` seconds" is about).

    python benchmarks/bench_kill_window.py --kills 8 --warmup 20
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

_CHILD = r"""
import sys, time
import numpy as np, torch
sys.path.insert(0, {bench_dir!r})
from _data import fetch_push_transitions
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem import ZarrStorage
torch.set_num_threads(1)
path, stamps_path, batch, commit_interval = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
stamps = np.memmap(stamps_path, dtype=np.float64, mode="r+", shape=(1_000_000,))
data = fetch_push_transitions(batch * 8)
batches = [data[i * batch:(i + 1) * batch].clone() for i in range(8)]
rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 100_000_000, commit_interval=commit_interval))
print("ready", flush=True)
i = 0
while True:
    rb.extend(batches[i % 8])
    stamps[i] = time.time()   # after extend returned: these rows must survive
    i += 1
"""


def one_kill(tmp: Path, *, batch: int, warmup: float, commit_interval: float, rng: random.Random) -> dict:
    path = tmp / "m.zarr"
    stamps_path = tmp / "stamps.bin"
    np.memmap(stamps_path, dtype=np.float64, mode="w+", shape=(1_000_000,))[:] = 0
    child = tmp / "child.py"
    child.write_text(_CHILD.format(bench_dir=str(Path(__file__).resolve().parent)))
    proc = subprocess.Popen([sys.executable, str(child), str(path), str(stamps_path), str(batch),
                             str(commit_interval)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    time.sleep(warmup + rng.uniform(0, 2.0))
    proc.send_signal(signal.SIGKILL)
    t_kill = time.time()
    proc.wait()
    stamps = np.memmap(stamps_path, dtype=np.float64, mode="r", shape=(1_000_000,))
    completed = int(np.count_nonzero(stamps))
    from torchrl_robotmem import ZarrStorage

    n = len(ZarrStorage(path, read_only=True))
    kept_batches = n // batch
    last_kept = stamps[kept_batches - 1] if kept_batches else stamps[0]
    out = {
        "extended_rows": completed * batch,
        "rows_in_store": n,
        "rows_lost": completed * batch - n,
        "loss_window_s": max(0.0, t_kill - last_kept) if completed > kept_batches else 0.0,
        "write_rate_rows_per_s": completed * batch / max(1e-9, stamps[completed - 1] - stamps[0]),
    }
    import shutil

    shutil.rmtree(path)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kills", type=int, default=8)
    ap.add_argument("--warmup", type=float, default=20.0, help="seconds of sustained writing before a kill")
    ap.add_argument("--batch", type=int, default=1000, help="rows per extend")
    ap.add_argument("--commit-interval", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench_results/kill_window.json")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.kills):
            r = one_kill(Path(tmp), batch=args.batch, warmup=args.warmup,
                         commit_interval=args.commit_interval, rng=rng)
            results.append(r)
            print(f"kill {k}: {r['rows_lost']:>9,} of {r['extended_rows']:>11,} rows lost, "
                  f"window {r['loss_window_s']:.2f} s, writing {r['write_rate_rows_per_s']:,.0f} rows/s",
                  flush=True)
    windows = [r["loss_window_s"] for r in results]
    summary = {
        "commit_interval_s": args.commit_interval,
        "warmup_s": args.warmup,
        "batch": args.batch,
        "loss_window_s_median": statistics.median(windows),
        "loss_window_s_max": max(windows),
        "rows_lost_median": statistics.median(r["rows_lost"] for r in results),
        "write_rate_median": statistics.median(r["write_rate_rows_per_s"] for r in results),
        "kills": results,
    }
    print(json.dumps({k: v for k, v in summary.items() if k != "kills"}, indent=1))
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(summary, f, indent=1)


if __name__ == "__main__":
    main()
