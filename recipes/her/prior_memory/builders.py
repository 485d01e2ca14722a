"""The prior-memory parts of a run, built from the ``prior`` config group (``prior/{none,mix}.yaml``)."""
from __future__ import annotations

from omegaconf import DictConfig

from torchrl_robotmem import make_env

from .layout import check_prior_layout, describe_prior, prior_summary
from .mix import TRANSITION_KEYS, PriorMix
from .schedules import prior_ratio

__all__ = ["check_prior_config", "check_prior_memories", "make_prior_mix"]


def check_prior_config(cfg: DictConfig) -> None:
    """Refuses ``prior.*`` settings that do not go together, before anything is opened or written."""
    if cfg.prior.name == "none" and cfg.prior.paths:
        raise ValueError("prior.paths names prior memories but prior=none: choose prior=mix (sampled beside "
                         "the run's own).")
    if cfg.prior.name != "none" and not cfg.prior.paths:
        raise ValueError(f"prior={cfg.prior.name} samples prior memories beside the run's own: "
                         "set prior.paths=[path, ...] too.")


def check_prior_memories(cfg: DictConfig, priors: list, log=print) -> tuple[dict, list[dict]]:
    """Every prior memory checked against the run's task, and summarised, before the run's memory is opened.

    Each prior's keys, shapes and dtypes are compared with one transition of
    ``cfg.env.name`` (:func:`~.layout.check_prior_layout`: floating dtypes that
    differ are cast, anything else is refused) and its path, rows, episodes and
    success rate printed (:func:`~.layout.prior_summary`).

    Args:
        cfg (DictConfig): the run's config (``env.name``).
        priors (list): HER buffers over the read-only prior memories (``utils.make_prior_buffers``).
        log: where the lines go.

    Returns:
        ``(dtypes, summaries)``: ``{key: dtype}`` to cast prior rows to, and one summary dict a prior.

    Example:
        >>> dtypes, summaries = check_prior_memories(cfg, make_prior_buffers(cfg))
        >>> mix = make_prior_mix(cfg, own_buffer, priors, dtypes=dtypes)
    """
    dtypes, summaries = {}, []
    if not priors:
        return dtypes, summaries
    env = make_env(cfg.env.name)
    try:
        example = env.fake_tensordict()
    finally:
        env.close()
    for buffer in priors:
        summaries.append(prior_summary(buffer.storage))
        log(describe_prior(summaries[-1]))
        dtypes.update(check_prior_layout(buffer.storage, example, TRANSITION_KEYS, cfg.env.name, log=log))
    return dtypes, summaries


def make_prior_mix(cfg: DictConfig, own, priors: list, example=None, dtypes: dict | None = None) -> PriorMix | None:
    """A :class:`PriorMix` of the run's buffer and its prior memories (``None`` without ``prior.paths``).

    ``dtypes``: the casts of :func:`check_prior_memories` (priors already checked); ``example``:
    one transition of the task to check them against here instead.
    """
    if not priors:
        return None
    mix = PriorMix(own, priors, cfg.prior.ratio, cfg.env.name, TRANSITION_KEYS, example=example, dtypes=dtypes)
    mix.ratio = prior_ratio(cfg, 0)  # raises on a ratio or schedule end outside [0, 1]
    return mix
