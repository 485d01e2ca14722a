"""Cross-environment transfer: do FetchPush memories help a scripted FetchSlide controller?

One command builds the memories, runs every arm on the same FetchSlide episodes
(paired by env seed), and writes ``results.json``, ``report.md`` and
``cross_env.png`` to ``--out``:

    python -m experiments.cross_env.run                   # the pre-registered experiment (docs/cross_env.md)
    python -m experiments.cross_env.run seeds=1 episodes=2 push_episodes=2 slide_episodes=2 \
        tune_episodes=2 speeds=0.8 out=/tmp/cross_env # smoke run
    python -m experiments.cross_env.run learned_only=true learned_frames=60000 learned_jobs=2  # the learned arm alone, resumable
    python -m experiments.cross_env.run learned_only=true learned_frames=60000 learned_arms=clone  # ... its clone runs

Per seed (replicate) ``s`` one memory (a :class:`~torchrl_robotmem.ZarrStorage`)
holds ``push_episodes`` noisy scripted FetchPush episodes and ``slide_episodes``
noisy FetchSlide episodes (``experiments.scripted.collect``); every arm then runs the
same ``episodes`` FetchSlide env seeds. What the memory may change, the key it
is searched by, ``k`` and the filters are fixed in :data:`PREREGISTERED`.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from tensordict import TensorDict

from experiments.scripted.collect import DISTANCE_SCALE, collect, episode_geometry, gym_episodes, kv_args, open_memory
from experiments.scripted.controllers import StrikeParams, default_params
from experiments.scripted.recall_params import SUCCESS_KEY, episode_index, mean_params, recall_episodes
from recipes.her.tools.stats import mcnemar, wilson

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository
PUSH, SLIDE = "FetchPush-v4", "FetchSlide-v4"

#: Fixed before the main run (docs/cross_env.md, "Pre-registration").
PREREGISTERED = {
    "primary": ("pooled_memory", "pooled_control"),
    "alpha": 0.01,
    "min_effect": 0.10,
    "k": 5,
    # what memory supplies: how to strike. Where the stroke ends (strike_length,
    # strike_reach) is the task's own choice and stays at FetchSlide's defaults.
    "supplied": ["approach_offset", "approach_height", "strike_height", "aim_angle", "strike_speed"],
    "key": "geometry/scaled_distance",   # object->target xy distance / the task's median distance
    "raw_key": "geometry/distance",      # secondary arm push_memory_raw only
    "success_only": True,                # episode_success > 0.5
    "tuned": "strike_speed",             # the baseline's only tuned parameter, on held-out seeds
}

#: arm -> (label, description)
ARMS: dict[str, tuple[str, str]] = {
    "baseline": ("baseline", "tuned default parameters"),
    "push_control": ("Push control", "mean of the supplied parameters over all FetchPush successes"),
    "push_memory": ("Push memory", "mean over the k FetchPush successes nearest in scaled distance"),
    "push_memory_raw": ("Push memory (raw)", "the same, nearest in raw distance (secondary)"),
    "pooled_control": ("pooled control", "mean over all FetchSlide successes of the pooled memory "
                       "(FetchPush successes only if it has none)"),
    "pooled_memory": ("pooled memory", "mean over the k FetchSlide successes nearest in scaled distance, "
                      "topped up with the nearest FetchPush successes"),
    "pooled_mixed": ("pooled, env-blind", "mean over the k successes of either env nearest in scaled "
                     "distance (secondary)"),
}

# Env seeds: disjoint ranges for tuning, memories and evaluation.
_TUNE_SEED = 900_000
_EVAL_SEED = 10_000_000


def _eval_seeds(replicate: int, episodes: int) -> list[int]:
    return [_EVAL_SEED + replicate * 100_000 + i for i in range(episodes)]


# -- arms ----------------------------------------------------------------------------

ParamFn = Callable[[int, np.ndarray, np.ndarray], StrikeParams]


def run_arm(param_fn: ParamFn, seeds: list[int]) -> tuple[np.ndarray, list[float]]:
    """FetchSlide outcomes (0/1, last-step ``is_success``) and strike speeds, one per env seed."""
    outcomes, speeds = [], []
    for td in gym_episodes("slide", param_fn, seeds):
        outcomes.append(float(td["episode_success"][0]))
        speeds.append(float(td["params", "strike_speed"][0]))
    return np.asarray(outcomes), speeds


def tune_baseline(speeds: list[float], episodes: int, log=print) -> tuple[StrikeParams, dict]:
    """FetchSlide defaults with the strike speed that succeeds most on held-out env seeds."""
    seeds = [_TUNE_SEED + i for i in range(episodes)]
    table = {}
    for v in speeds:
        p = dataclasses.replace(default_params("slide"), strike_speed=float(v))
        table[float(v)] = float(run_arm(lambda e, o, g, p=p: p, seeds)[0].mean())
        log(f"tune: strike_speed={v:.2f} -> {table[float(v)]:.1%} on {episodes} held-out episodes")
    best = max(table, key=lambda v: (table[v], -abs(v - default_params("slide").strike_speed)))
    return dataclasses.replace(default_params("slide"), strike_speed=best), table


def _key(name: str) -> tuple[str, str]:
    return tuple(name.split("/"))  # type: ignore[return-value]


def make_arms(storage, baseline: StrikeParams, k: int) -> dict[str, ParamFn]:
    """Parameter sources of every scripted arm over one memory."""
    names = PREREGISTERED["supplied"]
    scaled = episode_index(storage, _key(PREREGISTERED["key"]))
    raw = episode_index(storage, _key(PREREGISTERED["raw_key"]))

    def apply(means: dict | None) -> StrikeParams:
        return baseline if means is None else dataclasses.replace(baseline, **means)

    def successes(env: str):
        # first row of each successful episode of ``env``; columns read one by one, since
        # a ZarrStorage's row reads leave out its tags (env, episode, run) by default
        keep = ((storage[SUCCESS_KEY] > 0.5) & (storage["env"] == storage.env_code(env))
                & (storage["step_count"].reshape(-1) == 0))
        rows = torch.nonzero(keep).reshape(-1)
        return TensorDict({("params", n): storage[("params", n)][rows] for n in names}, [rows.numel()])

    push_mean = apply(mean_params(successes(PUSH), names))
    slide_rows = successes(SLIDE)
    pooled_mean = apply(mean_params(slide_rows, names)) if slide_rows.shape[0] else push_mean

    def geometry(obs, goal):
        geo = episode_geometry("slide", obs, goal)
        return float(geo["scaled_distance"][0]), float(geo["distance"][0])

    def push_memory(e, obs, goal):
        q, _ = geometry(obs, goal)
        return apply(mean_params(recall_episodes(scaled, q, k, env=PUSH), names))

    def push_memory_raw(e, obs, goal):
        _, d = geometry(obs, goal)
        return apply(mean_params(recall_episodes(raw, d, k, env=PUSH), names))

    def pooled_memory(e, obs, goal):
        q, _ = geometry(obs, goal)
        own = recall_episodes(scaled, q, k, env=SLIDE)
        if own.shape[0] < k:
            other = recall_episodes(scaled, q, k - own.shape[0], env=PUSH)
            own = torch.cat([own, other.select(*own.keys(True, True))]) if own.shape[0] else other
        return apply(mean_params(own, names))

    def pooled_mixed(e, obs, goal):
        q, _ = geometry(obs, goal)
        return apply(mean_params(recall_episodes(scaled, q, k, env=[PUSH, SLIDE]), names))

    return {
        "baseline": lambda e, o, g: baseline,
        "push_control": lambda e, o, g: push_mean,
        "push_memory": push_memory,
        "push_memory_raw": push_memory_raw,
        "pooled_control": lambda e, o, g: pooled_mean,
        "pooled_memory": pooled_memory,
        "pooled_mixed": pooled_mixed,
    }


# the learned arm's runs: recipes/her overrides on top of env=slide (the clone arm is the recipe that met the
# FetchPush and PickAndPlace goals at frame 0, docs/results.md sections 11-12: experiments.prior_variants.train)
LEARNED_ARMS: dict[str, list[str]] = {
    "prior": ["prior=mix"],
    "scratch": [],
    # prior=clone: prior.clone_steps=4000 prior.freeze_normalizer=true prior.actor_update=crr
    "clone": ["algo=td3", "prior=clone", "collector.init_random_frames=0"],
}


def learned_arm(memory: str | None, *, frames: int, seeds: int, workdir: str,
                eval_episodes: int = 100, eval_iter: int = 2500, overrides: list[str] | None = None,
                jobs: int = 1, arms: tuple[str, ...] = ("prior", "scratch"), log=print) -> dict:
    """FetchSlide SAC+HER (``recipes/her``) with ``memory`` as a read-only prior vs from scratch.

    Both arms run the same recipe, seeds and frame budget; the prior arm adds
    ``prior=mix 'prior.paths=[memory]'`` (sampled as half of every batch, rewards recomputed
    for FetchSlide, hindsight relabelling on its rows too). The optional
    ``clone`` arm clones the memory's successful episodes into a TD3 actor
    before the first frame and then trains it by critic-regularised regression
    (:data:`LEARNED_ARMS`), with the memory as prior too. Each run is a
    subprocess writing its own memory, hydra logs and curve (``summary.json``)
    under ``workdir/learned``. Runs are launched with
    ``collector.resume=true``: the command run again continues runs that were
    stopped and keeps finished ones (``learned_only=true`` skips the scripted arms).

    Args:
        memory: the pooled memory (FetchPush + FetchSlide scripted episodes).
        frames: new env frames per run; ``0`` skips the arm (hours on a CPU).
        seeds: training seeds per arm.
        workdir: where the runs' memories, hydra logs and ``summary.json`` go (resumable state).
        eval_episodes / eval_iter: deterministic evaluation episodes, every this many frames.
        overrides: extra hydra overrides for both arms (e.g. ``["collector.cpu_budget_s=3000"]``).
        jobs: runs at a time (each is one single-threaded process: ``2`` on a 2-core machine);
            seed ``i``'s runs of every arm go first, so a cut-off arm stays paired.
        arms: which of :data:`LEARNED_ARMS` to run (``prior`` and ``scratch`` by default).
    """
    if frames <= 0 or memory is None:
        return {"status": "not run",
                "reason": "learned_frames=0; set learned_frames=N (about 75 CPU-ms a frame here) to run it"}
    recipe = [sys.executable, os.path.join(ROOT, "recipes", "her", "train.py")]
    variants = [sys.executable, "-m", "experiments.prior_variants.train"]  # the clone arm: recipes/her + prior=clone
    if jobs < 1:
        raise ValueError(f"learned_jobs must be >= 1, got {jobs}")
    unknown = [a for a in arms if a not in LEARNED_ARMS]
    if unknown or not arms:
        raise ValueError(f"learned_arms must name some of {', '.join(LEARNED_ARMS)}, got {','.join(arms)!r}")

    def run_one(seed: int, arm: str) -> dict:
        name = f"{arm}-s{seed}"
        run_dir = os.path.abspath(os.path.join(workdir, "learned", name))  # hydra logs, summary.json
        mem = os.path.abspath(os.path.join(workdir, "learned", f"{name}.zarr"))
        if not os.path.isdir(f"{mem}-agent"):  # nothing to resume: start this run afresh
            for p in (mem, f"{mem}-runs.jsonl"):
                if os.path.isdir(p):
                    shutil.rmtree(p)
                elif os.path.exists(p):
                    os.remove(p)
        # collector.resume: a run stopped earlier (killed, out of time) continues, a finished one is kept
        cmd = [*(variants if arm == "clone" else recipe), "env=slide", f"seed={seed}", f"memory.path={mem}",
               f"collector.total_frames={frames}", f"logger.eval_iter={eval_iter}",
               f"logger.eval_episodes={eval_episodes}", "logger.plot=false", f"hydra.run.dir={run_dir}",
               "collector.resume=true", *LEARNED_ARMS[arm], *(overrides or [])]
        if arm != "scratch":
            cmd.append(f"prior.paths=[{os.path.abspath(memory)}]")
        log(f"learned arm: {name}: {' '.join(cmd[1:])}")
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, cwd=ROOT)
        with open(os.path.join(run_dir, "summary.json")) as f:
            summary = json.load(f)
        log(f"learned arm: {name}: success {summary['curve'][-1][1]:.2f} after {summary['frames']} "
            f"frames ({summary['cpu_s']:.0f} CPU-s)")
        return summary

    tasks = [(seed, arm) for seed in range(seeds) for arm in arms]
    with ThreadPoolExecutor(max_workers=jobs) as pool:  # threads only wait on the subprocesses
        summaries = list(pool.map(lambda t: run_one(*t), tasks))
    runs: dict[str, list[dict]] = {arm: [] for arm in arms}
    for (_, arm), summary in zip(tasks, summaries):
        runs[arm].append(summary)
    final = {arm: [r["curve"][-1][1] for r in rs] for arm, rs in runs.items()}
    return {"status": "run", "reason": f"{seeds} seeds x {frames} frames per arm ({', '.join(arms)}), "
                                       f"{eval_episodes}-episode evals",
            "memory": os.path.abspath(memory), "runs": runs, "final": final,
            "mean_final": {arm: float(np.mean(v)) for arm, v in final.items()}}


def plot_learned(learned: dict, path: str) -> bool:
    """Eval-success curves of the learned arm (one line a run)."""
    if learned.get("status") != "run":
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4))
    styles = {"prior": ("#fd8d3c", "prior memory"), "scratch": ("#6baed6", "from scratch"),
              "clone": ("#31a354", "cloned from the memory")}
    for arm, (color, label) in styles.items():
        for i, run in enumerate(learned["runs"].get(arm, [])):
            xs, ys = zip(*run["curve"])
            ax.plot(xs, ys, color=color, alpha=0.8, label=label if i == 0 else None)
    ax.set_xlabel("new env frames")
    ax.set_ylabel("FetchSlide eval success")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


# -- memory --------------------------------------------------------------------------


def build_memory(path: str, replicate: int, push_episodes: int, slide_episodes: int,
                 baseline: StrikeParams, log=print) -> dict:
    """FetchPush then FetchSlide noisy scripted episodes in one ZarrStorage (env-tagged).

    The memory is written to ``path + ".building"`` and renamed to ``path`` once complete, so
    ``path`` never names a half-written memory: a build that is killed leaves only the
    ``.building`` directory, which the next build removes.
    """
    building = path + ".building"
    for stale in (building, path):
        if os.path.exists(stale):
            shutil.rmtree(stale)
    rb = open_memory(building, max(50 * (push_episodes + slide_episodes), 1000))
    try:
        push = collect("push", push_episodes, building, noise=1.0, seed=100 + replicate, backend="gym", rb=rb)
        slide = collect("slide", slide_episodes, building, noise=1.0, seed=200 + replicate, backend="gym",
                        base=baseline, rb=rb)
    finally:
        rb.storage.close()
    os.rename(building, path)
    push["path"] = slide["path"] = path
    log(f"memory {replicate}: FetchPush {push['successes']}/{push_episodes}, "
        f"FetchSlide {slide['successes']}/{slide_episodes} successes")
    return {"push": push, "slide": slide}


# -- report --------------------------------------------------------------------------


def summarise(outcomes: dict[str, list[np.ndarray]], speeds: dict[str, list]) -> dict:
    arms = {}
    for arm, per_seed in outcomes.items():
        allv = np.concatenate(per_seed)
        s, n = int(allv.sum()), int(allv.size)
        lo, hi = wilson(s, n)
        arms[arm] = {
            "successes": s, "n": n, "rate": s / max(n, 1), "ci95": [lo, hi],
            "per_seed": [float(x.mean()) for x in per_seed],
            "mean_strike_speed": float(np.mean(speeds[arm])),
        }
    flat = {a: np.concatenate(v) for a, v in outcomes.items()}
    tests = {}
    for mem, ctl in [("pooled_memory", "pooled_control"), ("pooled_memory", "baseline"),
                     ("push_memory", "push_control"), ("push_memory", "baseline"),
                     ("push_control", "baseline"), ("push_memory_raw", "push_control"),
                     ("pooled_control", "baseline"), ("pooled_mixed", "pooled_control")]:
        tests[f"{mem} vs {ctl}"] = mcnemar(flat[mem], flat[ctl])
    return {"arms": arms, "tests": tests}


def plot(summary: dict, path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arms = list(summary["arms"])
    rates = np.array([summary["arms"][a]["rate"] for a in arms]) * 100
    ci = np.array([summary["arms"][a]["ci95"] for a in arms]) * 100
    err = np.stack([rates - ci[:, 0], ci[:, 1] - rates])
    colors = ["#999999" if "baseline" in a else "#6baed6" if "control" in a else "#fd8d3c" for a in arms]
    fig, ax = plt.subplots(figsize=(9, 4.2))
    x = np.arange(len(arms))
    ax.bar(x, rates, yerr=err, capsize=4, color=colors, edgecolor="black", linewidth=0.5)
    for i, a in enumerate(arms):
        ys = np.array(summary["arms"][a]["per_seed"]) * 100
        ax.scatter(np.full(len(ys), i) + np.linspace(-0.15, 0.15, len(ys)), ys, s=10, color="black", zorder=3)
    ax.set_xticks(x, [ARMS[a][0] for a in arms], rotation=20, ha="right")
    ax.set_ylabel("FetchSlide success (%)")
    ax.set_title(title, fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report_md(res: dict) -> str:
    cfg, summ = res["config"], res["summary"]
    lines = [
        f"FetchSlide, {cfg['seeds']} seeds x {cfg['episodes']} paired episodes per arm; memories of "
        f"{cfg['push_episodes']} FetchPush + {cfg['slide_episodes']} FetchSlide noisy scripted episodes per seed; "
        f"k = {cfg['k']}; baseline strike_speed {res['baseline']['strike_speed']:.2f} (tuned on "
        f"{cfg['tune_episodes']} held-out episodes).",
        "",
        "| arm | success | 95% CI (Wilson) | per seed | mean strike speed |",
        "|---|---|---|---|---|",
    ]
    for arm, a in summ["arms"].items():
        per = " ".join(f"{100 * r:.1f}" for r in a["per_seed"])
        lines.append(f"| {ARMS[arm][0]} | {100 * a['rate']:.1f}% ({a['successes']}/{a['n']}) | "
                     f"{100 * a['ci95'][0]:.1f} - {100 * a['ci95'][1]:.1f}% | {per} | {a['mean_strike_speed']:.3f} |")
    lines += ["", "| paired test (exact McNemar) | difference | a only / b only | p |", "|---|---|---|---|"]
    for name, t in summ["tests"].items():
        lines.append(f"| {name} | {100 * t['diff']:+.1f} pp | {t['a_only']} / {t['b_only']} | {t['p']:.2g} |")
    prim = summ["tests"][" vs ".join(PREREGISTERED["primary"])]
    met = prim["diff"] >= PREREGISTERED["min_effect"] and prim["p"] < PREREGISTERED["alpha"]
    lines += ["", f"Primary contrast {' vs '.join(PREREGISTERED['primary'])}: {100 * prim['diff']:+.1f} pp, "
              f"p = {prim['p']:.2g}: goal (>= +{100 * PREREGISTERED['min_effect']:.0f} pp at p < "
              f"{PREREGISTERED['alpha']}) {'met' if met else 'NOT met'}.",
              f"Learned arm: {res['learned']['status']} ({res['learned']['reason']})."]
    learned = res["learned"]
    if learned.get("status") == "run":
        names = {"prior": "prior memory", "scratch": "from scratch", "clone": "cloned from the memory"}
        arms = [a for a in names if a in learned["runs"]]
        lines += ["", "| learned arm, seed | " + " | ".join(
            f"{names[a]}: success at frame 0 / final (frames, CPU-s)" for a in arms) + " |",
            "|---" * (len(arms) + 1) + "|"]
        for i in range(max(len(learned["runs"][a]) for a in arms)):
            cells = []
            for a in arms:
                r = learned["runs"][a][i] if i < len(learned["runs"][a]) else None
                cells.append("" if r is None else f"{r['curve'][0][1]:.2f} / {r['curve'][-1][1]:.2f} "
                             f"({r['frames']}, {r['cpu_s']:.0f})")
            lines.append(f"| {i} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


# -- main ----------------------------------------------------------------------------


def _learned_arms(args: argparse.Namespace) -> tuple[str, ...]:
    return tuple(a.strip() for a in str(args.learned_arms).split(",") if a.strip())


def _parse(argv):
    p = argparse.ArgumentParser(prog="python -m experiments.cross_env.run", description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=5, help="replicates (a memory and an eval set each)")
    p.add_argument("--episodes", type=int, default=200, help="FetchSlide episodes per arm and seed")
    p.add_argument("--push_episodes", type=int, default=500)
    p.add_argument("--slide_episodes", type=int, default=300)
    p.add_argument("--tune_episodes", type=int, default=200, help="held-out episodes per tuned speed")
    p.add_argument("--speeds", default="0.65,0.7,0.75,0.8,0.85,0.9,0.95")
    p.add_argument("--k", type=int, default=PREREGISTERED["k"])
    p.add_argument("--workdir", default="memory/cross_env", help="where the memories are written")
    p.add_argument("--out", default="docs/cross_env", help="results.json, report.md, cross_env.png")
    p.add_argument("--learned_frames", type=int, default=0,
                   help="FetchSlide SAC+HER frames per run of the learned arm (0: skip; hours on a CPU)")
    p.add_argument("--learned_seeds", type=int, default=3)
    p.add_argument("--learned_jobs", type=int, default=1, help="learned-arm runs at a time (2 on a 2-core machine)")
    p.add_argument("--learned_eval_episodes", type=int, default=100)
    p.add_argument("--learned_eval_iter", type=int, default=2500)
    p.add_argument("--learned_arms", default="prior,scratch",
                   help=f"comma-separated learned-arm runs per seed, of {','.join(LEARNED_ARMS)}")
    p.add_argument("--learned_overrides", default="", help="extra hydra overrides for both arms, separated by ';'")
    p.add_argument("--learned_only", type=lambda v: str(v).lower() in ("1", "true", "yes"), default=False,
                   help="true: only run (or continue) the learned arm, next to the scripted arms of out/results.json")
    return p.parse_args(kv_args(argv))


def main(argv: list[str] | None = None) -> dict:
    torch.set_num_threads(1)
    args = _parse(sys.argv[1:] if argv is None else argv)
    os.makedirs(args.out, exist_ok=True)
    os.makedirs(args.workdir, exist_ok=True)
    t0 = time.time()

    def log(msg):
        print(f"[{time.time() - t0:7.1f}s] {msg}", flush=True)

    if args.learned_only:
        return learned_only(args, log)
    speeds = [float(v) for v in str(args.speeds).split(",")]
    baseline, tune_table = tune_baseline(speeds, args.tune_episodes, log)
    log(f"baseline strike_speed = {baseline.strike_speed}")

    outcomes = {a: [] for a in ARMS}
    used_speeds = {a: [] for a in ARMS}
    memories = []
    for r in range(args.seeds):
        path = os.path.join(args.workdir, f"seed{r}.zarr")
        memories.append(build_memory(path, r, args.push_episodes, args.slide_episodes, baseline, log))
        rb = open_memory(path)
        try:
            arms = make_arms(rb.storage, baseline, args.k)
            seeds = _eval_seeds(r, args.episodes)
            for arm, fn in arms.items():
                out, sp = run_arm(fn, seeds)
                outcomes[arm].append(out)
                used_speeds[arm] += sp
                log(f"seed {r}: {arm:16s} {out.mean():.1%}")
        finally:
            rb.storage.close()

    res = {
        "config": {**vars(args), "speeds": speeds},
        "preregistered": PREREGISTERED,
        "distance_scale": DISTANCE_SCALE,
        "baseline": dataclasses.asdict(baseline),
        "tuning": tune_table,
        "memories": memories,
        "summary": summarise(outcomes, used_speeds),
        "outcomes": {a: [o.astype(int).tolist() for o in v] for a, v in outcomes.items()},
        "learned": learned_arm(
            os.path.join(args.workdir, "seed0.zarr") if args.seeds else None,
            frames=args.learned_frames, seeds=args.learned_seeds, workdir=args.workdir,
            eval_episodes=args.learned_eval_episodes, eval_iter=args.learned_eval_iter,
            overrides=[o for o in str(args.learned_overrides).split(";") if o], jobs=args.learned_jobs,
            arms=_learned_arms(args), log=log),
        "seconds": round(time.time() - t0, 1),
    }
    return write_results(res, args.out)


def write_results(res: dict, out: str) -> dict:
    """``results.json``, ``report.md``, ``cross_env.png`` (and ``learned.png``) under ``out``."""
    cfg = res["config"]
    with open(os.path.join(out, "results.json"), "w") as f:
        json.dump(res, f, indent=1)
    md = report_md(res)
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write(md)
    plot(res["summary"], os.path.join(out, "cross_env.png"),
         f"FetchSlide success, {cfg['seeds']} seeds x {cfg['episodes']} paired episodes per arm "
         "(95% Wilson CI; dots: seeds)")
    plot_learned(res["learned"], os.path.join(out, "learned.png"))
    print(md)
    return res


def learned_only(args: argparse.Namespace, log) -> dict:
    """Run (or continue) the learned arm alone, next to the scripted arms of ``out/results.json``.

    The pooled memory of replicate 0 is rebuilt from the recorded baseline when
    ``workdir`` no longer holds it, or holds only a build that was killed (the same
    seeds give the same episodes).
    """
    path = os.path.join(args.out, "results.json")
    if not os.path.exists(path):
        raise FileNotFoundError(f"learned_only=true needs the scripted arms' {path}: run the command without it first.")
    with open(path) as f:
        res = json.load(f)
    if not res["config"]["seeds"]:
        raise ValueError(f"{path} was run with seeds=0: no pooled memory to learn from.")
    memory = os.path.join(args.workdir, "seed0.zarr")
    if not os.path.isdir(memory):
        cfg = res["config"]
        build_memory(memory, 0, cfg["push_episodes"], cfg["slide_episodes"], StrikeParams(**res["baseline"]), log)
    t0 = time.time()
    before = res.get("learned", {})
    res["learned"] = learned_arm(
        memory, frames=args.learned_frames, seeds=args.learned_seeds, workdir=args.workdir,
        eval_episodes=args.learned_eval_episodes, eval_iter=args.learned_eval_iter,
        overrides=[o for o in str(args.learned_overrides).split(";") if o], jobs=args.learned_jobs,
        arms=_learned_arms(args), log=log)
    if before.get("status") == "run":  # arms run earlier and not named this time stay in the results
        for arm, runs in before["runs"].items():
            res["learned"]["runs"].setdefault(arm, runs)
            res["learned"]["final"].setdefault(arm, before["final"][arm])
            res["learned"]["mean_final"].setdefault(arm, before["mean_final"][arm])
    res["config"].update({k: v for k, v in vars(args).items() if k.startswith("learned")})
    res["learned_seconds"] = round(time.time() - t0, 1)
    return write_results(res, args.out)


if __name__ == "__main__":
    main()
