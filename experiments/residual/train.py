"""Residual SAC on a scripted controller recalled from a memory (issue 27, goal 2).

The memory of a noisy scripted controller (FetchPush, 500 episodes, 66.8% success)
holds more than its success rate: recalling, per episode, the mean parameters of
the 5 successful episodes nearest in goal geometry gives a controller that scores
0.955-0.99 before any new frame (docs/results.md). This recipe starts from that
controller and learns a residual on it with SAC, the loop of TorchRL's
``sota-implementations/sac/sac.py``:

* the env runs the controller (:class:`~experiments.residual.base.ScriptedBase`) and
  writes its action and phase as observations, at the root and under ``"next"``;
* the actor's mean is the controller's action plus a learned residual that starts
  at zero (``agent.py``), so the first evaluation is the controller's;
* the critics learn first (``collector.actor_freeze_frames``), then both learn;
* the transitions go to a :class:`~torchrl_robotmem.ZarrStorage` at ``memory.path``;
* evaluation is ``recipes/her``'s: 100 deterministic episodes on the same fixed goals
  (``seed + 10000``), written to ``eval_episodes.jsonl``, so ``recipes.her.tools.paired``
  and ``compare`` read these runs beside the HER runs.

No HER: the controller already reaches the goal on most episodes, and a relabelled
goal would need the controller's state for that goal, which the transition does not hold.

    python -m experiments.residual.train seed=0 base.memory=bench_results/prior/scripted-push-500.zarr
"""
from __future__ import annotations

import json
import time

import hydra
import numpy as np
import torch
import tqdm
from hydra.utils import instantiate, to_absolute_path
from omegaconf import DictConfig
from torchrl.checkpoint import Checkpoint
from torchrl.collectors import Collector
from torchrl.data import RandomSampler, TensorDictReplayBuffer
from torchrl.envs import RewardSum
from torchrl.envs.utils import ExplorationType, set_exploration_type

from experiments.prior_variants.bc import CRRActorLoss
from experiments.residual.agent import AGENT_INPUTS, make_agent, make_loss, make_optimizers
from recipes.her.run_record import CpuClock, first_reach, record_episodes
from recipes.her.utils import GoalNormalizer, evaluate, make_logger, make_storage, mean_losses
from torchrl_robotmem import make_env

# actor outputs not worth keeping in the memory
_NOT_STORED = ("scale", "loc")


def make_envs(cfg: DictConfig):
    """Train env (one env, seed ``seed``) and eval env (``logger.eval_episodes`` envs, ``recipes/her``'s seeds)."""
    def base():
        node = dict(cfg.base)
        if node.get("memory"):
            node["memory"] = to_absolute_path(node["memory"])
        return instantiate(node)

    train = make_env(cfg.env.name, 1, seed=cfg.seed, max_episode_steps=cfg.env.max_episode_steps,
                     transforms=[RewardSum(), base()])
    evaluation = make_env(cfg.env.name, cfg.logger.eval_episodes, seed=cfg.seed + 10_000,
                          max_episode_steps=cfg.env.max_episode_steps, transforms=[RewardSum(), base()])
    return train, evaluation


def update(loss_module, optimizers: dict, target_updater, batch, actor_frozen: bool,
           residual_penalty: float = 0.0, crr: CRRActorLoss | None = None) -> torch.Tensor:
    """One step: the critics always, the actor (and SAC's entropy coefficient) unless ``actor_frozen``.

    The actor's loss is SAC's (``-Q(s, pi(s))`` and entropy) or, with ``crr``, critic-regularised regression
    onto the stored residuals the critics rate above the actor's (``algo.actor_update=crr``; the entropy
    coefficient stays where it is: the policy's spread is not trained). ``residual_penalty``: weight of the
    mean squared deterministic residual, added to the actor's loss.
    """
    losses = loss_module(batch)
    total = losses["loss_qvalue"]
    groups = ["critic"]
    if not actor_frozen:
        if crr is not None:
            out = crr(batch)
            losses.set("loss_actor", out["loss_actor"])
            losses.set("crr_kept", out["crr_kept"].detach())
            groups += ["actor"]
            total = total + out["loss_actor"]
        else:
            groups += ["actor", "alpha"]
            total = total + losses["loss_actor"] + losses["loss_alpha"]
        residual_sq = deterministic_residual(loss_module, batch).pow(2).sum(-1).mean()
        losses.set("residual_sq", residual_sq.detach())
        if residual_penalty:
            total = total + residual_penalty * residual_sq
    for g in groups:
        optimizers[g].zero_grad(set_to_none=True)
    total.backward()
    for g in groups:
        optimizers[g].step()
    target_updater.step()
    keys = ["loss_qvalue", "loss_actor", "loss_alpha"] + ([] if actor_frozen else ["residual_sq"])
    keys += ["crr_kept"] if crr is not None and not actor_frozen else []
    return losses.select(*keys).detach()


def deterministic_residual(loss_module, batch) -> torch.Tensor:
    """The actor's deterministic residual on ``batch``, differentiable in the loss's actor parameters (as
    :class:`~torchrl.objectives.SACLoss` calls its actor): ``tanh(loc) * residual_max``."""
    actor = loss_module.actor_network
    with set_exploration_type(ExplorationType.DETERMINISTIC), loss_module.actor_network_params.to_module(actor):
        return actor.get_dist(batch.select(*AGENT_INPUTS)).deterministic_sample


