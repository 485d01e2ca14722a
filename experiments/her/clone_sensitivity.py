"""How far can a cloned actor's weights move before it stops pushing? (docs/notes/results_log.md section 12)

Clones a prior memory's successful actions into a fresh FetchPush TD3 actor, as
``prior.clone_steps`` does in ``experiments/prior_variants/train.py`` (statistics of the prior only,
``experiments.prior_variants.pretrain_actor``), then adds Gaussian noise of standard deviation ``sigma``
to every weight and evaluates the recipe's deterministic policy (100 episodes,
the run's fixed evaluation goals). For each ``sigma`` it prints the evaluated
success and the mean absolute change of the deterministic action on the
demonstration states. One Adam step moves every weight by up to the learning
rate, so ``N`` steps at ``lr`` move a weight by up to ``N * lr``: 1250 actor
steps at 1e-5 reach 0.0125::

    python -m experiments.her.clone_sensitivity bench_results/prior/scripted-push-500-n0.zarr \
        --plot docs/img/clone_sensitivity.png

``--replot FILE.jsonl`` redraws the plot from the printed rows without re-running.
"""
from __future__ import annotations

import argparse
import json
import os

import torch
from hydra import compose, initialize_config_dir
from torchrl.envs.utils import ExplorationType, set_exploration_type

from experiments.prior_variants import load_demos, pretrain_actor
from recipes.her import utils
from torchrl_robotmem import ZarrStorage

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
RECIPE_DIR = os.path.join(ROOT, "recipes", "her")  # config.yaml and its groups


def sensitivity(prior: str, sigmas: list[float], steps: int = 4000, seed: int = 0,
                episodes: int = 100, env: str = "push") -> list[dict]:
    """Evaluated success of the cloned actor with N(0, sigma^2) added to each weight, for each ``sigma``."""
    with initialize_config_dir(config_dir=RECIPE_DIR, version_base="1.3"):
        cfg = compose("config", overrides=[f"env={env}", "algo=td3", f"seed={seed}", f"logger.eval_episodes={episodes}"])
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(seed)
    train_env, eval_env = utils.make_environment(cfg)
    storage = ZarrStorage(prior, read_only=True)
    normalizer = utils.GoalNormalizer()
    normalizer.update(storage[: len(storage)])
    model, _ = utils.make_agent(cfg, train_env, normalizer)
    loss = utils.make_loss_module(cfg, model)[0]
    demos = load_demos(loss, [storage])
    mse = pretrain_actor(loss, [storage], steps, batch_size=cfg.optim.batch_size, lr=cfg.optim.lr, seed=seed, demos=demos)
    params = list(loss.actor_network_params.values(True, True))
    base = [p.detach().clone() for p in params]
    actor = model[0]
    states = demos[torch.randperm(demos.shape[0])[:2048]].exclude("action")

    def actions() -> torch.Tensor:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            return actor(states.clone())["action"]

    clean = actions()
    out = []
    gen = torch.Generator().manual_seed(seed)
    for sigma in sigmas:
        with torch.no_grad():
            for p, b in zip(params, base):
                p.copy_(b + sigma * torch.randn(b.shape, generator=gen))
        success = utils.evaluate(cfg, eval_env, actor)["eval/success_rate"]
        row = {"sigma": sigma, "success": success, "mean_abs_action_change": (actions() - clean).abs().mean().item(),
               "clone_mse": mse}
        print(json.dumps(row), flush=True)
        out.append(row)
    train_env.close()
    eval_env.close()
    return out


def plot(rows: list[dict], out: str) -> None:
    """Evaluated success and mean action change against the weight noise (log x axis)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    clean = [r["success"] for r in rows if r["sigma"] == 0]
    rows = [r for r in rows if r["sigma"] > 0]
    sigmas = [r["sigma"] for r in rows]
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    ax.plot(sigmas, [r["success"] for r in rows], "o-", label="evaluated success (100 episodes)")
    ax.plot(sigmas, [r["mean_abs_action_change"] for r in rows], "s--", label="mean |action change|")
    if clean:
        ax.axhline(clean[0], color="grey", ls=":", label=f"no noise: {clean[0]:.2f}")
    ax.set_xscale("log")
    ax.set_xlabel("std of the Gaussian noise added to every actor weight")
    ax.set_ylim(0, 1)
    ax.set_title("FetchPush-v4: the cloned actor under weight noise")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    print(f"wrote {out}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("prior", help="a scripted memory (experiments.scripted.collect)")
    p.add_argument("--sigmas", default="0,0.001,0.003,0.01,0.03")
    p.add_argument("--steps", type=int, default=4000, help="cloning steps (prior.clone_steps)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--env", default="push")
    p.add_argument("--plot", default="", help="write a PNG of success against sigma here")
    p.add_argument("--replot", default="", help="a file of the printed JSON rows: plot them, run nothing")
    args = p.parse_args(argv)
    if args.replot:
        with open(args.replot) as f:
            rows = [json.loads(line) for line in f if line.startswith("{")]
    else:
        rows = sensitivity(args.prior, [float(s) for s in args.sigmas.split(",")], args.steps, args.seed,
                           args.episodes, args.env)
    if args.plot:
        plot(rows, args.plot)


if __name__ == "__main__":
    main()
