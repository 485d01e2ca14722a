"""SAC / TD3 / DDPG + HER on Fetch and Shadow Hand, over a persistent memory.

The loop of TorchRL's ``sota-implementations/sac/sac.py`` (collect, extend, update, log, evaluate). The replay
buffer is TorchRL's ``HERReplayBuffer`` (as :class:`~torchrl_robotmem.PersistentHERReplayBuffer`, which also
samples a memory that has filled and wraps) over a :class:`~torchrl_robotmem.ZarrStorage` at
``memory.path``: the next run on the same path continues on it, fresh networks first learning from it
(``pretrain.py``); ``prior=mix 'prior.paths=[...]'`` samples read-only memories beside it (``prior_memory/``).
The agent and the run's progress are saved at every evaluation (``collector.resume=true`` continues a stopped
run); the run ends with its frames and CPU-seconds (``run_record.py``). recipes/README.md has every option.

    python recipes/her/train.py                        # SAC, FetchReach-v4
    python recipes/her/train.py algo=td3 env=push seed=1
    python recipes/her/train.py env=push prior=mix 'prior.paths=[memory/scripted/push.zarr]'
    python recipes/her/train.py env=push collector.total_frames=60000 collector.resume=true  # again after a kill
"""
from __future__ import annotations

import functools
import time

import hydra
import numpy as np
import torch
import tqdm
from hydra.utils import to_absolute_path
from omegaconf import DictConfig
from pretrain import pretrain_on_memory
from prior_memory import check_prior_config, check_prior_memories, make_prior_mix, prior_ratio
from run_record import (
    CpuClock,
    finish_run,
    first_reach,
    read_history,
    record_episodes,
    recover_checkpoint,
    run_progress,
)
from targets import clip_targets
from tensordict import TensorDictBase
from torchrl.checkpoint import Checkpoint
from update import LossTerms, Updater, compile_settings, draw_batches
from utils import (
    RECALL_KEYS,
    GoalNormalizer,
    check_env_batch,
    current_goals,
    evaluate,
    load_agent,
    loss_keys,
    make_agent,
    make_collector,
    make_environment,
    make_eval_env,
    make_logger,
    make_loss_module,
    make_optimizer,
    make_prior_buffers,
    make_replay_buffer,
    make_sampler,
    make_storage,
    mean_losses,
    memory_device,
    refresh_recall,
    start_normalizer,
    to_device,
    train_device,
)

from torchrl_robotmem import GoalProposer


