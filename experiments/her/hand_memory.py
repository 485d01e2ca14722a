"""What a HandReach-v3 memory holds, and what cloning it with hindsight goals gives (docs/results.md, "Shadow Hand").

Three measurements on the memory a ``recipes/her/train.py env=hand_reach`` run wrote:

* ``cover``: for evaluation goals drawn as the env draws them (``reset(seed=10_000 + i)``),
  the nearest achieved goal anywhere in the memory, by exact :func:`torchrl_robotmem.recall`:
  does the memory already hold the pinches the agent is asked for?
* ``clone``: hindsight inverse dynamics: an MLP regresses the stored action ``a_t`` on
  ``(o_t, ag_{t+k})``, ``0 <= k < horizon`` within the episode, over every row, then acts
  on ``(o, desired_goal)``; evaluated on 100 deterministic episodes (the same goals as ``cover``).
  ``prior.clone_goals=hindsight`` does the same in ``experiments.prior_variants.train``.
* ``gcsl``: ``clone``, then rounds of 100 episodes collected with the clone plus Gaussian noise,
  added to the data, and cloned again (goal-conditioned supervised learning, Ghosh et al. 2019).

::

    python -m experiments.her.hand_memory cover bench_results/i27/hand_reach-s1.zarr
    python -m experiments.her.hand_memory clone bench_results/i27/hand_reach-s1.zarr --horizon 1 3 10
    python -m experiments.her.hand_memory gcsl bench_results/i27/hand_reach-s1.zarr --horizon 3 --rounds 5

Each result is printed as one JSON line (and appended to ``--out``). ``plot`` draws the runs'
evaluation curves (``--runs NAME=RUN``: a run's hydra dir, or the JSON ``compare --archive`` wrote for it)
and the clone / gcsl lines of the result files, placed at the frames of the memory they came from::

    python -m experiments.her.hand_memory plot docs/runs/hand_memory.jsonl \
        --runs "SAC s0=docs/runs/hand_reach-s0-out.json" "SAC s1=docs/runs/hand_reach-s1-out.json" \
        --png docs/img/hand_reach.png

``curves`` draws GCSL result files, one line a seed, one colour a file::

    python -m experiments.her.hand_memory curves "GCSL=docs/runs/hand43-gcsl-control.jsonl" \
        "GCSL + GoalProposer, rate 0.5=docs/runs/hand43-gcsl-propose.jsonl" \
        "GCSL + GoalProposer, rate 0.25=docs/runs/hand43-gcsl-propose25.jsonl" \
        "GCSL + GoalProposer near the env's goal, rate 0.5=docs/runs/hand43-gcsl-near.jsonl" \
        "GCSL + GoalProposer reached in 2 episodes, rate 0.5=docs/runs/hand43-gcsl-reached2.jsonl" \
        --png docs/img/hand43_gcsl.png
"""
from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import gymnasium_robotics
import numpy as np
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import TensorDictReplayBuffer

from experiments.prior_variants.hindsight import numbered_episodes
from recipes.her.tools.compare import load_run
from torchrl_robotmem import GoalProposer, ZarrStorage, recall

ENV = "HandReach-v3"
EVAL_SEED = 10_000  # evaluation goals: reset(seed=EVAL_SEED + i)
HELDOUT_SEED = 5_000_000  # held-out goals, for choosing a setting: reset(seed=HELDOUT_SEED + i), never the evaluation's


def read_rows(paths: list[str]) -> dict[str, torch.Tensor]:
    """observation, action, next achieved goal and an episode number per row, of every memory in ``paths``."""
    parts, offset = [], 0
    for path in paths:
        with ZarrStorage(path, read_only=True) as store:
            rows = store[: len(store)]
        ep = numbered_episodes(rows, first=offset)
        offset = int(ep.max()) + 1
        parts.append({"obs": rows["observation"].float(), "act": rows["action"].float(),
                      "ag": rows["next", "achieved_goal"].float(), "ep": ep})
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


