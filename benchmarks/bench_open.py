"""Opening a memory: ``ZarrStorage(path)`` and ``ZarrStorage(path, read_only=True)`` against ``LazyMemmapStorage``.

Builds a store of FetchPush-shaped transitions (``_data.fetch_push_transitions``,
1M rows by default) and a ``LazyMemmapStorage`` holding the same rows, then
times each open in a fresh process (page cache warm, imports not counted),
``--repeat`` times in rotating order, and prints the medians as a markdown
table with the ratio to the memmap reopen, then what each phase of the Zarr
opens costs (medians). Every integrity check an open makes is part of the
time. Run from the repository root::

    python benchmarks/bench_open.py                        # 1M rows, 5 repeats
    python benchmarks/bench_open.py --rows 200000 --repeat 7
    python benchmarks/bench_open.py --keep /tmp/open_bench  # build once, reuse

The memmap reopen is TorchRL's own: ``LazyMemmapStorage(n, scratch_dir=d)``
then ``loads(d)`` on the directory it wrote (``dumps``), which maps the files.
``--baseline DIR`` times another version of the package (a directory holding
its ``torchrl_robotmem``) on the same stores, interleaved with this one.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
import torch
torch.set_num_threads(1)
kind, path, rows = sys.argv[1], sys.argv[2], int(sys.argv[3])
phases = {}
if kind == "memmap":
    from pathlib import Path
    from torchrl.data import LazyMemmapStorage
    t = time.perf_counter()
    s = LazyMemmapStorage(rows, scratch_dir=path)
    s.loads(Path(path))
    n = len(s)
else:
    from torchrl_robotmem.storage import ZarrStorage, integrity, loader
    from torchrl_robotmem.storage.handle import StoreHandle
    from torchrl_robotmem.storage.mirror import RamMirror
    from torchrl_robotmem.storage.store import MemoryStore

    def timed(owner, name, phase):
        fn = getattr(owner, name)
        def wrapper(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                phases[phase] = phases.get(phase, 0.0) + time.perf_counter() - t0
        setattr(owner, name, wrapper)

    timed(loader, "open_record", "open_record")
    timed(integrity, "check_open", "check_open")
    timed(RamMirror, "load", "read rows")
    timed(StoreHandle, "check_read", "listing after the read")
    timed(MemoryStore, "note_stored", "episode bookkeeping")
    timed(MemoryStore, "close_open_episodes", "episode bookkeeping")
    timed(MemoryStore, "open_arrays", "writer's array handles")
    t = time.perf_counter()
    s = ZarrStorage(path, read_only=kind == "read-only")
    n = len(s)
if kind != "memmap":
    total = time.perf_counter() - t
    phases["store open, format, partial files"] = phases.pop("open_record") - phases["check_open"]
    phases["integrity.check_open (record, arrays, chunk listing)"] = phases.pop("check_open")
    phases["other"] = total - sum(phases.values())
else:
    total = time.perf_counter() - t
import torchrl_robotmem
print(json.dumps({"total": total, "rows": n, "phases": phases, "package": torchrl_robotmem.__file__}))
if kind != "memmap":
    s.close()
"""

KINDS = ("writable", "read-only", "memmap")


