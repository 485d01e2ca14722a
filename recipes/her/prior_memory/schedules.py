"""The prior's share of a batch, as a function of the run's new env frames (``prior.ratio_final``)."""
from __future__ import annotations

from omegaconf import DictConfig

__all__ = ["prior_ratio"]


def prior_ratio(cfg: DictConfig, frames: int) -> float:
    """Share of a batch drawn from ``prior.paths`` after ``frames`` new env frames.

    ``prior.ratio`` throughout, or, with ``prior.ratio_final`` set, linear from
    ``ratio`` to ``ratio_final`` over ``prior.anneal_frames``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"prior": {"ratio": 0.5, "ratio_final": 0.1, "anneal_frames": 1000}})
        >>> prior_ratio(cfg, 500)
        0.3
    """
    start, final, horizon = cfg.prior.ratio, cfg.prior.ratio_final, cfg.prior.anneal_frames
    if final is not None and not 0.0 <= final <= 1.0:
        raise ValueError(f"prior.ratio_final must be in [0, 1], got {final}.")
    if final is None or horizon <= 0:
        return float(start)
    t = min(1.0, frames / horizon)
    return float(start + t * (final - start))
