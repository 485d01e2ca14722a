"""The row tier (issue 41): write, open, resident memory and sample of ``ZarrStorage`` against ``LazyMemmapStorage``.

Fetch-shaped rows of incompressible noise (``observation`` f32[25], ``achieved_goal`` /
``desired_goal`` f32[3], ``action`` f32[4], ``done`` / ``terminated`` / ``truncated``
bool[1], and under ``next``: ``observation``, ``achieved_goal``, ``desired_goal``,
``reward`` f32[1], ``done`` / ``terminated`` / ``truncated``; 274 bytes a row), ``--rows``
of them (1M by default). Every measurement runs in a fresh process (``sys.executable``),
contestants interleaved and their order rotated every repetition; medians, and
ratios taken within a repetition.

1. **Write**: ``TensorDictReplayBuffer.extend`` in batches of 1000 rows (the noise is
   generated outside the timers). Foreground rows/s counts the time inside the extend
   calls. Durable rows/s runs from the first extend until the rows survive a SIGKILL
   of the writer: ``ZarrStorage.flush()`` returned; for ``LazyMemmapStorage`` (its rows
   are in ``MAP_SHARED`` pages from the extend on) ``storage.dumps(dir)`` returned, which
   writes the metadata TorchRL needs to reload it. ``fsync`` rows/s adds an ``os.fsync``
   of every file of the store and of its directories (survives a power loss), for both.
   ``LazyTensorStorage`` (RAM only) gives the foreground reference.
2. **Open**, each in a fresh process, imports not counted (the same modules are imported
   before every kind): ``ZarrStorage(path, read_only=True)``, ``ZarrStorage(path)``,
   ``LazyMemmapStorage(n, scratch_dir=dir)`` + ``loads(dir)`` (TorchRL's reload, which maps
   the files; the reference of every ratio), ``TensorDict.load_memmap(dir)``, and
   ``LazyTensorStorage(n)`` + ``loads(dir)`` (a copy in RAM). Recorded: open seconds;
   resident memory (``/proc/self/status`` VmRSS, RssAnon, RssFile) after the imports,
   after the open and after 1,000 gathers ``storage.get(torch.randint(len, (256,)))``
   (what ``sample(256)`` reads), plus that of the opener's child processes (the commit
   worker of a writable ``ZarrStorage``); the median time of those 1,000 gathers and of
   ``--samples`` more (warm page cache). ``--cold`` adds the same opens after dropping the
   store's pages from the page cache (``posix_fadvise(DONTNEED)`` on every file).
3. ``--cgroup``: the read-only opens (Zarr, memmap) inside a memory cgroup of a quarter
   of the rows' uncompressed size (``--cgroup-bytes`` to change it): ``systemd-run --user
   --scope -p MemoryMax=``, else a cgroup v2 or v1 memory directory made beside this
   process's own; where none can be made, the reason is recorded instead. The store's
   pages are dropped from the page cache first (a page is charged to the cgroup that
   reads it first), so the rows the process touches count against its limit. The
   limit covers the interpreter and its imports too (about 0.3-0.5 GB with torch).

Prints markdown tables and writes ``--out`` (JSON, default ``bench_results/row_tier_<rows>.json``).

    python benchmarks/bench_row_tier.py --quick                      # 100k rows, 1 repetition
    python benchmarks/bench_row_tier.py --rows 1000000 --cgroup --rev HEAD
    python benchmarks/bench_row_tier.py --rows 10000000 --repeat 3 --cgroup --scratch /tmp/bench41

``--rev REV`` times the package as committed at REV (``git archive``, unpacked under the
scratch directory), so that edits in progress in the checkout are not measured;
``--package DIR`` a directory that holds another ``torchrl_robotmem``.
"""
from __future__ import annotations

import argparse
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

from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
BATCH = 1000
SAMPLE_BS = 256
GATHERS = 1000

# -- the children -------------------------------------------------------------------------------