def build(root: Path, rows: int) -> tuple[Path, Path]:
    """The Zarr store and the memmap directory of ``rows`` FetchPush transitions under ``root`` (reused if there)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    zpath, mpath = root / "memory.zarr", root / "memmap"
    if (zpath / "zarr.json").exists() and (mpath / "storage_metadata.json").exists():
        return zpath, mpath
    import torch
    from _data import fetch_push_transitions
    from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer

    from torchrl_robotmem import ZarrStorage

    torch.set_num_threads(1)
    data = fetch_push_transitions(rows, seed=0)[:rows]
    with ZarrStorage(zpath, rows, env="FetchPush-v4") as storage:
        rb = TensorDictReplayBuffer(storage=storage, batch_size=256)
        for i in range(0, rows, 1000):
            rb.extend(data[i:i + 1000])
    storage = LazyMemmapStorage(rows, scratch_dir=mpath)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=256)
    for i in range(0, rows, 10_000):
        rb.extend(data[i:i + 10_000])
    storage.dumps(mpath)
    os.sync()
    return zpath, mpath


def open_once(kind: str, zpath: Path, mpath: Path, rows: int, package_dir: str | None = None) -> dict:
    """One open in a fresh process; ``package_dir``: the directory holding another ``torchrl_robotmem`` to time."""
    path = mpath if kind == "memmap" else zpath
    env = dict(os.environ)
    if package_dir:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [package_dir, env.get("PYTHONPATH")]))
    # run outside the checkout: `python -c` puts the working directory first on sys.path
    out = subprocess.run([sys.executable, "-c", CHILD, kind, str(path), str(rows)], capture_output=True, text=True,
                         check=True, env=env, cwd=zpath.parent)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    if package_dir and not Path(result["package"]).resolve().is_relative_to(Path(package_dir).resolve()):
        raise RuntimeError(f"--baseline {package_dir}: the child imported {result['package']} instead")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--keep", default=None, help="directory for the stores, kept (reused when already built)")
    parser.add_argument("--baseline", default=None,
                        help="a directory holding another torchrl_robotmem (e.g. `git archive <commit> torchrl_robotmem "
                             "| tar -x -C DIR`), timed in the same run, interleaved")
    args = parser.parse_args()
    root = Path(args.keep or tempfile.mkdtemp(prefix="bench_open_"))
    root.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    zpath, mpath = build(root, args.rows)
    print(f"stores under {root} ({time.perf_counter() - t:.0f} s)", file=sys.stderr)
    cases = [(k, None) for k in KINDS]
    if args.baseline:
        cases += [("writable", args.baseline), ("read-only", args.baseline)]
    for kind, pkg in cases:  # warm the page cache
        open_once(kind, zpath, mpath, args.rows, pkg)
    runs: dict[tuple, list] = {c: [] for c in cases}
    for rep in range(args.repeat):
        for case in cases[rep % len(cases):] + cases[:rep % len(cases)]:
            runs[case].append(open_once(case[0], zpath, mpath, args.rows, case[1]))
    med = {c: statistics.median(r["total"] for r in v) for c, v in runs.items()}
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    print(f"{args.rows:,} FetchPush rows, median of {args.repeat} fresh-process opens each (page cache warm, "
          f"imports not counted), {len(os.sched_getaffinity(0))} CPUs, commit {head}"
          + (f", baseline {args.baseline}" if args.baseline else "") + "\n")
    print("| open | s (median) | min - max | x memmap reopen |")
    print("|---|---|---|---|")
    labels = {"writable": "`ZarrStorage(path)`", "read-only": "`ZarrStorage(path, read_only=True)`",
              "memmap": "`LazyMemmapStorage` + `loads` (maps the files)"}
    memmap = med[("memmap", None)]
    for case in cases:
        times = [r["total"] for r in runs[case]]
        label = labels[case[0]] + (" baseline" if case[1] else "")
        print(f"| {label} | {med[case]:.3f} | {min(times):.3f} - {max(times):.3f} | {med[case] / memmap:.0f}x |")
    zarr_cases = [c for c in cases if c[0] != "memmap"]
    print("\n| phase (median s) | " + " | ".join(c[0] + (" baseline" if c[1] else "") for c in zarr_cases) + " |")
    print("|---|" + "---|" * len(zarr_cases))
    names = list(dict.fromkeys(p for c in zarr_cases for r in runs[c] for p in r["phases"]))
    for name in names:
        cells = [statistics.median(r["phases"].get(name, 0.0) for r in runs[c]) for c in zarr_cases]
        print(f"| {name} | " + " | ".join(f"{x:.3f}" for x in cells) + " |")


if __name__ == "__main__":
    main()
