"""The prior-memory variants of recipes/her: what an actor learns from a prior memory's actions.

``recipes/her`` samples a prior memory beside the run's own (``prior=mix``); the
studies of docs/results.md also cloned its actions into the actor, kept that
clone by a trust region or trained it by CRR. Those variants live here, on top
of the recipe's pieces (``recipes.her.prior_memory``, ``recipes.her.utils``):

* ``train``: the recipe's loop with them (``python -m experiments.prior_variants.train``);
  ``variants.yaml`` and ``prior/{bc,clone}.yaml`` its config;
* ``actor_critic``: the actor's deterministic action and the critics' min Q,
  live parameters, that the terms below evaluate;
* ``bc``: :class:`PriorBC` (Q-filtered behaviour cloning, ``prior.bc``),
  :class:`CRRActorLoss` (``prior.actor_update=crr``), :func:`pretrain_actor`
  and :func:`load_demos` (``prior.clone_steps``);
* ``hindsight``: :class:`HindsightGoals`, every prior row aimed at what its
  episode achieved a few steps on (``prior.clone_goals=hindsight``);
* ``anchor``: :class:`CloneAnchor`, a trust region around the cloned actor
  (``prior.clone_anchor``); ``schedules``: its annealed weight;
* ``terms``: :class:`PriorTerms`, the one object the update asks for its loss;
* ``builders``: all of the above from the ``prior`` config group.
"""
from .anchor import CloneAnchor
from .bc import CRRActorLoss, PriorBC, load_demos, pretrain_actor
from .builders import check_prior_config, make_prior_terms, step_schedules
from .hindsight import HindsightGoals, episode_ids, numbered_episodes
from .schedules import clone_anchor_weight
from .terms import PriorTerms

__all__ = [
    "CRRActorLoss",
    "CloneAnchor",
    "HindsightGoals",
    "PriorBC",
    "PriorTerms",
    "check_prior_config",
    "clone_anchor_weight",
    "episode_ids",
    "load_demos",
    "make_prior_terms",
    "numbered_episodes",
    "pretrain_actor",
    "step_schedules",
]
