"""Learning benchmarks of the HER recipe (``recipes/her/train.py``), against Stable-Baselines3.

Every TorchRL figure comes from running the recipe itself as a subprocess
(hydra overrides shown in the output); SB3 runs in its own subprocess in the
same benchmark run, interleaved seed by seed, so ratios compare like with like
on a shared machine. CPU-seconds are process CPU time of the training loop,
evaluation excluded, one torch thread on both sides.

    python benchmarks/bench_learning.py reach --seeds 5      # 1 + 2: SAC+HER vs SB3, then a 2nd run on the memory
    python benchmarks/bench_learning.py algos --seeds 3      # 3: TD3+HER, DDPG+HER
    python benchmarks/bench_learning.py ablations --seeds 5  # 4: goal sampler, recall transform
    python benchmarks/bench_learning.py budget --cpu 600     # 5: HandReach-v3, FetchPush-v4 for a CPU budget
    python benchmarks/bench_learning.py report               # tables (markdown) and plots from the results

Results are written as they come to ``bench_results/learning/`` (git-ignored),
plots to ``docs/img/``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench_results" / "learning"
IMG = ROOT / "docs" / "img"
RECIPE = ROOT / "recipes" / "her" / "train.py"
TARGET = 0.95
EVAL_EVERY = 250
EVAL_EPISODES = 20


# -- runners -----------------------------------------------------------------


def run_recipe(name: str, *overrides: str, fresh: bool = True) -> dict:
    """Runs the recipe; returns its summary.json (saved as RESULTS/<name>.json)."""
    if (RESULTS / f"{name}.json").exists() and os.environ.get("BENCH_RESUME"):
        return json.loads((RESULTS / f"{name}.json").read_text())
    out = RESULTS / "runs" / name
    if fresh and out.exists():
        subprocess.run(["rm", "-rf", str(out)], check=True)
    cmd = [
        sys.executable, str(RECIPE), *overrides,
        f"hydra.run.dir={out}", "logger.plot=false",
        f"logger.eval_iter={EVAL_EVERY}", f"logger.eval_episodes={EVAL_EPISODES}",
    ]
    print("$", " ".join(cmd[1:]).replace(str(ROOT) + "/", ""), flush=True)
    t0 = time.time()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if proc.returncode:
        print(proc.stdout[-2000:], proc.stderr[-4000:])
        raise RuntimeError(f"recipe run {name} failed")
    summary = json.loads((out / "summary.json").read_text())
    summary["wall_s"] = round(time.time() - t0, 1)
    summary["command"] = "python " + " ".join(cmd[1:]).replace(str(ROOT) + "/", "")
    _save(name, summary)
    print(f"  -> frames to {TARGET}: {summary['frames_to_target']}, CPU-s {summary['cpu_s']}", flush=True)
    return summary


def run_sb3(name: str, seed: int, total_frames: int = 10_000) -> dict:
    cmd = [sys.executable, __file__, "_sb3", "--seed", str(seed), "--frames", str(total_frames), "--name", name]
    print("$", "python benchmarks/bench_learning.py _sb3 --seed", seed, flush=True)
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if proc.returncode:
        print(proc.stdout[-2000:], proc.stderr[-4000:])
        raise RuntimeError(f"SB3 run {name} failed")
    summary = json.loads((RESULTS / f"{name}.json").read_text())
    print(f"  -> frames to {TARGET}: {summary['frames_to_target']}, CPU-s {summary['cpu_s']}", flush=True)
    return summary


def _sb3_worker(seed: int, total_frames: int, name: str) -> None:
    """SB3 SAC+HER with the rl-zoo FetchReach settings (no TimeFeatureWrapper: sb3-contrib is not a dependency)."""
    try:
        import farama_notifications

        farama_notifications.notifications.pop("gymnasium_robotics", None)
    except ImportError:
        pass
    import gymnasium as gym
    import gymnasium_robotics
    import numpy as np
    import torch
    from stable_baselines3 import SAC, HerReplayBuffer
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(1)
    gym.register_envs(gymnasium_robotics)
    env = VecNormalize(DummyVecEnv([lambda: gym.make("FetchReach-v4")]), gamma=0.95)
    env.seed(seed)
    eval_env = gym.make("FetchReach-v4")
    model = SAC(
        "MultiInputPolicy", env,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs=dict(n_sampled_goal=4, goal_selection_strategy="future"),
        buffer_size=1_000_000, batch_size=256, ent_coef="auto", gamma=0.95,
        learning_rate=1e-3, learning_starts=1000,
        policy_kwargs=dict(net_arch=[64, 64], n_critics=1), seed=seed, verbose=0,
    )

    class Eval(BaseCallback):
        def _on_training_start(self):
            self.start, self.excluded, self.curve, self.reached = time.process_time(), 0.0, [], None
            self.evaluate()

        def evaluate(self):
            t0 = time.process_time()
            successes = []
            for i in range(EVAL_EPISODES):  # fixed goals, as the recipe's evaluation
                obs, _ = eval_env.reset(seed=10_000 + i)
                for _ in range(50):
                    action, _ = model.predict(env.normalize_obs(obs), deterministic=True)
                    obs, _, _, _, info = eval_env.step(action)
                successes.append(float(info["is_success"]))
            rate = float(np.mean(successes))
            self.excluded += time.process_time() - t0
            self.curve.append((self.num_timesteps, rate))
            if rate >= TARGET and self.reached is None:
                self.reached = self.num_timesteps
            return rate

        def _on_step(self):
            if self.num_timesteps % EVAL_EVERY == 0:
                return self.evaluate() < TARGET
            return True

        def cpu(self):
            return time.process_time() - self.start - self.excluded

    cb = Eval()
    model.learn(total_frames, callback=cb)
    _save(name, {
        "impl": "sb3", "env": "FetchReach-v4", "algo": "SAC", "seed": seed,
        "frames": cb.num_timesteps, "frames_to_target": cb.reached, "cpu_s": round(cb.cpu(), 2),
        "curve": cb.curve, "sb3_version": __import__("stable_baselines3").__version__,
    })


def _save(name: str, summary: dict) -> None:
    path = RESULTS / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(summary))


def _load(prefix: str) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(RESULTS.glob(f"{prefix}*.json"))]


# -- experiments ---------------------------------------------------------------


def reach(seeds: int) -> None:
    """1: SAC+HER vs SB3 on FetchReach; 2: a second run, fresh networks, on the first run's memory."""
    for s in range(seeds):
        if all((RESULTS / f"{n}-seed{s}.json").exists() for n in ("reach/torchrl", "reach/sb3", "memory/second")):
            continue  # done in an earlier, interrupted benchmark run
        mem = RESULTS / "memory" / f"reach-seed{s}.zarr"
        subprocess.run(["rm", "-rf", str(mem), f"{mem}-agent", f"{mem}-runs.jsonl"], check=True)
        common = [f"memory.path={mem}", f"logger.target_success={TARGET}"]
        run_recipe(f"reach/torchrl-seed{s}", f"seed={s}", *common)
        run_sb3(f"reach/sb3-seed{s}", s)
        run_recipe(f"memory/second-seed{s}", f"seed={s + 100}", *common)


