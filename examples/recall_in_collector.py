"""What a FetchPush agent recalls from its memory at the start of each episode.

1. A TorchRL ``Collector`` plays ``FetchPush-v4`` with a random policy and its
   transitions go into a persistent :class:`~torchrl_robotmem.ZarrStorage`.
2. The store is closed: from now on the memory is just a path on disk.
3. A new env carries ``RecallTransform(path, k)``: at every reset it recalls
   the ``k`` remembered transitions whose achieved goal is nearest to the new
   desired goal, and the policy sees them as ``prior_goals`` (+ distances,
   mask, and here the recalled actions and episode ids).
4. The same transform inside a collector: the priors are stored with every
   transition, ready for a replay buffer.

    python examples/recall_in_collector.py                  # a temporary memory
    python examples/recall_in_collector.py --path memory/fetchpush.zarr --episodes 40

For multi-process collectors (``MultiSyncCollector``, ``MultiAsyncCollector``)
pass the path, not the storage: ``partial(make_env, ENV_ID,
transforms=[RecallTransform(path, k)])`` pickles, and each worker opens the
store read-only.
"""
from __future__ import annotations

import argparse
import tempfile
from functools import partial
from pathlib import Path

import torch
from torchrl.collectors import Collector
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import RecallTransform, ZarrStorage, make_env

ENV_ID = "FetchPush-v4"
EPISODE_LEN = 50


def _xyz(v: torch.Tensor) -> str:
    return "(" + ", ".join(f"{x:.3f}" for x in v.tolist()) + ")"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--path", default=None, help="memory store (default: a temporary directory)")
    parser.add_argument("--episodes", type=int, default=20, help="episodes to remember")
    parser.add_argument("--k", type=int, default=3, help="goals recalled per episode")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    tmp = tempfile.TemporaryDirectory() if args.path is None else None
    path = args.path or str(Path(tmp.name) / "fetchpush.zarr")

    # 1-2. remember some episodes, then close the store
    storage = ZarrStorage(path, max_size=100_000, env=ENV_ID)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=256)
    collector = Collector(partial(make_env, ENV_ID, seed=args.seed), None,
                          frames_per_batch=5 * EPISODE_LEN, total_frames=args.episodes * EPISODE_LEN)
    for data in collector:
        rb.extend(data.reshape(-1))
    collector.shutdown()
    summary = storage.summary()
    storage.close()
    print(f"memory {path}: {summary['rows']} transitions, {summary['episodes']} episodes, "
          f"envs {list(summary['envs'])}")

    # 3. a new env recalls from the path at each reset
    recall = RecallTransform(path, k=args.k, context_keys={"action": "prior_actions", "episode": "prior_episodes"})
    env = make_env(ENV_ID, seed=args.seed + 1, transforms=[recall])
    print(f"\n{recall}\n")
    for episode in range(3):
        td = env.reset()
        print(f"new episode {episode}: desired goal {_xyz(td['desired_goal'])}")
        print("    #  recalled achieved goal    distance  from episode  its action")
        for i in range(args.k):
            if not td["prior_goals_mask"][i]:
                print(f"   {i:2d}  (nothing)")
                continue
            action = ", ".join(f"{a:+.2f}" for a in td["prior_actions"][i].tolist())
            print(f"   {i:2d}  {_xyz(td['prior_goals'][i]):24s} {100 * td['prior_goals_dist'][i]:6.1f} cm"
                  f"  {int(td['prior_episodes'][i]):12d}  ({action})")
        sources = td["prior_episodes"][td["prior_goals_mask"]].unique()
        if len(sources) == 1 and args.k > 1:
            print("    (all from one episode: an object nobody touched achieves the same goal at every step)")
        rollout = env.rollout(EPISODE_LEN, auto_reset=False, tensordict=td)
        same = bool((rollout["next", "prior_goals"] == td["prior_goals"]).all())
        print(f"    ... {rollout.shape[0]} steps later the policy still sees the same priors: {same}\n")
    env.close()

    # 4. inside a collector: the priors are part of every stored transition
    collector = Collector(partial(make_env, ENV_ID, seed=args.seed + 2, transforms=[RecallTransform(path, k=args.k)]),
                          None, frames_per_batch=2 * EPISODE_LEN, total_frames=2 * EPISODE_LEN)
    data = next(iter(collector))
    collector.shutdown()
    print("a collected batch carries:")
    for key in ("prior_goals", "prior_goals_dist", "prior_goals_mask"):
        value = data[key]
        print(f"    {key:18s} {str(tuple(value.shape)):12s} {value.dtype}")
    print(f"    recalled goals within 5 cm of the desired goal: "
          f"{(data['prior_goals_dist'][data['prior_goals_mask']] < 0.05).float().mean():.0%}")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
