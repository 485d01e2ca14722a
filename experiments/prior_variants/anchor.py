"""A trust region in action space around the cloned actor (``prior.clone_anchor``)."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase, TensorDictParams
from torchrl.objectives import LossModule

from .actor_critic import ActorCritic

__all__ = ["CloneAnchor"]


class CloneAnchor(torch.nn.Module):
    """A trust region in action space around the cloned actor, on every state of every batch.

    ``prior.clone_anchor=w`` keeps a frozen copy ``pi_0`` of the actor as it is
    right after ``prior.clone_steps`` (call :meth:`reset` then) and adds
    to each actor update, over all rows of the batch (the run's own states and
    the prior's, with their relabelled goals)::

        loss_anchor = w * mean|Q(s, pi(s))| * mean_batch(mean_dims((pi(s) - pi_0(s))^2))

    Unlike the BC terms it anchors the actor's *outputs* to the clone's own on
    the states the run visits, not to stored actions (which are not the
    clone's: noisy, or aimed at other goals): the algorithm's actor loss can
    only move the actions by about ``grad_a Q / (2 w mean|Q|)``. A weight-noise
    test put the FetchPush clone's tolerance near a mean action change of 0.01
    (docs/notes/results_log.md section 12); ``train/anchor_shift`` logs the mean absolute
    change. The copy is saved in the run's checkpoint, so a resumed run keeps
    the same anchor.

    Args:
        loss_module: the run's SAC / TD3 / DDPG loss; the actor's live parameters are anchored.
        weight (float): ``w`` above, in units of the batch's mean ``|Q|`` (``> 0``).

    Example:
        >>> anchor = CloneAnchor(loss_module, weight=10.0)
        >>> pretrain_actor(loss_module, [storage], steps=4000)
        >>> anchor.reset()                   # pi_0: the clone
        >>> out = anchor(batch)              # {"loss_anchor": ..., "anchor_shift": ...}
        >>> (loss_td["loss_actor"] + out["loss_anchor"]).backward()
    """

    def __init__(self, loss_module: LossModule, weight: float) -> None:
        super().__init__()
        if weight <= 0:
            raise ValueError(f"prior.clone_anchor must be > 0 (0 disables it), got {weight}.")
        self.weight = float(weight)
        self.nets = ActorCritic(loss_module)  # its actor and critic passes (not a module: not saved)
        self.anchor = TensorDictParams(loss_module.actor_network_params.data.clone(), no_convert=True)

    def reset(self) -> None:
        """Take the actor's current parameters (the clone) as ``pi_0``."""
        self.anchor.data.update_(self.nets.loss_module.actor_network_params.data)

    def forward(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        pi = self.nets.action(batch)
        with torch.no_grad():
            pi_0 = self.nets.action(batch, self.anchor)
        (q_pi,) = self.nets.min_q(batch, pi.detach())
        loss = self.weight * q_pi.abs().mean() * (pi - pi_0).pow(2).mean()
        return {"loss_anchor": loss, "anchor_shift": (pi - pi_0).detach().abs().mean()}
