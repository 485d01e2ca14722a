"""ZarrStorage vs LazyTensorStorage vs LazyMemmapStorage on FetchPush-v4 transitions.

Same process, same data, repetitions interleaved (the order of the storages is
rotated every repetition); one thread (``torch.set_num_threads(1)``); medians.

* extend: ``rb.extend`` in batches of 1000 up to ``--rows`` rows. Foreground rows/s
  counts the time spent inside the extend calls; durable rows/s (ZarrStorage) counts
  from the first extend until ``flush()`` returns after the last one.
* sample: ``rb.sample(256)`` (uniform), and ``HERReplayBuffer.sample(256)``
  (future strategy, her_ratio 0.8) on the same storage; every storage of a
  repetition is filled first, then sampling is timed in interleaved rounds.
* size on disk (Zarr store vs LazyMemmapStorage files), and the time to reopen the
  store in a fresh process (``ZarrStorage(path)``; page cache warm).

Prints a markdown table and writes ``bench_results/storage.json``.

    python benchmarks/bench_storage.py                 # 1M rows, 3 repetitions
    python benchmarks/bench_storage.py --rows 200000   # quick
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torchrl.data import HERReplayBuffer, LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import bytes_per_row, fetch_push_transitions, fetch_reward_fn  # noqa: E402

from torchrl_robotmem.storage import ZarrStorage  # noqa: E402

torch.set_num_threads(1)

BATCH = 1000
SAMPLE_BS = 256
DEFAULT = "ZarrStorage"


def configs(with_variants: bool):
    out = {
        "LazyTensorStorage": lambda d, n: LazyTensorStorage(n),
        "LazyMemmapStorage": lambda d, n: LazyMemmapStorage(n, scratch_dir=d),
        DEFAULT: lambda d, n: ZarrStorage(d, n),
        # the same, with commits written by the background thread instead of the commit worker process
        "Zarr in-process commits": lambda d, n: ZarrStorage(d, n, commit_process=False),
    }
    if with_variants:
        out.update(
            {
                "Zarr blosc level 3": lambda d, n: ZarrStorage(d, n, compressor="blosc", compression_level=3),
                "Zarr zstd level 1": lambda d, n: ZarrStorage(d, n, compressor="zstd", compression_level=1),
                "Zarr zstd level 3": lambda d, n: ZarrStorage(d, n, compressor="zstd", compression_level=3),
                "Zarr no compression": lambda d, n: ZarrStorage(d, n, compressor=None),
                "Zarr chunk_rows=4096": lambda d, n: ZarrStorage(d, n, chunk_rows=4096),
                "Zarr chunk_rows=65536": lambda d, n: ZarrStorage(d, n, chunk_rows=65536),
            }
        )
    return out


def disk_bytes(path: Path) -> tuple[int, int]:
    """(allocated, apparent) bytes of every file under ``path``."""
    alloc = apparent = 0
    for root, _, files in os.walk(path):
        for f in files:
            st = os.stat(os.path.join(root, f))
            alloc += st.st_blocks * 512
            apparent += st.st_size
    return alloc, apparent


def timed_median(fn, n, warmup=3):
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def extend_one(name, make, data, scratch: Path, progress: tqdm):
    """Fills a fresh storage; returns its timings, the storage, its buffer and its path."""
    rows = data.shape[0]
    path = scratch / name.replace(" ", "_").replace("=", "")
    shutil.rmtree(path, ignore_errors=True)
    storage = make(path, rows)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=SAMPLE_BS)
    is_zarr = isinstance(storage, ZarrStorage)
    gc.collect()
    gc.disable()
    fg = 0.0
    t_start = time.perf_counter()
    for lo in range(0, rows, BATCH):
        batch = data[lo : lo + BATCH].copy()  # shallow: the buffer writes "index" into it
        t0 = time.perf_counter()
        rb.extend(batch)
        fg += time.perf_counter() - t0
        progress.update(len(batch))
    t_last = time.perf_counter()
    if is_zarr:
        storage.flush()
    t_durable = time.perf_counter()
    gc.enable()
    res = {
        "extend_fg_s": fg,
        "extend_fg_rows_s": rows / fg,
        "durable_s": t_durable - t_start,
        "durable_rows_s": rows / (t_durable - t_start),
        "flush_after_last_extend_s": t_durable - t_last,
    }
    if type(storage) is not LazyTensorStorage:  # on disk
        res["disk_bytes"], res["disk_apparent_bytes"] = disk_bytes(path)
    if is_zarr:
        res["chunk_rows"] = storage.chunk_rows
        res["codec"] = f"{storage._schema.compressor} level {storage._schema.level}"
    return res, storage, rb, path


def sample_all(bufs: dict, n_samples: int, rounds: int = 10) -> dict:
    """Median sample(256) time of every buffer, rounds interleaved across buffers."""
    names = list(bufs)
    times = {n: [] for n in names}
    per_round = max(1, n_samples // rounds)
    for n in names:  # warm up (HER builds its episode cache here)
        for _ in range(3):
            bufs[n].sample()
    for r in range(rounds):
        for n in names[r % len(names) :] + names[: r % len(names)]:
            rb = bufs[n]
            for _ in range(per_round):
                t0 = time.perf_counter()
                rb.sample()
                times[n].append(time.perf_counter() - t0)
    return {n: 1e3 * statistics.median(t) for n, t in times.items()}


def run_repetition(cfgs: dict, order: list, data, scratch: Path, n_samples: int, keep: str | None, progress):
    """Extends every storage (in ``order``), then times sampling interleaved across them."""
    live, results, kept = {}, {}, None
    for name in order:
        progress.set_postfix_str(name)
        res, storage, rb, path = extend_one(name, cfgs[name], data, scratch, progress)
        # The kernel writes LazyMemmapStorage's dirty pages back lazily; without this the
        # writeback of one contestant runs during the next one's timed loop.
        os.sync()
        live[name] = (storage, rb, path)
        results[name] = res
    progress.set_postfix_str("sampling")
    uniform = sample_all({n: v[1] for n, v in live.items()}, n_samples)
    hers = {
        n: HERReplayBuffer(fetch_reward_fn, storage=v[0], batch_size=SAMPLE_BS, achieved_goal_key=("next", "achieved_goal"))
        for n, v in live.items()
    }
    her = sample_all(hers, max(40, n_samples // 4))
    for name, (storage, _rb, path) in live.items():
        results[name]["sample_ms"] = uniform[name]
        results[name]["her_sample_ms"] = her[name]
        if isinstance(storage, ZarrStorage):
            storage.close()
        if name == keep:
            kept = path
        else:
            shutil.rmtree(path, ignore_errors=True)
    del live, hers
    gc.collect()
    return results, kept


REOPEN_CODE = r"""
import json, sys, time
t0 = time.perf_counter()
import torch
torch.set_num_threads(1)
from torchrl_robotmem.storage import ZarrStorage
t1 = time.perf_counter()
st = ZarrStorage(sys.argv[1])
t2 = time.perf_counter()
n = len(st)
st.close()
t3 = time.perf_counter()
ro = ZarrStorage(sys.argv[1], read_only=True)
t4 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "open_s": t2 - t1, "close_s": t3 - t2,
                  "open_read_only_s": t4 - t3, "rows": n}))
