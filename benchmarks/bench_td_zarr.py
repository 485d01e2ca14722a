"""tensordict 0.14's Zarr backend (``TensorDict.to_zarr`` / ``PersistentTensorDict``) beside ZarrStorage.

Same process, same FetchPush-v4 rows (``_data.fetch_push_transitions``, 23 leaves, 307 bytes a
row), one thread, contestants interleaved in every round; medians over ``--rounds``.

* ``ZarrStorage``: ``TensorDictReplayBuffer.extend`` in batches of 1000, then ``flush()`` (the
  rows are durable); random reads are ``storage.get(idx)`` (its RAM mirror); reopen is
  ``ZarrStorage(path, read_only=True)`` (checks the store, loads every row into RAM).
* ``td.to_zarr``: the whole TensorDict in one call (tensordict's default layout: one
  uncompressed chunk per leaf). Reads ``ptd[idx].to_tensordict()`` go to Zarr.
* ``td in-place``: what appending takes with tensordict (a ``PersistentTensorDict`` cannot grow):
  a store of ``rows`` zero rows with ZarrStorage's chunking and codec (``chunks=(chunk_rows,)``,
  Blosc zstd level 1, byte shuffle), then ``ptd[lo:hi] = batch`` per batch of 1000.
* reopen of the tensordict stores: ``TensorDict.from_zarr(path)`` (lazy: metadata only) and
  ``.to_tensordict()`` (every row into RAM, what a replay buffer needs).

``--kills K`` also kills a child writing ``ptd[lo:hi] = batch`` in place (every leaf of write
``k`` holds ``k``) with SIGKILL at a random moment, K times, and counts the 1000-row blocks
whose leaves disagree (a row made of two writes) in what it left.

    python benchmarks/bench_td_zarr.py                     # 50k rows, 3 rounds
    python benchmarks/bench_td_zarr.py --rows 50000 --rounds 3 --kills 3
"""
from __future__ import annotations

import argparse
import gc
import json
import random
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from tensordict import PersistentTensorDict, TensorDict
from torchrl.data import TensorDictReplayBuffer
from zarr.codecs import BloscCodec

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import fetch_push_transitions  # noqa: E402

from torchrl_robotmem import ZarrStorage  # noqa: E402

torch.set_num_threads(1)
BATCH, READ_BS = 1000, 256


def blosc():
    return BloscCodec(cname="zstd", clevel=1, shuffle="shuffle")


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def read_ms(get, rows: int, draws: int, gen: torch.Generator) -> float:
    """Median ms of ``get(idx)`` for ``draws`` random 256-row index tensors."""
    times = []
    for _ in range(draws):
        idx = torch.randint(0, rows, (READ_BS,), generator=gen)
        t, _ = timed(lambda idx=idx: get(idx))
        times.append(t)
    return 1e3 * statistics.median(times)


def zarr_storage_round(data, path: Path, draws: int, gen) -> dict:
    rows = data.shape[0]

    def fill():
        st = ZarrStorage(path, rows, env="FetchPush-v4")
        rb = TensorDictReplayBuffer(storage=st, batch_size=READ_BS)
        for lo in range(0, rows, BATCH):
            rb.extend(data[lo:lo + BATCH].copy())  # shallow copy: the buffer writes "index" into it
        st.flush()
        return st

    t_extend, st = timed(fill)
    chunk_rows = st.chunk_rows
    get_ms = read_ms(st.get, rows, draws * 10, gen)
    st.close()
    gc.collect()
    t_open, ro = timed(lambda: ZarrStorage(path, read_only=True))
    ro.close()
    return {"extend_s": t_extend, "read_ms": get_ms, "reopen_s": t_open, "chunk_rows": chunk_rows}


def td_one_shot_round(data, path: Path, draws: int, gen) -> dict:
    rows = data.shape[0]
    t_write, _ = timed(lambda: data.to_zarr(str(path)))
    return {"extend_s": t_write, **td_reads(path, rows, draws, gen)}


def td_in_place_round(data, path: Path, chunk_rows: int, draws: int, gen) -> dict:
    rows = data.shape[0]
    t_alloc, ptd = timed(lambda: PersistentTensorDict.from_dict(
        torch.zeros_like(data), str(path), backend="zarr", chunks=(chunk_rows,), compressors=blosc()))

    def write():
        for lo in range(0, rows, BATCH):
            ptd[lo:lo + BATCH] = data[lo:lo + BATCH]

    t_write, _ = timed(write)
    return {"alloc_s": t_alloc, "extend_s": t_alloc + t_write, **td_reads(path, rows, draws, gen)}


def td_reads(path: Path, rows: int, draws: int, gen) -> dict:
    t_open, ptd = timed(lambda: TensorDict.from_zarr(str(path)))
    out_of_core = read_ms(lambda idx: ptd[idx].to_tensordict(), rows, draws, gen)
    t_load, ram = timed(lambda: TensorDict.from_zarr(str(path)).to_tensordict())
    in_ram = read_ms(lambda idx: ram[idx], rows, draws * 10, gen)
    return {"read_ms": out_of_core, "read_ram_ms": in_ram, "reopen_lazy_s": t_open, "reopen_s": t_load}


