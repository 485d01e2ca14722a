"""PPO (ClipPPOLoss + GAE) on a Fetch task, over a persistent memory.

The loop of TorchRL's ``sota-implementations/ppo/ppo_mujoco.py`` (collect,
GAE, epochs of minibatches, log, evaluate), with these changes:

* every collected batch is extended into a :class:`~torchrl_robotmem.ZarrStorage`
  at ``memory.path``, which keeps it: the run leaves its experience behind, in
  the layout of the HER recipe's memory (same columns), for off-policy runs
  (``recipes/her`` with ``prior=mix 'prior.paths=[...]'`` or the same
  ``memory.path``), recall and later runs;
* the minibatches come from that storage through
  :class:`~torchrl_robotmem.samplers.on_policy.OnPolicyBatchSampler`: the newest
  batch only, without replacement, ``loss.ppo_epochs`` epochs; PPO's per-row
  values (log-probabilities, advantages, value targets) and the recalled goals
  stay in RAM and are joined to the drawn rows by their batch position;
* ``memory.recall.enabled=true`` adds a :class:`~torchrl_robotmem.RecallTransform`:
  actor and critic also see the remembered achieved goals nearest the desired goal
  (this run's memory, live, or ``memory.recall.memory=<path>``);
* observations and goals are normalised by running statistics of every
  collected row (of the memory too, for fresh networks on a non-empty one);
* ``collector.resume=true`` continues a stopped run from its last checkpoint
  (agent, optimiser, statistics and the run's progress, saved at every
  evaluation), on the same memory.

    python recipes/ppo/train.py                                  # FetchReach-v4, sparse reward
    python recipes/ppo/train.py env=reach_dense                  # FetchReachDense-v4
    python recipes/ppo/train.py memory.recall.enabled=true
    python recipes/ppo/train.py collector.resume=true            # again after a kill
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import hydra
import numpy as np
import torch
import tqdm
from hydra.utils import to_absolute_path
from omegaconf import DictConfig
from torchrl.checkpoint import Checkpoint, CheckpointError
from utils import (
    PPO_KEYS,
    RECALL_KEYS,
    RunningNorm,
    check_batch,
    evaluate,
    make_collector,
    make_logger,
    make_loss_module,
    make_ppo_models,
    make_replay_buffer,
    make_task_env,
    memory_rows,
    refresh_log_prob,
)

sys.path.append(str(Path(__file__).resolve().parents[2]))  # the repository root: the HER recipe's run record
from recipes.her.run_record import CpuClock, finish_run, first_reach, read_history, recover_checkpoint, run_progress  # noqa: E402


def load_agent(checkpoint: Checkpoint, path: str) -> None:
    try:
        checkpoint.load(path)
    except CheckpointError as err:
        raise RuntimeError(f"the agent checkpoint {path} does not fit this agent (saved with other network / "
                           "memory.recall settings?). Use the settings it was saved with, or fresh networks "
                           "(memory.resume_agent=false, collector.resume=false).") from err


@hydra.main(version_base="1.3", config_path="", config_name="config")
def main(cfg: DictConfig) -> None:  # noqa: C901  (the loop reads top to bottom, as the sota script)
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    check_batch(cfg)
    if str(cfg.device) != "cpu":
        raise ValueError(f"device={cfg.device}: the PPO recipe runs on the CPU (small networks; the envs dominate).")
    memory_path = to_absolute_path(cfg.memory.path)
    checkpoint_path = to_absolute_path(cfg.memory.checkpoint)
    history_path = to_absolute_path(cfg.memory.history)
    history = read_history(history_path)
    logger = make_logger(cfg)

    # The memory (every row kept) and the on-policy sampler (the newest batch's minibatches)
    buffer = make_replay_buffer(cfg, memory_path)
    remembered = len(buffer)

    # Envs (the recall transform reads the memory live), agent, loss, optimiser
    train_env = make_task_env(cfg, cfg.env.num_envs, cfg.seed, buffer.storage)
    eval_env = make_task_env(cfg, cfg.logger.eval_episodes, cfg.seed + 10_000, buffer.storage)
    normalizer = RunningNorm()
    actor, critic = make_ppo_models(cfg, train_env, normalizer)
    loss_module, adv_module = make_loss_module(cfg, actor, critic)
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=cfg.optim.lr, eps=cfg.optim.eps)
    checkpoint = Checkpoint(loss_module=loss_module, optimizer=optimizer, normalizer=normalizer)
    recover_checkpoint(checkpoint_path)
    progress = run_progress(cfg, checkpoint_path, remembered)
    resumed = (cfg.memory.resume_agent or progress is not None) and Checkpoint.is_checkpoint(checkpoint_path)
    if resumed:
        load_agent(checkpoint, checkpoint_path)
    elif remembered:
        normalizer.update(buffer.storage[:remembered])  # fresh networks: the statistics of the whole memory
    if progress is not None:
        remembered = progress["memory_rows_before"]
    collected = len(buffer) - remembered if progress else 0
    updates = progress["updates"] if progress else 0
    curve = [tuple(p) for p in progress["curve"]] if progress else []
    cpu = CpuClock(offset=progress["cpu_s"] if progress else 0.0,
                   eval_offset=progress.get("eval_cpu_s", 0.0) if progress else 0.0,
                   process_offset=progress.get("process_cpu_s", 0.0) if progress else 0.0)
    if progress:  # other episodes than the first launch's
        torch.manual_seed(cfg.seed + collected)
    print(f"PPO on {cfg.env.name} | memory {memory_path}: {len(buffer)} transitions"
          + (" | agent resumed from checkpoint" if resumed else "")
          + (f" | run resumed at {collected} frames" if progress else ""))

    def save(finished: bool) -> None:
        with cpu.paused():
            if hasattr(buffer.storage, "flush"):
                buffer.storage.flush()  # the memory first: a checkpoint never counts rows that were lost
            checkpoint.save(checkpoint_path, metadata={
                "env": cfg.env.name, "algo": "PPO", "seed": cfg.seed, "updates": updates,
                "memory_rows_before": remembered, "memory_rows": len(buffer), "frames": collected,
                "cpu_s": cpu.seconds(), "eval_cpu_s": cpu.evaluation(), "process_cpu_s": cpu.process(),
                "curve": [list(p) for p in curve], "finished": finished,
            })

    def log_eval(frames: int) -> float:
        with cpu.evaluating():
            metrics = evaluate(cfg, eval_env, actor)
        metrics.update({"time/cpu_s": cpu.seconds(), "time/eval_cpu_s": cpu.evaluation(), "train/updates": updates})
        curve.append((frames, metrics["eval/success_rate"]))
        if logger is not None:
            logger.log_metrics(metrics, frames)
        return metrics["eval/success_rate"]

    if not curve:
        log_eval(0)
        save(finished=False)
    target = cfg.logger.target_success
    reached_at = first_reach(curve, target)
    total = cfg.collector.total_frames
    done_already = reached_at is not None or collected >= total
    collector = make_collector(cfg, train_env, actor, total_frames=max(total - collected, 1), seed=cfg.seed + collected)
    pbar = tqdm.tqdm(total=total, initial=collected, desc=f"PPO {cfg.env.name}", leave=False)
    loop = {"frames": 0, "wall_s": 0.0}
    tick = time.perf_counter()
    for data in (collector if not done_already else ()):
        # Extend: the memory keeps the batch (the sampler learns its rows from the write)
        buffer.extend(memory_rows(data))
        frames = data.numel()
        collected += frames
        pbar.update(frames)

        # Statistics with this batch, then its log-probabilities under them (PPO's ratio starts at 1)
        normalizer.update(data)
        refresh_log_prob(actor, data)
        frac = 1.0 - (collected - frames) / total if cfg.optim.anneal_lr else 1.0
        for group in optimizer.param_groups:
            group["lr"] = cfg.optim.lr * frac
        if cfg.loss.anneal_clip_epsilon:
            loss_module.clip_epsilon.copy_(cfg.loss.clip_epsilon * frac)

        # Epochs: GAE with the critic now, then the sampler's minibatches of the newest batch
        losses = []
        for _ in range(cfg.loss.ppo_epochs):
            with torch.no_grad():
                adv_module(data)
            extra = data.select(*PPO_KEYS, *[k for k in RECALL_KEYS if k in data.keys()]).reshape(-1)
            for batch in buffer:
                batch.update(extra[batch["batch_position"]])
                loss = loss_module(batch)
                total_loss = sum(v for k, v in loss.items() if k.startswith("loss_"))
                total_loss.backward()
                torch.nn.utils.clip_grad_norm_(loss_module.parameters(), cfg.optim.max_grad_norm)
                optimizer.step()
                optimizer.zero_grad()
                updates += 1
                losses.append(loss.select(*[k for k in loss.keys() if k.startswith("loss_")], "kl_approx",
                                          "clip_fraction", strict=False).detach())
        collector.update_policy_weights_()

        # Log
        metrics = {f"train/{k}": v.float().mean().item() for k, v in torch.stack(losses).items()}
        metrics["train/lr"] = optimizer.param_groups[0]["lr"]
        done = data["next", "done"].squeeze(-1)
        if done.any():
            metrics["train/return"] = data["next", "episode_reward"][done].mean().item()
            metrics["train/success_rate"] = data["next", "is_success"][done].float().mean().item()
        if logger is not None:
            logger.log_metrics(metrics, collected)
        loop["frames"] += frames
        loop["wall_s"] += time.perf_counter() - tick

        # Evaluate
        if collected % cfg.logger.eval_iter < frames or collected >= total:
            success = log_eval(collected)
            save(finished=False)
            pbar.set_postfix(success=f"{success:.2f}")
            if target is not None and success >= target:
                reached_at = collected
                break
        if cfg.collector.cpu_budget_s is not None and cpu.seconds() >= cfg.collector.cpu_budget_s:
            break
        tick = time.perf_counter()

    pbar.close()
    collector.shutdown()
    if curve[-1][0] != collected:
        log_eval(collected)
    save(finished=True)
    summary = {
        "env": cfg.env.name, "algo": "PPO", "seed": cfg.seed, "memory_rows_before": remembered,
        "memory_rows_after": len(buffer), "frames": collected, "frames_to_target": reached_at,
        "success": curve[-1][1], "cpu_s": round(cpu.seconds(), 2), "updates": updates, "curve": curve,
        "recall": bool(cfg.memory.recall.enabled), "loop_wall_s": round(loop["wall_s"], 3),
        "frames_per_s": round(loop["frames"] / loop["wall_s"], 2) if loop["wall_s"] else None,
    }
    if hasattr(buffer.storage, "close"):
        buffer.storage.close()
    for env in (eval_env, train_env):
        if not env.is_closed:
            env.close()
    finish_run(cfg, history, history_path, summary, clock=cpu)


if __name__ == "__main__":
    main()
