"""Prior memories in the HER recipe: read-only stores sampled beside the run's own, and what the actor learns from them.

One job a module:

* ``mix``: :class:`PriorMix`, batches drawn from the run's buffer and the prior
  memories (RLPD's symmetric sampling), prior rows marked ``from_prior``;
* ``actor_critic``: the actor's deterministic action and the critics' min Q,
  live parameters, that the terms below evaluate;
* ``bc``: :class:`PriorBC` (Q-filtered behaviour cloning, ``prior.bc``),
  :class:`CRRActorLoss` (``prior.actor_update=crr``), :func:`pretrain_actor`
  and :func:`load_demos` (``prior.clone_steps``);
* ``hindsight``: :class:`HindsightGoals`, every prior row aimed at what its
  episode achieved a few steps on (``prior.clone_goals=hindsight``);
* ``anchor``: :class:`CloneAnchor`, a trust region around the cloned actor
  (``prior.clone_anchor``);
* ``schedules``: the annealed prior share and anchor weight;
* ``terms``: :class:`PriorTerms`, the one object the update asks for its loss;
* ``layout``: each prior's keys, shapes and dtypes checked against the run's
  task (floating dtypes cast, the rest refused), and its summary;
* ``builders``: all of the above from the ``prior`` config group.

``recipes/her/train.py`` imports it as ``prior_memory`` (a script's own
directory is on ``sys.path``); the tools import ``recipes.her.prior_memory``.
"""
from .anchor import CloneAnchor
from .bc import CRRActorLoss, PriorBC, load_demos, pretrain_actor
from .builders import check_prior_config, check_prior_memories, make_prior_mix, make_prior_terms, step_schedules
from .hindsight import HindsightGoals, episode_ids, numbered_episodes
from .layout import cast_rows, check_prior_layout, describe_prior, prior_summary
from .mix import PRIOR_KEY, TRANSITION_KEYS, PriorMix
from .schedules import clone_anchor_weight, prior_ratio
from .terms import PriorTerms

__all__ = [
    "PRIOR_KEY",
    "TRANSITION_KEYS",
    "CRRActorLoss",
    "CloneAnchor",
    "HindsightGoals",
    "PriorBC",
    "PriorMix",
    "PriorTerms",
    "cast_rows",
    "check_prior_config",
    "check_prior_layout",
    "check_prior_memories",
    "describe_prior",
    "episode_ids",
    "clone_anchor_weight",
    "load_demos",
    "make_prior_mix",
    "make_prior_terms",
    "numbered_episodes",
    "pretrain_actor",
    "prior_ratio",
    "prior_summary",
    "step_schedules",
]
