"""Probe (issue 27, goal 2): clone the noisy FetchPush memory, then clone-collect-clone rounds.

Self-imitation by filtered cloning (GCSL / filtered BC without a critic): an MLP
``a = pi(o, g)`` (``experiments.her.hand_memory.InverseModel``) is regressed
onto the actions of the memory's episodes that ended within ``--threshold`` of
their goal (0.05: FetchPush's own success radius), evaluated on 100
deterministic episodes (reset seeds 10000-10099), then each round collects 100
episodes with the clone plus N(0, sigma^2) action noise, adds the ones that
succeeded (``--mode relabel``: also the failed ones whose block moved > 5 cm,
their goal replaced by where the block ended) and fits on.

    python -m experiments.notes.push_self_imitation --mode success --rounds 6     # 0.52, 0.58, 0.45 ... (results.md)
    python -m experiments.notes.push_self_imitation --rounds 0 --threshold 0.03   # a tighter filter: fewer episodes
    python -m experiments.notes.push_self_imitation --rounds 0 --steps 4000 --shift 0.1   # rows shifted on the table

Needs ``bench_results/prior/scripted-push-500.zarr``
(``python -m experiments.scripted.collect env=push episodes=500 noise=1 seed=0 backend=gym path=...``).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import gymnasium as gym
import gymnasium_robotics  # noqa: F401  (registers the Fetch envs)
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from experiments.her.hand_memory import InverseModel, fit  # noqa: E402
from torchrl_robotmem import ZarrStorage  # noqa: E402

STEPS = 50


def kept(obs, act, goal, ach, succeeded, relabel: bool):
    """The episodes cloned: the successful ones, and with ``relabel`` the failed ones whose block moved."""
    o, a, g = [obs[succeeded]], [act[succeeded]], [goal[succeeded]]
    if relabel:
        moved = (~succeeded) & ((ach[:, -1] - ach[:, 0]).norm(dim=-1) > 0.05)
        o.append(obs[moved])
        a.append(act[moved])
        g.append(ach[moved][:, -1:].expand(-1, STEPS, -1))
    return torch.cat(o), torch.cat(a), torch.cat(g)


def fit_shifted(model, opt, data, steps: int, shift: float, gen: torch.Generator) -> float:
    """``fit`` with every row's gripper (obs 0:2), block (obs 3:5) and goal (0:2) moved by one random
    table offset in [-shift, shift]^2: FetchPush is translation invariant on the table."""
    n = data["obs"].shape[0]
    model.refresh(data)
    loss = torch.zeros(())
    for _ in range(steps):
        i = torch.randint(n, (512,), generator=gen)
        obs, goal = data["obs"][i].clone(), data["ag"][i].clone()
        d = (torch.rand(512, 2, generator=gen) * 2 - 1) * shift
        obs[:, 0:2] += d
        obs[:, 3:5] += d
        goal[:, 0:2] += d
        loss = (model(obs, goal) - data["act"][i]).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return float(loss.detach())


def as_rows(obs, act, goal) -> dict[str, torch.Tensor]:
    n = obs.shape[0]
    return {"obs": obs.reshape(n * STEPS, -1), "act": act.reshape(n * STEPS, -1), "ag": goal.reshape(n * STEPS, -1),
            "ep": torch.arange(n).repeat_interleave(STEPS)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--memory", default="bench_results/prior/scripted-push-500.zarr")
    p.add_argument("--mode", choices=["success", "relabel"], default="success")
    p.add_argument("--threshold", type=float, default=0.05, help="an episode is kept if it ends this close to its goal")
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--steps", type=int, default=2000, help="Adam steps a round (twice as many first)")
    p.add_argument("--sigma", type=float, default=0.1)
    p.add_argument("--shift", type=float, default=0.0, help="> 0: train on rows shifted on the table (fit_shifted)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="jsonl of the rounds")
    args = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    gen, rng = torch.Generator().manual_seed(args.seed), np.random.default_rng(args.seed)
    with ZarrStorage(args.memory, read_only=True) as store:
        rows = store[: len(store)]
    n = rows.shape[0] // STEPS
    obs, act = rows["observation"].reshape(n, STEPS, -1), rows["action"].reshape(n, STEPS, -1)
    goal, ach = rows["desired_goal"].reshape(n, STEPS, -1), rows["next", "achieved_goal"].reshape(n, STEPS, -1)
    relabel = args.mode == "relabel"
    ep_obs, ep_act, ep_goal = kept(obs, act, goal, ach, (ach[:, -1] - goal[:, -1]).norm(dim=-1) < args.threshold, relabel)
    data = as_rows(ep_obs, ep_act, ep_goal)
    model = InverseModel(data)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    env = gym.make("FetchPush-v4")

    def rollout(reset_seed: int, sigma: float):
        o, _ = env.reset(seed=reset_seed)
        ob, ac, go, ag = [], [], [], []
        for _ in range(STEPS):
            with torch.no_grad():
                a = model(torch.as_tensor(o["observation"]).float(), torch.as_tensor(o["desired_goal"]).float()).numpy()
            if sigma:
                a = np.clip(a + sigma * rng.standard_normal(a.shape), -1, 1)
            ob.append(o["observation"]), ac.append(a), go.append(o["desired_goal"])
            o, _, _, _, info = env.step(a)
            ag.append(o["achieved_goal"])
        t = [torch.as_tensor(np.array(x)).float() for x in (ob, ac, go, ag)]
        return (*t, bool(info["is_success"]))

    out = open(args.out, "w") if args.out else None
    new_frames, cpu = 0, time.process_time()
    for r in range(args.rounds + 1):
        steps = args.steps * (2 if r == 0 else 1)
        loss = fit_shifted(model, opt, data, steps, args.shift, gen) if args.shift else fit(model, opt, data, 1, steps, gen)
        success = float(np.mean([rollout(10_000 + e, 0.0)[-1] for e in range(100)]))
        rec = {"mode": args.mode, "threshold": args.threshold, "sigma": args.sigma, "shift": args.shift,
               "seed": args.seed, "round": r,
               "new_frames": new_frames, "episodes": int(data["obs"].shape[0] // STEPS), "success": success,
               "loss": loss, "cpu_s": round(time.process_time() - cpu, 1)}
        print(json.dumps(rec), flush=True)
        if out:
            out.write(json.dumps(rec) + "\n")
            out.flush()
        if r == args.rounds:
            break
        eps = [rollout(1_000_000 * (args.seed + 1) + 100 * r + e, args.sigma) for e in range(100)]
        new_frames += 100 * STEPS
        o, a, g, ag = (torch.stack([e[i] for e in eps]) for i in range(4))
        succeeded = torch.tensor([e[4] for e in eps])
        print(json.dumps({"round": r, "collected_success": float(succeeded.float().mean())}), flush=True)
        new_obs, new_act, new_goal = kept(o, a, g, ag, succeeded, relabel)
        ep_obs, ep_act, ep_goal = torch.cat([ep_obs, new_obs]), torch.cat([ep_act, new_act]), torch.cat([ep_goal, new_goal])
        data = as_rows(ep_obs, ep_act, ep_goal)
    env.close()


if __name__ == "__main__":
    main()