def algos(seeds: int) -> None:
    """3: TD3+HER and DDPG+HER on FetchReach (fresh memories)."""
    for s in range(seeds):
        for algo in ("td3", "ddpg"):
            mem = RESULTS / "memory" / f"{algo}-seed{s}.zarr"
            subprocess.run(["rm", "-rf", str(mem), f"{mem}-agent", f"{mem}-runs.jsonl"], check=True)
            run_recipe(f"algos/{algo}-seed{s}", f"algo={algo}", f"seed={s}", f"memory.path={mem}",
                       f"logger.target_success={TARGET}")


def ablations(seeds: int) -> None:
    """4: GoalSimilaritySampler on/off, RecallTransform on/off; the control (both off) runs interleaved."""
    variants = {
        "off": [],
        "sampler": ["replay_buffer.sampler.enabled=true"],
        "recall": ["memory.recall.enabled=true"],
        "both": ["replay_buffer.sampler.enabled=true", "memory.recall.enabled=true"],
    }
    for s in range(seeds):
        for name, extra in variants.items():
            mem = RESULTS / "memory" / f"{name}-seed{s}.zarr"
            subprocess.run(["rm", "-rf", str(mem), f"{mem}-agent", f"{mem}-runs.jsonl"], check=True)
            run_recipe(f"ablations/{name}-seed{s}", f"seed={s}", f"memory.path={mem}",
                       f"logger.target_success={TARGET}", *extra)


def budget(cpu_s: int, envs: list[str]) -> None:
    """5: HandReach-v3 / FetchPush-v4 for a fixed CPU budget, and the random-policy rate."""
    for env in envs:
        mem = RESULTS / "memory" / f"budget-{env}.zarr"
        subprocess.run(["rm", "-rf", str(mem), f"{mem}-agent", f"{mem}-runs.jsonl"], check=True)
        summary = run_recipe(
            f"budget/{env}", f"env={env}", "seed=0", f"memory.path={mem}",
            f"collector.cpu_budget_s={cpu_s}", "collector.total_frames=10_000_000",
        )
        summary["random_success"] = random_success(summary["env"])
        _save(f"budget/{env}", summary)


