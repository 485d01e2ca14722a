"""Q-filtered behaviour cloning on prior rows (Nair et al., 2018).

``memory.prior_bc=w`` adds to the actor's loss, for the rows of each batch that
came from a prior memory (``PriorMix`` marks them ``from_prior``), the squared
distance between the actor's deterministic action and the stored action:

    loss_bc = w * mean|Q(s, pi(s))| * sum_prior(keep * mean_dims((pi(s) - a)^2)) / n_prior

* **Q filter**: a row counts only where the critics rate the stored action above
  the actor's (``min_i Q_i(s, a) > min_i Q_i(s, pi(s))``), so bad scripted
  actions, and actions that do not suit a relabelled goal, are not imitated,
  and the term fades as the actor overtakes the prior (``train/bc_kept`` logs
  the share kept).
* **Scale**: as TD3+BC (Fujimoto & Gu, 2021) the term is multiplied by the
  batch's mean ``|Q|`` (detached), so ``w`` does not depend on the reward scale
  or horizon: TD3+BC's ``alpha = 2.5`` is ``w = 0.4``.

The scripted controllers behind ``recipes/scripted`` reach the goal precisely
(FetchPush at default parameters: 96.6%), which is what SAC+HER alone plateaus
short of (near misses at 5-10 cm, docs/results.md section 9).
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import LossModule

__all__ = ["PRIOR_KEY", "PriorBC"]

#: bool ``[batch]``: True for the rows a batch drew from a prior memory.
PRIOR_KEY = "from_prior"


class PriorBC:
    """The Q-filtered behaviour-cloning term of the actor, on a batch's prior rows.

    Args:
        loss_module: the run's SAC / TD3 / DDPG loss (its live actor and critic parameters are used).
        weight (float): ``w`` above, in units of the batch's mean ``|Q|``; ``0`` disables the term.
        q_filter (bool): imitate only where the critics prefer the stored action.

    Example:
        >>> bc = PriorBC(loss_module, weight=0.4)
        >>> extra = bc(batch)            # {"loss_bc": ..., "bc_kept": ...}, zeros without prior rows
        >>> (loss_td["loss_actor"] + extra["loss_bc"]).backward()
    """

    def __init__(self, loss_module: LossModule, weight: float, q_filter: bool = True) -> None:
        if weight < 0:
            raise ValueError(f"memory.prior_bc must be >= 0, got {weight}.")
        self.loss_module, self.weight, self.q_filter = loss_module, float(weight), bool(q_filter)
        self._action_key = getattr(loss_module.tensor_keys, "action", "action")  # DDPG's keys name none
        if hasattr(loss_module, "qvalue_network"):  # SAC, TD3: stacked twin critics
            self._critic, self._critic_params = loss_module.qvalue_network, "qvalue_network_params"
        else:  # DDPG: one critic
            self._critic, self._critic_params = loss_module.value_network, "value_network_params"

    def _q(self, td: TensorDictBase, *actions: torch.Tensor) -> list[torch.Tensor]:
        """``min_i Q_i(s, a)`` for each of ``actions``, live critic parameters, no gradient, one pass per critic."""
        params = getattr(self.loss_module, self._critic_params).detach()
        stacked = len(params.batch_size) > 0  # SAC / TD3: one slice of parameters per critic
        key = self.loss_module.tensor_keys.state_action_value
        q_td = torch.cat([td.select(*self._critic.in_keys, strict=False)] * len(actions), 0)
        q_td.set(self._action_key, torch.cat(actions, 0))
        qs = []
        with torch.no_grad():
            for p in (params.unbind(0) if stacked else [params]):
                with p.to_module(self._critic):
                    qs.append(self._critic(q_td.clone(False)).get(key).squeeze(-1))
        return list(torch.stack(qs).min(0)[0].split(td.shape[0]))

    def __call__(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        mask = batch.get(PRIOR_KEY, None)
        if not self.weight or mask is None or not mask.any():  # nothing to imitate in this batch
            zero = torch.zeros(())
            return {"loss_bc": zero, "bc_kept": zero}
        prior = batch[mask]
        actor = self.loss_module.actor_network
        with set_exploration_type(ExplorationType.DETERMINISTIC), \
                self.loss_module.actor_network_params.to_module(actor):
            pi = actor(prior.select(*actor.in_keys, strict=False)).get(self._action_key)
        demo = prior.get(self._action_key)
        if self.q_filter:
            q_pi, q_demo = self._q(prior, pi.detach(), demo)
            keep = (q_demo > q_pi).float()
        else:
            (q_pi,) = self._q(prior, pi.detach())
            keep = torch.ones_like(q_pi)
        mse = (pi - demo).pow(2).mean(-1)
        loss = self.weight * q_pi.abs().mean() * (keep * mse).sum() / mask.sum()
        return {"loss_bc": loss, "bc_kept": keep.mean()}
