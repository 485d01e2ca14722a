"""robotmem's quick start, on torchrl_robotmem: FetchPickAndPlace-v4 with a persistent memory.

The loop is the seed's (``RobotMemory`` / ``recall`` / ``save_perception``), with
two fixes the original lacked: the env is reset when an episode ends, and the
episode end is passed to the memory. The policy is a simple scripted one that
moves the gripper toward the nearest remembered achieved goal (a stand-in for
``policy.predict(obs, prior_goals=prior)``) with some noise.

    python examples/quickstart.py --steps 1000 --path memory/pickandplace.zarr

Run it twice: the second run recalls what the first one stored.
"""
from __future__ import annotations

import argparse

import gymnasium as gym
import gymnasium_robotics
import numpy as np
import torch
import tqdm

from torchrl_robotmem import RobotMemory

gym.register_envs(gymnasium_robotics)
ENV_ID = "FetchPickAndPlace-v4"


def policy(obs: dict, prior, rng: np.random.Generator) -> np.ndarray:
    """Move the gripper toward the closest remembered goal (or the desired goal), plus noise."""
    target = obs["desired_goal"]
    if bool(prior["mask"][0]):
        target = prior["next", "achieved_goal"][0].numpy()
    grip = obs["observation"][:3]
    action = np.zeros(4, dtype=np.float32)
    action[:3] = np.clip(10.0 * (target - grip), -1, 1)
    action[3] = rng.uniform(-1, 1)
    return np.clip(action + rng.normal(0, 0.3, 4), -1, 1).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--path", default="memory/pickandplace.zarr")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)

    mem = RobotMemory(args.path, env=ENV_ID)
    print(f"memory at {args.path}: {len(mem)} transitions from earlier runs")
    env = gym.make(ENV_ID)
    obs, info = env.reset(seed=args.seed)
    episodes = successes = 0
    for _ in tqdm.trange(args.steps, desc=ENV_ID):
        # Recall past transitions whose achieved goals are nearest to the goal we want
        prior = mem.recall(obs["desired_goal"], top_k=5)
        action = policy(obs, prior, rng)
        obs, reward, terminated, truncated, info = env.step(action)
        # Save every achieved goal with its full observation context
        mem.save_perception(
            observation=obs["observation"],
            action=action,
            reward=reward,
            metadata={
                "achieved_goal": obs["achieved_goal"],
                "desired_goal": obs["desired_goal"],
                "is_success": info["is_success"],
                "env": ENV_ID,
                "terminated": terminated,
                "truncated": truncated,
            },
        )
        if terminated or truncated:
            episodes += 1
            successes += int(info["is_success"])
            obs, info = env.reset()

    goal = obs["desired_goal"]
    best = mem.recall(goal, top_k=3, success_only=True)
    print(f"\n{episodes} episodes this run, {successes} ended in success")
    print(f"memory now holds {len(mem)} transitions; summary: {mem.summary()}")
    print(f"3 nearest successful memories to goal {np.round(goal, 3).tolist()}:")
    for i in range(3):
        if not bool(best["mask"][i]):
            print("  (no more successful memories)")
            break
        print(f"  achieved {np.round(best['next', 'achieved_goal'][i].numpy(), 3).tolist()} "
              f"distance {float(best['distance'][i]):.3f} episode {int(best['episode'][i])} run {int(best['run'][i])}")
    mem.close()


if __name__ == "__main__":
    main()
