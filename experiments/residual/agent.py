"""The residual SAC agent: a TanhNormal policy over what to add to the scripted controller's action.

The env adds the controller's action to the policy's (``ScriptedBase(residual=True)``),
so SAC runs unchanged on the residual: its entropy bonus spreads the residual, not
the controller's saturated actions. The actor's last layer starts at zero: the
deterministic residual is 0 and the first policy is the controller itself. Actor and critic see the observation and goal
(normalised, ``recipes.her.utils.GoalNormalizer``), the controller's action and
its state (phase, time). The loss is TorchRL's :class:`~torchrl.objectives.SACLoss`.
"""
from __future__ import annotations

import torch
from omegaconf import DictConfig
from tensordict.nn import InteractionType, TensorDictModule
from tensordict.nn.distributions import NormalParamExtractor
from torch import nn, optim
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.modules.distributions import TanhNormal
from torchrl.objectives import SACLoss, SoftUpdate

from recipes.her.targets import clip_targets
from recipes.her.utils import GoalMLP, GoalNormalizer

__all__ = ["AGENT_INPUTS", "make_agent", "make_loss", "make_optimizers"]

#: what actor and critic read: env observation and goal, the controller's action and state
AGENT_INPUTS = ["observation", "desired_goal", "base_action", "base_state"]
def make_agent(cfg: DictConfig, env, normalizer: GoalNormalizer) -> nn.ModuleList:
    """``ModuleList([actor, qvalue])``; the actor's deterministic residual at initialisation is 0.

    Its residual lies in ``(-algo.residual_max, algo.residual_max)`` per action dimension.
    """
    spec = env.action_spec_unbatched
    n_act = spec.shape[-1]
    bound = float(cfg.algo.residual_max)
    mlp = dict(num_cells=list(cfg.network.hidden_sizes), activation_class=nn.ReLU)
    delta_net = GoalMLP(AGENT_INPUTS, normalizer, out_features=2 * n_act,
                        head=NormalParamExtractor(scale_mapping=f"biased_softplus_{cfg.algo.residual_scale}",
                                                  scale_lb=cfg.algo.scale_lb), **mlp)
    last = delta_net.mlp[-1]
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)  # loc = 0, scale = residual_scale
    actor = ProbabilisticActor(
        TensorDictModule(delta_net, in_keys=AGENT_INPUTS, out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": torch.full((n_act,), -bound), "high": torch.full((n_act,), bound),
                             "tanh_loc": False},
        default_interaction_type=InteractionType.RANDOM,
        return_log_prob=False,
    )
    qvalue = ValueOperator(GoalMLP(["action", *AGENT_INPUTS], normalizer, out_features=1, **mlp),
                           in_keys=["action", *AGENT_INPUTS])
    model = nn.ModuleList([actor, qvalue])
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td = env.fake_tensordict().reshape(-1)[:1]
        for net in model:
            net(td)
    return model


def make_loss(cfg: DictConfig, model: nn.ModuleList) -> tuple[SACLoss, SoftUpdate]:
    """TorchRL's SAC loss (twin critics, learned entropy) with HER's clamped TD targets, and its target updater."""
    actor, qvalue = model
    loss = SACLoss(actor_network=actor, qvalue_network=qvalue, num_qvalue_nets=2, loss_function="l2",
                   delay_actor=False, delay_qvalue=True, alpha_init=cfg.algo.alpha_init,
                   target_entropy=cfg.algo.target_entropy, deactivate_vmap=True)
    loss.make_value_estimator(gamma=cfg.optim.gamma)
    clip_targets(loss, cfg.optim.target_clip, cfg.optim.gamma)
    return loss, SoftUpdate(loss, eps=cfg.optim.target_update_polyak)


def make_optimizers(cfg: DictConfig, loss: SACLoss) -> dict[str, optim.Optimizer]:
    """One Adam each for the actor, the critics and the entropy coefficient (the actor's can sit out)."""
    return {
        "actor": optim.Adam(list(loss.actor_network_params.flatten_keys().values()), lr=cfg.optim.actor_lr),
        "critic": optim.Adam(list(loss.qvalue_network_params.flatten_keys().values()), lr=cfg.optim.lr),
        "alpha": optim.Adam([loss.log_alpha], lr=cfg.optim.lr),
    }