"""


def reopen_times(path: Path, repeats: int):
    outs = []
    for _ in range(repeats):
        out = subprocess.run(
            [sys.executable, "-c", REOPEN_CODE, str(path)], capture_output=True, text=True, check=True
        )
        outs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return {k: statistics.median(o[k] for o in outs) for k in outs[0]}


def _git_state():
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "torchrl_robotmem"], capture_output=True, text=True).stdout.strip()
        return {"head": head, "package_modified": bool(dirty)}
    except OSError:
        return None


def median_of(results, name, key):
    vals = [r[key] for r in results[name] if key in r]
    return statistics.median(vals) if vals else None


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--samples", type=int, default=200, help="timed sample() calls per repetition")
    ap.add_argument("--out", default="bench_results/storage.json")
    ap.add_argument("--scratch", default=None, help="directory for the stores (default: a temp dir)")
    ap.add_argument("--no-variants", action="store_true", help="skip the zstd / no-compression / chunk variants")
    args = ap.parse_args()

    scratch = Path(args.scratch or tempfile.mkdtemp(prefix="bench_storage_"))
    scratch.mkdir(parents=True, exist_ok=True)
    data = fetch_push_transitions(args.rows, seed=0)
    cfgs = configs(not args.no_variants)
    names = list(cfgs)
    results = {n: [] for n in names}
    total = args.rows * args.repeats * len(names)
    kept = None
    with tqdm(total=total, unit="rows", unit_scale=True, mininterval=2.0, desc="extend") as progress:
        for rep in range(args.repeats):
            progress.set_description(f"rep {rep + 1}/{args.repeats}")
            order = names[rep % len(names) :] + names[: rep % len(names)]
            keep = DEFAULT if rep == args.repeats - 1 else None
            res, path = run_repetition(cfgs, order, data, scratch, args.samples, keep, progress)
            for name in names:
                results[name].append(res[name])
            kept = path or kept
    reopen = reopen_times(kept, 3) if kept is not None else None

    def ratio(name, key, base, base_key=None, invert=False):
        """Median over repetitions of the same-repetition ratio name/base."""
        vals = []
        for r, b in zip(results[name], results[base]):
            if key in r and (base_key or key) in b:
                x, y = r[key], b[base_key or key]
                vals.append(y / x if invert else x / y)
        return statistics.median(vals) if vals else None

    summary = {}
    for name in names:
        s = {k: median_of(results, name, k) for k in results[name][0] if k != "codec"}
        if "codec" in results[name][0]:
            s["codec"] = results[name][0]["codec"]
        s["fg_vs_memmap"] = ratio(name, "extend_fg_rows_s", "LazyMemmapStorage")
        s["durable_vs_memmap"] = ratio(name, "durable_rows_s", "LazyMemmapStorage", "extend_fg_rows_s")
        s["sample_speed_vs_lts"] = ratio(name, "sample_ms", "LazyTensorStorage", invert=True)
        s["her_speed_vs_lts"] = ratio(name, "her_sample_ms", "LazyTensorStorage", invert=True)
        if s.get("disk_bytes"):
            s["disk_vs_memmap"] = ratio(name, "disk_bytes", "LazyMemmapStorage")
        summary[name] = s

    bpr = bytes_per_row(data)
    print(f"\n{args.rows:,} FetchPush-v4 transitions ({bpr} B each, {bpr * args.rows / 2**20:.0f} MiB), "
          f"extend in batches of {BATCH}, sample({SAMPLE_BS}); median of {args.repeats} interleaved "
          f"repetitions; ratios are medians of same-repetition ratios (durable: vs LazyMemmapStorage's "
          f"extend rate); torch threads=1; {os.cpu_count()} CPUs.\n")
    print("| storage | extend rows/s (foreground) | vs memmap | durable rows/s | vs memmap | "
          "sample(256) ms | speed vs LTS | HER sample(256) ms | speed vs LTS | disk MiB | vs memmap |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        s = summary[name]
        zarr_like = name not in ("LazyTensorStorage", "LazyMemmapStorage")
        dur = f"{s['durable_rows_s']:,.0f}" if zarr_like else "n/a"
        durr = f"{s['durable_vs_memmap']:.2f}x" if zarr_like else ""
        disk = f"{s['disk_bytes'] / 2**20:,.0f}" if s.get("disk_bytes") else "RAM"
        diskr = f"{s['disk_vs_memmap']:.2f}x" if s.get("disk_vs_memmap") else ""
        label = f"{name} default ({s['codec']}, chunk_rows={s['chunk_rows']:.0f})" if name == DEFAULT else name
        print(f"| {label} | {s['extend_fg_rows_s']:,.0f} | {s['fg_vs_memmap']:.2f}x | {dur} | {durr} | "
              f"{s['sample_ms']:.2f} | {s['sample_speed_vs_lts']:.2f}x | {s['her_sample_ms']:.2f} | "
              f"{s['her_speed_vs_lts']:.2f}x | {disk} | {diskr} |")
    if reopen:
        print(f"\nReopen {args.rows:,}-row store in a fresh process (median of 3, page cache warm): "
              f"ZarrStorage(path) {reopen['open_s']:.2f} s (writable), read_only {reopen['open_read_only_s']:.2f} s; "
              f"imports {reopen['import_s']:.2f} s.")
    for name in [n for n in (DEFAULT, "Zarr in-process commits") if n in results]:
        per_rep = ", ".join(
            f"{r['extend_fg_rows_s'] / 1e3:,.0f}k ({r['extend_fg_rows_s'] / m['extend_fg_rows_s']:.2f}x memmap)"
            for r, m in zip(results[name], results["LazyMemmapStorage"])
        )
        print(f"\n{name}, foreground rows/s per repetition (same-repetition ratio): {per_rep}")
    worst = min(r["extend_fg_rows_s"] / m["extend_fg_rows_s"] for r, m in zip(results[DEFAULT], results["LazyMemmapStorage"]))
    d = summary[DEFAULT]
    targets = {
        "foreground >= 0.8x memmap in every repetition": worst >= 0.8,
        "durable >= 0.25x memmap": d["durable_vs_memmap"] >= 0.25,
        "sample >= 1.0x LazyTensorStorage speed": d["sample_speed_vs_lts"] >= 1.0,
        "HER sample >= 1.0x LazyTensorStorage speed": d.get("her_speed_vs_lts", 0) >= 1.0,
        "disk <= 0.8x memmap": d.get("disk_vs_memmap", 9) <= 0.8,
        "reopen <= 3 s": reopen is not None and reopen["open_s"] <= 3.0,
    }
    print("\nTargets (default ZarrStorage): " + "; ".join(f"{k}: {'met' if v else 'MISSED'}" for k, v in targets.items()))

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w") as f:
        json.dump(
            {
                "rows": args.rows,
                "git": _git_state(),
                "repeats": args.repeats,
                "batch": BATCH,
                "sample_batch": SAMPLE_BS,
                "bytes_per_row": bpr,
                "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                            "python": platform.python_version(), "torch": torch.__version__},
                "summary": summary,
                "reopen": reopen,
                "targets": targets,
                "runs": results,
            },
            f,
            indent=1,
        )
    print(f"\nwrote {out}")
    shutil.rmtree(scratch, ignore_errors=True) if args.scratch is None else None


if __name__ == "__main__":
    main()
