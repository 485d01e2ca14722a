"""MaMuJoCo transitions into ZarrStorage against LazyTensorStorage: extend, sample, reopen.

Collects ``--frames`` random-action frames of MaMuJoCo HalfCheetah 2x3 once (a TorchRL
Collector), then writes them in batches of ``--batch`` rows into each storage, draws
``--samples`` batches of 256, and (ZarrStorage) reopens the store and checks every row
bit-exact. Prints one JSON line of milliseconds.

    python benchmarks/bench_multiagent_storage.py --frames 5000 --batch 500
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
from functools import partial
from pathlib import Path

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_robotmem.envs_multiagent import make_mamujoco_env
from torchrl_robotmem.storage.zarr_storage import ZarrStorage

warnings.filterwarnings("ignore", message="PettingZoo in TorchRL is tested")


def _time_buffer(rb: TensorDictReplayBuffer, data, batch: int, samples: int) -> dict:
    t = time.perf_counter()
    for i in range(0, data.shape[0], batch):
        rb.extend(data[i : i + batch])
    extend = time.perf_counter() - t
    t = time.perf_counter()
    for _ in range(samples):
        rb.sample()
    sample = time.perf_counter() - t
    return {"extend_ms_per_batch": round(1e3 * extend / -(-data.shape[0] // batch), 2),
            "sample_ms": round(1e3 * sample / samples, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5000)
    parser.add_argument("--batch", type=int, default=500)
    parser.add_argument("--samples", type=int, default=200)
    args = parser.parse_args()
    torch.manual_seed(0)
    t = time.perf_counter()
    collector = Collector(partial(make_mamujoco_env, "HalfCheetah", "2x3", max_episode_steps=100, seed=0), None,
                          frames_per_batch=args.batch, total_frames=args.frames)
    data = torch.cat([d.reshape(-1) for d in collector])
    collector.shutdown()
    out = {"frames": args.frames, "collect_fps": round(args.frames / (time.perf_counter() - t), 1)}
    out["lazy"] = _time_buffer(TensorDictReplayBuffer(storage=LazyTensorStorage(100_000), batch_size=256),
                               data, args.batch, args.samples)
    with tempfile.TemporaryDirectory() as tmp:
        rb = TensorDictReplayBuffer(storage=ZarrStorage(f"{tmp}/m.zarr", 100_000, goal_conditioned=False), batch_size=256)
        out["zarr"] = _time_buffer(rb, data, args.batch, args.samples)
        t = time.perf_counter()
        rb.storage.close()
        out["zarr"]["close_ms"] = round(1e3 * (time.perf_counter() - t), 1)
        t = time.perf_counter()
        reopened = ZarrStorage(f"{tmp}/m.zarr", read_only=True)
        out["zarr"]["reopen_ms"] = round(1e3 * (time.perf_counter() - t), 1)
        rows = reopened[:]
        out["zarr"]["bit_exact"] = all(torch.equal(rows.get(k), data.get(k)) for k in data.keys(True, True))
        out["zarr"]["agents_batch"] = list(rows["agents"].batch_size)
        disk = sum(f.stat().st_size for f in Path(f"{tmp}/m.zarr").rglob("*") if f.is_file())
        out["zarr"]["disk_bytes_per_row"] = round(disk / args.frames, 1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
