"""SAC / TD3 / DDPG + HER on Fetch and Shadow Hand, over a persistent memory.

The loop of TorchRL's ``sota-implementations/sac/sac.py`` (collect, extend,
update, log, evaluate), with three changes:

* the replay buffer is a :class:`~torchrl.data.HERReplayBuffer` over a
  :class:`~torchrl_robotmem.ZarrStorage` at ``memory.path``: transitions outlive
  the run, and the next run with the same path continues on them;
* a run that starts fresh networks on a non-empty memory first does
  ``memory.pretrain_updates`` updates on it, before collecting anything;
* optionally, :class:`~torchrl_robotmem.GoalSimilaritySampler` draws rows near
  the goals being chased now, and :class:`~torchrl_robotmem.RecallTransform`
  shows actor and critic the remembered goals nearest to their goal;
* ``memory.prior=[path, ...]``: read-only memories of other runs, tasks or
  scripted controllers, sampled beside the run's own buffer (``prior.py``);
  ``memory.prior_bc=w`` also clones their actions where the critics prefer
  them (``bc.py``).

The agent (networks, optimiser, normaliser) is saved next to the memory at every
evaluation, with the run's progress (frames, curve, CPU time) in the
checkpoint's metadata: ``collector.resume=true`` continues a run that was
stopped (killed, out of time) from its last evaluation, on the same memory.

    python recipes/her/train.py                        # SAC, FetchReach-v4
    python recipes/her/train.py algo=td3 env=push seed=1
    python recipes/her/train.py replay_buffer.storage._target_=torchrl.data.LazyTensorStorage
    python recipes/her/train.py env=push 'memory.prior=[memory/scripted/push.zarr]'
    python recipes/her/train.py env=push collector.total_frames=60000 collector.resume=true  # again after a kill
"""
from __future__ import annotations

import json
import os

import hydra
import numpy as np
import torch
import tqdm
from bc import CloneAnchor, CRRActorLoss, PriorBC, load_demos, pretrain_actor
from compare import first_reach
from hydra.utils import to_absolute_path
from prior import TRANSITION_KEYS, PriorMix, make_prior_buffers
from tensordict import TensorDict
from torchrl.checkpoint import Checkpoint, CheckpointError
from torchrl.record.loggers import generate_exp_name, get_logger
from utils import (
    RECALL_KEYS,
    CpuClock,
    GoalNormalizer,
    append_history,
    clone_anchor_weight,
    current_goals,
    evaluate,
    loss_keys,
    make_agent,
    make_collector,
    make_environment,
    make_loss_module,
    make_optimizer,
    make_replay_buffer,
    make_sampler,
    make_storage,
    mean_losses,
    plot_success,
    prior_ratio,
    read_history,
    refresh_recall,
    run_progress,
    train_device,
)


