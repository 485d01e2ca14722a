"""The prior-memory variants of a run, built from the ``prior`` config group (``prior/*.yaml`` here and in
``recipes/her``): the recipe's prior mix, plus what the actor learns from the prior's actions."""
from __future__ import annotations

from omegaconf import DictConfig
from torchrl.objectives import LossModule

from recipes.her.prior_memory import PriorMix, prior_ratio

from .anchor import CloneAnchor
from .bc import PriorBC, load_demos
from .schedules import clone_anchor_weight
from .terms import PriorTerms

__all__ = ["check_prior_config", "make_prior_terms", "step_schedules"]

ACTOR_UPDATES = ("q_gradient", "crr")
CLONE_GOALS = ("original", "hindsight")


def check_prior_config(cfg: DictConfig) -> None:
    """Refuses ``prior.*`` settings that do not go together, before anything is opened or written."""
    prior = cfg.prior
    if prior.actor_update not in ACTOR_UPDATES:
        raise ValueError(f"prior.actor_update must be q_gradient or crr, got {prior.actor_update!r}.")
    if prior.clone_goals not in CLONE_GOALS:
        raise ValueError(f"prior.clone_goals must be original or hindsight, got {prior.clone_goals!r}.")
    if prior.clone_goals == "hindsight":
        if prior.clone_horizon < 1:
            raise ValueError(f"prior.clone_horizon must be >= 1 (1: the next achieved goal), got {prior.clone_horizon}.")
        if prior.bc and prior.bc_original_goals:
            raise ValueError("prior.clone_goals=hindsight clones every prior row, failed episodes too: "
                             "prior.bc_original_goals=true would imitate them with their own goals. Set one of them.")
        if cfg.memory.recall.enabled:
            raise ValueError("prior.clone_goals=hindsight relabels the goals the actor reads, and the recalled "
                             "prior_goals of a row belong to its own goal: set memory.recall.enabled=false.")
    if prior.clone_anchor and not prior.clone_steps:
        raise ValueError("prior.clone_anchor keeps the actor near the one cloned by prior.clone_steps: "
                         "set prior.clone_steps=N (and prior.paths=[path, ...]) too, or use prior=clone.")
    for option in ("bc", "clone_steps"):
        if prior[option] and not prior.paths:
            raise ValueError(f"prior.{option} clones the actions of prior memory rows: "
                             f"set prior.paths=[path, ...] too (prior=bc or prior=clone).")
    if prior.name == "none" and prior.paths:
        raise ValueError("prior.paths names prior memories but prior=none: choose prior=mix (sampled beside "
                         "the run's own), prior=bc or prior=clone.")
    if prior.name != "none" and not prior.paths:
        raise ValueError(f"prior={prior.name} samples prior memories beside the run's own: "
                         "set prior.paths=[path, ...] too.")


def make_prior_terms(cfg: DictConfig, loss_module: LossModule, keys: tuple, priors: list,
                     dtypes: dict | None = None) -> PriorTerms:
    """The :class:`~.terms.PriorTerms` of ``prior.bc`` / ``prior.actor_update`` / ``prior.clone_anchor``.

    ``dtypes``: the casts of :func:`check_prior_memories`, applied to the rows cloned into the actor.
    """
    prior = cfg.prior
    demos = None  # the rows cloned (successful, own goals; every row with hindsight) and imitated by BC, read once
    if prior.clone_steps or (prior.bc and prior.bc_original_goals):
        demos = load_demos(loss_module, [b.storage for b in priors], dtypes=dtypes,
                           hindsight=prior.clone_goals == "hindsight")
    bc = None
    if prior.bc:
        bc = PriorBC(loss_module, prior.bc, q_filter=prior.bc_q_filter,
                     demos=demos if prior.bc_original_goals else None)
    anchor = None  # the cloned actor's outputs, kept near on every batch (saved with the agent)
    if prior.clone_anchor:
        anchor = CloneAnchor(loss_module, prior.clone_anchor)
        anchor.weight = clone_anchor_weight(cfg, 0)  # raises on a schedule end <= 0
    horizon = prior.clone_horizon if prior.clone_goals == "hindsight" else 0
    return PriorTerms(loss_module, keys, bc=bc, crr=prior.actor_update == "crr", anchor=anchor, demos=demos,
                      clone_horizon=horizon)


def step_schedules(cfg: DictConfig, frames: int, mix: PriorMix | None, anchor: CloneAnchor | None) -> dict:
    """Sets the prior share and the anchor's weight for ``frames`` new env frames; returns them as metrics."""
    metrics = {}
    if mix is not None:
        mix.ratio = prior_ratio(cfg, frames)
        metrics["train/prior_ratio"] = mix.ratio
    if anchor is not None:  # prior.clone_anchor_final: the trust region widens as the run goes
        anchor.weight = clone_anchor_weight(cfg, frames)
        metrics["train/anchor_weight"] = anchor.weight
    return metrics
