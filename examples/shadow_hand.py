"""What a Shadow Hand agent recalls about a block pose, with the pose metric.

``HandManipulateBlock-v1`` goals are 7-D poses: position xyz + orientation
quaternion wxyz. Plain Euclidean distance on those 7 numbers mixes metres with
quaternion components and calls ``q`` and ``-q`` (the same orientation) far
apart. ``metric="pose"`` (:class:`~torchrl_robotmem.goal_index.metrics.PoseMetric`)
measures ``|dp| + 0.1 m/rad * rotation angle``.

1. A ``Collector`` plays with a random policy; transitions go to a ZarrStorage.
2. A new env with ``RecallTransform(path, k, metric="pose")`` shows, at each
   reset, the remembered block poses nearest to the target pose, split into
   position error and rotation angle, next to what a Euclidean recall would
   have picked.

    python examples/shadow_hand.py                       # a temporary memory
    python examples/shadow_hand.py --episodes 20 --path memory/hand_block.zarr
"""
from __future__ import annotations

import argparse
import math
import tempfile
from functools import partial
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import RecallTransform, ZarrStorage, make_env

ENV_ID = "HandManipulateBlock-v1"
EPISODE_LEN = 100


def _split(goal: torch.Tensor, other: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Position error (cm) and rotation angle (degrees) between poses ``[..., 7]``."""
    pos = 100 * torch.linalg.vector_norm(goal[..., :3] - other[..., :3], dim=-1)
    qa = torch.nn.functional.normalize(goal[..., 3:], dim=-1)
    qb = torch.nn.functional.normalize(other[..., 3:], dim=-1)
    angle = 2 * torch.arccos((qa * qb).sum(-1).abs().clamp(max=1.0))
    return pos, angle * 180 / math.pi


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--path", default=None, help="memory store (default: a temporary directory)")
    parser.add_argument("--episodes", type=int, default=10, help="episodes to remember")
    parser.add_argument("--k", type=int, default=3, help="poses recalled per episode")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    tmp = tempfile.TemporaryDirectory() if args.path is None else None
    path = args.path or str(Path(tmp.name) / "hand_block.zarr")

    storage = ZarrStorage(path, max_size=100_000, env=ENV_ID)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=256)
    collector = Collector(partial(make_env, ENV_ID, seed=args.seed), None,
                          frames_per_batch=2 * EPISODE_LEN, total_frames=args.episodes * EPISODE_LEN)
    for data in collector:
        rb.extend(data.reshape(-1))
    collector.shutdown()
    summary = storage.summary()
    storage.close()
    print(f"memory {path}: {summary['rows']} transitions, {summary['episodes']} episodes of {ENV_ID}\n")

    pose = RecallTransform(path, k=args.k, metric="pose")
    euclid = RecallTransform(path, k=args.k)  # for comparison, applied offline with forward()
    env = make_env(ENV_ID, seed=args.seed + 1, transforms=[pose])
    for episode in range(3):
        td = env.reset()
        goal = td["desired_goal"]
        print(f"new episode {episode}: target position {[round(x, 3) for x in goal[:3].tolist()]}, "
              f"quaternion {[round(x, 2) for x in goal[3:].tolist()]}")
        pos, ang = _split(goal, td["prior_goals"])
        print("    #  pose recall: position  rotation  pose distance")
        for i in range(args.k):
            if td["prior_goals_mask"][i]:
                print(f"   {i:2d}  {pos[i]:19.1f} cm {ang[i]:7.1f} deg {td['prior_goals_dist'][i]:9.3f}")
        other = euclid.forward(TensorDict({"desired_goal": goal}, []))
        epos, eang = _split(goal, other["prior_goals"][0])
        print(f"    Euclidean-on-7-numbers would recall first: {epos:.1f} cm, {eang:.1f} deg\n")
    env.close()
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
