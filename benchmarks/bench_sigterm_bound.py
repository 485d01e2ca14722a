"""Time from SIGTERM to exit of a writer with unsaved rows, its commit worker alive or SIGSTOPped.

Each case starts a writer process (``commit_interval=3600``: only the SIGTERM
flush commits), extends 11k or 101k rows of 168 bytes, optionally stops its
commit worker with SIGSTOP, sends SIGTERM and times the exit; then it checks
that every extended row is in the store. docs/storage.md ("Worker faults, full
disks and what they cost") quotes the figures.

    python benchmarks/bench_sigterm_bound.py
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time

CHILD = textwrap.dedent("""
    import sys, time, torch
    from tensordict import TensorDict
    from torchrl.data import TensorDictReplayBuffer
    from torchrl_robotmem import ZarrStorage
    from torchrl_robotmem.storage._commit_worker import CommitWorker
    st = ZarrStorage(sys.argv[1], 2_000_000, commit_interval=3600)
    while not st._engine._use_worker():  # benchmark only: wait until commits go through the worker
        time.sleep(0.02)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    def b(i):
        return TensorDict({"obs": torch.arange(i * 1000, (i + 1) * 1000).double().unsqueeze(-1),
                           "x": torch.randn(1000, 32)}, [1000])
    rb.extend(b(0)); st.flush()
    print(CommitWorker._instance.proc.pid, flush=True)
    sys.stdin.readline()
    for i in range(1, int(sys.argv[2]) + 1):
        rb.extend(b(i))
    print("extended", len(rb), flush=True)
    while True:
        time.sleep(0.01)
""")


def run(stop_worker: bool, batches: int) -> dict:
    from torchrl_robotmem import ZarrStorage

    d = tempfile.mkdtemp()
    p = subprocess.Popen([sys.executable, "-c", CHILD, d + "/m.zarr", str(batches)], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    worker = int(p.stdout.readline())
    if stop_worker:
        os.kill(worker, signal.SIGSTOP)
    p.stdin.write("go\n")
    p.stdin.flush()
    line = p.stdout.readline()
    t0 = time.monotonic()
    p.send_signal(signal.SIGTERM)
    p.wait(600)
    dt = time.monotonic() - t0
    stored = len(ZarrStorage(d + "/m.zarr", read_only=True))
    return {"worker_stopped": stop_worker, "batches": batches, "rows_extended": int(line.split()[1]),
            "rows_stored": stored, "sigterm_to_exit_s": round(dt, 2), "rc": p.returncode}


if __name__ == "__main__":
    for batches in (10, 100):
        for stop in (False, True):
            print(json.dumps(run(stop, batches)), flush=True)
