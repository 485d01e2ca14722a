"""A memory larger than RAM (issue 41): 100M rows written, closed, reopened, sampled and recalled.

Run once, by hand (about an hour and 35 GB of disk at 100M rows), not in ``make test``.
FetchReach-shaped rows of incompressible noise (``observation`` f32[10],
``achieved_goal`` / ``desired_goal`` f32[3], ``action`` f32[4], ``done`` / ``terminated``
/ ``truncated`` bool[1], and under ``next``: ``observation``, ``achieved_goal``,
``desired_goal``, ``reward`` f32[1], the three flags), written into a ``ZarrStorage``
**without a declared capacity** (``ZarrStorage(path)``: it grows as rows arrive; ``--capacity``
declares one instead). Every step runs in a fresh process:

1. **write**: ``TensorDictReplayBuffer.extend`` in batches of ``--batch`` rows (noise made
   outside the timer), then ``flush()`` and ``close()``; foreground and durable rows/s, the
   store's bytes on disk (chunks, row file);
2. **open**: ``ZarrStorage(path, read_only=True)`` with a warm page cache, with the store's
   pages dropped (cold), and cold inside a memory cgroup of ``--cgroup-fraction`` of the rows'
   uncompressed size (``bench_row_tier.Cgroup``); open seconds, resident memory after the open
   and after 1,000 gathers of 256 rows (what ``sample(256)`` reads), the gathers' median time;
   then a writable open (``ZarrStorage(path)``);
3. **recall**: a ``GoalIndex`` over every row's ``("next", "achieved_goal")``: build time, its
   resident memory and ``nbytes()``, top-5 per-query time (one query, and 256 at once); the
   top-5 of ``--exact`` queries checked against a brute-force scan of the whole column.

Prints a markdown table and writes ``--out`` (JSON, default ``bench_results/scale_<rows>.json``),
step by step as each finishes.

    python benchmarks/bench_scale.py --rows 2000000 --scratch /tmp/scale       # a check, a minute
    python benchmarks/bench_scale.py --rows 100000000 --scratch /tmp/scale     # the run
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_row_tier import Cgroup, disk_bytes, drop_cache  # noqa: E402 - the sibling script's helpers

ROOT = Path(__file__).resolve().parents[1]
GATHERS = 1000


def rss_mb() -> dict:
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(("VmRSS", "RssAnon", "RssFile", "VmHWM")):
                k, v = line.split(":")
                out[k] = int(v.split()[0]) / 1024
    return out


def part_write(path: str, rows: int, batch: int, capacity: bool, seed: int) -> dict:
    import torch
    from tensordict import TensorDict
    from torchrl.data import TensorDictReplayBuffer

    from torchrl_robotmem.storage import ZarrStorage

    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(seed)

    def noise(n):
        def f(*s):
            return torch.rand(n, *s, generator=gen)

        def b():
            return torch.rand(n, 1, generator=gen) < 0.02

        return TensorDict({
            "observation": f(10), "achieved_goal": f(3), "desired_goal": f(3), "action": f(4),
            "done": b(), "terminated": b(), "truncated": b(),
            "next": {"observation": f(10), "achieved_goal": f(3), "desired_goal": f(3), "reward": f(1),
                     "done": b(), "terminated": b(), "truncated": b()},
        }, [n])

    shutil.rmtree(path, ignore_errors=True)
    storage = ZarrStorage(path, rows if capacity else None, env="FetchReach-v4")
    rb = TensorDictReplayBuffer(storage=storage, batch_size=256)
    fg = gen_s = 0.0
    t_start = time.perf_counter()
    last_note = t_start
    for lo in range(0, rows, batch):
        t0 = time.perf_counter()
        data = noise(min(batch, rows - lo))
        t1 = time.perf_counter()
        rb.extend(data)
        t2 = time.perf_counter()
        fg += t2 - t1
        gen_s += t1 - t0
        if t2 - last_note > 30:
            last_note = t2
            print(f"write: {lo + len(data):,} rows, {fg:.0f} s in extend, {t2 - t_start:.0f} s in all", file=sys.stderr,
                  flush=True)
    t_last = time.perf_counter()
    storage.flush()
    t_durable = time.perf_counter()
    storage.close()
    durable = t_durable - t_start - gen_s
    return {"rows": rows, "bytes_per_row": sum(v[0].numel() * v.element_size() for v in data.values(True, True)),
            "extend_fg_s": fg, "extend_fg_rows_s": rows / fg, "durable_s": durable, "durable_rows_s": rows / durable,
            "flush_after_last_extend_s": t_durable - t_last, "noise_s": gen_s, "peak_rss_mb": rss_mb()["VmHWM"]}


def part_open(path: str, writable: bool, seed: int) -> dict:
    import torch

    torch.set_num_threads(1)
    from torchrl_robotmem.storage import ZarrStorage

    before = rss_mb()
    t = time.perf_counter()
    storage = ZarrStorage(path, read_only=not writable)
    open_s = time.perf_counter() - t
    after_open = rss_mb()
    n = len(storage)
    gen = torch.Generator().manual_seed(seed)
    times = []
    for _ in range(GATHERS):
        idx = torch.randint(n, (256,), generator=gen)
        t = time.perf_counter()
        storage.get(idx)
        times.append(time.perf_counter() - t)
    after = rss_mb()
    storage.close()
    times.sort()
    return {"open_s": open_s, "len": n, "gather256_median_ms": 1e3 * times[len(times) // 2],
            "gather256_mean_ms": 1e3 * sum(times) / len(times),
            "rss_open_mb": after_open["VmRSS"] - before["VmRSS"], "rss_after_gathers_mb": after["VmRSS"] - before["VmRSS"],
            "rss_anon_after_gathers_mb": after["RssAnon"] - before["RssAnon"], "rss_total_mb": after["VmRSS"]}


def part_recall(path: str, exact: int, seed: int) -> dict:
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from torchrl_robotmem.goal_index import GoalIndex
    from torchrl_robotmem.storage import ZarrStorage

    storage = ZarrStorage(path, read_only=True)
    before = rss_mb()
    index = GoalIndex(storage)
    c0, t0 = time.process_time(), time.perf_counter()
    index.refresh()
    build_s, build_cpu = time.perf_counter() - t0, time.process_time() - c0
    built = rss_mb()
    n = len(storage)
    goals = storage._storage["next", "achieved_goal"][:n]  # the mapped column (what the index snapshots)
    rng = np.random.default_rng(seed)
    queries = goals[torch.from_numpy(rng.integers(0, n, 256))].numpy().astype(np.float64)
    queries += rng.normal(size=queries.shape) * 0.01
    qt = torch.from_numpy(queries)
    one = []
    for i in range(256):
        t = time.perf_counter()
        index.search(qt[i], 5)
        one.append(time.perf_counter() - t)
    one.sort()
    t = time.perf_counter()
    d, p, _ = index.search(qt, 5)
    batch_s = time.perf_counter() - t
    # brute force over the whole column, in blocks (every stored goal is looked at)
    q = queries[:exact].astype(np.float32)
    best_d = np.full((exact, 5), np.inf, np.float32)
    best_p = np.zeros((exact, 5), np.int64)
    t = time.perf_counter()
    block = 5_000_000
    scan = storage.scanning()  # a scan: the row file's readahead on
    scan.__enter__()
    for lo in range(0, n, block):
        g = goals[lo:lo + block].numpy()
        dist = ((g[None, :, :] - q[:, None, :]) ** 2).sum(-1)
        part = np.argpartition(dist, 5, axis=1)[:, :5] if dist.shape[1] > 5 else np.tile(np.arange(dist.shape[1]), (exact, 1))
        cand_d = np.concatenate([best_d, np.take_along_axis(dist, part, 1)], 1)
        cand_p = np.concatenate([best_p, part + lo], 1)
        order = np.argsort(cand_d, 1)[:, :5]
        best_d, best_p = np.take_along_axis(cand_d, order, 1), np.take_along_axis(cand_p, order, 1)
    scan.__exit__(None, None, None)
    scan_s = time.perf_counter() - t
    got_d = d[:exact].numpy() ** 2 if bool((d >= 0).all()) else None
    same = [bool(set(p[i].tolist()) == set(best_p[i].tolist())
                 or np.allclose(np.sort(got_d[i]), np.sort(best_d[i]), rtol=1e-4)) for i in range(exact)]
    return {"rows": n, "build_s": build_s, "build_cpu_s": build_cpu, "index_rss_mb": built["VmRSS"] - before["VmRSS"],
            "index_anon_mb": built["RssAnon"] - before["RssAnon"], "peak_rss_mb": built["VmHWM"],
            "index_nbytes_mb": index.nbytes() / 2**20 if hasattr(index, "nbytes") else None,
            "query1_median_ms": 1e3 * one[len(one) // 2], "query256_ms": 1e3 * batch_s,
            "exact_checked": exact, "exact_equal": sum(same), "brute_force_scan_s": scan_s}


PARTS = {"write": part_write, "open": part_open, "recall": part_recall}


def child(part: str, *args, prefix: list[str] | None = None, timeout: float | None = None) -> dict:
    cmd = (prefix or []) + [sys.executable, __file__, "--part", part, "--args", json.dumps(args)]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    t = time.perf_counter()
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"failed": f"timed out after {timeout} s"}
    if out.returncode != 0:
        return {"failed": f"exit {out.returncode}", "stderr_tail": out.stderr[-1500:], "wall_s": time.perf_counter() - t}
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["wall_s"] = time.perf_counter() - t
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", type=int, default=100_000_000)
    ap.add_argument("--batch", type=int, default=10_000, help="rows per extend")
    ap.add_argument("--capacity", action="store_true", help="declare max_size=rows (default: a memory that grows)")
    ap.add_argument("--scratch", help="directory for the store (required; kept with --keep)")
    ap.add_argument("--keep", action="store_true", help="keep the store; reuse it if it is there (no write)")
    ap.add_argument("--cgroup-fraction", type=float, default=0.25)
    ap.add_argument("--cgroup-timeout", type=float, default=1800, help="seconds the open and its gathers may take there")
    ap.add_argument("--steps", default="open_warm,open_cold,open_cgroup,open_writable,recall",
                    help="which steps after the write (comma-separated)")
    ap.add_argument("--exact", type=int, default=8, help="queries checked against a brute-force scan")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    ap.add_argument("--part", help=argparse.SUPPRESS)
    ap.add_argument("--args", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.part:
        print(json.dumps(PARTS[a.part](*json.loads(a.args))))
        return
    if not a.scratch:
        ap.error("--scratch DIR is required (the store is written there)")
    path = str(Path(a.scratch) / "memory.zarr")
    out = Path(a.out or ROOT / "bench_results" / f"scale_{a.rows}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    steps = set(a.steps.split(","))
    res: dict = {"rows": a.rows, "rev": rev, "python": platform.python_version(), "cpus": os.cpu_count(),
                 "ram_bytes": os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"),
                 "command": " ".join([Path(sys.executable).name, *sys.argv])}

    def save(step: str, value: dict) -> None:
        res[step] = value
        out.write_text(json.dumps(res, indent=1))
        print(f"{step}: {json.dumps(value)}", flush=True)

    if not (a.keep and os.path.isdir(path)):
        os.makedirs(a.scratch, exist_ok=True)
        save("write", child("write", path, a.rows, a.batch, a.capacity, a.seed))
        if "failed" in res["write"]:
            sys.exit(f"the write failed: {res['write']}")
    rows_bytes = disk_bytes(Path(path) / "_rows")
    save("disk", {"store_bytes": disk_bytes(Path(path)), "row_file_bytes": rows_bytes,
                  "chunk_bytes": disk_bytes(Path(path)) - rows_bytes})
    if "open_warm" in steps:
        save("open_warm", child("open", path, False, a.seed))
    if "open_cold" in steps:
        drop_cache(Path(path))
        save("open_cold", child("open", path, False, a.seed))
    limit = int(rows_bytes * a.cgroup_fraction)
    cg = Cgroup(limit, "scale") if "open_cgroup" in steps else None
    if cg is None:
        pass
    elif cg.method is None:
        save("open_cgroup", {"skipped": cg.reason, "limit_bytes": limit})
    else:
        try:
            drop_cache(Path(path))
            r = child("open", path, False, a.seed, prefix=cg.prefix(), timeout=a.cgroup_timeout)
            r.update(limit_bytes=limit, method=cg.method, events=cg.events())
            save("open_cgroup", r)
        finally:
            cg.remove()
    if "open_writable" in steps:
        save("open_writable", child("open", path, True, a.seed))
    if "recall" in steps:
        save("recall", child("recall", path, a.exact, a.seed))
    if not a.keep:
        shutil.rmtree(a.scratch, ignore_errors=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
