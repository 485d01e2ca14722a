"""MADDPG / IDDPG on MaMuJoCo with a persistent replay memory.

The loop of TorchRL's ``sota-implementations/multiagent/maddpg_iddpg.py`` (collect,
extend, update, anneal the exploration, log), on a Gymnasium-Robotics MaMuJoCo task
(``torchrl_robotmem.envs_multiagent.make_mamujoco_env``), with the replay buffer on
``ZarrStorage`` at ``memory.path``: run it again and the buffer starts with every
stored transition (per-agent keys with their agent dimension), updates start at once,
and new rows are appended under a new ``run`` tag. ``memory.resume_agent=true`` also
continues the networks, optimiser and exploration noise from ``memory.checkpoint``.

    python recipes/multiagent/train.py                          # MADDPG, HalfCheetah 2x3, 5k frames
    python recipes/multiagent/train.py model.centralised_critic=false   # IDDPG
    python recipes/multiagent/train.py memory.resume_agent=true         # continue on the same memory

Writes ``summary.json`` in the run directory (returns before/after, frames/s, memory rows and runs).
"""
from __future__ import annotations

import json
import os
import time
import warnings

import hydra
import torch
import utils  # recipes/multiagent/utils.py (run as a script, as TorchRL's sota scripts)
from hydra.utils import to_absolute_path
from omegaconf import DictConfig

# MaMuJoCo is not goal-conditioned: rows without a success flag are what this memory holds
warnings.filterwarnings("ignore", message="PettingZoo in TorchRL is tested using version")


def _update(cfg: DictConfig, rb, loss, target, optim) -> dict:
    batch = rb.sample()
    out = loss(batch)
    total = out["loss_actor"] + out["loss_value"]
    total.backward()
    torch.nn.utils.clip_grad_norm_(loss.parameters(), cfg.train.max_grad_norm)
    optim.step()
    optim.zero_grad()
    target.step()
    return {"loss_actor": out["loss_actor"].item(), "loss_value": out["loss_value"].item()}


def _memory_tags(storage) -> dict:
    """Rows, runs and episodes the memory holds (``ZarrStorage`` tags; empty for other storages)."""
    try:
        runs, episodes = storage["run"], storage["episode"]
    except (KeyError, IndexError, RuntimeError):
        return {}
    return {"memory_runs": sorted(set(runs.tolist())), "memory_episodes": len(set(episodes.tolist()))}


@hydra.main(version_base="1.3", config_path="", config_name="config")
def main(cfg: DictConfig) -> None:
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.num_threads)
    rb = utils.make_replay_buffer(cfg)
    rows_before = len(rb)
    env = utils.make_env_fn(cfg, cfg.seed)()
    eval_env = utils.make_env_fn(cfg, cfg.seed + 1000)()
    policy, policy_explore, value = utils.make_agent(cfg, env)
    env.close()
    loss, target, optim = utils.make_loss(cfg, policy, value)
    checkpoint = to_absolute_path(str(cfg.memory.checkpoint))
    frames_before = 0
    if cfg.memory.resume_agent and os.path.exists(checkpoint):
        frames_before = utils.load_agent(checkpoint, loss, optim, policy_explore[1])
    logger = utils.make_logger(cfg)
    max_steps, episodes = cfg.env.max_episode_steps, cfg.eval.episodes
    return_before = utils.evaluate(eval_env, policy, max_steps, episodes)

    ready = max(cfg.train.minibatch_size, cfg.collector.init_random_frames)  # rows needed before updating
    updates, t0 = 0, time.perf_counter()
    if len(rb) >= ready:  # the memory's stored rows: train on them before the first new frame
        for _ in range(cfg.memory.pretrain_updates):
            _update(cfg, rb, loss, target, optim)
            updates += 1
    pretrain_s = time.perf_counter() - t0
    init_random = 0 if len(rb) >= ready or frames_before else cfg.collector.init_random_frames
    collector = utils.make_collector(cfg, policy_explore, cfg.collector.total_frames, init_random)
    frames, collect_s, extend_s, train_s, train_returns = 0, 0.0, 0.0, 0.0, []
    t_collect = time.perf_counter()
    for data in collector:
        t_extend = time.perf_counter()
        collect_s += t_extend - t_collect
        frames += data.numel()
        # the actor's ("agents", "param") is an intermediate (= the action before noise): not kept, and
        # the warm-up's random batches lack it, so keeping it would add a column to the memory mid-run
        rb.extend(data.reshape(-1).exclude((utils.GROUP, "param")))
        extend_s += time.perf_counter() - t_extend
        done = data["next", "done"].squeeze(-1)
        train_returns += data["next", utils.GROUP, "episode_reward"].mean(-2)[done].flatten().tolist()
        t_train, metrics = time.perf_counter(), {}
        if len(rb) >= ready:
            for _ in range(cfg.train.updates_per_batch):
                metrics = _update(cfg, rb, loss, target, optim)
                updates += 1
        policy_explore[1].step(frames=data.numel())
        collector.update_policy_weights_()
        train_s += time.perf_counter() - t_train
        if logger is not None:
            metrics.update(frames=frames, memory_rows=len(rb), collect_fps=frames / max(collect_s, 1e-9))
            if train_returns:
                metrics["train/episode_return"] = train_returns[-1]
            logger.log_metrics(metrics, step=frames)
        t_collect = time.perf_counter()
    collector.shutdown()
    return_after = utils.evaluate(eval_env, policy, max_steps, episodes)
    eval_env.close()
    utils.save_agent(checkpoint, loss, optim, policy_explore[1], frames_before + frames)
    summary = {
        "algo": utils.algo_name(cfg), "env": f"{cfg.env.scenario}-{cfg.env.agent_conf}", "seed": cfg.seed,
        "frames": frames, "agent_frames_before": frames_before, "memory_rows_before": rows_before,
        "memory_rows_after": len(rb), "updates": updates, "pretrain_s": round(pretrain_s, 2),
        "return_before": return_before, "return_after": return_after, "train_episode_returns": train_returns,
        "collect_s": round(collect_s, 2), "extend_s": round(extend_s, 3), "train_s": round(train_s, 2),
        "collect_fps": round(frames / max(collect_s, 1e-9), 1),
        "fps": round(frames / max(collect_s + extend_s + train_s, 1e-9), 1), **_memory_tags(rb.storage),
    }
    if logger is not None:
        logger.log_metrics({"eval/return_before": return_before, "eval/return_after": return_after}, step=frames)
    with open("summary.json", "w") as f:
        json.dump(summary, f)
    print(json.dumps({k: v for k, v in summary.items() if k != "train_episode_returns"}))
    close = getattr(rb.storage, "close", None)
    if close is not None:
        close()


if __name__ == "__main__":
    main()