def eval_goals(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` goals as the env draws them, and which of them are the rest pose (HandReach's 10%)."""
    env = gym.make(ENV)
    goals, rest = [], []
    for i in range(n):
        obs, _ = env.reset(seed=EVAL_SEED + i)
        goals.append(obs["desired_goal"])
        rest.append(np.linalg.norm(obs["desired_goal"] - obs["achieved_goal"]) < 0.02)
    env.close()
    return np.stack(goals), np.array(rest)


def cover(paths: list[str], n: int = 200) -> dict:
    """Distance from each evaluation goal to the nearest achieved goal in the memory (exact recall)."""
    goals, rest = eval_goals(n)
    dist = []
    for path in paths:
        with ZarrStorage(path, read_only=True) as store:
            dist.append([float(recall(store, torch.as_tensor(g), k=1)["distance"][0]) for g in goals])
    d = np.min(np.array(dist), axis=0)
    pinch = d[~rest]
    return {"what": "cover", "memories": paths, "pinch_goals": int((~rest).sum()),
            "nearest_median": float(np.median(pinch)), "nearest_p10": float(np.quantile(pinch, 0.1)),
            "within_0.01": float((pinch < 0.01).mean()), "within_0.02": float((pinch < 0.02).mean()),
            "rest_within_0.01": float((d[rest] < 0.01).mean())}


class InverseModel(nn.Module):
    """a = pi(o, g): 3x256 ReLU MLP, tanh head, inputs standardised with the data's statistics."""

    def __init__(self, data: dict[str, torch.Tensor]) -> None:
        super().__init__()
        obs_dim, goal_dim, act_dim = data["obs"].shape[-1], data["ag"].shape[-1], data["act"].shape[-1]
        self.net = nn.Sequential(nn.Linear(obs_dim + goal_dim, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(),
                                 nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, act_dim), nn.Tanh())
        self.refresh(data)

    def refresh(self, data: dict[str, torch.Tensor]) -> None:
        self.stats = [(x.mean(0), x.std(0).clamp_min(1e-2)) for x in (data["obs"], data["ag"])]

    def forward(self, obs: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        (om, os_), (gm, gs) = self.stats
        return self.net(torch.cat([((obs - om) / os_).clamp(-5, 5), ((goal - gm) / gs).clamp(-5, 5)], -1))


def fit(model: InverseModel, opt, data: dict[str, torch.Tensor], horizon: int, steps: int,
        gen: torch.Generator) -> float:
    """``steps`` Adam steps of MSE between ``model(o_t, ag_{t+k})`` and ``a_t``; the last step's loss."""
    n = data["obs"].shape[0]
    model.refresh(data)
    loss = torch.zeros(())
    for _ in range(steps):
        i = torch.randint(n, (512,), generator=gen)
        j = (i + torch.randint(horizon, i.shape, generator=gen)).clamp(max=n - 1)
        j = torch.where(data["ep"][j] == data["ep"][i], j, i)
        loss = (model(data["obs"][i], data["ag"][j]) - data["act"][i]).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return float(loss.detach())


def rollout(env, model: InverseModel, seed: int, sigma: float, rng: np.random.Generator,
            goal: torch.Tensor | None = None) -> tuple[dict, bool]:
    """One episode with ``model`` (plus N(0, sigma^2) action noise); its rows and whether it succeeded.

    ``goal``: the goal the episode pursues instead of the env's own (a proposed one); success is then
    the env's (its own goal), which a collection episode does not use.
    """
    o, _ = env.reset(seed=seed)
    obs, act, ag = [], [], []
    for _ in range(50):
        pursued = torch.as_tensor(o["desired_goal"]).float() if goal is None else goal
        with torch.no_grad():
            a = model(torch.as_tensor(o["observation"]).float(), pursued).numpy()
        if sigma:
            a = np.clip(a + sigma * rng.standard_normal(a.shape), -1.0, 1.0)
        obs.append(o["observation"])
        act.append(a)
        o, _, _, _, info = env.step(a)
        ag.append(o["achieved_goal"])
    rows = {"obs": torch.as_tensor(np.array(obs)).float(), "act": torch.as_tensor(np.array(act)).float(),
            "ag": torch.as_tensor(np.array(ag)).float()}
    return rows, bool(info["is_success"])


def store_rows(memory: TensorDictReplayBuffer, rows: dict[str, torch.Tensor]) -> None:
    """Append rows (``obs``, ``act``, ``ag``, ``ep``) to a memory :func:`read_rows` reads back."""
    memory.extend(TensorDict({"observation": rows["obs"], "action": rows["act"],
                              ("next", "achieved_goal"): rows["ag"], ("collector", "traj_ids"): rows["ep"]},
                             batch_size=[rows["obs"].shape[0]]))


def episode_seed(seed: int, r: int, e: int) -> int:
    """The reset seed of collection episode ``e`` of round ``r`` (its env goal: the proposer's ``near``)."""
    return 1_000_000 * (seed + 1) + 100 * r + e


def gcsl(paths: list[str], horizon: int, steps: int, rounds: int, sigma: float, seed: int, log,
         episodes: int = 100, memory_out: str | None = None, propose_rate: float = 0.0, stop_at: float | None = None,
         candidates: str = "uniform", reached_in: int = 0, eval_seed: int = EVAL_SEED) -> list[dict]:
    """Clone, then ``rounds`` of: 100 noisy episodes with the clone, added to the data, cloned further.

    Each clone is evaluated on ``episodes`` deterministic episodes (the goals of :func:`eval_goals`).

    Args:
        memory_out: a new memory (:class:`ZarrStorage`, no capacity) that holds every row the rounds
            learn from: the starting memories' rows, then each round's episodes as they are collected;
            a second run reads it (``gcsl memory_out ...``).
        propose_rate: the probability that a collection episode pursues a goal a
            :class:`~torchrl_robotmem.GoalProposer` over ``memory_out`` proposes (the stored achieved goal
            of lowest density among 100 candidates, MEGA) instead of the env's own; ``0`` (the control):
            every episode pursues the env's goal. Evaluation always uses the env's goals.
        stop_at: stop after the first evaluation at or above this success (a second run: frames it needed).
        eval_seed: the evaluation goals are ``reset(seed=eval_seed + i)``: :data:`EVAL_SEED` (the evaluation),
            or :data:`HELDOUT_SEED` where a setting is being chosen (recorded as ``eval_seed`` then).
        candidates: the proposer's candidates: ``"uniform"`` (among every stored row) or ``"near_goal"``
            (the 100 stored achieved goals nearest the goal the env drew for the episode).
        reached_in: the proposer's ``reached_in``: only goals the memory reached in this many episodes compete.
    """
    torch.manual_seed(seed)
    gen, rng = torch.Generator().manual_seed(seed), np.random.default_rng(seed)
    data = read_rows(paths)
    model = InverseModel(data)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    env = gym.make(ENV)
    memory = proposer = None
    if memory_out is not None:
        memory = TensorDictReplayBuffer(storage=ZarrStorage(memory_out, env=ENV, goal_conditioned=False))
        store_rows(memory, data)
    if propose_rate:
        if memory is None:
            raise ValueError("propose_rate > 0 proposes from memory_out: give --memory-out")
        proposer = GoalProposer(memory, ENV, rate=propose_rate, warmup_rows=0, seed=seed, candidates=candidates,
                                reached_in=reached_in)
    coin = torch.Generator().manual_seed(seed + 1)
    results, new_frames, cpu = [], 0, time.process_time()
    for r in range(rounds + 1):
        loss = fit(model, opt, data, horizon, steps, gen)
        outcomes = [rollout(env, model, eval_seed + e, 0.0, rng)[1] for e in range(episodes)]
        success = np.mean(outcomes)
        line = {"what": "gcsl" if rounds else "clone", "memories": paths, "horizon": horizon, "seed": seed,
                "round": r, "steps": steps, "new_frames": new_frames, "memory_rows": int(data["obs"].shape[0]),
                "success": float(success), "loss": loss, "cpu_s": round(time.process_time() - cpu, 1),
                "propose_rate": propose_rate, "outcomes": "".join("1" if o else "0" for o in outcomes)}
        if eval_seed != EVAL_SEED:  # held-out goals
            line["eval_seed"] = eval_seed
        if proposer is not None:
            line.update(proposed=proposer.proposed, propose_s=round(proposer.seconds, 2), candidates=candidates)
            if reached_in:
                line["reached_in"] = reached_in
        results.append(line)
        log(results[-1])
        if r == rounds or (stop_at is not None and success >= stop_at):
            break
        proposed = 0
        if proposer is not None:
            chosen = torch.rand(100, generator=coin) < propose_rate
            near = torch.stack([torch.as_tensor(env.reset(seed=episode_seed(seed, r, e))[0]["desired_goal"]).float()
                                for e in range(100) if chosen[e]]) if bool(chosen.any()) else None
            goals = proposer.propose(int(chosen.sum()), near=near)
            proposed = 0 if goals is None else goals.shape[0]
            proposer.proposed += proposed
        for e in range(100):
            goal = goals[int(chosen[:e].sum())] if proposed and chosen[e] else None
            rows, _ = rollout(env, model, episode_seed(seed, r, e), sigma, rng, goal=goal)
            rows["ep"] = torch.full((50,), int(data["ep"].max()) + 1)
            data = {k: torch.cat([data[k], rows[k]]) for k in data}
            if memory is not None:
                store_rows(memory, rows)
            new_frames += 50
    env.close()
    if memory is not None:
        memory.storage.close()
    return results


def plot(runs: list[str], results: list[str], png: str) -> None:
    """Evaluation curves of the runs, and the clone / gcsl lines of ``results`` at their memory's frames (+ new ones)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for spec in runs:
        name, run_dir = spec.split("=", 1)
        curve = load_run(run_dir)["curve"]
        ax.plot([f / 1000 for f, _ in curve], [s for _, s in curve], marker=".", label=name)
    for path in results:
        rows = [json.loads(line) for line in open(path)]
        for what, marker in (("clone", "*"), ("gcsl", "x")):
            for horizon in sorted({r["horizon"] for r in rows if r["what"] == what}):
                pts = [r for r in rows if r["what"] == what and r["horizon"] == horizon]
                memory = min(r["memory_rows"] - r["new_frames"] for r in pts)  # the memory's own frames
                ax.plot([(memory + r["new_frames"]) / 1000 for r in pts], [r["success"] for r in pts], marker,
                        markersize=10 if what == "clone" else 7, linestyle="-" if what == "gcsl" else "none",
                        label=(f"hindsight clone of the SAC seed-1 memory, horizon {horizon}" if what == "clone" else
                               f"GCSL rounds from that memory (5k frames each), horizon {horizon}"))
    ax.axhline(0.1, color="grey", linestyle=":", linewidth=1)
    ax.text(0.99, 0.06, "rest-pose goals (10%)", color="grey", fontsize=8, ha="right",
            transform=ax.get_yaxis_transform())
    _finish(fig, ax, "env frames (thousands)", "HandReach-v3", png)


def curves(results: list[str], png: str) -> None:
    """Success against frames in all (the memory's rows), one line a seed, one colour a result file (an arm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    colours = plt.get_cmap("tab10")
    for j, spec in enumerate(results):
        label, _, path = spec.rpartition("=")
        rows = [json.loads(line) for line in open(path) if line.strip()]
        for i, seed in enumerate(sorted({r["seed"] for r in rows})):
            pts = sorted((r for r in rows if r["seed"] == seed), key=lambda r: r["round"])
            ax.plot([r["memory_rows"] / 1000 for r in pts], [r["success"] for r in pts], color=colours(j % 10),
                    alpha=0.8, linestyle=("-", "--", ":")[i % 3], label=(label or path) if i == 0 else None)
    _finish(fig, ax, "env frames in all (thousands; the first 10k random)",
            "HandReach-v3, GCSL (one line a seed: -, --, :)", png)


def _finish(fig, ax, xlabel: str, title: str, png: str) -> None:
    """The 0.9 goal line, the labels and legend of a success-against-frames figure; saved to ``png``."""
    ax.axhline(0.9, color="black", linestyle="--", linewidth=1)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("evaluated success (100 episodes)")
    ax.set_title(title)
    ax.set_ylim(-0.02, 1.0)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["cover", "clone", "gcsl", "plot", "curves"])
    parser.add_argument("memories", nargs="*", help="HandReach memories (ZarrStorage paths); plot: result files")
    parser.add_argument("--horizon", type=int, nargs="+", default=[3], help="relabelling horizons (clone: each)")
    parser.add_argument("--steps", type=int, default=5000, help="Adam steps of the clone (a gcsl round: this many)")
    parser.add_argument("--rounds", type=int, default=5, help="gcsl: collect-and-clone rounds of 100 episodes")
    parser.add_argument("--sigma", type=float, default=0.1, help="gcsl: action noise while collecting")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-seed", type=int, default=EVAL_SEED,
                        help=f"evaluation goals reset(seed=EVAL_SEED + i); {HELDOUT_SEED}: held-out goals, to choose a "
                             f"setting on (default {EVAL_SEED}: the evaluation's)")
    parser.add_argument("--episodes", type=int, default=100,
                        help="evaluation episodes of a clone (cover: twice as many goals)")
    parser.add_argument("--memory-out", default=None,
                        help="gcsl: a new memory of every row the rounds learn from (the proposer's; a second run's)")
    parser.add_argument("--candidates", choices=["uniform", "near_goal"], default="uniform",
                        help="gcsl: the proposer's candidates (GoalProposer(candidates=...))")
    parser.add_argument("--reached-in", type=int, default=0,
                        help="gcsl: the proposer's reached_in (only goals reached in this many episodes compete)")
    parser.add_argument("--propose-rate", type=float, default=0.0,
                        help="gcsl: share of collection episodes that pursue a GoalProposer's goal (0: the control)")
    parser.add_argument("--stop-at", type=float, default=None, help="gcsl: stop at this evaluated success")
    parser.add_argument("--out", default=None, help="also append the JSON lines to this file (plot: read them)")
    parser.add_argument("--runs", nargs="*", default=[], help="plot: NAME=RUN_DIR of recipe runs")
    parser.add_argument("--png", default="hand_reach.png", help="plot: the figure")
    args = parser.parse_args(argv)
    gym.register_envs(gymnasium_robotics)
    torch.set_num_threads(1)

    def log(row: dict) -> None:
        print(json.dumps(row), flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")

    if args.what == "plot":
        plot(args.runs, args.memories + ([args.out] if args.out else []), args.png)
        return
    if args.what == "curves":  # memories: LABEL=RESULT_FILE of gcsl runs
        curves(args.memories, args.png)
        return
    if not args.memories:
        parser.error(f"{args.what} needs at least one memory path")
    if args.what == "cover":
        log(cover(args.memories, n=2 * args.episodes))
        return
    for horizon in args.horizon:
        gcsl(args.memories, horizon, args.steps, args.rounds if args.what == "gcsl" else 0, args.sigma, args.seed, log,
             episodes=args.episodes, memory_out=args.memory_out, propose_rate=args.propose_rate, stop_at=args.stop_at,
             candidates=args.candidates, reached_in=args.reached_in, eval_seed=args.eval_seed)


if __name__ == "__main__":
    main()
