"""The clone anchor's weight as a function of the run's new env frames (``prior.clone_anchor_final``).

The prior's share of a batch has its schedule in the recipe (``recipes.her.prior_memory.prior_ratio``).
"""
from __future__ import annotations

from omegaconf import DictConfig

__all__ = ["clone_anchor_weight"]


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