def random_success(env_id: str, episodes: int = 100) -> float:
    """Success (is_success at the last step) of a uniform-random policy."""
    sys.path.insert(0, str(RECIPE.parent))
    import torch
    import utils  # noqa: F401  (silences the gymnasium-robotics import notice)

    from torchrl_robotmem import make_env

    env = make_env(env_id, num_envs=10, seed=12345)
    rates = []
    for _ in range(episodes // 10):
        rollout = env.rollout(env.max_episode_steps, break_when_any_done=False)
        rates.append(rollout["next", "is_success"][:, -1].float().mean().item())
    env.close()
    return round(float(torch.tensor(rates).mean()), 3)


# -- report ---------------------------------------------------------------------


def _reached(run) -> int | None:
    """First evaluated frame at or above TARGET, from the curve: runs before the float64 fix in
    ``utils.evaluate`` logged 19/20 as 0.9499999 and went on past a 0.95 they had reached."""
    return next((f for f, s in run["curve"] if s >= TARGET - 1e-6), None)


def _frames(runs):
    return [_reached(r) for r in runs]


def _med(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def report() -> None:
    tr, sb = _load("reach/torchrl-seed"), _load("reach/sb3-seed")
    second = _load("memory/second-seed")
    lines = []
    if tr:
        lines.append("### 1. FetchReach-v4, SAC+HER: TorchRL recipe vs SB3 (same benchmark run)\n")
        lines.append("| seed | recipe frames to 0.95 | recipe CPU-s | SB3 frames to 0.95 | SB3 CPU-s | CPU ratio |")
        lines.append("|---:|---:|---:|---:|---:|---:|")
        ratios = []
        for a, b in zip(tr, sb):
            ratio = a["cpu_s"] / b["cpu_s"] if b else None
            ratios.append(ratio)
            lines.append(f"| {a['seed']} | {a['frames_to_target']} | {a['cpu_s']:.1f} | "
                         f"{b['frames_to_target']} | {b['cpu_s']:.1f} | {ratio:.2f} |")
        fr = [a["frames_to_target"] / b["frames_to_target"] for a, b in zip(tr, sb)
              if a["frames_to_target"] and b["frames_to_target"]]
        lines.append(f"| **median** | **{_med(_frames(tr))}** | **{_med([r['cpu_s'] for r in tr]):.1f}** | "
                     f"**{_med(_frames(sb))}** | **{_med([r['cpu_s'] for r in sb]):.1f}** | "
                     f"**{_med(ratios):.2f}** |")
        lines.append(f"\nFrames ratio (recipe / SB3), median of seeds: {_med(fr):.2f}.\n")
    if second:
        lines.append("### 2. Second run, fresh networks, on the first run's memory\n")
        lines.append("| seed | memory rows | new frames to 0.95 | CPU-s (incl. pretraining updates) | first run's frames |")
        lines.append("|---:|---:|---:|---:|---:|")
        for a, b in zip(second, tr):
            lines.append(f"| {b['seed']} | {a['memory_rows_before']} | {a['frames_to_target']} | "
                         f"{a['cpu_s']:.1f} | {b['frames_to_target']} |")
        lines.append(f"| **median** | | **{_med(_frames(second))}** | "
                     f"**{_med([r['cpu_s'] for r in second]):.1f}** | **{_med(_frames(tr))}** |\n")
    groups = {
        "SAC (item 1 runs)": tr,
        "TD3": _load("algos/td3-seed"), "DDPG": _load("algos/ddpg-seed"),
        "SAC, both off (ablation control)": _load("ablations/off-seed"),
        "SAC + GoalSimilaritySampler": _load("ablations/sampler-seed"),
        "SAC + RecallTransform": _load("ablations/recall-seed"),
        "SAC + both": _load("ablations/both-seed"),
    }
    if any(groups.values()):
        lines.append("### 3-4. Frames to 0.95 on FetchReach-v4 by variant\n")
        lines.append("| variant | seeds | frames to 0.95 per seed | median | min-max | median CPU-s |")
        lines.append("|---|---:|---|---:|---|---:|")
        for label, runs in groups.items():
            if not runs:
                continue
            fr = _frames(runs)
            ok = [x for x in fr if x is not None]
            span = f"{min(ok)}-{max(ok)}" if ok else "-"
            lines.append(f"| {label} | {len(runs)} | {', '.join(str(x) for x in fr)} | {_med(fr)} | {span} | "
                         f"{_med([r['cpu_s'] for r in runs]):.1f} |")
        lines.append("")
    for run in _load("budget/"):
        best = max(s for _, s in run["curve"])
        lines.append(f"### 5. {run['env']}: {run['cpu_s']:.0f} CPU-s, {run['frames']} frames: final eval success "
                     f"{run['curve'][-1][1]:.2f} (best {best:.2f}); random policy {run.get('random_success')}\n")
    print("\n".join(lines))
    plots(tr, sb, second)


def plots(tr, sb, second) -> None:
    sys.path.insert(0, str(RECIPE.parent))
    from run_record import plot_success

    IMG.mkdir(parents=True, exist_ok=True)
    if tr:
        curves = {f"TorchRL seed {r['seed']}": r["curve"] for r in tr}
        curves.update({f"SB3 seed {r['seed']}": r["curve"] for r in sb})
        plot_success(curves, str(IMG / "reach_sac_vs_sb3.png"), "FetchReach-v4, SAC+HER: TorchRL recipe vs SB3")
    if second:
        curves = {}
        for a, b in zip(tr, second):
            curves[f"run 1 seed {a['seed']} (empty memory)"] = a["curve"]
            curves[f"run 2 seed {a['seed']} ({b['memory_rows_before']} rows)"] = b["curve"]
        plot_success(curves, str(IMG / "reach_memory_second_run.png"),
                     "FetchReach-v4: fresh networks, empty vs remembered memory")
    plot_ablations()
    for run in _load("budget/"):
        plot_success({f"{run['algo']}+HER": run["curve"], "random policy": [
            (0, run.get("random_success", 0)), (run["frames"], run.get("random_success", 0))]},
            str(IMG / f"budget_{run['env']}.png"), f"{run['env']}, {run['cpu_s']:.0f} CPU-s")
    print(f"plots in {IMG.relative_to(ROOT)}/")


ABLATIONS = {
    "off": "both off (control)", "sampler": "+ GoalSimilaritySampler",
    "recall": "+ RecallTransform", "both": "+ both",
}


def plot_ablations() -> None:
    """One panel per ablation variant, every seed's eval curve, the median frames to 0.95 marked."""
    runs = {k: _load(f"ablations/{k}-seed") for k in ABLATIONS}
    runs = {k: v for k, v in runs.items() if v}
    if not runs:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(runs), figsize=(3.2 * len(runs), 3.4), sharey=True, sharex=True)
    for ax, (key, group) in zip(list(axes) if len(runs) > 1 else [axes], runs.items()):
        for r in group:
            frames, success = zip(*r["curve"])
            ax.plot(frames, success, marker="o", markersize=2, lw=1, label=f"seed {r['seed']}")
        med = _med(_frames(group))
        if med is not None:
            ax.axvline(med, color="k", lw=0.8, ls=":")
        ax.axhline(TARGET, color="grey", lw=0.8, ls="--")
        ax.set(title=f"SAC {ABLATIONS[key]}\nmedian {med} frames", xlabel="env frames", ylim=(-0.02, 1.02))
        ax.grid(alpha=0.3)
    (axes[0] if len(runs) > 1 else axes).set_ylabel("eval success rate")
    (axes[0] if len(runs) > 1 else axes).legend(fontsize=7)
    fig.suptitle("FetchReach-v4, SAC+HER: memory components on/off", fontsize=10)
    fig.tight_layout()
    fig.savefig(IMG / "reach_ablations.png", dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["reach", "algos", "ablations", "budget", "report", "all", "_sb3"])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--cpu", type=int, default=600, help="CPU-seconds per env for 'budget'")
    parser.add_argument("--envs", default="hand_reach,push", help="env= groups for 'budget'")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--name", default="sb3")
    args = parser.parse_args()
    if args.what == "_sb3":
        return _sb3_worker(args.seed, args.frames, args.name)
    if args.what in ("reach", "all"):
        reach(args.seeds)
    if args.what in ("algos", "all"):
        algos(min(args.seeds, 3) if args.what == "all" else args.seeds)
    if args.what in ("ablations", "all"):
        ablations(args.seeds)
    if args.what in ("budget", "all"):
        budget(args.cpu, args.envs.split(","))
    report()


if __name__ == "__main__":
    os.environ.setdefault("PYTHONWARNINGS", "ignore::DeprecationWarning")
    main()
