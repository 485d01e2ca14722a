"""The prior share of a batch and the anchor's weight, as functions of the run's new env frames."""
from __future__ import annotations

from omegaconf import DictConfig

__all__ = ["clone_anchor_weight", "prior_ratio"]


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


def clone_anchor_weight(cfg: DictConfig, frames: int) -> float:
    """``w`` of ``prior.clone_anchor`` after ``frames`` new env frames.

    ``prior.clone_anchor`` throughout, or, with ``prior.clone_anchor_final`` set,
    geometric from ``clone_anchor`` to ``clone_anchor_final`` over
    ``prior.clone_anchor_anneal_frames`` (the trust region's radius, about
    ``1 / w``, then widens by the same factor every frame), constant after.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"prior": {"clone_anchor": 100.0, "clone_anchor_final": 1.0,
        ...                                   "clone_anchor_anneal_frames": 1000}})
        >>> round(clone_anchor_weight(cfg, 500), 6)
        10.0
    """
    start = float(cfg.prior.clone_anchor)
    final = cfg.prior.get("clone_anchor_final")  # absent or null: no schedule
    if final is None or cfg.prior.clone_anchor_anneal_frames <= 0:
        return start
    if not final > 0:
        raise ValueError(f"prior.clone_anchor_final must be > 0 (the anchor's last weight), got {final}.")
    t = min(1.0, frames / cfg.prior.clone_anchor_anneal_frames)
    return float(start * (float(final) / start) ** t)