KILL_CHILD = r"""
import sys, torch
sys.path.insert(0, sys.argv[2])
from _data import fetch_push_transitions
from tensordict import PersistentTensorDict
torch.set_num_threads(1)
ptd = PersistentTensorDict.from_zarr(sys.argv[1], mode="r+")
rows = ptd.shape[0]
block = fetch_push_transitions(1000)
k = 0
print("ready", flush=True)
while True:
    k += 1
    lo = (k * 1000) % rows
    ptd[lo:lo + 1000] = block.apply(lambda x: torch.full_like(x, k) if x.is_floating_point() else x)
"""


def kill_round(path: Path, rows: int, chunk_rows: int, rng: random.Random) -> dict:
    """Kills a child writing in place; returns the blocks whose float leaves disagree."""
    float_rows = fetch_push_transitions(rows).apply(lambda x: torch.zeros_like(x))
    PersistentTensorDict.from_dict(float_rows, str(path), backend="zarr", chunks=(chunk_rows,), compressors=blosc())
    child = subprocess.Popen([sys.executable, "-c", KILL_CHILD, str(path), str(Path(__file__).parent)],
                             stdout=subprocess.PIPE, text=True)
    child.stdout.readline()
    time.sleep(rng.uniform(1.0, 8.0))
    child.send_signal(signal.SIGKILL)
    child.wait()
    left = TensorDict.from_zarr(str(path)).to_tensordict()
    leaves = [v.reshape(rows, -1)[:, 0] for v in left.values(True, True) if v.is_floating_point()]
    stacked = torch.stack(leaves, -1).reshape(rows // BATCH, BATCH, -1)
    torn = [b for b in range(rows // BATCH) if stacked[b].unique().numel() > 1]
    return {"torn_blocks": len(torn), "writes_seen": int(stacked.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=50_000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--draws", type=int, default=5, help="random 256-row reads timed per round (x10 for RAM reads)")
    ap.add_argument("--kills", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench_results/td_zarr.json")
    args = ap.parse_args()
    data = fetch_push_transitions(args.rows, seed=args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    scratch = Path(tempfile.mkdtemp(prefix="bench_td_zarr_"))
    results: dict[str, list[dict]] = {"ZarrStorage": [], "td.to_zarr": [], "td in-place": []}
    try:
        for r in range(args.rounds):
            order = list(results)[r % 3:] + list(results)[:r % 3]
            chunk_rows = 16384
            for name in order:
                path = scratch / f"{name.replace(' ', '_')}-{r}.zarr"
                gc.collect()
                if name == "ZarrStorage":
                    res = zarr_storage_round(data, path, args.draws, gen)
                    chunk_rows = res["chunk_rows"]
                elif name == "td.to_zarr":
                    res = td_one_shot_round(data, path, args.draws, gen)
                else:
                    res = td_in_place_round(data, path, chunk_rows, args.draws, gen)
                results[name].append(res)
                shutil.rmtree(path, ignore_errors=True)
            print(f"round {r + 1}/{args.rounds} done", file=sys.stderr)
        medians = {n: {k: statistics.median(x[k] for x in rs) for k in rs[0]} for n, rs in results.items()}
        kills = []
        rng = random.Random(args.seed)
        for i in range(args.kills):
            kills.append(kill_round(scratch / f"kill-{i}.zarr", args.rows, medians["ZarrStorage"]["chunk_rows"], rng))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    report(args, medians, kills)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"args": vars(args), "rounds": results, "medians": medians,
                                          "kills": kills}, indent=1))


def report(args, medians: dict, kills: list) -> None:
    z = medians["ZarrStorage"]
    print(f"\n{args.rows} FetchPush rows, {args.rounds} rounds (medians); ratios are to ZarrStorage\n")
    print("| contestant | write all rows (s) | 256-row random read (ms) | reopen (s) | reopen lazy (s) |")
    print("|---|---|---|---|---|")
    for name, m in medians.items():
        lazy = f"{m['reopen_lazy_s']:.3f}" if "reopen_lazy_s" in m else "-"
        print(f"| {name} | {m['extend_s']:.3f} ({m['extend_s'] / z['extend_s']:.2f}x) "
              f"| {m['read_ms']:.2f} ({m['read_ms'] / z['read_ms']:.1f}x) "
              f"| {m['reopen_s']:.3f} ({m['reopen_s'] / z['reopen_s']:.2f}x) | {lazy} |")
    for name in ("td.to_zarr", "td in-place"):
        print(f"{name}: read from the loaded TensorDict {medians[name]['read_ram_ms']:.3f} ms")
    for i, k in enumerate(kills):
        print(f"kill {i + 1}: {k['torn_blocks']} torn 1000-row blocks after {k['writes_seen']} writes")


if __name__ == "__main__":
    main()
