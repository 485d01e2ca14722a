"""The prior-memory experiments of docs/results.md (docs/notes/results_log.md sections 8-15), as one resumable queue.

Every run is ``python -m experiments.prior_variants.train`` (recipes/her/train.py with the prior-memory
variants: ``prior=bc|clone``, ``prior.clone_anchor``, ...) with 60k new env frames, 100 deterministic
evaluation episodes every 2500 frames and ``collector.resume=true``: launching
this script again (next session, after a kill) continues each stopped run from
its last evaluation and skips finished ones. ``--jobs`` runs go at a time
(two on a 2-core machine), in the order listed; each writes its memory and
hydra directory under ``--root`` and its log to ``--root/NAME.log``. Run
directories are machine-local: keep a finished run's curve with
``python -m recipes.her.tools.compare --archive docs/runs`` (docs/notes/results_log.md section 10)::

    python -m experiments.her.prior_runs --list                    # names, state, overrides
    python -m experiments.her.prior_runs --jobs 2                   # everything not finished yet
    python -m experiments.her.prior_runs --only anneal-push-s0,anneal-push-s1

The scripted prior memories are made once by ``experiments.scripted.collect``::

    python -m experiments.scripted.collect env=push episodes=500 noise=1 seed=0 backend=gym \\
        path=bench_results/prior/scripted-push-500.zarr
    python -m experiments.scripted.collect env=push episodes=500 noise=0 seed=0 backend=gym \\
        path=bench_results/prior/scripted-push-500-n0.zarr
    python -m experiments.scripted.collect env=pick_and_place episodes=500 noise=1 seed=0 backend=gym \\
        path=bench_results/prior/scripted-pnp-500.zarr
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
#: what every run trains with: the recipe and the prior-memory variants, run from ROOT
TRAIN = [sys.executable, "-m", "experiments.prior_variants.train"]
PUSH_PRIOR = "bench_results/prior/scripted-push-500.zarr"
PUSH_PRIOR_CLEAN = "bench_results/prior/scripted-push-500-n0.zarr"  # default parameters: 96.6% success
PNP_PRIOR = "bench_results/prior/scripted-pnp-500.zarr"
PNP_PRIOR_CLEAN = "bench_results/prior/scripted-pnp-500-n0.zarr"  # default parameters: 100% in docs/scripted.md
# memory.pretrain_eval_every=0: every pretraining update, unchecked, as when these runs were made (issue 25
# stops pretraining at the target or a plateau by default)
COMMON = ["collector.total_frames=60000", "logger.eval_iter=2500", "logger.eval_episodes=100",
          "logger.target_success=0.9", "collector.resume=true", "memory.pretrain_eval_every=0"]
ANNEAL = ["prior.ratio_final=0.1", "prior.anneal_frames=30000"]
# RLPD-style: two updates a frame on half the batch (the same matmul cost as one update at 512) and
# LayerNorm critics, RLPD's stabiliser for high update-to-data ratios on prior data
UTD2 = ["optim.utd_ratio=2", "optim.batch_size=256", "network.critic_layer_norm=true"]
# clone the prior's actions into the actor first (4000 steps), then 3000 critic-only updates, then SAC with
# the Q-filtered BC term (prior=bc: TD3+BC's weight 0.4); evaluated every 2500 frames to 20k without the 0.9
# stop, to see whether RL keeps it
CLONE = ["prior=bc", "prior.clone_steps=4000"]
# the clone kept by a trust region (prior_variants.CloneAnchor) with TD3's own actor loss and the start's statistics
ANCHOR = ["prior=mix", "prior.clone_steps=4000", "collector.init_random_frames=0", "prior.freeze_normalizer=true"]


def _runs() -> dict[str, list[str]]:
    runs: dict[str, list[str]] = {}
    for seed in range(3):  # FetchPush: prior memory, annealed prior share, from scratch
        runs[f"prior-push-s{seed}"] = ["env=push", f"seed={seed}", "prior=mix", f"prior.paths=[{PUSH_PRIOR}]"]
        runs[f"scratch-push-s{seed}"] = ["env=push", f"seed={seed}"]
        runs[f"anneal-push-s{seed}"] = [*runs[f"prior-push-s{seed}"], *ANNEAL]
        runs[f"cleanprior-push-s{seed}"] = ["env=push", f"seed={seed}", "prior=mix", f"prior.paths=[{PUSH_PRIOR_CLEAN}]"]
        runs[f"bc-push-s{seed}"] = ["env=push", f"seed={seed}", "prior=bc", f"prior.paths=[{PUSH_PRIOR_CLEAN}]"]
        runs[f"clone-push-s{seed}"] = ["env=push", f"seed={seed}", f"prior.paths=[{PUSH_PRIOR_CLEAN}]", *CLONE,
                                       "collector.total_frames=20000", "logger.target_success=null"]
        # the same with TD3 + unfiltered BC (TD3+BC, Fujimoto & Gu 2021): SAC's online updates undid the clone
        runs[f"clonetd3-push-s{seed}"] = ["env=push", "algo=td3", f"seed={seed}", f"prior.paths=[{PUSH_PRIOR_CLEAN}]",
                                          *CLONE, "prior.bc_q_filter=false", "collector.init_random_frames=0",
                                          "collector.total_frames=20000", "logger.target_success=null"]
        # ... with a ten times stronger anchor (w=4): does cloning on every update keep the policy?
        runs[f"clonetd3bc4-push-s{seed}"] = [*runs[f"clonetd3-push-s{seed}"], "prior.bc=4.0"]
        # ... imitating only original-goal rows of successful prior episodes (relabelled goals are not the scripted aim)
        runs[f"clonetd3og-push-s{seed}"] = [*runs[f"clonetd3bc4-push-s{seed}"], "prior.bc_original_goals=true"]
        # ... with the actor frozen for the first 10k frames, so the critics learn the clone's returns first
        runs[f"clonefreeze-push-s{seed}"] = [*runs[f"clonetd3og-push-s{seed}"], "prior.actor_freeze_frames=10000"]
        # keep the clone: frozen normaliser statistics (the clone's inputs keep their meaning) and a 100x
        # smaller actor learning rate, to 60k frames without the 0.9 stop
        runs[f"keep-push-s{seed}"] = [o for o in runs[f"clonetd3og-push-s{seed}"] if not o.startswith("collector.total")]
        runs[f"keep-push-s{seed}"] += ["prior.freeze_normalizer=true", "prior.actor_lr=1e-5"]
        # the cloned actor trained by critic-regularised regression (prior_variants.CRRActorLoss): no action
        # gradient, so no offset from the data; frozen normaliser statistics; no extra BC term (prior=clone)
        runs[f"crr-push-s{seed}"] = ["env=push", "algo=td3", f"seed={seed}", "prior=clone",
                                     f"prior.paths=[{PUSH_PRIOR_CLEAN}]", "collector.init_random_frames=0",
                                     "logger.target_success=null"]
        # ... with a quarter of TD3's exploration noise (0.05): the regression targets of the run's own rows are
        # the clone's actions plus that noise, which the actor fits
        runs[f"crrlow-push-s{seed}"] = [*runs[f"crr-push-s{seed}"], "algo.exploration_noise=0.05"]
        # a trust region around the clone's own outputs on every batch state (prior_variants.CloneAnchor), with
        # TD3's own actor loss: the actions move by about grad_a Q / (2 w mean|Q|); to 20k frames without the 0.9 stop
        runs[f"anchor-push-s{seed}"] = ["env=push", "algo=td3", f"seed={seed}", f"prior.paths=[{PUSH_PRIOR_CLEAN}]",
                                        *ANCHOR, "prior.clone_anchor=10",
                                        "collector.total_frames=20000", "logger.target_success=null"]
        runs[f"anchor100-push-s{seed}"] = [o.replace("prior.clone_anchor=10", "prior.clone_anchor=100")
                                           for o in runs[f"anchor-push-s{seed}"]]
        # ... with the weight annealed geometrically from 100 to 1 over 20k frames (the trust region widens
        # 100x): can RL improve on the clone once the critics have learned its returns? 30k frames
        runs[f"annealanchor-push-s{seed}"] = [
            *[o for o in runs[f"anchor100-push-s{seed}"] if not o.startswith("collector.total")],
            "prior.clone_anchor_final=1", "prior.clone_anchor_anneal_frames=20000", "collector.total_frames=30000"]
        runs[f"utd2-push-s{seed}"] = [*runs[f"cleanprior-push-s{seed}"], *UTD2]
    for seed in range(3):  # FetchPickAndPlace: Push-only prior (cross-task), its own prior, from scratch
        runs[f"pushprior-pnp-s{seed}"] = ["env=pick_and_place", f"seed={seed}", "prior=mix", f"prior.paths=[{PUSH_PRIOR}]"]
        runs[f"ownprior-pnp-s{seed}"] = ["env=pick_and_place", f"seed={seed}", "prior=mix", f"prior.paths=[{PNP_PRIOR}]"]
        runs[f"scratch-pnp-s{seed}"] = ["env=pick_and_place", f"seed={seed}"]
        # issue 43: the same run with GoalProposer choosing each training episode's goal (its control: scratch-pnp,
        # run again beside it with the same code; --root bench_results/i43/pnp60)
        runs[f"propose-pnp-s{seed}"] = ["env=pick_and_place", f"seed={seed}", "memory.propose.enabled=true"]
        # ... seeds 1 and 2 of the 150k-frame comparison (seed 0: the two runs above resumed to 150k)
        runs[f"propose150-pnp-s{seed}"] = [*runs[f"propose-pnp-s{seed}"], "collector.total_frames=150000"]
        runs[f"scratch150-pnp-s{seed}"] = [*runs[f"scratch-pnp-s{seed}"], "collector.total_frames=150000"]
        # the cloned actor on PickAndPlace (prior=clone): from its own default-parameter memory, and from FetchPush's
        # (cross-task); stops at the first evaluation at or above 0.9 (frame 0 when the clone alone does it)
        clone = ["env=pick_and_place", "algo=td3", f"seed={seed}", "prior=clone", "collector.init_random_frames=0"]
        runs[f"clone-pnp-s{seed}"] = [*clone, f"prior.paths=[{PNP_PRIOR_CLEAN}]"]
        # ... from the noisy-parameter memory (80.2%): only its 401 successful episodes are cloned
        runs[f"clonenoisy-pnp-s{seed}"] = [*clone, f"prior.paths=[{PNP_PRIOR}]"]
        # (a probe: the Push clone's success on PickAndPlace at frame 0, and 2500 frames of RL after it)
        runs[f"clonepush-pnp-s{seed}"] = [*clone, f"prior.paths=[{PUSH_PRIOR_CLEAN}]", "collector.total_frames=2500"]
        # the FetchPush trust region (anchor100-push) on PickAndPlace: its own default-parameter memory, and
        # FetchPush's (cross-task); to 10k frames without the 0.9 stop
        anchor = ["env=pick_and_place", "algo=td3", f"seed={seed}", *ANCHOR, "prior.clone_anchor=100",
                  "collector.total_frames=10000", "logger.target_success=null"]
        runs[f"anchor100-pnp-s{seed}"] = [*anchor, f"prior.paths=[{PNP_PRIOR_CLEAN}]"]
        runs[f"anchor100push-pnp-s{seed}"] = [*anchor, f"prior.paths=[{PUSH_PRIOR_CLEAN}]"]
    return runs


RUNS = _runs()


def command(name: str, root: str) -> list[str]:
    """The ``train.py`` command line of run ``name``."""
    memory = os.path.abspath(os.path.join(root, f"{name}.zarr"))
    own = {o.split("=", 1)[0] for o in RUNS[name]}
    common = [o for o in COMMON if o.split("=", 1)[0] not in own]  # a run's own settings win
    return [*TRAIN, *RUNS[name], *common, f"memory.path={memory}", f"hydra.run.dir={os.path.abspath(os.path.join(root, name))}"]


def state(name: str, root: str) -> str:
    """``finished``, ``stopped at N frames``, or ``not started``."""
    summary = os.path.join(root, name, "summary.json")
    if os.path.exists(summary):
        with open(summary) as f:
            s = json.load(f)
        return f"finished: {s['frames']} frames, final {s['curve'][-1][1]:.2f}, {s['cpu_s']:.0f} CPU-s"
    agent = os.path.join(root, f"{name}.zarr-agent")
    if os.path.isdir(agent):
        from torchrl.checkpoint import Checkpoint

        meta = Checkpoint.manifest(agent).get("metadata") or {}
        if "frames" in meta:
            return f"stopped at {meta['frames']} frames (last eval {meta['curve'][-1][1]:.2f})"
    return "not started"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--root", default="bench_results/p60", help="memories, hydra run dirs and logs")
    p.add_argument("--jobs", type=int, default=2, help="runs at a time")
    p.add_argument("--only", default="", help="comma-separated run names (default: all, in order)")
    p.add_argument("--nice", type=int, default=5)
    p.add_argument("--list", action="store_true", help="print each run's state and command, run nothing")
    args = p.parse_args(argv)
    names = [n for n in args.only.split(",") if n] or list(RUNS)
    unknown = [n for n in names if n not in RUNS]
    if unknown:
        p.error(f"unknown runs {unknown}; known: {', '.join(RUNS)}")
    os.makedirs(args.root, exist_ok=True)
    if args.list:
        for n in names:
            print(f"{n:22s} {state(n, args.root)}\n    {' '.join(RUNS[n])}")
        return
    queue = [n for n in names if not state(n, args.root).startswith("finished")]
    running: dict[str, subprocess.Popen] = {}
    while queue or running:
        while queue and len(running) < args.jobs:
            name = queue.pop(0)
            log = open(os.path.join(args.root, f"{name}.log"), "a")
            print(f"[{time.strftime('%H:%M:%S')}] start {name} ({state(name, args.root)})", flush=True)
            running[name] = subprocess.Popen(["nice", "-n", str(args.nice), *command(name, args.root)],
                                             stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        time.sleep(10)
        for name, proc in list(running.items()):
            if proc.poll() is not None:
                del running[name]
                print(f"[{time.strftime('%H:%M:%S')}] {name}: exit {proc.returncode}, {state(name, args.root)}",
                      flush=True)


if __name__ == "__main__":
    main()
