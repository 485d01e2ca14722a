"""Builders for the PPO recipe (``train.py``): logger, memory, envs, collector, models, loss, evaluation.

Laid out as TorchRL's ``sota-implementations/ppo/utils_mujoco.py``; the memory
parts (storage, on-policy sampler, recall transform) are built from the
``_target_`` entries of ``config.yaml``. ``train.py`` imports it as ``utils``
(a script's own directory is on ``sys.path``); it imports no sibling module.
"""
from __future__ import annotations

import inspect
import logging
import warnings

import torch
from hydra.utils import get_class, instantiate, to_absolute_path
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import RewardSum
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, ValueOperator
from torchrl.modules.distributions import TanhNormal
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE
from torchrl.record.loggers import Logger, generate_exp_name, get_logger

from torchrl_robotmem import make_env

try:  # gymnasium-robotics prints an Adroit reward notice on every import
    import farama_notifications

    farama_notifications.notifications.pop("gymnasium_robotics", None)
except ImportError:  # pragma: no cover
    pass
warnings.filterwarnings("ignore", category=DeprecationWarning)
logging.getLogger("matplotlib").setLevel(logging.WARNING)

#: what the recall transform adds: the policy's inputs at collection time, kept in RAM for the
#: minibatches of that batch, never stored (the HER recipe recomputes them after relabelling)
RECALL_KEYS = ("prior_goals", "prior_goals_dist", "prior_goals_mask")
#: PPO's per-row values, computed on the collected batch and joined to the drawn rows, never stored:
#: the memory keeps the same columns as the HER recipe's (SAC) memory, so either recipe can continue on it
LOG_PROB_KEY = "action_log_prob"
PPO_KEYS = (LOG_PROB_KEY, "state_value", "advantage", "value_target")


# ====================================================================
# Logger
# ------


def make_logger(cfg: DictConfig) -> Logger | None:
    """The run's logger (``logger.backend``: csv | tensorboard | wandb), ``None`` for ``""``."""
    if not cfg.logger.backend:
        return None
    return get_logger(cfg.logger.backend, logger_name="ppo_logging",
                      experiment_name=generate_exp_name("PPO", cfg.logger.exp_name),
                      wandb_kwargs={"mode": cfg.logger.mode, "project": cfg.logger.project_name})


# ====================================================================
# Memory: storage, on-policy sampler, replay buffer
# -------------------------------------------------


def build(node: DictConfig, **kwargs):
    """``instantiate(node)``, passing only the ``kwargs`` its target accepts (``enabled`` dropped).

    So ``replay_buffer.storage._target_=torchrl.data.LazyTensorStorage`` runs the recipe
    unchanged: the memory path and env name go only to targets that take ``path`` / ``env``.
    """
    node = OmegaConf.to_container(node, resolve=True)
    node.pop("enabled", None)
    params = inspect.signature(get_class(node["_target_"])).parameters
    takes_any = any(p.kind is p.VAR_KEYWORD for p in params.values())
    kwargs = {k: v for k, v in kwargs.items() if takes_any or k in params}
    return instantiate(node, **kwargs, _convert_="all")


def make_replay_buffer(cfg: DictConfig, path: str) -> TensorDictReplayBuffer:
    """The memory at ``path`` (every row kept) with the on-policy sampler (the newest batch's minibatches)."""
    storage = build(cfg.replay_buffer.storage, path=path, env=cfg.env.name)
    return TensorDictReplayBuffer(storage=storage, sampler=build(cfg.replay_buffer.sampler),
                                  batch_size=cfg.loss.mini_batch_size)


def memory_rows(data: TensorDictBase) -> TensorDictBase:
    """The collected batch as the memory keeps it: flat, without PPO's values and the recalled goals."""
    drop = [*PPO_KEYS, *RECALL_KEYS]
    return data.reshape(-1).exclude(*drop, *[("next", k) for k in drop])


# ====================================================================
# Environment and collector
# -------------------------