COMMON = r"""
import json, os, sys, time
import torch
torch.set_num_threads(1)
from tensordict import TensorDict
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
import torchrl_robotmem
from torchrl_robotmem.storage import ZarrStorage

def status():
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            k, _, v = line.partition(":")
            if k in ("VmRSS", "RssAnon", "RssFile", "RssShmem", "VmHWM"):
                out[k] = int(v.split()[0]) * 1024
    return out

def children_rss():
    pids, total = [], 0
    for tid in os.listdir("/proc/self/task"):
        try:
            pids += open(f"/proc/self/task/{tid}/children").read().split()
        except OSError:
            pass
    while pids:
        pid = pids.pop()
        try:
            for line in open(f"/proc/{pid}/status"):
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
            for tid in os.listdir(f"/proc/{pid}/task"):
                pids += open(f"/proc/{pid}/task/{tid}/children").read().split()
        except OSError:
            pass
    return total

def fsync_tree(path):
    for root, dirs, files in os.walk(path):
        for name in files:
            fd = os.open(os.path.join(root, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        fd = os.open(root, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
"""

WRITE_CHILD = COMMON + r"""
import gc, shutil
kind, path, rows, seed = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
gen = torch.Generator().manual_seed(seed)

def noise(n):
    f = lambda *s: torch.rand(n, *s, generator=gen)
    b = lambda: torch.rand(n, 1, generator=gen) < 0.5
    return TensorDict({
        "observation": f(25), "achieved_goal": f(3), "desired_goal": f(3), "action": f(4),
        "done": b(), "terminated": b(), "truncated": b(),
        "next": {"observation": f(25), "achieved_goal": f(3), "desired_goal": f(3), "reward": f(1),
                 "done": b(), "terminated": b(), "truncated": b()},
    }, [n])

shutil.rmtree(path, ignore_errors=True)
if kind == "zarr":
    storage = ZarrStorage(path, rows)
elif kind == "memmap":
    storage = LazyMemmapStorage(rows, scratch_dir=path)
else:
    storage = LazyTensorStorage(rows)
rb = TensorDictReplayBuffer(storage=storage, batch_size=256)
batches = [noise(min(BATCH, rows)) for _ in range(2)]  # warm the generator's code path
fg = 0.0
gc.collect()
gc.disable()
t_start = time.perf_counter()
gen_s = 0.0
for lo in range(0, rows, BATCH):
    t0 = time.perf_counter()
    batch = noise(min(BATCH, rows - lo))
    t1 = time.perf_counter()
    rb.extend(batch)
    fg += time.perf_counter() - t1
    gen_s += t1 - t0
t_last = time.perf_counter()
if kind == "zarr":
    storage.flush()
elif kind == "memmap":
    from pathlib import Path
    storage.dumps(Path(path))
t_durable = time.perf_counter()
if kind != "tensor":
    fsync_tree(path)
t_fsync = time.perf_counter()
gc.enable()
res = {"rows": len(storage), "bytes_per_row": sum(v[0].numel() * v.element_size() for v in batch.values(True, True)),
       "extend_fg_s": fg, "extend_fg_rows_s": rows / fg, "noise_s": gen_s}
if kind != "tensor":
    # the noise is generated inside the durable window; it is taken out of it
    durable = t_durable - t_start - gen_s
    res.update({"durable_s": durable, "durable_rows_s": rows / durable,
                "after_last_extend_s": t_durable - t_last, "fsync_s": t_fsync - t_durable,
                "durable_fsync_rows_s": rows / (durable + t_fsync - t_durable)})
    if kind == "zarr":
        storage.close()
res["package"] = torchrl_robotmem.__file__
print(json.dumps(res))
"""
WRITE_CHILD = WRITE_CHILD.replace("BATCH", str(BATCH))

