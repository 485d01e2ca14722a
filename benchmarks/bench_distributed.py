"""Frames/s of multi-process collectors feeding a ZarrStorage buffer vs a LazyTensorStorage one.

For each number of workers (``--workers 1 2 4``), ONE ``MultiSyncCollector``
(or ``--collector async``: ``MultiAsyncCollector``) steps ``FetchPush-v4`` with
a random policy in spawned worker processes; the main process (the single
writer) extends the buffers. Its batches go alternately to a
``TensorDictReplayBuffer`` on ``ZarrStorage`` and to one on
``LazyTensorStorage`` (the order flips every pair), so both storages see the
same collector, the same workers and the same machine noise. The time of an
iteration is from the previous ``extend`` returning to this one returning
(waiting for the batch, then writing it); frames/s of a storage is the
frames of its iterations over their summed time, and the table reports the
median iteration too. Worker start-up is not timed.

    python benchmarks/bench_distributed.py                        # 1 2 4 workers, 20 batches of 200 frames
    python benchmarks/bench_distributed.py --workers 2 --batches 40 --collector async

Writes ``outputs/bench/distributed.json``.
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
from torchrl.collectors import MultiAsyncCollector, MultiSyncCollector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage, make_env

ENV_ID = "FetchPush-v4"


def run(workers: int, batches: int, frames_per_batch: int, collector_cls) -> dict:
    tmp = tempfile.mkdtemp()
    buffers = {
        "zarr": TensorDictReplayBuffer(storage=ZarrStorage(f"{tmp}/m.zarr", batches * frames_per_batch, env=ENV_ID)),
        "lazy": TensorDictReplayBuffer(storage=LazyTensorStorage(batches * frames_per_batch)),
    }
    make = partial(make_env, ENV_ID)
    collector = collector_cls([make] * workers, None, frames_per_batch=frames_per_batch,
                              total_frames=(batches + 2) * frames_per_batch)
    times = {"zarr": [], "lazy": []}
    frames = {"zarr": 0, "lazy": 0}
    t_start = time.perf_counter()
    try:
        it = iter(collector)
        first = next(it)  # worker start-up: not timed
        buffers["zarr"].extend(first.reshape(-1))
        t_prev = time.perf_counter()
        for i in range(batches):
            order = ("zarr", "lazy") if (i // 2) % 2 == 0 else ("lazy", "zarr")
            name = order[i % 2]
            data = next(it).reshape(-1)
            buffers[name].extend(data)
            now = time.perf_counter()
            times[name].append(now - t_prev)
            frames[name] += data.numel()
            t_prev = now
    finally:
        collector.shutdown()
    buffers["zarr"].storage.close()
    out = {"workers": workers, "wall_s": time.perf_counter() - t_start}
    for name in ("zarr", "lazy"):
        out[name] = {
            "fps": frames[name] / sum(times[name]),
            "median_iter_s": statistics.median(times[name]),
            "iters": len(times[name]),
        }
    out["ratio_fps_zarr_over_lazy"] = out["zarr"]["fps"] / out["lazy"]["fps"]
    return out


def main() -> None:
    torch.set_num_threads(1)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--batches", type=int, default=20, help="timed batches per worker count (half per storage)")
    parser.add_argument("--frames-per-batch", type=int, default=200)
    parser.add_argument("--collector", choices=["sync", "async"], default="sync")
    parser.add_argument("--out", default="outputs/bench/distributed.json")
    args = parser.parse_args()
    cls = MultiSyncCollector if args.collector == "sync" else MultiAsyncCollector
    results = []
    for w in args.workers:
        r = run(w, args.batches, args.frames_per_batch, cls)
        results.append(r)
        print(f"workers={w}  zarr {r['zarr']['fps']:6.0f} fps (median iter {r['zarr']['median_iter_s']:.3f} s)  "
              f"lazy {r['lazy']['fps']:6.0f} fps (median iter {r['lazy']['median_iter_s']:.3f} s)  "
              f"ratio {r['ratio_fps_zarr_over_lazy']:.2f}  load {os.getloadavg()[0]:.1f}", flush=True)
    out = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "load_avg": os.getloadavg()},
           "collector": cls.__name__, "frames_per_batch": args.frames_per_batch, "batches": args.batches,
           "results": results}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
