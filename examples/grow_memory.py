"""Grow a persistent FetchPush memory with a TorchRL collector (random policy).

Every run collects episodes of ``FetchPush-v4`` with a random policy through a
TorchRL ``Collector`` into a ``TensorDictReplayBuffer`` whose storage is a
:class:`~torchrl_robotmem.ZarrStorage`, then prints what the memory holds. Run
it twice: the second run appends to the first run's memory (new ``run`` id,
episode ids continue), it does not start from nothing.

    python examples/grow_memory.py --episodes 20 --path memory/fetchpush.zarr
"""
from __future__ import annotations

import argparse
import time
from functools import partial

import torch
import tqdm
from torchrl.collectors import Collector
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage, make_env

ENV_ID = "FetchPush-v4"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--path", default="memory/fetchpush.zarr", help="where the memory lives")
    parser.add_argument("--episodes", type=int, default=20, help="episodes to collect this run")
    parser.add_argument("--max-size", type=int, default=1_000_000, help="capacity in transitions")
    parser.add_argument("--seed", type=int, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)

    storage = ZarrStorage(args.path, max_size=args.max_size, env=ENV_ID)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=256)
    before = storage.summary()
    print(f"memory at {args.path}: {before['rows']} transitions, {before['episodes']} episodes, "
          f"{before['runs']} earlier runs")

    episode_len = 50
    frames = args.episodes * episode_len
    seed = args.seed if args.seed is not None else int(time.time())
    collector = Collector(
        partial(make_env, ENV_ID, seed=seed),
        policy=None,  # a random policy over the env's action spec
        frames_per_batch=episode_len * 5,
        total_frames=frames,
    )
    with tqdm.tqdm(total=frames, desc=f"collecting {ENV_ID}", unit="frame") as pbar:
        for data in collector:
            rb.extend(data.reshape(-1))
            pbar.update(data.numel())
    collector.shutdown()
    storage.flush()

    after = storage.summary()
    this_run = int(storage["run"][: len(storage)].max())
    batch = rb.sample()
    print(
        f"\nthis run (run id {this_run}) added {after['rows'] - before['rows']} transitions\n"
        f"memory now: {after['rows']} transitions | {after['episodes']} episodes | "
        f"{after['runs']} runs | episodes ending in success {after.get('episode_success_rate', 0.0):.1%} | "
        f"envs {list(after['envs'])} | {after['bytes_on_disk'] / 1e6:.2f} MB on disk\n"
        f"a sampled batch of {batch.shape[0]} spans runs {sorted(storage['run'][batch['index']].unique().tolist())}\n"
        f"run again to append to the same memory: python examples/grow_memory.py --path {args.path}"
    )
    storage.close()


if __name__ == "__main__":
    main()
