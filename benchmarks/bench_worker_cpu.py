"""Where the commit worker's CPU goes (issue 41): the worker in a write, against the same commits replayed alone.

Two measurements, ``--repeat`` times each, interleaved, every one in a fresh process:

* **write**: ``--rows`` Fetch-shaped rows of noise (the row tier benchmark's rows, made before the timer)
  ``extend``-ed in batches of 1,000 into ``ZarrStorage(path, rows)`` with its commit worker (started and ready
  before the first extend), then ``flush()``. Recorded: the seconds of the extends and until ``flush()``
  returned, the CPU seconds of the writer process and of the worker (``/proc/PID/stat``) over that time.
* **replay**: the same rows written with the engine's own commits held (``CommitEngine.held``), their
  chunk snapshots taken as the worker would receive them, then handed to the worker's own code
  (``_commit_worker._commit``, one request a chunk, as a write sends them) in this process, alone on the box.
  Recorded: the CPU seconds of the replay.

The difference is what the worker pays for sharing two cores with the training loop.
``--malloc`` runs every child with glibc's ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` set
(buffers reused instead of mapped and zeroed again; the worker inherits them), and records the replay
process's anonymous resident memory once its buffers are freed.

    python benchmarks/bench_worker_cpu.py --rows 1000000 --repeat 3
    python benchmarks/bench_worker_cpu.py --rows 1000000 --repeat 3 --malloc 33554432,134217728

Writes ``--out`` (JSON, default ``bench_results/worker_cpu_<rows>.json``) and prints the medians.
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

CHILD = r"""
import json, os, sys, time, torch, warnings
warnings.simplefilter("ignore")
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage import _commit_worker as cw
mode, path, rows = sys.argv[1], sys.argv[2], int(sys.argv[3])
gen = torch.Generator().manual_seed(0)
def noise(n):
    f = lambda *s: torch.rand(n, *s, generator=gen)
    b = lambda: torch.rand(n, 1, generator=gen) < 0.5
    return TensorDict({"observation": f(25), "achieved_goal": f(3), "desired_goal": f(3), "action": f(4),
        "done": b(), "terminated": b(), "truncated": b(),
        "next": {"observation": f(25), "achieved_goal": f(3), "desired_goal": f(3), "reward": f(1),
                 "done": b(), "terminated": b(), "truncated": b()}}, [n])
batches = [noise(min(1000, rows - lo)) for lo in range(0, rows, 1000)]
def cpu(pid):
    st = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(st[11]) + int(st[12])) / os.sysconf("SC_CLK_TCK")
res = {"mode": mode}
if mode == "write":
    w = cw.CommitWorker.get()
    t = time.monotonic()
    while not w.ready():
        assert time.monotonic() - t < 120, "the commit worker did not start"
        time.sleep(0.01)
    st = ZarrStorage(path, rows, goal_conditioned=False)
    rb = TensorDictReplayBuffer(storage=st, batch_size=256)
    c0, w0, t0 = time.process_time(), cpu(w.proc.pid), time.perf_counter()
    for b in batches:
        rb.extend(b)
    t1 = time.perf_counter()
    st.flush()
    res.update(extend_s=t1 - t0, durable_s=time.perf_counter() - t0, writer_cpu_s=time.process_time() - c0,
               worker_cpu_s=cpu(w.proc.pid) - w0, via_worker=bool(st._engine._via_worker))
    st.close()
else:
    from torchrl_robotmem.storage.commit import worker_header
    sys.path.insert(0, os.path.dirname(cw.__file__))  # the worker's own imports (it runs as a script there)
    st = ZarrStorage(path, rows, goal_conditioned=False, commit_process=False)
    rb = TensorDictReplayBuffer(storage=st, batch_size=256)
    eng = st._engine
    with eng.held():
        for b in batches:
            rb.extend(b)
        with eng.cv:
            snaps = {c: st._mirror.copy_chunk(c) for c in sorted(eng.dirty)}
    requests = []
    for c, snap in snaps.items():
        h = worker_header(st._mirror, path, {c: snap}, None, False)
        requests.append((h, bytearray(snap[0].numpy().tobytes())))
    st._store.give_up_writes()  # nothing of it committed here: the replay writes the chunks
    store = cw._Store(path, None)
    c0, t0 = time.process_time(), time.perf_counter()
    for h, payload in requests:
        cw._commit(store, h, payload)
    res.update(replay_cpu_s=time.process_time() - c0, replay_s=time.perf_counter() - t0)
    del requests, snaps, payload, h
    import gc
    gc.collect()
    anon = lambda: int(next(l for l in open("/proc/self/status") if l.startswith("RssAnon")).split()[1])  # noqa: E731
    res.update(rss_anon_kb=anon())  # what the freed buffers of the replay still hold (glibc keeps or returns them)
print(json.dumps(res))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--malloc", default=None, help="MMAP_THRESHOLD,TRIM_THRESHOLD (bytes) for every child")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    scratch = Path(tempfile.mkdtemp(prefix="bench_worker_cpu_"))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    if args.malloc:
        mmap_t, trim_t = args.malloc.split(",")
        env.update(MALLOC_MMAP_THRESHOLD_=mmap_t, MALLOC_TRIM_THRESHOLD_=trim_t)
    runs: dict[str, list] = {"write": [], "replay": []}
    try:
        for rep in range(args.repeat):
            for mode in (("write", "replay") if rep % 2 == 0 else ("replay", "write")):
                path = scratch / f"{mode}{rep}.zarr"
                out = subprocess.run([sys.executable, "-c", CHILD, mode, str(path), str(args.rows)],
                                     capture_output=True, text=True, env=env, cwd=scratch)
                if out.returncode:
                    raise RuntimeError(out.stderr[-3000:])
                res = json.loads(out.stdout.strip().splitlines()[-1])
                shutil.rmtree(path, ignore_errors=True)
                runs[mode].append(res)
                print(rep, res, flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    med = {k: statistics.median(r[k] for r in rs) for rs in runs.values() for k in rs[0] if k not in ("mode", "via_worker")}
    print(f"\n{args.rows:,} rows, median of {args.repeat}, malloc={args.malloc}: worker CPU in the write "
          f"{med['worker_cpu_s']:.2f} s (writer {med['writer_cpu_s']:.2f} s; durable {med['durable_s']:.2f} s), "
          f"the same commits replayed alone {med['replay_cpu_s']:.2f} s (anonymous memory left after it {med['rss_anon_kb'] / 1024:.0f} MB)")
    dest = Path(args.out or ROOT / "bench_results" / f"worker_cpu_{args.rows}.json")
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps({"meta": {"rows": args.rows, "repeat": args.repeat, "malloc": args.malloc,
                                         "cpus": len(os.sched_getaffinity(0))}, "median": med, "runs": runs}, indent=1))
    print(f"wrote {dest}")


if __name__ == "__main__":
    main()