OPEN_CHILD = COMMON + r"""
kind, path, rows, samples = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
from pathlib import Path
before = status()
t = time.perf_counter()
if kind == "zarr-ro":
    s = ZarrStorage(path, read_only=True)
elif kind == "zarr-rw":
    s = ZarrStorage(path)
elif kind == "memmap":
    s = LazyMemmapStorage(rows, scratch_dir=path)
    s.loads(Path(path))
elif kind == "load_memmap":
    s = TensorDict.load_memmap(path)
elif kind == "tensor":
    s = LazyTensorStorage(rows)
    s.loads(Path(path))
open_s = time.perf_counter() - t
n = len(s)
after_open = status()
after_open_children = children_rss()
get = (lambda i: s[i]) if kind == "load_memmap" else s.get
g = torch.Generator().manual_seed(1)
first = []
for _ in range(GATHERS):
    idx = torch.randint(n, (256,), generator=g)
    t0 = time.perf_counter()
    get(idx)
    first.append(time.perf_counter() - t0)
after_gathers = status()
after_gathers_children = children_rss()
warm = []
for _ in range(samples):
    idx = torch.randint(n, (256,), generator=g)
    t0 = time.perf_counter()
    get(idx)
    warm.append(time.perf_counter() - t0)
first.sort()
warm.sort()
print(json.dumps({"open_s": open_s, "rows": n, "before": before, "after_open": after_open,
                  "after_gathers": after_gathers, "children_after_open": after_open_children,
                  "children_after_gathers": after_gathers_children,
                  "gathers_ms": 1e3 * first[len(first) // 2], "gathers_total_s": sum(first),
                  "sample_warm_ms": 1e3 * warm[len(warm) // 2], "package": torchrl_robotmem.__file__}), flush=True)
if kind.startswith("zarr"):
    s.close()
"""
OPEN_CHILD = OPEN_CHILD.replace("GATHERS", str(GATHERS))

WRITE_KINDS = ("zarr", "memmap", "tensor")
WRITE_LABELS = {"zarr": "`ZarrStorage`", "memmap": "`LazyMemmapStorage`", "tensor": "`LazyTensorStorage` (RAM)"}
OPEN_KINDS = ("zarr-ro", "zarr-rw", "memmap", "load_memmap", "tensor")
OPEN_LABELS = {"zarr-ro": "`ZarrStorage(path, read_only=True)`", "zarr-rw": "`ZarrStorage(path)`",
               "memmap": "`LazyMemmapStorage` + `loads` (maps)", "load_memmap": "`TensorDict.load_memmap`",
               "tensor": "`LazyTensorStorage` + `loads` (RAM copy)"}


# -- running them --------------------------------------------------------------------------------

class Runner:
    def __init__(self, scratch: Path, package: str | None):
        self.scratch, self.package = scratch, package
        self.env = dict(os.environ)
        if package:
            self.env["PYTHONPATH"] = os.pathsep.join(filter(None, [package, self.env.get("PYTHONPATH")]))

    def cmd(self, code: str, *args) -> list[str]:
        return [sys.executable, "-c", code, *map(str, args)]

    def parse(self, out: subprocess.CompletedProcess) -> dict:
        if out.returncode != 0:
            raise RuntimeError(f"child failed ({out.returncode}):\n{out.stderr[-3000:]}")
        res = json.loads(out.stdout.strip().splitlines()[-1])
        if self.package and not Path(res["package"]).resolve().is_relative_to(Path(self.package).resolve()):
            raise RuntimeError(f"--package {self.package}: the child imported {res['package']} instead")
        return res

    def run(self, code: str, *args, prefix: list[str] | None = None, check: bool = True, timeout: float | None = None):
        # run outside the checkout: `python -c` puts the working directory first on sys.path
        try:
            out = subprocess.run((prefix or []) + self.cmd(code, *args), capture_output=True, text=True,
                                 env=self.env, cwd=self.scratch, timeout=timeout)
        except subprocess.TimeoutExpired as e:  # the child is killed; what it printed is kept
            stdout = e.stdout.decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
            stderr = e.stderr.decode() if isinstance(e.stderr, bytes) else (e.stderr or "")
            out = subprocess.CompletedProcess(e.cmd, "timeout", stdout, stderr)
        return self.parse(out) if check else out


