"""Builders of recipes/multiagent/train.py (MADDPG / IDDPG on MaMuJoCo), as in TorchRL's
``sota-implementations/multiagent/maddpg_iddpg.py``: env, policy, critic, loss, collector,
replay buffer over the persistent memory, evaluation, agent checkpoint."""
from __future__ import annotations

import os
from functools import partial

import torch
from hydra.utils import instantiate, to_absolute_path
from omegaconf import DictConfig
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import AdditiveGaussianModule, ProbabilisticActor, TanhDelta, ValueOperator
from torchrl.modules.models.multiagent import MultiAgentMLP
from torchrl.objectives import DDPGLoss, SoftUpdate, ValueEstimators
from torchrl.record.loggers import generate_exp_name, get_logger

GROUP = "agents"
ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU}


def algo_name(cfg: DictConfig) -> str:
    """``MADDPG`` (centralised critic) or ``IDDPG``, ``Het`` prefixed without shared parameters (as the sota script)."""
    return ("" if cfg.model.shared_parameters else "Het") + ("MA" if cfg.model.centralised_critic else "I") + "DDPG"


def make_env_fn(cfg: DictConfig, seed: int):
    """A picklable env constructor: ``functools.partial`` of the ``env._target_`` (plain values only)."""
    return partial(instantiate(cfg.env, _partial_=True), seed=seed)


def memory_path(cfg: DictConfig) -> str:
    """``memory.path`` resolved against the launch directory (hydra changes into ``outputs/``)."""
    return to_absolute_path(str(cfg.memory.path))


def make_replay_buffer(cfg: DictConfig) -> TensorDictReplayBuffer:
    """The replay buffer over ``replay_buffer.storage._target_`` (``ZarrStorage`` at ``memory.path`` by default)."""
    node = cfg.replay_buffer.storage
    kwargs = {}
    if str(node._target_).endswith("ZarrStorage"):
        kwargs = {"path": memory_path(cfg), "env": f"MaMuJoCo-{cfg.env.scenario}-{cfg.env.agent_conf}"}
    else:  # another storage (LazyTensorStorage) takes none of ZarrStorage's own arguments
        node = {k: v for k, v in node.items() if k != "goal_conditioned"}
    storage = instantiate(node, **kwargs, _convert_="all")
    return TensorDictReplayBuffer(storage=storage, batch_size=cfg.train.minibatch_size)


def make_agent(cfg: DictConfig, env):
    """``(policy, policy_explore, value_module)``: deterministic ``TanhDelta`` actor, Gaussian exploration, Q critic."""
    obs_dim = env.observation_spec[GROUP, "observation"].shape[-1]
    action_spec = env.full_action_spec_unbatched
    act_dim = action_spec[GROUP, "action"].shape[-1]
    n_agents = action_spec[GROUP, "action"].shape[-2]
    mlp = dict(n_agents=n_agents, share_params=cfg.model.shared_parameters, depth=cfg.model.depth,
               num_cells=cfg.model.num_cells, activation_class=ACTIVATIONS[cfg.model.activation])
    actor_net = MultiAgentMLP(n_agent_inputs=obs_dim, n_agent_outputs=act_dim, centralised=False, **mlp)
    policy = ProbabilisticActor(
        module=TensorDictModule(actor_net, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "param")]),
        spec=action_spec, in_keys=[(GROUP, "param")], out_keys=[(GROUP, "action")], distribution_class=TanhDelta,
        distribution_kwargs={"low": action_spec[GROUP, "action"].space.low,
                             "high": action_spec[GROUP, "action"].space.high},
        return_log_prob=False,
    )
    explore = AdditiveGaussianModule(spec=action_spec, action_key=(GROUP, "action"),
                                     sigma_init=cfg.exploration.sigma_init, sigma_end=cfg.exploration.sigma_end,
                                     annealing_num_steps=int(cfg.exploration.annealing_frames))
    critic_net = MultiAgentMLP(n_agent_inputs=obs_dim + act_dim, n_agent_outputs=1,
                               centralised=cfg.model.centralised_critic, **mlp)
    value = ValueOperator(module=critic_net, in_keys=[(GROUP, "observation"), (GROUP, "action")],
                          out_keys=[(GROUP, "state_action_value")])
    return policy, TensorDictSequential(policy, explore), value


def make_loss(cfg: DictConfig, policy, value):
    """``(loss_module, target_updater, optimiser)``: per-agent rewards and done flags, TD(0) targets."""
    loss = DDPGLoss(actor_network=policy, value_network=value, delay_value=True)
    loss.set_keys(state_action_value=(GROUP, "state_action_value"), reward=(GROUP, "reward"),
                  done=(GROUP, "done"), terminated=(GROUP, "terminated"))
    loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.loss.gamma)
    return loss, SoftUpdate(loss, tau=cfg.loss.tau), torch.optim.Adam(loss.parameters(), cfg.train.lr)


def make_collector(cfg: DictConfig, policy_explore, total_frames: int, init_random_frames: int) -> Collector:
    """A TorchRL ``Collector`` on one MaMuJoCo env (random actions for the first ``init_random_frames``)."""
    return Collector(make_env_fn(cfg, cfg.seed), policy_explore, frames_per_batch=cfg.collector.frames_per_batch,
                     total_frames=total_frames, init_random_frames=init_random_frames)


def evaluate(env, policy, max_steps: int, episodes: int) -> float:
    """Mean undiscounted episode return (reward summed over steps, averaged over agents) of the deterministic policy."""
    returns = []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            td = env.rollout(max_steps, policy, break_when_any_done=True)
            returns.append(float(td["next", GROUP, "reward"].mean(-2).sum()))
    return sum(returns) / len(returns)


def make_logger(cfg: DictConfig):
    """The run's logger (``logger.backend``: csv | tensorboard | wandb), ``None`` for ``""``."""
    if not cfg.logger.backend:
        return None
    return get_logger(cfg.logger.backend, logger_name="multiagent_logging",
                      experiment_name=generate_exp_name(algo_name(cfg), cfg.logger.exp_name))


def save_agent(path: str, loss, optim, explore, frames: int) -> None:
    """Networks (with targets), optimiser, exploration noise scale and frame count, beside the memory."""
    tmp = path + ".tmp"
    torch.save({"loss": loss.state_dict(), "optim": optim.state_dict(), "explore": explore.state_dict(),
                "frames": int(frames)}, tmp)
    os.replace(tmp, path)


def load_agent(path: str, loss, optim, explore) -> int:
    """Loads what :func:`save_agent` wrote (tensors and ints only: ``weights_only``); returns its frame count."""
    state = torch.load(path, weights_only=True)
    loss.load_state_dict(state["loss"])
    optim.load_state_dict(state["optim"])
    explore.load_state_dict(state["explore"])
    return int(state["frames"])
