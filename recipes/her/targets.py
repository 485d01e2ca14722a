"""The range of the critics' TD targets: HER's ``clip_return``, for TorchRL's SAC / TD3 / DDPG losses.

A sparse goal reward is -1 or 0, so every discounted return lies in
``[-1 / (1 - gamma), 0]``. The HER baselines (Andrychowicz et al. 2017;
``clip_return`` in OpenAI baselines' ``her``) clamp the critic's targets to that
range. Without it, this recipe's SAC+HER critic on FetchSlide-v4 (pooled prior,
seed 2) diverged after 45k frames: the critic loss went from 2 to 16,000, the
actor's Q from -7 to +527 on rewards that are never positive, and evaluated
success from 0.31 to 0.01 (docs/results.md, "To 100k frames").

``optim.target_clip`` sets it: ``auto`` (that range, from ``optim.gamma``),
``null`` (no clamp, the recipe before this option), or ``[low, high]``.
``train.py`` imports it as ``targets``; it imports no sibling module.
"""
from __future__ import annotations

import math

from torchrl.objectives.value import TD0Estimator

__all__ = ["ClippedTD0Estimator", "clip_targets", "target_range"]


class ClippedTD0Estimator(TD0Estimator):
    """TorchRL's :class:`~torchrl.objectives.value.TD0Estimator`, its targets clamped to ``target_range``.

    Made from the estimator a loss built for itself (:meth:`from_loss`), so the
    loss's keys, value network and gamma stay exactly as TorchRL set them.

    Example:
        >>> from torchrl.modules import MLP, ValueOperator
        >>> from torchrl.objectives import DDPGLoss
        >>> actor = ValueOperator(MLP(3, 1, num_cells=[8]), in_keys=["observation"], out_keys=["action"])
        >>> critic = ValueOperator(MLP(4, 1, num_cells=[8]), in_keys=["observation", "action"])
        >>> loss = DDPGLoss(actor, critic)
        >>> loss.make_value_estimator(gamma=0.98)
        >>> ClippedTD0Estimator.from_loss(loss, (-50.0, 0.0)).target_range
        (-50.0, 0.0)
    """

    target_range: tuple[float, float] = (-math.inf, math.inf)

    @classmethod
    def from_loss(cls, loss, target_range: tuple[float, float]) -> ClippedTD0Estimator:
        """Turns ``loss.value_estimator`` (a TD(0) estimator) into this class, clamping at ``target_range``."""
        estimator = loss.value_estimator
        if type(estimator) is not TD0Estimator:
            raise TypeError(f"optim.target_clip clamps TD(0) targets; {type(loss).__name__} uses "
                            f"{type(estimator).__name__}: set optim.target_clip=null.")
        low, high = (float(x) for x in target_range)
        if not low < high:
            raise ValueError(f"optim.target_clip must be [low, high] with low < high, got {list(target_range)}.")
        estimator.__class__ = cls  # the same module, its state untouched; only value_estimate changes
        estimator.target_range = (low, high)
        return estimator

    def value_estimate(self, tensordict, *args, **kwargs):
        low, high = self.target_range
        return super().value_estimate(tensordict, *args, **kwargs).clamp(low, high)


def target_range(target_clip, gamma: float) -> tuple[float, float] | None:
    """``optim.target_clip`` as ``(low, high)``: ``auto`` is ``(-1 / (1 - gamma), 0)``, ``None`` no clamp.

    Example:
        >>> target_range("auto", 0.98)
        (-50.0, 0.0)
        >>> target_range(None, 0.98) is None
        True
    """
    if target_clip is None:
        return None
    if target_clip == "auto":
        return (round(-1.0 / (1.0 - float(gamma)), 9), 0.0)
    if isinstance(target_clip, str) or len(target_clip) != 2:
        raise ValueError(f"optim.target_clip must be auto, null or [low, high], got {target_clip!r}.")
    return (float(target_clip[0]), float(target_clip[1]))


def clip_targets(loss, target_clip, gamma: float) -> tuple[float, float] | None:
    """Clamps ``loss``'s TD targets as ``optim.target_clip`` says; returns the range (``None``: unclamped)."""
    bounds = target_range(target_clip, gamma)
    if bounds is not None:
        ClippedTD0Estimator.from_loss(loss, bounds)
    return bounds