def disk_bytes(path: Path) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            total += os.stat(os.path.join(root, f)).st_blocks * 512
    return total


def drop_cache(path: Path) -> None:
    """Drops ``path``'s pages from the page cache (written back first; clean pages only go)."""
    os.sync()
    for root, _, files in os.walk(path):
        for f in files:
            fd = os.open(os.path.join(root, f), os.O_RDONLY)
            try:
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            finally:
                os.close(fd)


# -- memory cgroup -------------------------------------------------------------------------------

class Cgroup:
    """A way to run a command under a memory limit, or the reason there is none (``self.reason``)."""

    def __init__(self, limit: int, tag: str):
        self.limit, self.method, self.dir, self.reason, self.tried = limit, None, None, None, []
        if shutil.which("systemd-run"):
            out = subprocess.run(["systemd-run", "--user", "--scope", "--quiet", "-p", f"MemoryMax={limit}", "true"],
                                 capture_output=True, text=True)
            if out.returncode == 0:
                self.method = "systemd-run --user --scope"
                return
            self.tried.append(f"systemd-run: {(out.stderr or out.stdout).strip()[:200]}")
        else:
            self.tried.append("systemd-run: not installed")
        for version, mount in (("v2", "/sys/fs/cgroup"), ("v2", "/sys/fs/cgroup/unified"), ("v1", "/sys/fs/cgroup/memory")):
            try:
                parent = self._own(version, mount)
                d = Path(parent) / f"bench41_{tag}_{os.getpid()}"
                d.mkdir()
                try:
                    if version == "v2":
                        (d / "memory.max").write_text(str(limit))
                        (d / "memory.swap.max").write_text("0") if (d / "memory.swap.max").exists() else None
                    else:
                        (d / "memory.limit_in_bytes").write_text(str(limit))
                except OSError:
                    d.rmdir()
                    raise
                self.method, self.dir, self.version = f"cgroup {version} ({d})", d, version
                return
            except (OSError, ValueError) as e:
                self.tried.append(f"cgroup {version} under {mount}: {e}")
        self.reason = "; ".join(self.tried)

    @staticmethod
    def _own(version: str, mount: str) -> str:
        for line in Path("/proc/self/cgroup").read_text().splitlines():
            _, ctrl, rel = line.split(":", 2)
            if (version == "v2" and ctrl == "") or (version == "v1" and "memory" in ctrl.split(",")):
                d = mount + rel
                if version == "v2" and "memory" not in Path(mount, "cgroup.controllers").read_text().split():
                    raise ValueError(f"{mount}: no memory controller")
                if not os.path.isdir(d):
                    raise ValueError(f"{d} is not there")
                return d
        raise ValueError(f"no {version} memory line in /proc/self/cgroup")

    def prefix(self) -> list[str]:
        if self.method.startswith("systemd-run"):
            return ["systemd-run", "--user", "--scope", "--quiet", "-p", f"MemoryMax={self.limit}", "-p", "MemorySwapMax=0"]
        return ["sh", "-c", f'echo $$ > {self.dir}/cgroup.procs && exec "$@"', "sh"]

    def events(self) -> dict:
        if self.dir is None:
            return {}
        out = {}
        if self.version == "v1":
            for name in ("memory.max_usage_in_bytes", "memory.failcnt"):
                out[name] = int((self.dir / name).read_text())
            for line in (self.dir / "memory.oom_control").read_text().splitlines():
                k, v = line.split()
                out[k] = int(v)
        else:
            for line in (self.dir / "memory.events").read_text().splitlines():
                k, v = line.split()
                out[k] = int(v)
            if (self.dir / "memory.peak").exists():
                out["memory.peak"] = int((self.dir / "memory.peak").read_text())
        return out

    def reset(self) -> None:
        if self.dir is not None and self.version == "v1":
            for name in ("memory.max_usage_in_bytes", "memory.failcnt"):
                try:
                    (self.dir / name).write_text("0")
                except OSError:
                    pass

    def remove(self) -> None:
        if self.dir is not None:
            for _ in range(50):
                try:
                    self.dir.rmdir()
                    return
                except OSError:
                    time.sleep(0.1)