@hydra.main(version_base="1.3", config_path="", config_name="config")
def main(cfg: DictConfig) -> None:
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    check_prior_config(cfg)  # prior.* settings that do not go together are refused before anything is written
    check_env_batch(cfg)  # several envs: each env's share of a collection batch must be whole episodes
    algo = cfg.algo.name
    device = train_device(cfg)  # networks and updates; envs, memory and collected data stay on the CPU
    # hydra has already moved into outputs/<date>/<time>: resolve against the launch dir
    memory_path = to_absolute_path(cfg.memory.path)
    checkpoint_path = to_absolute_path(cfg.memory.checkpoint)
    history_path = to_absolute_path(cfg.memory.history)
    history = read_history(history_path)
    logger = make_logger(cfg)

    # Prior memories (read-only): checked against this task (keys, shapes, dtypes) and summarised first
    priors = make_prior_buffers(cfg, device=memory_device(cfg))
    prior_dtypes, prior_summaries = check_prior_memories(cfg, priors)

    # Create the memory: storage, optional goal sampler, HER on top (every draw names its size)
    replay_buffer = make_replay_buffer(cfg, make_storage(cfg, memory_path, device=memory_device(cfg)), make_sampler(cfg),
                                       batch_size=None)
    goal_sampler = replay_buffer.sampler if cfg.replay_buffer.sampler.enabled else None
    remembered = len(replay_buffer)

    # Create environments (the recall transform and the goal proposer read the same memory, live)
    train_env, eval_env = make_environment(cfg, memory=replay_buffer.storage)
    recall = train_env.transform[-1] if cfg.memory.recall.enabled else None
    proposer = next((t for t in train_env.transform if isinstance(t, GoalProposer)), None)
    mix = make_prior_mix(cfg, replay_buffer, priors, dtypes=prior_dtypes)  # priors sampled beside the run's buffer

    # Create agent, loss, optimiser
    normalizer = GoalNormalizer(device=device)
    model, exploration_policy = make_agent(cfg, train_env, normalizer)
    fast = compile_settings(cfg, device)  # compile.*: torch.compile and CUDA graphs for the update
    loss_module, target_net_updater = make_loss_module(cfg, model, compiled=fast["compile"])
    clip_targets(loss_module, cfg.optim.get("target_clip"), cfg.optim.gamma)  # HER's clip_return (targets.py)
    optimizer = make_optimizer(cfg, loss_module, capturable=fast["cudagraphs"])
    checkpoint = Checkpoint(loss_module=loss_module, optimizer=optimizer, normalizer=normalizer)

    # A stopped run resumes (collector.resume); fresh networks take the memory's and priors' statistics
    recover_checkpoint(checkpoint_path)  # a save a kill interrupted leaves only its backup
    progress = run_progress(cfg, checkpoint_path, remembered)
    resumed = (cfg.memory.resume_agent or progress is not None) and Checkpoint.is_checkpoint(checkpoint_path)
    if resumed:
        load_agent(checkpoint, checkpoint_path)
    start_normalizer(normalizer, replay_buffer, progress, resumed, mix)
    if progress is not None:
        remembered = progress["memory_rows_before"]

    # One gradient step; TD3 moves its actor and targets every policy_update_delay-th step. Eager, or
    # compiled / CUDA-graphed (compile.*)
    update = Updater(LossTerms(loss_module, loss_keys(cfg)), optimizer, target_net_updater,
                     policy_delay=cfg.algo.policy_update_delay if algo == "TD3" else 1, compile=fast["compile"],
                     compile_mode=fast["mode"], compile_backend=fast["backend"],
                     cudagraphs=fast["cudagraphs"], warmup=fast["warmup"])
    update.num_updates = progress["updates"] if progress else 0

    # frames of this run so far: every row it added to its memory (a resumed run counts those after its checkpoint)
    collected_frames = len(replay_buffer) - remembered if progress else 0
    print(f"{algo}+HER on {cfg.env.name} | memory {memory_path}: {len(replay_buffer)} transitions"
          + (" | agent resumed from checkpoint" if resumed else "")
          + (f" | run resumed at {collected_frames} frames" if progress else ""))
    cpu = CpuClock.resumed(progress)  # training, evaluation and process CPU-s, carried on from a stopped run
    curve: list[tuple[int, float]] = [tuple(point) for point in progress["curve"]] if progress else []
    if progress:  # other episodes than the first launch's
        torch.manual_seed(cfg.seed + collected_frames)
        np.random.seed(cfg.seed + collected_frames)

    def save(finished: bool) -> None:
        """The agent and the run's progress (one atomic write), after the memory: no checkpoint counts lost rows."""
        with cpu.paused():
            if hasattr(replay_buffer.storage, "flush"):
                replay_buffer.storage.flush()
            checkpoint.save(checkpoint_path, metadata={
                "env": cfg.env.name, "algo": algo, "seed": cfg.seed, "updates": update.num_updates,
                "memory_rows_before": remembered, "memory_rows": len(replay_buffer),
                "frames": collected_frames, "cpu_s": cpu.seconds(), "curve": [list(p) for p in curve],
                "eval_cpu_s": cpu.evaluation(), "process_cpu_s": cpu.process(), "finished": finished,
            })

    outcomes: list[int] = []  # each episode's success in the last evaluation on eval_env (eval_episodes.jsonl)

    def full_eval(env=eval_env, held_out: bool = False) -> dict:
        with cpu.evaluating():
            return evaluate(cfg, env, model[0], outcomes if env is eval_env else None, held_out=held_out)

    def log_eval(frames: int, metrics: dict | None = None) -> float:
        metrics = dict(full_eval() if metrics is None else metrics)
        if outcomes:
            record_episodes(frames, cfg.seed, outcomes)
            outcomes.clear()
        metrics.update({"time/cpu_s": cpu.seconds(), "time/eval_cpu_s": cpu.evaluation(),
                        "train/updates": update.num_updates})
        curve.append((frames, metrics["eval/success_rate"]))
        if logger is not None:
            logger.log_metrics(metrics, frames)
        return metrics["eval/success_rate"]

    def sample(size: int = cfg.optim.batch_size, query=None) -> TensorDictBase:
        """``size`` rows (HER-relabelled; near ``query``; with the prior's share), recalled priors, on ``device``."""
        if mix is not None:
            batch = mix.sample(size, query)
        elif query is not None:
            with goal_sampler.query(query):
                batch = replay_buffer.sample(size)
        else:
            batch = replay_buffer.sample(size)
        if recall is not None:
            refresh_recall(batch, recall)
        return to_device(batch, device)

    # Fresh networks on a memory that already holds transitions: learn from it first, until it has done its job
    pretrained = {"updates": 0, "checks": [], "stopped": None}
    if (remembered or mix is not None) and not resumed and cfg.memory.pretrain_updates:
        pretrained = pretrain_on_memory(
            cfg, lambda: update(sample()), full_eval,
            lambda episodes: make_eval_env(cfg, episodes, replay_buffer.storage, held_out=True), cpu, logger)
        log_eval(0, pretrained["metrics"])
    success = curve[-1][1] if curve else log_eval(0)
    save(finished=False)

    # Main loop
    init_random_frames = max(0, cfg.collector.init_random_frames - remembered - collected_frames)
    collector = make_collector(cfg, train_env, exploration_policy, init_random_frames=init_random_frames,
                               total_frames=max(cfg.collector.total_frames - collected_frames, 1),
                               seed=cfg.seed + collected_frames)
    target = cfg.logger.target_success
    reached_at = first_reach(curve, target)
    done_already = reached_at is not None or collected_frames >= cfg.collector.total_frames
    pbar = tqdm.tqdm(total=cfg.collector.total_frames, initial=collected_frames,
                     desc=f"{algo} {cfg.env.name}", leave=False)

    loop = {"frames": 0, "wall_s": 0.0}  # this launch's collection and updates, evaluation excluded: frames/s
    tick = time.perf_counter()
    for data in (collector if not done_already else ()):
        # Extend: flat transitions; recalled priors are recomputed at sampling
        data = data.reshape(-1).exclude(*RECALL_KEYS, *[("next", k) for k in RECALL_KEYS])
        replay_buffer.extend(data)
        normalizer.update(data)
        frames = data.numel()
        collected_frames += frames
        pbar.update(frames)

        # Update: the batches of a step drawn together (optim.batches_per_draw), near the goals chased now
        metrics = {}
        if mix is not None:  # prior.ratio_final: the prior's share of a batch anneals
            mix.ratio = metrics["train/prior_ratio"] = prior_ratio(cfg, collected_frames)
        if collected_frames >= init_random_frames:
            n = max(1, int(frames * cfg.optim.utd_ratio))
            losses = []  # kept on the device until the step's end: no host sync an update
            query = current_goals(collector, data) if goal_sampler is not None else None
            group = max(1, cfg.optim.batches_per_draw)
            for first in range(0, n, group):
                batches = draw_batches(functools.partial(sample, query=query), min(group, n - first), cfg.optim.batch_size)
                losses += [update(batch) for batch in batches]
            metrics.update(mean_losses(torch.stack(losses)))
            if algo == "SAC":
                metrics["train/alpha"] = loss_module.log_alpha.exp().item()
        collector.update_policy_weights_()

        # Log
        done = data["next", "done"].squeeze(-1)
        if done.any():
            metrics["train/return"] = data["next", "episode_reward"][done].mean().item()
            metrics["train/success_rate"] = data["next", "is_success"][done].float().mean().item()
        if logger is not None and metrics:
            logger.log_metrics(metrics, collected_frames)
        loop["frames"] += frames
        loop["wall_s"] += time.perf_counter() - tick

        # Evaluate
        if collected_frames % cfg.logger.eval_iter < frames:
            success = log_eval(collected_frames)
            save(finished=False)
            pbar.set_postfix(success=f"{success:.2f}")
            if target is not None and success >= target:
                reached_at = collected_frames
                break
        if cfg.collector.cpu_budget_s is not None and cpu.seconds() >= cfg.collector.cpu_budget_s:
            break
        tick = time.perf_counter()

    pbar.close()
    collector.shutdown()
    if curve[-1][0] != collected_frames:
        log_eval(collected_frames)

    # Persist the memory, then save the agent next to it; close the store (its commit worker's CPU counts
    # once it has ended); the run's summary, plot and report
    save(finished=True)
    summary = {
        "env": cfg.env.name, "algo": algo, "seed": cfg.seed, "memory_rows_before": remembered,
        "memory_rows_after": len(replay_buffer), "frames": collected_frames, "frames_to_target": reached_at,
        "cpu_s": round(cpu.seconds(), 2), "updates": update.num_updates, "curve": curve,
        "pretrain_updates": pretrained["updates"], "pretrain_checks": pretrained["checks"],
        "pretrain_stopped": pretrained["stopped"], "priors": prior_summaries,
        "loop_wall_s": round(loop["wall_s"], 3),
        "frames_per_s": round(loop["frames"] / loop["wall_s"], 2) if loop["wall_s"] else None,
        "proposer": None if proposer is None else {"proposed": proposer.proposed, "kept": proposer.kept,
                                                    "seconds": round(proposer.seconds, 3)},
    }
    if hasattr(replay_buffer.storage, "close"):
        replay_buffer.storage.close()
    for env in (eval_env, train_env):
        if not env.is_closed:
            env.close()
    finish_run(cfg, history, history_path, summary, clock=cpu)


if __name__ == "__main__":
    main()