def check_batch(cfg: DictConfig) -> None:
    """Refuses settings that would cut episodes apart in the memory or leave no minibatch."""
    n, frames, steps = cfg.env.num_envs, cfg.collector.frames_per_batch, cfg.env.max_episode_steps
    if n < 1:
        raise ValueError(f"env.num_envs must be >= 1, got {n}.")
    if n > 1 and frames % (n * steps):
        good = n * steps * max(1, round(frames / (n * steps)))
        raise ValueError(
            f"collector.frames_per_batch={frames} with env.num_envs={n}: each env's share of a batch must be whole "
            f"episodes of env.max_episode_steps={steps}, so that the memory holds episodes in one piece (the HER "
            f"recipe reads them so): e.g. collector.frames_per_batch={good}.")
    if not 0 < cfg.loss.mini_batch_size <= frames:
        raise ValueError(f"loss.mini_batch_size={cfg.loss.mini_batch_size} must be in [1, "
                         f"collector.frames_per_batch={frames}].")


def make_recall(cfg: DictConfig, memory):
    """A :class:`~torchrl_robotmem.RecallTransform` (over ``memory.recall.memory`` or this run's memory), or ``None``."""
    if not cfg.memory.recall.enabled:
        return None
    other = cfg.memory.recall.memory
    return build(cfg.memory.recall, memory=to_absolute_path(str(other)) if other else memory)


def make_task_env(cfg: DictConfig, num_envs: int, seed: int, memory=None):
    """``num_envs`` envs of ``cfg.env.name`` with the episode reward and (when enabled) recall."""
    recall = make_recall(cfg, memory)
    transforms = [RewardSum()] + ([recall] if recall is not None else [])
    return make_env(cfg.env.name, num_envs, seed=seed, max_episode_steps=cfg.env.max_episode_steps,
                    transforms=transforms)


def make_collector(cfg: DictConfig, env, policy, total_frames: int, seed: int) -> Collector:
    collector = Collector(env, policy, frames_per_batch=cfg.collector.frames_per_batch, total_frames=total_frames,
                          device="cpu", storing_device="cpu")
    collector.set_seed(seed)
    return collector


# ====================================================================
# Models
# ------


class RunningNorm:
    """Mean and std of observations and goals over every collected row; a plain object shared by actor and critic.

    The statistics move once a batch, before its epochs (``train.py`` then recomputes the batch's
    log-probabilities with them, so PPO's ratio starts at 1). Saved with the agent (``state_dict``).
    """

    def __init__(self, eps: float = 1e-2, clip: float = 5.0):
        self.eps, self.clip = eps, clip
        self.stats: dict[str, torch.Tensor] = {}  # name -> [3, d]: count, sum, sum of squares

    def update(self, data: TensorDictBase) -> None:
        goals = torch.cat([data["desired_goal"].reshape(-1, data["desired_goal"].shape[-1]),
                           data["next", "achieved_goal"].reshape(-1, data["desired_goal"].shape[-1])])
        for name, x in (("observation", data["observation"]), ("goal", goals)):
            x = x.reshape(-1, x.shape[-1]).double()
            new = torch.stack([torch.full_like(x[0], x.shape[0]), x.sum(0), x.pow(2).sum(0)])
            self.stats[name] = new + self.stats[name] if name in self.stats else new

    def __call__(self, name: str, x: torch.Tensor) -> torch.Tensor:
        if name not in self.stats:
            return x
        count, total, squares = self.stats[name]
        mean = total / count
        std = (squares / count - mean.pow(2)).clamp_min(0).sqrt().clamp_min(self.eps)
        return ((x - mean.to(x)) / std.to(x)).clamp(-self.clip, self.clip)

    def state_dict(self) -> dict:
        return {k: v.clone() for k, v in self.stats.items()}

    def load_state_dict(self, state_dict: dict) -> None:
        self.stats = {k: torch.as_tensor(v, dtype=torch.float64).clone() for k, v in state_dict.items()}


_NORMALISED = {"observation": "observation", "desired_goal": "goal", "prior_goals": "goal"}