@hydra.main(version_base="1.3", config_path="", config_name="config")
def main(cfg: DictConfig):  # noqa: F821
    # One thread: on a busy 2-core machine two threads made SAC updates 6-10x slower.
    torch.set_num_threads(1)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    algo = cfg.algo.name
    device = train_device(cfg)  # networks and updates; envs, memory and collected data stay on the CPU
    # hydra has already moved into outputs/<date>/<time>: resolve against the launch dir
    memory_path = to_absolute_path(cfg.memory.path)
    checkpoint_path = to_absolute_path(cfg.memory.checkpoint)
    history_path = to_absolute_path(cfg.memory.history)
    history = read_history(history_path)

    # Create logger
    logger = None
    if cfg.logger.backend:
        logger = get_logger(
            cfg.logger.backend,
            logger_name="her_logging",
            experiment_name=generate_exp_name(algo, cfg.logger.exp_name),
            wandb_kwargs={"mode": cfg.logger.mode, "project": cfg.logger.project_name},
        )

    # Create the memory: storage, optional goal sampler, HER on top
    # beside prior memories the run's buffer is sampled in part-batches (PriorMix): no default size
    own_batch = None if cfg.memory.get("prior") else cfg.optim.batch_size
    replay_buffer = make_replay_buffer(cfg, make_storage(cfg, memory_path), make_sampler(cfg), batch_size=own_batch)
    goal_sampler = replay_buffer.sampler if cfg.replay_buffer.sampler.enabled else None
    remembered = len(replay_buffer)

    # Create environments (the recall transform reads the same memory, live)
    train_env, eval_env = make_environment(cfg, memory=replay_buffer.storage)
    recall = train_env.transform[-1] if cfg.memory.recall.enabled else None

    # Prior memories (read-only), sampled beside the run's own buffer
    priors = make_prior_buffers(cfg, make_replay_buffer)
    mix = None
    if priors:
        mix = PriorMix(replay_buffer, priors, cfg.memory.prior_ratio, cfg.env.name, TRANSITION_KEYS,
                       example=train_env.fake_tensordict())
        mix.ratio = prior_ratio(cfg, 0)  # raises on a ratio or schedule end outside [0, 1]

    # Create agent, loss, optimiser
    normalizer = GoalNormalizer(device=device)
    model, exploration_policy = make_agent(cfg, train_env, normalizer)
    loss_module, target_net_updater = make_loss_module(cfg, model)
    optimizer = make_optimizer(cfg, loss_module)
    checkpoint = Checkpoint(loss_module=loss_module, optimizer=optimizer, normalizer=normalizer)
    anchor = None  # memory.clone_anchor: the cloned actor's outputs, kept near on every batch (saved with the agent)
    if cfg.memory.get("clone_anchor", 0):
        if not cfg.memory.get("prior_pretrain_bc", 0):
            raise ValueError("memory.clone_anchor keeps the actor near the one cloned by memory.prior_pretrain_bc: "
                             "set memory.prior_pretrain_bc=N (and memory.prior=[path, ...]) too.")
        anchor = CloneAnchor(loss_module, cfg.memory.clone_anchor)
        anchor.weight = clone_anchor_weight(cfg, 0)  # raises on a schedule end <= 0
        checkpoint.register("clone_anchor", anchor)
    progress = run_progress(cfg, checkpoint_path, remembered)  # collector.resume: where the run stopped
    freeze_stats = bool(cfg.memory.get("freeze_normalizer", False))  # memory.freeze_normalizer: the start's statistics
    resumed = (bool(cfg.memory.resume_agent) or progress is not None) and Checkpoint.is_checkpoint(checkpoint_path)
    if resumed:
        try:
            checkpoint.load(checkpoint_path)
        except CheckpointError as err:
            raise RuntimeError(
                f"the agent checkpoint {checkpoint_path} does not fit this agent (saved with other "
                "algo / network / memory.recall settings?). Use the settings it was saved with, "
                "or start fresh networks on the memory with memory.resume_agent=false."
            ) from err
    elif remembered:
        normalizer.update(replay_buffer[:])  # fresh networks: statistics of the whole memory
    if progress is not None:
        remembered = progress["memory_rows_before"]
        if len(replay_buffer) > progress["memory_rows"] and not freeze_stats:  # collected after the last checkpoint
            normalizer.update(replay_buffer.storage[progress["memory_rows"]:len(replay_buffer)])
    if mix is not None and not resumed:
        for buffer in priors:
            normalizer.update(buffer[:].select(*mix.keys, strict=False))
    keys = loss_keys(cfg)
    num_updates = progress["updates"] if progress else 0
    for option in ("prior_bc", "prior_pretrain_bc"):
        if cfg.memory.get(option, 0) and mix is None:
            raise ValueError(f"memory.{option} clones the actions of memory.prior rows: set memory.prior=[path, ...] too.")
    demos = None  # the prior's successful rows with their own goals, read once for both options below
    if cfg.memory.get("prior_pretrain_bc", 0) or (cfg.memory.get("prior_bc", 0) and cfg.memory.get("prior_bc_original_goals")):
        demos = load_demos(loss_module, [b.storage for b in priors])
    bc = None
    if cfg.memory.get("prior_bc", 0.0):
        bc = PriorBC(loss_module, cfg.memory.prior_bc, q_filter=cfg.memory.get("prior_bc_q_filter", True),
                     demos=demos if cfg.memory.get("prior_bc_original_goals") else None)

    actor_update = cfg.optim.get("actor_update", "q_gradient")
    if actor_update not in ("q_gradient", "crr"):
        raise ValueError(f"optim.actor_update must be q_gradient or crr, got {actor_update!r}.")
    crr = CRRActorLoss(loss_module) if actor_update == "crr" else None
    critic_only = False  # pretraining the critics of a cloned actor (memory.prior_pretrain_bc)
    skipped = torch.full((), float("nan"), device=device)  # an actor-side term on an update that did not train the actor

    def update(batch):
        nonlocal num_updates
        if recall is not None:
            refresh_recall(batch, recall)
        used = keys
        if critic_only:
            used = keys[1:2]  # loss_qvalue / loss_value
        if algo == "TD3" and num_updates % cfg.algo.policy_update_delay:
            used = ("loss_qvalue",)  # delayed actor and target updates
        extra = bc(batch) if bc is not None and "loss_actor" in used else {}
        loss_td = loss_module(batch)
        if crr is not None:  # optim.actor_update=crr: regression onto the better stored actions, no action gradient
            regressed = crr(batch) if "loss_actor" in used else {"loss_actor": torch.zeros((), device=device), "crr_kept": skipped}
            loss_td.set("loss_actor", regressed["loss_actor"])
        total = sum(loss_td[k] for k in used)
        if extra:
            total = total + extra["loss_bc"]
        anchored = anchor(batch) if anchor is not None and "loss_actor" in used else {}
        if anchored:
            total = total + anchored["loss_anchor"]
        total.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if used is keys or critic_only:
            target_net_updater.step()
        num_updates += 1
        out = loss_td.select(*keys).detach()
        if crr is not None:
            out.set("crr_kept", regressed["crr_kept"].detach())
        if bc is not None:  # the same keys every update (NaN on critic-only steps: left out of the logged mean)
            out.update({k: extra.get(k, skipped).detach() for k in ("loss_bc", "bc_kept")})
        if anchor is not None:
            out.update({k: anchored.get(k, skipped).detach() for k in ("loss_anchor", "anchor_shift")})
        return out

    # frames of this run so far: every row it added to its memory (a resumed run
    # counts the rows collected after its last checkpoint too)
    collected_frames = len(replay_buffer) - remembered if progress else 0
    print(
        f"{algo}+HER on {cfg.env.name} | memory {memory_path}: {len(replay_buffer)} transitions"
        + (" | agent resumed from checkpoint" if resumed else "")
        + (f" | run resumed at {collected_frames} frames" if progress else "")
    )
    cpu = CpuClock(offset=progress["cpu_s"] if progress else 0.0)
    curve: list[tuple[int, float]] = [tuple(point) for point in progress["curve"]] if progress else []
    if progress:  # other episodes than the first launch's
        torch.manual_seed(cfg.seed + collected_frames)
        np.random.seed(cfg.seed + collected_frames)

    def save(finished: bool) -> None:
        """The agent, and the run's progress in the checkpoint's metadata (one atomic write).

        The memory is made durable first, so a kill after the save never leaves
        a checkpoint that counts rows the store lost.
        """
        with cpu.paused():
            if hasattr(replay_buffer.storage, "flush"):
                replay_buffer.storage.flush()
            checkpoint.save(checkpoint_path, metadata={
                "env": cfg.env.name, "algo": algo, "seed": cfg.seed, "updates": num_updates,
                "memory_rows_before": remembered, "memory_rows": len(replay_buffer),
                "frames": collected_frames, "cpu_s": cpu.seconds(), "curve": [list(p) for p in curve],
                "finished": finished,
            })

    def log_eval(frames: int) -> float:
        with cpu.paused():
            metrics = evaluate(cfg, eval_env, model[0])
        metrics["time/cpu_s"] = cpu.seconds()
        metrics["train/updates"] = num_updates
        curve.append((frames, metrics["eval/success_rate"]))
        if logger is not None:
            logger.log_metrics(metrics, frames)
        return metrics["eval/success_rate"]

    def sample(query=None):
        if mix is not None:
            batch = mix.sample(cfg.optim.batch_size, query)
        elif query is not None:
            with goal_sampler.query(query):
                batch = replay_buffer.sample()
        else:
            batch = replay_buffer.sample()
        return batch if device.type == "cpu" else batch.to(device, non_blocking=True)

    # Fresh networks and a prior memory: clone its actions into the actor first
    if mix is not None and not resumed and cfg.memory.get("prior_pretrain_bc", 0):
        bc_mse = pretrain_actor(loss_module, [b.storage for b in priors], int(cfg.memory.prior_pretrain_bc),
                                batch_size=cfg.optim.batch_size, lr=cfg.optim.lr, seed=cfg.seed, demos=demos)
        print(f"cloned the prior's actions into the actor: {cfg.memory.prior_pretrain_bc} steps, mse {bc_mse:.4f}")
        if anchor is not None:
            anchor.reset()
        critic_only = True  # the pretraining updates below evaluate the cloned actor, they do not move it
    # Fresh networks on a memory that already holds transitions: learn from it first
    if (remembered or mix is not None) and not resumed and cfg.memory.pretrain_updates:
        for _ in tqdm.trange(cfg.memory.pretrain_updates, desc="updates on the memory", leave=False):
            update(sample())
    critic_only = False
    freeze_frames = int(cfg.memory.get("actor_freeze_frames", 0) or 0)
    success = curve[-1][1] if curve else log_eval(0)
    save(finished=False)

    # Main loop
    init_random_frames = max(0, cfg.collector.init_random_frames - remembered - collected_frames)
    collector = make_collector(
        cfg, train_env, exploration_policy, init_random_frames=init_random_frames,
        total_frames=max(cfg.collector.total_frames - collected_frames, 1),
        seed=cfg.seed + collected_frames,
    )
    utd_ratio = cfg.optim.utd_ratio
    eval_iter = cfg.logger.eval_iter
    target = cfg.logger.target_success
    budget = cfg.collector.cpu_budget_s
    reached_at = first_reach(curve, target)
    done_already = reached_at is not None or collected_frames >= cfg.collector.total_frames
    pbar = tqdm.tqdm(total=cfg.collector.total_frames, initial=collected_frames,
                     desc=f"{algo} {cfg.env.name}", leave=False)

    for data in (collector if not done_already else ()):
        # Extend: flat transitions; recalled priors are recomputed at sampling
        data = data.reshape(-1).exclude(*RECALL_KEYS, *[("next", k) for k in RECALL_KEYS])
        replay_buffer.extend(data)
        if not freeze_stats:
            normalizer.update(data)
        frames = data.numel()
        collected_frames += frames
        pbar.update(frames)

        # Update
        metrics = {}
        if mix is not None:
            mix.ratio = prior_ratio(cfg, collected_frames)
            metrics["train/prior_ratio"] = mix.ratio
        if anchor is not None:  # memory.clone_anchor_final: the trust region widens as the run goes
            anchor.weight = clone_anchor_weight(cfg, collected_frames)
            metrics["train/anchor_weight"] = anchor.weight
        if collected_frames >= init_random_frames:
            critic_only = collected_frames <= freeze_frames  # memory.actor_freeze_frames: critics learn the actor's returns first
            n = max(1, int(frames * utd_ratio))
            losses = TensorDict(batch_size=[n])
            query = current_goals(collector, data) if goal_sampler is not None else None
            for i in range(n):
                losses[i] = update(sample(query))
            metrics.update(mean_losses(losses))
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

        # Evaluate
        if collected_frames % eval_iter < frames:
            success = log_eval(collected_frames)
            save(finished=False)
            pbar.set_postfix(success=f"{success:.2f}")
            if target is not None and success >= target:
                reached_at = collected_frames
                break
        if budget is not None and cpu.seconds() >= budget:
            break

    pbar.close()
    collector.shutdown()
    if curve[-1][0] != collected_frames:
        log_eval(collected_frames)

    # Persist the memory, then save the agent next to it
    save(finished=True)
    storage = replay_buffer.storage
    summary = {
        "env": cfg.env.name,
        "algo": algo,
        "seed": cfg.seed,
        "memory_rows_before": remembered,
        "memory_rows_after": len(replay_buffer),
        "frames": collected_frames,
        "frames_to_target": reached_at,
        "cpu_s": round(cpu.seconds(), 2),
        "updates": num_updates,
        "curve": curve,
    }
    with open("summary.json", "w") as f:
        json.dump(summary, f)
    append_history(history_path, summary)
    if cfg.logger.plot:  # this run, and the earlier runs on the same memory
        curves = {
            f"run {i + 1}: {run['algo']}, memory of {run['memory_rows_before']} transitions": run["curve"]
            for i, run in enumerate([*history, summary])
        }
        if plot_success(curves, "success_rate.png", title=f"{cfg.env.name}, eval success"):
            print(f"plot: {os.path.abspath('success_rate.png')}")
    print(
        f"evaluated success {curve[-1][1]:.2f} after {collected_frames} new env frames "
        f"({summary['cpu_s']:.1f} CPU-s, {num_updates} updates); memory now {len(replay_buffer)} transitions"
        + (f"; reached {target} at {reached_at} frames" if reached_at is not None else "")
    )
    earlier = [run for run in history if run.get("frames_to_target") is not None]
    if reached_at is not None and earlier:
        first = earlier[0]["frames_to_target"]
        print(
            f"the first run on this memory needed {first} frames to reach {target}; "
            f"this one {reached_at}: {first - reached_at} fewer"
        )
    if hasattr(storage, "close"):
        storage.close()
    if not eval_env.is_closed:
        eval_env.close()
    if not train_env.is_closed:
        train_env.close()


if __name__ == "__main__":
    main()