@hydra.main(version_base="1.3", config_path="", config_name="config")
def main(cfg: DictConfig) -> None:
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    memory_path = to_absolute_path(cfg.memory.path)
    if cfg.algo.actor_update not in ("sac", "crr"):  # before anything is written
        raise ValueError(f"algo.actor_update must be sac or crr, got {cfg.algo.actor_update!r}.")
    logger = make_logger(cfg)
    storage = make_storage(cfg, memory_path)  # ZarrStorage at memory.path (or any Storage _target_)
    buffer = TensorDictReplayBuffer(storage=storage, sampler=RandomSampler(), batch_size=cfg.optim.batch_size)
    if len(buffer):
        raise ValueError(f"memory.path={memory_path} already holds {len(buffer)} transitions: this recipe measures "
                         "a run from its scripted memory alone; give it a new path.")
    train_env, eval_env = make_envs(cfg)
    normalizer = GoalNormalizer()
    model = make_agent(cfg, train_env, normalizer)
    loss_module, target_updater = make_loss(cfg, model)
    optimizers = make_optimizers(cfg, loss_module)
    crr = CRRActorLoss(loss_module) if cfg.algo.actor_update == "crr" else None
    checkpoint = Checkpoint(loss_module=loss_module, normalizer=normalizer, **optimizers)
    cpu = CpuClock()
    curve: list[tuple[int, float]] = []
    outcomes: list[int] = []
    state = {"updates": 0, "frames": 0}

    def log_eval(frames: int) -> float:
        with cpu.evaluating():
            metrics = evaluate(cfg, eval_env, model[0], outcomes)
        record_episodes(frames, cfg.seed, outcomes)
        metrics.update({"time/cpu_s": cpu.seconds(), "time/eval_cpu_s": cpu.evaluation(),
                        "train/updates": state["updates"]})
        curve.append((frames, metrics["eval/success_rate"]))
        if logger is not None:
            logger.log_metrics(metrics, frames)
        with cpu.paused():
            if hasattr(storage, "flush"):
                storage.flush()
            checkpoint.save(memory_path + "-agent", metadata={"frames": frames, "curve": [list(p) for p in curve]})
        return metrics["eval/success_rate"]

    success = log_eval(0)  # the residual is 0: the recalled controller's own success
    print(f"residual SAC on {cfg.env.name} | base: {cfg.base.task} controller, parameters "
          f"{'recalled from ' + str(cfg.base.memory) if cfg.base.memory else 'default'} | success at 0 frames {success:.2f}")
    collector = Collector(train_env, model[0], frames_per_batch=cfg.collector.frames_per_batch,
                          total_frames=cfg.collector.total_frames, init_random_frames=0)
    collector.set_seed(cfg.seed)
    pbar = tqdm.tqdm(total=cfg.collector.total_frames, desc=f"residual SAC {cfg.env.name}", leave=False)
    target = cfg.logger.target_success
    loop = {"frames": 0, "wall_s": 0.0}
    tick = time.perf_counter()
    for data in collector:
        data = data.reshape(-1).exclude(*_NOT_STORED)
        buffer.extend(data)
        normalizer.update(data)
        frames = data.numel()
        state["frames"] += frames
        pbar.update(frames)
        metrics = {}
        if state["frames"] >= cfg.collector.warmup_frames:
            frozen = state["frames"] <= cfg.collector.actor_freeze_frames
            losses = [update(loss_module, optimizers, target_updater, buffer.sample(), frozen,
                             cfg.algo.residual_penalty, crr) for _ in range(max(1, int(frames * cfg.optim.utd_ratio)))]
            state["updates"] += len(losses)
            metrics.update(mean_losses(torch.stack(losses)))
            metrics["train/alpha"] = loss_module.log_alpha.exp().item()
        done = data["next", "done"].squeeze(-1)
        if done.any():
            metrics["train/success_rate"] = data["next", "is_success"][done].float().mean().item()
        if logger is not None and metrics:
            logger.log_metrics(metrics, state["frames"])
        collector.update_policy_weights_()
        loop["frames"] += frames
        loop["wall_s"] += time.perf_counter() - tick
        if state["frames"] % cfg.logger.eval_iter < frames:
            success = log_eval(state["frames"])
            pbar.set_postfix(success=f"{success:.2f}")
            if target is not None and success >= target:
                break
        tick = time.perf_counter()
    pbar.close()
    collector.shutdown()
    if curve[-1][0] != state["frames"]:
        log_eval(state["frames"])
    summary = {"env": cfg.env.name, "algo": "residual SAC", "seed": cfg.seed, "memory_rows_before": 0,
               "memory_rows_after": len(buffer), "frames": state["frames"],
               "frames_to_target": first_reach(curve, target), "cpu_s": round(cpu.seconds(), 2),
               "eval_cpu_s": round(cpu.evaluation(), 2), "process_cpu_s": round(cpu.process(), 2),
               "updates": state["updates"], "curve": curve, "base": dict(cfg.base),
               "frames_per_s": round(loop["frames"] / loop["wall_s"], 2) if loop["wall_s"] else None}
    if hasattr(storage, "close"):
        storage.close()
    for env in (eval_env, train_env):
        env.close()
    with open("summary.json", "w") as f:
        json.dump(summary, f)
    print(f"evaluated success {curve[0][1]:.2f} at 0 frames (the recalled controller), {curve[-1][1]:.2f} after "
          f"{state['frames']} frames ({summary['cpu_s']:.0f} training CPU-s, {state['updates']} updates)")


if __name__ == "__main__":
    main()
