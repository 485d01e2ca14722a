"""PersistentPrioritizedSampler at 1M rows: a 256-row draw, a 256-row priority update, writing and reading
the priorities in the store; against TorchRL's PrioritizedSampler where its C++ extension loads.

Every figure is the median of ``--repeat`` calls (draws and updates interleaved, as a training loop makes
them). The draw is ``sampler.sample(storage, 256)`` (indices and importance weights, no row gather); the
update is ``sampler.update_priority(index, priority)`` for 256 random rows. "flush, every chunk dirty" writes
all of the priorities into a ZarrStorage holding ``--rows`` one-float rows (after a 256-row update only the
chunks touched are written: with 256 random rows out of 1M, most of them); "reopen" is the first contact of a
new sampler with the reopened store (reading them back).

    python benchmarks/bench_prioritized.py                    # 1M rows, batch 256
    python benchmarks/bench_prioritized.py --rows 100000      # quicker
    python benchmarks/bench_prioritized.py --threads 2        # torch's intra-op threads (default 1)
"""
from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
import warnings

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.samplers.prioritized import PersistentPrioritizedSampler


def _ms(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def _draw_and_update(sampler, storage, rows: int, batch: int, repeat: int) -> tuple[float, float]:
    gen = torch.Generator().manual_seed(0)
    draw, update = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        sampler.sample(storage, batch)
        draw.append((time.perf_counter() - t) * 1e3)
        index = torch.randint(rows, (batch,), generator=gen)
        priority = torch.rand(batch, generator=gen) + 0.01
        t = time.perf_counter()
        sampler.update_priority(index, priority)
        update.append((time.perf_counter() - t) * 1e3)
    return statistics.median(draw), statistics.median(update)


def _filled(storage, rows: int):
    rb = TensorDictReplayBuffer(storage=storage, batch_size=256)
    for start in range(0, rows, 100_000):
        n = min(100_000, rows - start)
        rb.extend(TensorDict({"x": torch.zeros(n, 1)}, [n]))
    return rb


def torchrl_sampler(rows: int, batch: int, repeat: int) -> str:
    try:
        import torchrl._torchrl  # noqa: F401
        from torchrl.data import PrioritizedSampler
    except ImportError as err:
        return f"does not load with torch {torch.__version__}: {str(err).splitlines()[0][:120]}"
    storage = LazyTensorStorage(rows)
    sampler = PrioritizedSampler(rows, alpha=0.7, beta=0.5)
    _filled(storage, rows)
    sampler.update_priority(torch.arange(rows), torch.rand(rows) + 0.01)
    draw, update = _draw_and_update(sampler, storage, rows, batch, repeat)
    return f"draw {draw:.2f} ms, update {update:.2f} ms"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--repeat", type=int, default=201)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (on a loaded box, 1)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore")
    rows, batch = args.rows, args.batch
    print(f"torch {torch.__version__}, {platform.processor() or platform.machine()}, "
          f"{torch.get_num_threads()} threads; {rows:,} rows, batch {batch}, median of {args.repeat}")

    storage = LazyTensorStorage(rows)
    _filled(storage, rows)
    sampler = PersistentPrioritizedSampler(alpha=0.7, beta=0.5)
    sampler.update_priority(torch.arange(rows), torch.rand(rows) + 0.01, storage=storage)
    draw, update = _draw_and_update(sampler, storage, rows, batch, args.repeat)
    print("| sampler | draw 256 (ms) | update 256 (ms) |\n|---|---|---|")
    print(f"| PersistentPrioritizedSampler (pure PyTorch) | {draw:.2f} | {update:.2f} |")
    print(f"| TorchRL PrioritizedSampler (C++ trees) | {torchrl_sampler(rows, batch, args.repeat)} | |")

    with tempfile.TemporaryDirectory() as tmp:
        path = f"{tmp}/per.zarr"
        rb = _filled(ZarrStorage(path, rows), rows)
        sampler = PersistentPrioritizedSampler(alpha=0.7, beta=0.5, persist_interval=None)
        sampler.update_priority(torch.arange(rows), torch.rand(rows) + 0.01, storage=rb.storage)
        t = time.perf_counter()
        sampler.flush()
        full = (time.perf_counter() - t) * 1e3

        def touched():
            sampler.update_priority(torch.randint(rows, (batch,)), torch.rand(batch) + 0.01)
            sampler.flush()

        after_update = _ms(touched, 11)
        rb.storage.close()
        storage = ZarrStorage(path, read_only=True)
        fresh = PersistentPrioritizedSampler(alpha=0.7, beta=0.5)
        t = time.perf_counter()
        fresh.sample(storage, batch)
        reopen = (time.perf_counter() - t) * 1e3
        assert torch.equal(fresh.priority, sampler.priority)
        storage.close()
    print(f"\nin the store: flush, every chunk dirty {full:.0f} ms; update 256 + flush {after_update:.0f} ms; "
          f"reopen (first draw reads them back) {reopen:.0f} ms")


if __name__ == "__main__":
    main()
