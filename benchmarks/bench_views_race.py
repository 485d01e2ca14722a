"""How often ``rb[:]`` of a buffer another thread extends shows two columns that disagree.

TorchRL's ``TestUpdateIfPresent::test_concurrent_updates_do_not_tear_records`` as a loop: a writer
thread extends 8 rows at a time (columns ``a`` and ``b`` equal), the main thread samples, patches the
sampled rows with ``update_if_present`` and compares ``rb[:]["a"]`` with ``rb[:]["b"]``. ``rb[:]``
returns views of the live rows (for ``LazyTensorStorage`` as for ``ZarrStorage``), so a comparison made
after TorchRL's lock is released can see the writer's next rows in one column and not the other;
``--locked`` makes it under ``rb._replay_lock``, where no storage may show a torn row.

    python benchmarks/bench_views_race.py --kind zarr --loops 10
    python benchmarks/bench_views_race.py --kind zarr --loops 10 --locked
    python benchmarks/bench_views_race.py --kind lts --loops 10

Prints how many loops (of 200 steps each) saw a torn ``rb[:]`` at least once.
"""
from __future__ import annotations

import argparse
import tempfile
import threading
import warnings

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.writers import TensorDictRoundRobinWriter


def one_loop(kind: str, locked: bool, steps: int = 200) -> int:
    """Steps of one loop whose ``rb[:]`` showed ``a != b``."""
    if kind == "lts":
        storage = LazyTensorStorage(64)
    else:
        from torchrl_robotmem import ZarrStorage

        storage = ZarrStorage(tempfile.mkdtemp() + "/m.zarr", 64, goal_conditioned=False)
    rb = TensorDictReplayBuffer(storage=storage, writer=TensorDictRoundRobinWriter(track_generations=True),
                                batch_size=8)
    rb.extend(TensorDict({"a": torch.zeros(64), "b": torch.zeros(64)}, batch_size=[64]))
    stop = threading.Event()

    def writer_loop() -> None:
        value = 1.0
        while not stop.is_set():
            rb.extend(TensorDict({"a": torch.full((8,), value), "b": torch.full((8,), value)}, batch_size=[8]))
            value += 1.0

    thread = threading.Thread(target=writer_loop)
    thread.start()
    torn = 0
    try:
        for step in range(steps):
            sample = rb.sample()
            n = sample.batch_size[0]
            index = sample.get("index").reshape(n, -1)[:, 0]
            generation = sample.get("index_generation").reshape(n, -1)[:, 0]
            marker = torch.full((n,), 10_000.0 + step)
            rb.update_if_present(index=index, generation=generation, patch={"a": marker, "b": marker})
            if locked:
                with rb._replay_lock:
                    content = rb[:]
                    bad = not torch.equal(content["a"], content["b"])
            else:
                content = rb[:]
                bad = not torch.equal(content["a"], content["b"])
            torn += bad
    finally:
        stop.set()
        thread.join()
        if kind != "lts":
            storage.close()
    return torn


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", choices=["zarr", "lts"], default="zarr")
    ap.add_argument("--loops", type=int, default=10)
    ap.add_argument("--locked", action="store_true", help="compare under rb._replay_lock")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    torn = [one_loop(args.kind, args.locked) for _ in range(args.loops)]
    print(f"{args.kind}{' (compared under the lock)' if args.locked else ''}: "
          f"{sum(t > 0 for t in torn)} of {args.loops} loops saw a torn rb[:] ({sum(torn)} steps in all)")


if __name__ == "__main__":
    main()
