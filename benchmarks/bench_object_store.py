"""Commit latency of a ZarrStorage on an S3 object store, by chunk size.

A local moto S3 server (``moto_server`` in a subprocess on 127.0.0.1: no AWS,
no network) holds a FetchPush-v4-shaped store (307 bytes a row, 20 arrays).
For each ``chunk_rows``, the script extends the buffer by ``--batch`` rows at
a time (about one ``commit_interval`` of a fast collector) and times the
``flush()`` that makes them durable: one commit, that is the dirty chunks of
every array (a partial chunk is uploaded whole, again at every commit until
it is full) and then the commit record. It also times reopening the store
(a reader loading every row) and counts the objects.

    python benchmarks/bench_object_store.py                          # 1024 4096 16384 65536
    python benchmarks/bench_object_store.py --chunk-rows 4096 16384 --commits 40

Writes ``outputs/bench/object_store.json``. Latencies against moto on this
machine are upper bounds of the client side plus a local server sharing the
CPU; a real S3 endpoint adds 10-50 ms of network per round trip (one round
trip per commit's parallel uploads, plus one for the record).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import bytes_per_row, fetch_push_transitions  # noqa: E402
from _s3 import moto_subprocess, new_bucket  # noqa: E402
from torchrl.data import TensorDictReplayBuffer  # noqa: E402

from torchrl_robotmem import ZarrStorage  # noqa: E402


def run(server, chunk_rows: int, batch: int, commits: int) -> dict:
    so = server.storage_options
    url = f"s3://{new_bucket(server)}/bench.zarr"
    rows = fetch_push_transitions(batch * commits)
    storage = ZarrStorage(url, batch * commits, chunk_rows=chunk_rows, commit_interval=3600,
                          storage_options=so)
    rb = TensorDictReplayBuffer(storage=storage)
    rb.extend(rows[:batch])  # creates the arrays
    storage.flush()
    lat = []
    for i in range(1, commits):
        rb.extend(rows[i * batch:(i + 1) * batch])
        t0 = time.perf_counter()
        storage.flush()
        lat.append(time.perf_counter() - t0)
    storage.close()
    t0 = time.perf_counter()
    reader = ZarrStorage(url, read_only=True, storage_options=so)
    reopen = time.perf_counter() - t0
    assert len(reader) == batch * commits
    objects = len(server.client().list_objects_v2(Bucket=url.split("/")[2]).get("Contents", []))
    lat.sort()
    return {
        "chunk_rows": chunk_rows,
        "chunk_bytes": chunk_rows * bytes_per_row(rows[:1]),
        "commit_ms_median": 1e3 * statistics.median(lat),
        "commit_ms_p90": 1e3 * lat[int(0.9 * (len(lat) - 1))],
        "commit_ms_max": 1e3 * lat[-1],
        "rows_per_s_committed": batch / statistics.median(lat),
        "reopen_s": reopen,
        "objects": objects,
        "rows": batch * commits,
    }


def main() -> None:
    torch.set_num_threads(1)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--chunk-rows", type=int, nargs="+", default=[1024, 4096, 16384, 65536])
    parser.add_argument("--batch", type=int, default=1000, help="rows per commit")
    parser.add_argument("--commits", type=int, default=25)
    parser.add_argument("--out", default="outputs/bench/object_store.json")
    args = parser.parse_args()
    server = moto_subprocess()
    try:
        results = []
        for c in args.chunk_rows:
            r = run(server, c, args.batch, args.commits)
            results.append(r)
            print(f"chunk_rows={c:6d} ({r['chunk_bytes'] / 2**20:5.2f} MiB)  commit median "
                  f"{r['commit_ms_median']:7.1f} ms  p90 {r['commit_ms_p90']:7.1f} ms  max "
                  f"{r['commit_ms_max']:7.1f} ms  reopen {r['reopen_s']:5.2f} s  objects {r['objects']}",
                  flush=True)
    finally:
        server.stop()
    out = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                       "load_avg": os.getloadavg()},
           "batch": args.batch, "commits": args.commits, "results": results}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