def cgroup_runs(runner: Runner, zpath: Path, mpath: Path, rows: int, limit: int, samples: int, timeout: float) -> dict:
    cg = Cgroup(limit, str(rows))
    res = {"limit_bytes": limit, "method": cg.method, "tried": cg.tried, "timeout_s": timeout}
    if cg.method is None:
        res["skipped"] = cg.reason
        return res
    try:
        for kind in ("zarr-ro", "memmap"):
            cg.reset()
            before = cg.events()
            path = mpath if kind == "memmap" else zpath
            # pages already cached are charged to the cgroup that read them first, not to this one
            drop_cache(path)
            t = time.perf_counter()
            out = runner.run(OPEN_CHILD, kind, path, rows, samples, prefix=cg.prefix(), check=False, timeout=timeout)
            r = {"returncode": out.returncode, "wall_s": time.perf_counter() - t, "events": cg.events(),
                 "events_before": before}
            r["oom_kills"] = r["events"].get("oom_kill", 0) - before.get("oom_kill", 0)  # the counters are cumulative
            if out.returncode == 0:
                r.update(runner.parse(out))
            else:
                r["stderr_tail"] = out.stderr[-600:]
                r["killed"] = out.returncode in (-9, 137)
                if out.returncode == "timeout" and out.stdout.strip():  # opened, then too slow to finish sampling
                    r["partial"] = out.stdout.strip().splitlines()[-1]
            res[kind] = r
    finally:
        cg.remove()
    return res


# -- report --------------------------------------------------------------------------------------

