"""The run's actor and critics, read with their live parameters: what the prior-memory terms evaluate.

:class:`~.bc.PriorBC`, :class:`~.bc.CRRActorLoss` and :class:`~.anchor.CloneAnchor`
all need the actor's deterministic action (with a gradient into the actor) and
the critics' value of given actions (without one). Both passes live here, once.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import LossModule

__all__ = ["ActorCritic", "loss_device"]


def loss_device(loss_module: LossModule) -> torch.device:
    """The device of the loss module's (actor's) parameters."""
    return next(iter(loss_module.actor_network_params.values(True, True))).device


class ActorCritic:
    """The deterministic action of a loss module's actor and the min over its critics, live parameters.

    Args:
        loss_module: the run's SAC / TD3 / DDPG loss.

    Example:
        >>> nets = ActorCritic(loss_module)
        >>> pi = nets.action(batch)                      # gradient into the actor's parameters
        >>> q_pi, q_stored = nets.min_q(batch, pi.detach(), batch["action"])   # no gradient
    """

    def __init__(self, loss_module: LossModule) -> None:
        self.loss_module = loss_module
        self.action_key = getattr(loss_module.tensor_keys, "action", "action")  # DDPG's keys name none
        self.device = loss_device(loss_module)
        if hasattr(loss_module, "qvalue_network"):  # SAC, TD3: stacked twin critics
            self._critic, self._critic_params = loss_module.qvalue_network, "qvalue_network_params"
        else:  # DDPG: one critic
            self._critic, self._critic_params = loss_module.value_network, "value_network_params"

    def min_q(self, td: TensorDictBase, *actions: torch.Tensor) -> list[torch.Tensor]:
        """``min_i Q_i(s, a)`` for each of ``actions``, live critic parameters, no gradient, one pass per critic."""
        params = getattr(self.loss_module, self._critic_params).detach()
        stacked = len(params.batch_size) > 0  # SAC / TD3: one slice of parameters per critic
        key = self.loss_module.tensor_keys.state_action_value
        q_td = torch.cat([td.select(*self._critic.in_keys, strict=False)] * len(actions), 0)
        q_td.set(self.action_key, torch.cat(actions, 0))
        qs = []
        with torch.no_grad():
            for p in (params.unbind(0) if stacked else [params]):
                with p.to_module(self._critic):
                    qs.append(self._critic(q_td.clone(False)).get(key).squeeze(-1))
        return list(torch.stack(qs).min(0)[0].split(td.shape[0]))

    def action(self, rows: TensorDictBase, params: TensorDictBase | None = None) -> torch.Tensor:
        """The deterministic action of the actor with ``params`` (default: its live parameters)."""
        actor = self.loss_module.actor_network
        params = self.loss_module.actor_network_params if params is None else params
        with set_exploration_type(ExplorationType.DETERMINISTIC), params.to_module(actor):
            return actor(rows.select(*actor.in_keys, strict=False)).get(self.action_key)