class GoalNet(nn.Module):
    """An MLP over several inputs, each normalised (observation, goals), flattened and concatenated."""

    def __init__(self, in_keys, normalizer: RunningNorm, head: nn.Module | None = None, **mlp_kwargs):
        super().__init__()
        self.names = [_NORMALISED.get(k) for k in in_keys]
        self.normalizer = normalizer
        self.mlp = MLP(**mlp_kwargs)
        self.head = head if head is not None else nn.Identity()

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        lead = inputs[0].shape[:-1]
        xs = [(x if name is None else self.normalizer(name, x)).float() for name, x in zip(self.names, inputs)]
        return self.head(self.mlp(torch.cat([x.reshape(*lead, -1) for x in xs], -1)))


def agent_inputs(cfg: DictConfig) -> list[str]:
    keys = ["observation", "desired_goal"]
    return keys + list(RECALL_KEYS) if cfg.memory.recall.enabled else keys


def make_ppo_models(cfg: DictConfig, env, normalizer: RunningNorm):
    """Actor (TanhNormal, state-independent scale) and critic, orthogonally initialised as in TorchRL's sota PPO."""
    in_keys = agent_inputs(cfg)
    spec = env.action_spec_unbatched
    n_act = spec.shape[-1]
    act = {"tanh": nn.Tanh, "relu": nn.ReLU}[cfg.network.activation]
    mlp = dict(num_cells=list(cfg.network.hidden_sizes), activation_class=act)
    scale = AddStateIndependentNormalScale(n_act, scale_lb=1e-4, init_value=float(cfg.network.init_log_std))
    actor_net = GoalNet(in_keys, normalizer, head=scale, out_features=n_act, **mlp)
    value_net = GoalNet(in_keys, normalizer, out_features=1, **mlp)
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=in_keys, out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"], spec=spec, distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high, "tanh_loc": False},
        return_log_prob=True, log_prob_key=LOG_PROB_KEY, default_interaction_type=ExplorationType.RANDOM,
    )
    critic = ValueOperator(value_net, in_keys=in_keys)
    with torch.no_grad():  # the lazy layers take their input sizes, then their initial weights
        td = env.fake_tensordict().reshape(-1)[:1]
        actor(td)
        critic(td)
        for net, last_gain in ((actor_net, 0.01), (value_net, 1.0)):
            linears = [m for m in net.mlp.modules() if isinstance(m, nn.Linear)]
            for i, layer in enumerate(linears):
                nn.init.orthogonal_(layer.weight, last_gain if i == len(linears) - 1 else 2 ** 0.5)
                layer.bias.zero_()
    return actor, critic


def make_loss_module(cfg: DictConfig, actor, critic) -> tuple[ClipPPOLoss, GAE]:
    """TorchRL's ClipPPOLoss and its GAE advantage module."""
    adv = GAE(gamma=cfg.loss.gamma, lmbda=cfg.loss.gae_lambda, value_network=critic, average_gae=False)
    loss = ClipPPOLoss(actor_network=actor, critic_network=critic, clip_epsilon=cfg.loss.clip_epsilon,
                       entropy_bonus=cfg.loss.entropy_coeff > 0, entropy_coeff=cfg.loss.entropy_coeff or None,
                       critic_coeff=cfg.loss.critic_coeff, loss_critic_type=cfg.loss.loss_critic_type,
                       normalize_advantage=True)
    loss.set_keys(sample_log_prob=LOG_PROB_KEY)
    return loss, adv


@torch.no_grad()
def refresh_log_prob(actor, data: TensorDictBase) -> TensorDictBase:
    """The collected actions' log-probabilities under the actor now (after the statistics moved)."""
    dist = actor.get_dist(data)
    data.set(LOG_PROB_KEY, dist.log_prob(data["action"]))
    return data


# ====================================================================
# Evaluation
# ----------


@torch.no_grad()
def evaluate(cfg: DictConfig, eval_env, actor) -> dict[str, float]:
    """Deterministic episodes on fixed goals (the eval env is reseeded): success at the last step, return."""
    eval_env.set_seed(cfg.seed + 10_000)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = eval_env.rollout(cfg.env.max_episode_steps, actor, break_when_any_done=False)
    rollout = rollout.reshape(-1, rollout.shape[-1])
    return {
        "eval/success_rate": rollout["next", "is_success"][:, -1].double().mean().item(),
        "eval/return": rollout["next", "reward"].sum((-2, -1)).mean().item(),
    }
