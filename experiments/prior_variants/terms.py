"""The prior-memory side of an update: the loss terms it adds to (or puts in place of) the algorithm's."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule

from .actor_critic import loss_device
from .anchor import CloneAnchor
from .bc import CRRActorLoss, PriorBC, pretrain_actor

__all__ = ["PriorTerms"]


class PriorTerms:
    """The algorithm's loss with the prior-memory terms: Q-filtered BC, CRR, the clone anchor.

    :meth:`loss` returns the algorithm's own terms (``keys``) and, where set,
    ``crr_kept`` (CRR's actor loss then stands in ``loss_actor``),
    ``loss_bc`` / ``bc_kept`` and ``loss_anchor`` / ``anchor_shift``: the same
    keys on every update, NaN for an actor-side term on an update that does not
    train the actor (so the logged mean is over the actor's updates alone).
    :meth:`total` is what the update minimises. With nothing set it is the
    algorithm's loss alone.

    The terms are computed in the order the recipe always used (BC before the
    algorithm's loss, CRR and the anchor after), so a run draws the same random
    numbers as before.

    Args:
        loss_module: the run's SAC / TD3 / DDPG loss.
        keys (tuple): the algorithm's loss terms, the actor's first, then the critics' (``utils.loss_keys``).

    Keyword Args:
        bc (PriorBC, optional): the Q-filtered BC term (``prior.bc``).
        crr (bool): the actor's loss is :class:`CRRActorLoss` (``prior.actor_update=crr``).
        anchor (CloneAnchor, optional): the trust region around the clone (``prior.clone_anchor``).
        demos (TensorDictBase, optional): the prior rows :meth:`clone` imitates (``bc.load_demos``).
        clone_horizon (int): ``> 0``: :meth:`clone` relabels each row's goal with one its episode achieved
            at most this many steps on (``prior.clone_goals=hindsight``, ``hindsight.HindsightGoals``).

    Example:
        >>> terms = PriorTerms(loss_module, ("loss_actor", "loss_qvalue"), bc=PriorBC(loss_module, 0.4))
        >>> loss_td = terms.loss(batch, train_actor=True)
        >>> terms.total(loss_td, train_actor=True).backward()
    """

    def __init__(self, loss_module: LossModule, keys: tuple, *, bc: PriorBC | None = None, crr: bool = False,
                 anchor: CloneAnchor | None = None, demos: TensorDictBase | None = None,
                 clone_horizon: int = 0) -> None:
        self.loss_module, self.keys, self.clone_horizon = loss_module, tuple(keys), int(clone_horizon)
        self.bc, self.anchor, self.demos = bc, anchor, demos
        self.crr = CRRActorLoss(loss_module) if crr else None
        device = loss_device(loss_module)
        self._zero = torch.zeros((), device=device)
        self._skipped = torch.full((), float("nan"), device=device)  # an actor-side term on a critic-only update

    def loss(self, batch: TensorDictBase, train_actor: bool = True) -> TensorDictBase:
        """The algorithm's terms (``keys``) and the prior-memory ones, for one batch."""
        skipped = {"loss_bc": self._skipped, "bc_kept": self._skipped}
        bc = self.bc(batch) if self.bc is not None and train_actor else skipped
        loss_td = self.loss_module(batch).select(*self.keys)
        if self.crr is not None:  # regression onto the better stored actions, no critic action gradient
            crr = self.crr(batch) if train_actor else {"loss_actor": self._zero, "crr_kept": self._skipped}
            loss_td.set("loss_actor", crr["loss_actor"])
            loss_td.set("crr_kept", crr["crr_kept"])
        if self.bc is not None:
            loss_td.update(bc)
        if self.anchor is not None:
            anchored = self.anchor(batch) if train_actor else {"loss_anchor": self._skipped,
                                                                "anchor_shift": self._skipped}
            loss_td.update(anchored)
        return loss_td

    def total(self, loss_td: TensorDictBase, train_actor: bool = True) -> torch.Tensor:
        """What an update minimises: every term it trains (the critics' alone when ``train_actor`` is False)."""
        used = self.keys if train_actor else self.keys[1:2]
        if train_actor:
            used += tuple(k for k in ("loss_bc", "loss_anchor") if k in loss_td.keys())
        return sum(loss_td[k] for k in used)

    def clone(self, storages: list, steps: int, batch_size: int, lr: float, seed: int) -> float:
        """Clone the prior's actions into the actor (``prior.clone_steps``); the anchor then holds that clone."""
        mse = pretrain_actor(self.loss_module, storages, steps, batch_size=batch_size, lr=lr, seed=seed,
                             demos=self.demos, horizon=self.clone_horizon)
        if self.anchor is not None:
            self.anchor.reset()
        return mse
