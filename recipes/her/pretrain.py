"""Updates of fresh networks on a non-empty memory before collecting, stopped once they have done their job.

A run that starts fresh networks on a memory that already holds transitions
first learns from it (``memory.pretrain_updates`` at most). Every
``memory.pretrain_eval_every`` updates the actor is checked: the recipe's
deterministic evaluation on ``memory.pretrain_eval_episodes`` held-out goals (a
seed range disjoint from the evaluation goals: when to stop is a choice, and no
choice is made on the goals a run is evaluated on). Pretraining stops once a
check reaches ``memory.pretrain_target`` (``logger.target_success`` when null),
or when ``memory.pretrain_patience`` checks in a row did not beat the best one.
The run's evaluation at frame 0 is a full evaluation made after it stopped.

``train.py`` imports it as ``pretrain``; like ``utils.py`` it imports no sibling
(:func:`pretrain_on_memory` is given the check env's builder and the run's CPU clock).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import tqdm

__all__ = ["pretrain", "pretrain_on_memory"]


def pretrain(
    update: Callable[[], object],
    check: Callable[[], dict],
    max_updates: int,
    eval_every: int = 250,
    target: float | None = None,
    patience: int = 3,
    actor_fixed: bool = False,
    on_check: Callable[[int, dict], None] | None = None,
) -> dict:
    """Runs up to ``max_updates`` calls of ``update``, checking the actor every ``eval_every``; stops when done.

    Args:
        update: one gradient step (takes no argument).
        check: an evaluation of the actor as it is now, on held-out goals; returns metrics with
            ``"eval/success_rate"``.
        max_updates (int): the most updates (``memory.pretrain_updates``).
        eval_every (int): updates between two checks; ``0``: check only after all of them.
        target (float, optional): stop at this evaluated success or above.
        patience (int): stop after this many checks in a row without a better success
            than the best so far; ``0``: never for that reason.
        actor_fixed (bool): the updates do not move the actor (critic-only pretraining of a
            cloned actor): it is checked before them, where the target may already be met,
            and after all of them.
        on_check: called with ``(updates done, metrics)`` after every check (logging).

    Returns:
        ``{"updates": done, "checks": [[updates, success], ...], "stopped": "target" | "patience" | "max"}``.

    Example:
        >>> steps = []
        >>> out = pretrain(lambda: steps.append(1), lambda: {"eval/success_rate": min(1.0, len(steps) / 500)},
        ...                max_updates=3000, eval_every=250, target=0.95)
        >>> out["updates"], out["stopped"], out["checks"]
        (500, 'target', [[250, 0.5], [500, 1.0]])
        >>> flat = pretrain(lambda: None, lambda: {"eval/success_rate": 0.2}, 3000, 250, target=0.95, patience=2)
        >>> flat["updates"], flat["stopped"], flat["checks"]
        (750, 'patience', [[250, 0.2], [500, 0.2], [750, 0.2]])
    """
    checks: list[list] = []
    state = {"best": -math.inf, "since_best": 0}

    def look(done: int) -> str | None:
        metrics = check()
        success = metrics["eval/success_rate"]
        checks.append([done, success])
        if on_check is not None:
            on_check(done, metrics)
        if target is not None and success >= target:
            return "target"
        if success > state["best"]:
            state["best"], state["since_best"] = success, 0
        else:
            state["since_best"] += 1
        return "patience" if patience and state["since_best"] >= patience else None

    def result(done: int, stopped: str) -> dict:
        return {"updates": done, "checks": checks, "stopped": stopped}

    if actor_fixed:  # the actor will not move: one look before, one after
        if look(0) == "target":
            return result(0, "target")
        eval_every = 0
    done, stopped = 0, None
    with tqdm.tqdm(total=max_updates, desc="updates on the memory", leave=False) as bar:
        while done < max_updates and stopped is None:
            n = max_updates - done if eval_every <= 0 else min(eval_every, max_updates - done)
            for _ in range(n):
                update()
            done += n
            bar.update(n)
            stopped = look(done)
            if actor_fixed and stopped == "patience":  # one look after, whatever it says
                stopped = None
    return result(done, stopped or "max")


def pretrain_on_memory(cfg, step: Callable[[], object], full_eval: Callable[..., dict],
                       make_check_env: Callable[[int], object], cpu, logger=None, actor_fixed: bool = False) -> dict:
    """``memory.pretrain_*``: updates on the memory until a check reaches the target, a plateau or the maximum.

    The checks run ``memory.pretrain_eval_episodes`` episodes (at most ``logger.eval_episodes``) on
    held-out goals: ``make_check_env(episodes)`` builds their env (``utils.make_eval_env(...,
    held_out=True)``, a seed range disjoint from the evaluation's), so when pretraining stops is never
    chosen on the goals the run is evaluated on. ``full_eval(env, held_out=...)`` evaluates the actor;
    ``full_eval()`` is the run's evaluation, done once after pretraining stops and returned in
    ``"metrics"`` (the run's evaluation at frame 0): reported, never looked at to stop.

    Returns:
        :func:`pretrain`'s dict, with ``"metrics"``.
    """
    mem = cfg.memory
    episodes = min(mem.pretrain_eval_episodes or cfg.logger.eval_episodes, cfg.logger.eval_episodes)
    target = mem.pretrain_target if mem.pretrain_target is not None else cfg.logger.target_success
    with cpu.evaluating():
        check_env = make_check_env(episodes)

    def on_check(updates: int, metrics: dict) -> None:
        if logger is not None:
            logger.log_metrics({"pretrain/success_rate": metrics["eval/success_rate"]}, updates)

    out = pretrain(step, lambda: full_eval(check_env, held_out=True), mem.pretrain_updates, mem.pretrain_eval_every,
                   target=target, patience=mem.pretrain_patience, actor_fixed=actor_fixed, on_check=on_check)
    check_env.close()
    out["metrics"] = full_eval()
    why = {"target": f"the target {target}", "patience": f"a plateau ({mem.pretrain_patience} checks without a "
           "better success)", "max": "the maximum"}[out["stopped"]]
    print(f"pretraining on the memory: {out['updates']} of at most {mem.pretrain_updates} updates, stopped at {why}; "
          f"success at each check ({episodes} held-out episodes, every {mem.pretrain_eval_every or mem.pretrain_updates} "
          f"updates): {', '.join(f'{u}: {x:.2f}' for u, x in out['checks'])}; evaluation after it: "
          f"{out['metrics']['eval/success_rate']:.2f}")
    return out