def med(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def mb(x):
    return f"{x / 1e6:,.0f}" if x is not None else "-"


def summarize_writes(writes: dict) -> dict:
    summary = {}
    for kind, runs in writes.items():
        s = {k: med([r.get(k) for r in runs]) for k in runs[0] if isinstance(runs[0][k], (int, float))}
        for key in ("extend_fg_rows_s", "durable_rows_s", "durable_fsync_rows_s"):
            vals = [r[key] / m[key] for r, m in zip(runs, writes["memmap"]) if key in r and key in m]
            s[f"{key}_vs_memmap"] = med(vals)
        summary[kind] = s
    return summary


def summarize_opens(opens: dict) -> dict:
    summary = {}
    for kind, runs in opens.items():
        s = {"open_s": med([r["open_s"] for r in runs]), "gathers_ms": med([r["gathers_ms"] for r in runs]),
             "sample_warm_ms": med([r["sample_warm_ms"] for r in runs])}
        for stage in ("before", "after_open", "after_gathers"):
            for k in ("VmRSS", "RssAnon", "RssFile", "VmHWM"):
                s[f"{stage}.{k}"] = med([r[stage].get(k) for r in runs])
        for stage in ("after_open", "after_gathers"):
            s[f"{stage}.delta"] = med([r[stage]["VmRSS"] - r["before"]["VmRSS"] for r in runs])
            s[f"{stage}.children"] = med([r[f"children_{stage}"] for r in runs])
        summary[kind] = s
    ref = opens.get("memmap")
    for kind, runs in opens.items():
        if not ref:
            break
        s = summary[kind]
        pairs = list(zip(runs, ref))
        s["open_vs_memmap"] = med([r["open_s"] / m["open_s"] for r, m in pairs])
        s["rss_after_gathers_vs_memmap"] = med([r["after_gathers"]["VmRSS"] / m["after_gathers"]["VmRSS"] for r, m in pairs])
        s["rss_delta_after_gathers_vs_memmap"] = med(
            [(r["after_gathers"]["VmRSS"] - r["before"]["VmRSS"]) / max(1, m["after_gathers"]["VmRSS"] - m["before"]["VmRSS"])
             for r, m in pairs])
        s["sample_speed_vs_memmap"] = med([m["sample_warm_ms"] / r["sample_warm_ms"] for r, m in pairs])
    return summary


def print_tables(meta: dict, wsum: dict, osum: dict, cold: dict | None, cg: dict | None) -> None:
    rows, bpr = meta["rows"], meta["bytes_per_row"]
    print(f"\n{rows:,} Fetch-shaped rows of noise ({bpr} B each, {rows * bpr / 1e6:,.0f} MB uncompressed), "
          f"package {meta['package_label']}, {meta['cpus']} CPUs, torch threads 1, median of {meta['repeat']} "
          f"interleaved repetitions, each in a fresh process; ratios are medians of same-repetition ratios.\n")
    if wsum:
        print("| write | extend rows/s (foreground) | x memmap | durable rows/s (flush / dumps) | x memmap | "
              "+ fsync rows/s | x memmap | disk MB |")
        print("|---|---|---|---|---|---|---|---|")
        for kind, s in wsum.items():
            d = s.get("durable_rows_s")
            f = s.get("durable_fsync_rows_s")
            print(f"| {WRITE_LABELS[kind]} | {s['extend_fg_rows_s']:,.0f} | {s['extend_fg_rows_s_vs_memmap']:.2f}x | "
                  + (f"{d:,.0f} | {s['durable_rows_s_vs_memmap']:.2f}x | {f:,.0f} | {s['durable_fsync_rows_s_vs_memmap']:.2f}x | "
                     if d else "n/a | | n/a | | ")
                  + f"{mb(s.get('disk_bytes')) if s.get('disk_bytes') else 'RAM'} |")
        print()
    print("| open (fresh process, warm cache) | open s | x memmap | RSS after open MB (anon / file) | + over imports | "
          f"RSS after {GATHERS:,} gathers MB (anon / file) | + over imports | x memmap (total / +) | "
          "sample(256) ms warm | speed x memmap |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for kind, s in osum.items():
        kids = s.get("after_gathers.children") or 0
        kid = f" (+{mb(kids)} child)" if kids > 20e6 else ""
        print(f"| {OPEN_LABELS[kind]} | {s['open_s']:.4f} | {s.get('open_vs_memmap', 0):,.1f}x | "
              f"{mb(s['after_open.VmRSS'])} ({mb(s['after_open.RssAnon'])} / {mb(s['after_open.RssFile'])}) | "
              f"{mb(s['after_open.delta'])} | "
              f"{mb(s['after_gathers.VmRSS'])} ({mb(s['after_gathers.RssAnon'])} / {mb(s['after_gathers.RssFile'])}){kid} | "
              f"{mb(s['after_gathers.delta'])} | {s.get('rss_after_gathers_vs_memmap', 0):.2f}x / "
              f"{s.get('rss_delta_after_gathers_vs_memmap', 0):.2f}x | {s['sample_warm_ms']:.3f} | "
              f"{s.get('sample_speed_vs_memmap', 0):.2f}x |")
    if cold:
        print("\n| open, cold cache (`posix_fadvise(DONTNEED)` on the store first) | open s | x memmap | "
              f"first {GATHERS:,} gathers, median ms | x memmap | then warm ms |")
        print("|---|---|---|---|---|---|")
        for kind, s in cold.items():
            m = cold.get("memmap")
            print(f"| {OPEN_LABELS[kind]} | {s['open_s']:.4f} | {s['open_s'] / m['open_s']:,.1f}x | "
                  f"{s['gathers_ms']:.3f} | {s['gathers_ms'] / m['gathers_ms']:.2f}x | {s['sample_warm_ms']:.3f} |")
    if cg is not None:
        print(f"\nMemory cgroup of {cg['limit_bytes'] / 1e6:,.0f} MB (a quarter of the uncompressed rows), "
              f"method: {cg.get('method') or 'none'}")
        if cg.get("skipped"):
            print(f"\nskipped: {cg['skipped']}")
        else:
            print("\n| open in the cgroup | result | open s | sample(256) ms | peak MB |")
            print("|---|---|---|---|---|")
            for kind in ("zarr-ro", "memmap"):
                r = cg[kind]
                peak = r["events"].get("memory.max_usage_in_bytes") or r["events"].get("memory.peak")
                ok = r["returncode"] == 0
                result = "opened and sampled" if ok else (
                    f"killed (rc {r['returncode']}, {r['oom_kills']} OOM kill)" if r.get("killed")
                    else f"not done within {cg['timeout_s']:.0f} s" if r["returncode"] == "timeout"
                    else f"failed (rc {r['returncode']})")
                print(f"| {OPEN_LABELS[kind]} | {result} | {r['open_s']:.4f} | {r['sample_warm_ms']:.3f} | {mb(peak)} |"
                      if ok else f"| {OPEN_LABELS[kind]} | {result} | - | - | {mb(peak)} |")


# -- main ----------------------------------------------------------------------------------------

def git_state() -> dict:
    def git(*a):
        return subprocess.run(["git", "-C", str(ROOT), *a], capture_output=True, text=True).stdout.strip()
    return {"head": git("rev-parse", "--short", "HEAD"), "package_modified": bool(git("status", "--porcelain", "torchrl_robotmem"))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3, help="repetitions of every write and open (medians)")
    ap.add_argument("--samples", type=int, default=2000, help="warm sample(256) gathers timed after the first 1,000")
    ap.add_argument("--quick", action="store_true", help="100k rows, one repetition, 300 warm samples")
    ap.add_argument("--scratch", default=None, help="directory for the stores (default: a temp dir, removed)")
    ap.add_argument("--keep", action="store_true", help="keep the stores under --scratch (and reuse them: no --write)")
    ap.add_argument("--no-write", action="store_true", help="reuse the stores already under --scratch")
    ap.add_argument("--no-warmup", action="store_true",
                    help="no untimed round of opens first (the page cache is warm anyway right after the writes)")
    ap.add_argument("--no-tensor", action="store_true", help="leave LazyTensorStorage out (it holds the rows in RAM)")
    ap.add_argument("--cold", action="store_true", help="also open with the store's pages dropped from the page cache")
    ap.add_argument("--cgroup", action="store_true", help="also open read-only inside a memory cgroup")
    ap.add_argument("--cgroup-bytes", type=int, default=None, help="the cgroup's limit (default: uncompressed / 4)")
    ap.add_argument("--cgroup-timeout", type=float, default=300, help="seconds an open and its samples may take there")
    ap.add_argument("--rev", default=None, help="time the package as committed at this git revision")
    ap.add_argument("--package", default=None, help="a directory holding the torchrl_robotmem to time")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if args.quick:
        args.rows, args.repeat, args.samples = min(args.rows, 100_000), 1, 300

    scratch = Path(args.scratch or tempfile.mkdtemp(prefix="bench_row_tier_"))
    scratch.mkdir(parents=True, exist_ok=True)
    package, label = args.package, args.package or "checkout"
    if args.rev:
        package = str(scratch / f"pkg_{args.rev}")
        shutil.rmtree(package, ignore_errors=True)
        os.makedirs(package)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.rev, "torchrl_robotmem"], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", package], input=archive.stdout, check=True)
        rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", args.rev], capture_output=True, text=True).stdout.strip()
        label = f"as committed at {rev}"
    runner = Runner(scratch, package)
    zpath, mpath = scratch / f"zarr_{args.rows}", scratch / f"memmap_{args.rows}"
    tpath = scratch / f"tensor_{args.rows}"
    write_kinds = [k for k in WRITE_KINDS if not (args.no_tensor and k == "tensor")]
    open_kinds = [k for k in OPEN_KINDS if not (args.no_tensor and k == "tensor")]
    paths = {"zarr": zpath, "memmap": mpath, "tensor": tpath}

    writes: dict[str, list] = {k: [] for k in write_kinds}
    if not args.no_write:
        for rep in tqdm(range(args.repeat), desc=f"write {args.rows:,} rows", unit="rep"):
            order = write_kinds[rep % len(write_kinds):] + write_kinds[:rep % len(write_kinds)]
            for kind in order:
                r = runner.run(WRITE_CHILD, kind, paths[kind], args.rows, rep)
                if kind != "tensor":
                    r["disk_bytes"] = disk_bytes(paths[kind])
                writes[kind].append(r)
                os.sync()  # the writeback of one contestant must not land in the next one's timers
    bpr = next(iter(writes.values()))[0]["bytes_per_row"] if writes and writes[write_kinds[0]] else 274

    opens: dict[str, list] = {k: [] for k in open_kinds}
    path_of = {k: (zpath if k.startswith("zarr") else mpath) for k in open_kinds}
    steps = [(None, k) for k in open_kinds if not args.no_warmup] + [(rep, k) for rep in range(args.repeat)
                                               for k in open_kinds[rep % len(open_kinds):] + open_kinds[:rep % len(open_kinds)]]
    for rep, kind in tqdm(steps, desc="opens", unit="open"):
        r = runner.run(OPEN_CHILD, kind, path_of[kind], args.rows, args.samples)
        if rep is not None:
            opens[kind].append(r)

    cold = None
    if args.cold:
        cold_runs: dict[str, list] = {k: [] for k in open_kinds}
        for kind in tqdm(open_kinds, desc="cold opens", unit="open"):
            drop_cache(path_of[kind])
            cold_runs[kind].append(runner.run(OPEN_CHILD, kind, path_of[kind], args.rows, args.samples))
        cold = {k: {m: med([r[m] for r in v]) for m in ("open_s", "gathers_ms", "sample_warm_ms")} for k, v in cold_runs.items()}

    cg = None
    if args.cgroup:
        limit = args.cgroup_bytes or args.rows * bpr // 4
        cg = cgroup_runs(runner, zpath, mpath, args.rows, limit, args.samples, args.cgroup_timeout)
        imports = med([r["before"]["VmRSS"] for r in opens.get("memmap", [])])
        if imports and limit < imports:
            cg["note"] = (f"the limit ({limit / 1e6:.0f} MB) is below a process's resident memory after the "
                          f"imports alone ({imports / 1e6:.0f} MB): every contestant is expected to be killed")

    wsum = summarize_writes(writes) if writes and all(writes.values()) else {}
    osum = summarize_opens(opens)
    meta = {"rows": args.rows, "bytes_per_row": bpr, "repeat": args.repeat, "samples": args.samples,
            "batch": BATCH, "sample_batch": SAMPLE_BS, "gathers": GATHERS, "package_label": label,
            "package": package, "git": git_state(), "cpus": len(os.sched_getaffinity(0)),
            "platform": platform.platform(), "python": platform.python_version(),
            "date": time.strftime("%Y-%m-%d %H:%M")}
    print_tables(meta, wsum, osum, cold, cg)
    if cg and cg.get("note"):
        print(f"\n{cg['note']}")
    out = Path(args.out or ROOT / "bench_results" / f"row_tier_{args.rows}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"meta": meta, "write": wsum, "open": osum, "cold": cold, "cgroup": cg,
                               "runs": {"write": writes, "open": opens}}, indent=1))
    print(f"\nwrote {out}")
    if not args.keep:
        for p in (zpath, mpath, tpath):
            shutil.rmtree(p, ignore_errors=True)
        if args.scratch is None or args.rev:
            shutil.rmtree(package, ignore_errors=True) if args.rev else None
        if args.scratch is None:
            shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
