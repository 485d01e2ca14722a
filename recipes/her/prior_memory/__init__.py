"""Prior memories in the HER recipe (``prior=mix``): read-only stores sampled beside the run's own.

One job a module:

* ``mix``: :class:`PriorMix`, batches drawn from the run's buffer and the prior
  memories (RLPD's symmetric sampling), prior rows marked ``from_prior``;
* ``schedules``: the prior's share of a batch, annealed over the run (``prior.ratio_final``);
* ``layout``: each prior's keys, shapes and dtypes checked against the run's
  task (floating dtypes cast, the rest refused), and its summary;
* ``builders``: all of the above from the ``prior`` config group.

``recipes/her/train.py`` imports it as ``prior_memory`` (a script's own
directory is on ``sys.path``); the tools import ``recipes.her.prior_memory``.
What else an actor can learn from a prior memory (behaviour cloning, a clone
kept by a trust region, CRR: the variants the studies compared) is in
``experiments/prior_variants``, which builds on this package.
"""
from .builders import check_prior_config, check_prior_memories, make_prior_mix
from .layout import cast_rows, check_prior_layout, describe_prior, prior_summary
from .mix import PRIOR_KEY, TRANSITION_KEYS, PriorMix
from .schedules import prior_ratio

__all__ = [
    "PRIOR_KEY",
    "TRANSITION_KEYS",
    "PriorMix",
    "cast_rows",
    "check_prior_config",
    "check_prior_layout",
    "check_prior_memories",
    "describe_prior",
    "make_prior_mix",
    "prior_ratio",
    "prior_summary",
]
