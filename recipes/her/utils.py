"""Builders for the HER recipe (``train.py``): logger, envs, collector, replay buffer, agent, loss, optimiser.

Laid out as TorchRL's ``sota-implementations/{sac,td3,ddpg}/utils.py``; the
memory parts (storage, sampler, recall transform) are built from the
``_target_`` entries of ``config.yaml``. The prior-memory parts are in
``prior_memory/``; the pretraining on a stored memory in ``pretrain.py``. This module imports no sibling: ``train.py`` imports it as
``utils`` (a script's own directory is on ``sys.path``), the tools as
``recipes.her.utils``. What a run keeps of itself (CPU clock, progress for
``collector.resume``, history, summary, plot) is in ``run_record.py``.
"""
from __future__ import annotations

import inspect
import logging
import warnings

import torch
from hydra.utils import get_class, instantiate, to_absolute_path
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModule, TensorDictSequential
from tensordict.nn.distributions import NormalParamExtractor
from torch import nn, optim
from torchrl.checkpoint import Checkpoint, CheckpointError
from torchrl.collectors import Collector
from torchrl.envs import RewardSum
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import (
    MLP,
    AdditiveGaussianModule,
    ProbabilisticActor,
    TanhModule,
    ValueOperator,
)
from torchrl.modules.distributions import TanhNormal
from torchrl.objectives import DDPGLoss, SACLoss, SoftUpdate, TD3Loss, group_optimizers
from torchrl.record.loggers import Logger, generate_exp_name, get_logger

from torchrl_robotmem import PersistentHERReplayBuffer, ZarrStorage, make_env, make_reward_fn

# gymnasium-robotics prints an Adroit reward notice to stderr on every import
# (through farama_notifications); nothing above imports it, so drop it here.
try:
    import farama_notifications

    farama_notifications.notifications.pop("gymnasium_robotics", None)
except ImportError:  # pragma: no cover
    pass
warnings.filterwarnings("ignore", category=DeprecationWarning)
logging.getLogger("matplotlib").setLevel(logging.WARNING)

# The keys the recall transform adds; recomputed after every sample (HER
# replaces the goal they were recalled for), so never stored.
RECALL_KEYS = ("prior_goals", "prior_goals_dist", "prior_goals_mask")
# Goals by seed: evaluation episode i resets with cfg.seed + EVAL_SEED + i. Anything a run chooses by looking at
# its success (when pretraining stops) looks at held-out goals, cfg.seed + HELD_OUT_SEED + i, never at those.
EVAL_SEED = 10_000
HELD_OUT_SEED = 5_000_000


# ====================================================================
# Logger
# ------


def make_logger(cfg: DictConfig) -> Logger | None:
    """The run's logger (``logger.backend``: csv | tensorboard | wandb), ``None`` for ``""``."""
    if not cfg.logger.backend:
        return None
    return get_logger(
        cfg.logger.backend,
        logger_name="her_logging",
        experiment_name=generate_exp_name(cfg.algo.name, cfg.logger.exp_name),
        wandb_kwargs={"mode": cfg.logger.mode, "project": cfg.logger.project_name},
    )


# ====================================================================
# Memory: storage, sampler, recall transform, replay buffer
# ---------------------------------------------------------


def _build(node: DictConfig, **kwargs):
    """``instantiate(node)``, passing only the ``kwargs`` its target accepts.

    This is what lets ``replay_buffer.storage._target_=torchrl.data.LazyTensorStorage``
    run the recipe unchanged: the memory path and env name go to targets that
    take ``path`` / ``env`` (``ZarrStorage``), and are left out for the others.
    """
    node = OmegaConf.to_container(node, resolve=True)
    node.pop("enabled", None)
    params = inspect.signature(get_class(node["_target_"])).parameters
    takes_any = any(p.kind is p.VAR_KEYWORD for p in params.values())
    kwargs = {k: v for k, v in kwargs.items() if takes_any or k in params}
    return instantiate(node, **kwargs, _convert_="all")


def make_storage(cfg: DictConfig, path: str, device: torch.device | None = None):
    """The run's storage: a :class:`~torchrl_robotmem.ZarrStorage` at ``path`` by default.

    ``device``: where its rows are held and sampled (:func:`memory_device`); the
    ``_target_`` must take a ``device`` (``ZarrStorage`` and TorchRL's tensor storages do).
    """
    extra = {} if device is None or device.type == "cpu" else {"device": device}
    return _build(cfg.replay_buffer.storage, path=path, env=cfg.env.name, **extra)


def memory_device(cfg: DictConfig) -> torch.device:
    """``replay_buffer.device``: where the memory's rows are held and batches drawn.

    ``auto``: the training device (the CPU with the goal sampler or recall). On CUDA,
    ``ZarrStorage(device="cuda")`` keeps its RAM mirror on the GPU (the store stays on disk):
    batches are drawn, relabelled and rewarded there, with no host-to-device copy per update.
    """
    value = str(cfg.replay_buffer.get("device", "cpu") or "cpu")
    if value != "auto":
        return torch.device(value)
    # the goal sampler's draws are indices on its index's device, which TorchRL 0.14.1's HER cannot mix with
    # its CPU episode bounds, and the recall transform queries the memory from the envs on the CPU: with either
    # on, auto keeps the memory on the CPU (each drawn batch is copied over, pinned, without blocking)
    on_cpu = cfg.replay_buffer.sampler.enabled or cfg.memory.recall.enabled
    return torch.device("cpu") if on_cpu else train_device(cfg)


def to_device(batch: TensorDictBase, device: torch.device) -> TensorDictBase:
    """``batch`` on ``device``: as it is if already there, else through pinned memory, without blocking."""
    if batch.device == device:
        return batch
    if device.type == "cuda" and batch.device is not None and batch.device.type == "cpu":
        batch = batch.pin_memory()
    return batch.to(device, non_blocking=True)


def make_sampler(cfg: DictConfig):
    """A :class:`~torchrl_robotmem.GoalSimilaritySampler` when enabled, else ``None`` (uniform).

    ``replay_buffer.combined``: wrapped in combined experience replay, every batch holding the
    ``env.num_envs`` newest rows (:mod:`torchrl_robotmem.samplers.combined`).
    """
    sampler = _build(cfg.replay_buffer.sampler) if cfg.replay_buffer.sampler.enabled else None
    if cfg.replay_buffer.get("combined", False):
        from torchrl_robotmem.samplers.combined import CombinedExperienceSampler

        sampler = CombinedExperienceSampler(sampler, newest=int(cfg.env.num_envs))
    return sampler


def make_replay_buffer(cfg: DictConfig, storage, sampler=None, batch_size: int | None = -1) -> PersistentHERReplayBuffer:
    """HER over ``storage``: goals relabelled from ``("next", "achieved_goal")``.

    TorchRL's ``HERReplayBuffer`` as :class:`~torchrl_robotmem.PersistentHERReplayBuffer` (which samples a
    memory that has filled and wraps).

    ``batch_size`` defaults to ``optim.batch_size``; ``None`` builds a buffer that is
    only sampled with an explicit size (``PriorMix`` draws part-batches from each).

    The storage is an argument, not built here, so that the same function
    wraps any memory: the run's own store, or (for prior memories sampled
    beside it) a ``ZarrStorage(path, read_only=True)`` of another run.
    No prefetch: the goal sampler's query changes between samples.
    """
    return PersistentHERReplayBuffer(
        make_reward_fn(cfg.env.name),
        her_ratio=cfg.replay_buffer.her_ratio,
        strategy=cfg.replay_buffer.strategy,
        achieved_goal_key=("next", "achieved_goal"),
        storage=storage,
        sampler=sampler,
        batch_size=cfg.optim.batch_size if batch_size == -1 else batch_size,
    )


def make_prior_buffers(cfg: DictConfig, device: torch.device | None = None) -> list[PersistentHERReplayBuffer]:
    """One HER buffer per ``prior.paths`` entry, on a read-only :class:`~torchrl_robotmem.ZarrStorage`.

    They are sampled in part-batches only (``prior_memory.PriorMix``), so they have no batch size.
    ``device``: where their rows are held (that of the run's own memory).
    """
    buffers = []
    for path in cfg.prior.paths:
        storage = ZarrStorage(to_absolute_path(str(path)), read_only=True, device=device or "cpu")
        if not len(storage):
            raise ValueError(f"the prior memory {path!r} holds no transitions.")
        buffers.append(make_replay_buffer(cfg, storage, batch_size=None))
    return buffers


def make_recall(cfg: DictConfig, memory):
    """A :class:`~torchrl_robotmem.RecallTransform` (over ``memory.recall.memory`` or this run's memory), or ``None``.

    ``memory.recall.memory=<path>`` recalls from another memory, read-only: a prior run's, or the scripted
    controller's of ``prior.paths`` (what the seed calls states where past runs found success).
    """
    if not cfg.memory.recall.enabled:
        return None
    other = cfg.memory.recall.get("memory")
    return _build(cfg.memory.recall, memory=to_absolute_path(str(other)) if other else memory)


def make_proposer(cfg: DictConfig, memory, seed: int):
    """A :class:`~torchrl_robotmem.GoalProposer` over this run's memory (``memory.propose``), or ``None``.

    Training episodes then pursue remembered achieved goals where the memory is sparsest (MEGA); the
    evaluation env is built without it and keeps the env's own goals.
    """
    if not cfg.memory.get("propose") or not cfg.memory.propose.enabled:
        return None
    return _build(cfg.memory.propose, memory=memory, env=cfg.env.name, seed=seed)


def refresh_recall(batch: TensorDictBase, recall) -> TensorDictBase:
    """Recalls the priors of the (relabelled) goals of a sampled batch, at t and t+1."""
    recall.forward(batch)
    recall.forward(batch.get("next"))
    return batch


def current_goals(collector: Collector, data: TensorDictBase) -> torch.Tensor:
    """The goals the collector's envs are chasing now: the sampler's query.

    Read from the collector's carrier (the root of the next step); the last
    batch's final goals if a collector does not keep one.
    """
    carrier = getattr(collector, "_carrier", None)
    if carrier is not None and "desired_goal" in carrier.keys():
        return carrier["desired_goal"].reshape(-1, carrier["desired_goal"].shape[-1])
    goals = data["next", "desired_goal"]
    return goals.reshape(-1, goals.shape[-1])[-1:]


# ====================================================================
# Environment and collector
# -------------------------


def make_environment(cfg: DictConfig, memory=None):
    """Train env (``env.num_envs``, in worker processes with ``env.parallel``) and eval env (one env per episode).

    ``train.py`` has checked the collection batch against the envs (:func:`check_env_batch`) before opening the memory.
    """
    train = make_task_env(cfg, cfg.env.num_envs, cfg.seed, memory, parallel=bool(cfg.env.get("parallel", False)),
                          propose=True)
    return train, make_eval_env(cfg, cfg.logger.eval_episodes, memory)


def check_env_batch(cfg: DictConfig) -> None:
    """Refuses a collection batch that would cut episodes apart in the memory.

    The collector returns ``[num_envs, frames_per_batch / num_envs]``, stored env by
    env; HER finds an episode's future goals in the rows after it, so with several
    envs each env's share of a batch must hold whole episodes.
    """
    n, frames, steps = cfg.env.num_envs, cfg.collector.frames_per_batch, cfg.env.max_episode_steps
    if n < 1:
        raise ValueError(f"env.num_envs must be >= 1, got {n}.")
    if n > 1 and frames % (n * steps):
        good = n * steps * max(1, round(frames / (n * steps)))
        raise ValueError(
            f"collector.frames_per_batch={frames} with env.num_envs={n}: each env's share of a batch must be whole "
            f"episodes of env.max_episode_steps={steps} (HER reads an episode's rows in one piece), so "
            f"frames_per_batch must be a multiple of {n * steps}: e.g. collector.frames_per_batch={good}.")


def make_task_env(cfg: DictConfig, num_envs: int, seed: int, memory=None, parallel: bool = False,
                  propose: bool = False):
    """``num_envs`` envs of ``cfg.env.name`` (in series, or one process each with ``parallel``), with the episode
    reward and (when enabled) recall; the transforms run in this process, on the whole batch.

    ``propose``: a training env, whose goals the :class:`~torchrl_robotmem.GoalProposer` of ``memory.propose``
    chooses (when enabled); first, so that the episode reward and recall see the goal pursued.
    """
    recall = make_recall(cfg, memory) if memory is not None else None
    proposer = make_proposer(cfg, memory, seed) if memory is not None and propose else None
    transforms = ([proposer] if proposer is not None else []) + [RewardSum()] + ([recall] if recall is not None else [])
    return make_env(cfg.env.name, num_envs, seed=seed, max_episode_steps=cfg.env.max_episode_steps,
                    transforms=transforms, parallel=parallel and num_envs > 1)


def eval_seed(cfg: DictConfig, held_out: bool = False) -> int:
    """The seed of the first evaluation goal: the run's evaluation goals, or the held-out goals (``held_out``)."""
    return cfg.seed + (HELD_OUT_SEED if held_out else EVAL_SEED)


def make_eval_env(cfg: DictConfig, episodes: int, memory=None, *, held_out: bool = False):
    """An evaluation env: one env per episode, seeded as :func:`eval_rollout` reseeds it (fixed goals).

    The run's eval env has ``logger.eval_episodes`` on the evaluation goals; the pretraining checks
    one of ``memory.pretrain_eval_episodes`` on held-out goals (``held_out``: a seed range disjoint
    from the evaluation's), so that no choice of the run is made on the goals it is evaluated on.
    """
    return make_task_env(cfg, episodes, eval_seed(cfg, held_out), memory)


def train_device(cfg: DictConfig) -> torch.device:
    """``device``: where the networks live and the updates run (envs and memory stay on the CPU).

    ``cuda`` on a machine without one is refused with what to set, not silently
    run on the CPU (CPU-seconds measured on a GPU run are not comparable).
    """
    device = torch.device(str(cfg.device))
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device={cfg.device}: torch sees no CUDA device here "
                           f"(torch {torch.__version__}, a CPU-only build?). Run with device=cpu.")
    return device


def make_collector(
    cfg: DictConfig, train_env, policy, init_random_frames: int,
    total_frames: int | None = None, seed: int | None = None,
) -> Collector:
    """The collector of the run (``total_frames`` and ``seed`` default to the config's)."""
    collector = Collector(
        train_env,
        policy,
        frames_per_batch=cfg.collector.frames_per_batch,
        total_frames=cfg.collector.total_frames if total_frames is None else total_frames,
        init_random_frames=init_random_frames,
        policy_device=train_device(cfg),  # the actor where it trains; envs and collected data on the CPU
        env_device="cpu",
        storing_device="cpu",
    )
    collector.set_seed(cfg.seed if seed is None else seed)
    return collector


def start_normalizer(normalizer: GoalNormalizer, replay_buffer, progress: dict | None, resumed: bool,
                     mix=None) -> None:
    """The normaliser's statistics at a run's start.

    Fresh networks take those of the whole memory and of the prior memories (``mix``); a
    resumed agent has its own from the checkpoint, and a resumed run (``progress``) adds
    the rows collected after the checkpoint was written.
    """
    if not resumed and len(replay_buffer):
        normalizer.update(replay_buffer[:])
    if progress is not None and len(replay_buffer) > progress["memory_rows"]:
        normalizer.update(replay_buffer.storage[progress["memory_rows"]:len(replay_buffer)])
    if mix is not None and not resumed:
        for rows in mix.prior_rows():
            normalizer.update(rows)


def load_agent(checkpoint: Checkpoint, path: str) -> None:
    """Restores the agent saved at ``path``, or says which settings it was saved with."""
    try:
        checkpoint.load(path)
    except CheckpointError as err:
        raise RuntimeError(
            f"the agent checkpoint {path} does not fit this agent (saved with other "
            "algo / network / memory.recall settings?). Use the settings it was saved with, "
            "or start fresh networks on the memory with memory.resume_agent=false."
        ) from err


@torch.no_grad()
def eval_rollout(cfg: DictConfig, eval_env, actor, *, held_out: bool = False) -> TensorDictBase:
    """The deterministic evaluation episodes, ``[episodes, T]``, on fixed goals (the eval env is reseeded).

    ``held_out``: on the held-out goals (:func:`eval_seed`), for choices a run makes.
    """
    eval_env.set_seed(eval_seed(cfg, held_out))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = eval_env.rollout(
            cfg.env.max_episode_steps, actor, break_when_any_done=False, auto_cast_to_device=True
        )
    return rollout.reshape(-1, rollout.shape[-1])


def evaluate(cfg: DictConfig, eval_env, actor, outcomes: list | None = None, *,
             held_out: bool = False) -> dict[str, float]:
    """Success and return of :func:`eval_rollout`; success is ``is_success`` at an episode's last step.

    ``outcomes``: a list that is set to each episode's success (0 / 1), in the order of the fixed goals, so
    that two runs with the same seed can be compared goal by goal (``recipes.her.tools.paired``).
    """
    rollout = eval_rollout(cfg, eval_env, actor, held_out=held_out)
    # float64: 19/20 in float32 is 0.9499999, under a 0.95 target
    success = (rollout["next", "is_success"][:, -1] > 0.5).double()
    if outcomes is not None:
        outcomes[:] = success.int().tolist()
    return {
        "eval/success_rate": success.mean().item(),
        "eval/return": rollout["next", "reward"].sum((-2, -1)).mean().item(),
    }


# ====================================================================
# Agent
# -----


class GoalNormalizer:
    """Running mean and std of observations and goals, as in HER (Andrychowicz et al. 2017).

    Fetch positions sit around 1.3 m with a 10 cm spread: unnormalised, a
    small MLP hardly tells goals 5 cm apart (SAC+HER did not solve FetchReach
    in 3k frames without it; with it, 500 updates on random data did).
    The statistics are computed from the collected transitions (``update``),
    never from relabelled batches, and held outside the networks' parameters,
    so that the actor, both critics and their target copies share one set.
    Goals are normalised with the statistics of desired and achieved goals.
    """

    def __init__(self, eps: float = 1e-2, clip: float = 5.0, device: torch.device | str = "cpu"):
        self.eps, self.clip = eps, clip
        self.device = torch.device(device)  # of the mean and std the networks read; the sums stay on the CPU
        self.stats: dict[str, list[torch.Tensor]] = {}  # name -> [count, sum, sum of squares]

    def _accumulate(self, name: str, x: torch.Tensor) -> None:
        x = x.reshape(-1, x.shape[-1]).double().cpu()
        new = [torch.tensor(float(x.shape[0]), dtype=torch.float64), x.sum(0), x.pow(2).sum(0)]
        old = self.stats.get(name)
        self.stats[name] = new if old is None else [a + b for a, b in zip(old, new)]
        self._refresh(name)

    def _refresh(self, name: str) -> None:
        count, total, squares = self.stats[name]
        mean = total / count
        std = (squares / count - mean.pow(2)).clamp_min(0).sqrt().clamp_min(self.eps)
        current = getattr(self, f"_{name}", None)
        if current is None or current[0].shape != mean.shape:
            setattr(self, f"_{name}", (mean.float().to(self.device), std.float().to(self.device)))
        else:  # in place: a compiled or CUDA-graphed update keeps reading the same tensors
            current[0].copy_(mean, non_blocking=True)
            current[1].copy_(std, non_blocking=True)

    def update(self, data: TensorDictBase) -> None:
        self._accumulate("observation", data["observation"])
        self._accumulate("goal", torch.cat([data["desired_goal"], data["next", "achieved_goal"]]))

    def __call__(self, name: str, x: torch.Tensor) -> torch.Tensor:
        if name not in self.stats:
            return x
        mean, std = getattr(self, f"_{name}")
        return ((x - mean) / std).clamp(-self.clip, self.clip)

    def state_dict(self) -> dict:
        return {name: torch.stack([v[0].expand_as(v[1]), v[1], v[2]]) for name, v in self.stats.items()}

    def load_state_dict(self, state_dict: dict) -> None:
        self.stats = {name: [v[0, 0].clone(), v[1].clone(), v[2].clone()] for name, v in state_dict.items()}
        for name in self.stats:
            self._refresh(name)


# which statistics normalise which network input; others enter raw
_NORMALISED = {"observation": "observation", "desired_goal": "goal", "prior_goals": "goal"}


class GoalMLP(nn.Module):
    """An MLP over several inputs, each normalised, flattened and concatenated.

    ``prior_goals`` is ``[*B, k, goal_dim]``; the other inputs are ``[*B, d]``.
    """

    def __init__(self, in_keys, normalizer: GoalNormalizer, head: nn.Module | None = None, **mlp_kwargs):
        super().__init__()
        self.stat_names = [_NORMALISED.get(k) for k in in_keys]
        self.normalizer = normalizer  # a plain object: not a parameter, shared by every copy
        self.mlp = MLP(**mlp_kwargs)
        self.head = head if head is not None else nn.Identity()

    def forward(self, *inputs: torch.Tensor):
        lead = inputs[0].shape[:-1]
        xs = [x if name is None else self.normalizer(name, x) for name, x in zip(self.stat_names, inputs)]
        return self.head(self.mlp(torch.cat([x.reshape(*lead, -1) for x in xs], -1)))


def agent_inputs(cfg: DictConfig) -> list[str]:
    keys = ["observation", "desired_goal"]
    if cfg.memory.recall.enabled:
        keys += ["prior_goals", "prior_goals_dist"]
    return keys


def make_agent(cfg: DictConfig, env, normalizer: GoalNormalizer):
    """Actor and critic for ``cfg.algo.name`` on ``train_device(cfg)``; returns ``(model, exploration_policy)``."""
    in_keys = agent_inputs(cfg)
    device = train_device(cfg)
    action_spec = env.action_spec_unbatched.to(device)
    n_act = action_spec.shape[-1]
    mlp = dict(num_cells=list(cfg.network.hidden_sizes), activation_class=_activation(cfg))
    algo = cfg.algo.name

    if algo == "SAC":
        actor_net = GoalMLP(
            in_keys,
            normalizer,
            out_features=2 * n_act,
            head=NormalParamExtractor(
                scale_mapping=f"biased_softplus_{cfg.algo.default_policy_scale}",
                scale_lb=cfg.algo.scale_lb,
            ),
            **mlp,
        )
        actor = ProbabilisticActor(
            TensorDictModule(actor_net, in_keys=in_keys, out_keys=["loc", "scale"]),
            in_keys=["loc", "scale"],
            spec=action_spec,
            distribution_class=TanhNormal,
            distribution_kwargs={
                "low": action_spec.space.low,
                "high": action_spec.space.high,
                "tanh_loc": False,
            },
            default_interaction_type=InteractionType.RANDOM,
            return_log_prob=False,
        )
    elif algo in ("TD3", "DDPG"):
        actor = TensorDictSequential(
            TensorDictModule(GoalMLP(in_keys, normalizer, out_features=n_act, **mlp), in_keys=in_keys, out_keys=["param"]),
            TanhModule(in_keys=["param"], out_keys=["action"], spec=action_spec),
        )
    else:
        raise ValueError(f"algo.name must be SAC, TD3 or DDPG, got {algo!r}.")

    critic_mlp = dict(mlp)
    if cfg.network.critic_layer_norm:  # RLPD (Ball et al., 2023): LayerNorm after each hidden layer
        critic_mlp.update(norm_class=nn.LayerNorm,
                          norm_kwargs=[{"normalized_shape": h} for h in cfg.network.hidden_sizes])
    qvalue = ValueOperator(
        GoalMLP(["action", *in_keys], normalizer, out_features=1, **critic_mlp), in_keys=["action", *in_keys]
    )
    model = nn.ModuleList([actor, qvalue]).to(device)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td = env.fake_tensordict().reshape(-1)[:1].to(device)
        for net in model:
            net(td)

    if algo == "SAC":
        return model, actor
    exploration = TensorDictSequential(
        actor,
        AdditiveGaussianModule(
            spec=action_spec, sigma_init=1.0, sigma_end=1.0, mean=0.0, std=cfg.algo.exploration_noise
        ),
    )
    return model, exploration


def _activation(cfg: DictConfig):
    return {"relu": nn.ReLU, "tanh": nn.Tanh, "leaky_relu": nn.LeakyReLU}[cfg.network.activation]


# ====================================================================
# Loss and optimiser
# ------------------


def make_loss_module(cfg: DictConfig, model, compiled: bool = False):
    """The algorithm's TorchRL loss and its target-network updater.

    ``optim.deactivate_vmap`` (``auto``): a Python loop over the twin critics when
    the update runs eagerly (faster on the CPU), ``torch.func.vmap`` when it is
    ``compiled``: the loop's pytree switch changes a dict torch.compile guards on,
    so every compiled call would recompile (tensordict 0.14.3, torch 2.13).
    """
    actor, qvalue = model
    algo = cfg.algo.name
    no_vmap = cfg.optim.deactivate_vmap
    no_vmap = not compiled if no_vmap in ("auto", None) else bool(no_vmap)
    if algo == "SAC":
        loss = SACLoss(
            actor_network=actor,
            qvalue_network=qvalue,
            num_qvalue_nets=2,
            loss_function=cfg.optim.loss_function,
            delay_actor=False,
            delay_qvalue=True,
            alpha_init=cfg.algo.alpha_init,
            target_entropy=cfg.algo.target_entropy,
            deactivate_vmap=no_vmap,
        )
    elif algo == "TD3":
        loss = TD3Loss(
            actor_network=actor,
            qvalue_network=qvalue,
            num_qvalue_nets=2,
            loss_function=cfg.optim.loss_function,
            delay_actor=True,
            delay_qvalue=True,
            action_spec=actor[-1].spec,
            policy_noise=cfg.algo.policy_noise,
            noise_clip=cfg.algo.noise_clip,
            deactivate_vmap=no_vmap,
        )
    else:
        loss = DDPGLoss(
            actor_network=actor,
            value_network=qvalue,
            loss_function=cfg.optim.loss_function,
            delay_actor=True,
            delay_value=True,
        )
    loss.make_value_estimator(gamma=cfg.optim.gamma)
    loss = loss.to(train_device(cfg))  # SAC's log_alpha and target entropy with the networks
    return loss, SoftUpdate(loss, eps=cfg.optim.target_update_polyak)


def make_optimizer(cfg: DictConfig, loss_module, capturable: bool = False, actor_lr: float | None = None):
    """One Adam per parameter group (actor, critic, and SAC's entropy), grouped, at ``optim.lr``.

    ``actor_lr``: the actor's own learning rate instead (``experiments/prior_variants``' ``prior.actor_lr``).
    ``capturable``: the optimisers' state on the device, as a CUDA-graphed update needs.
    """
    critic = loss_module.qvalue_network_params if hasattr(loss_module, "qvalue_network_params") \
        else loss_module.value_network_params
    groups = [
        list(loss_module.actor_network_params.flatten_keys().values()),
        list(critic.flatten_keys().values()),
    ]
    kw = dict(weight_decay=cfg.optim.weight_decay, eps=cfg.optim.adam_eps)
    if capturable:
        kw["capturable"] = True
    actor_lr = actor_lr or cfg.optim.lr
    optimizers = [optim.Adam(g, lr=lr, **kw) for g, lr in zip(groups, (actor_lr, cfg.optim.lr))]
    if cfg.algo.name == "SAC":
        optimizers.append(optim.Adam([loss_module.log_alpha], lr=cfg.optim.lr, **({"capturable": True} if capturable else {})))
    return group_optimizers(*optimizers)


def loss_keys(cfg: DictConfig) -> tuple[str, ...]:
    return {
        "SAC": ("loss_actor", "loss_qvalue", "loss_alpha"),
        "TD3": ("loss_actor", "loss_qvalue"),
        "DDPG": ("loss_actor", "loss_value"),
    }[cfg.algo.name]


def mean_losses(losses: TensorDictBase) -> dict[str, float]:
    """``train/<key>`` means of a batch of update records, NaN entries left out.

    Actor-side terms (those of ``experiments/prior_variants``: ``loss_bc``, ``crr_kept``, ...)
    are recorded as NaN on the updates that do not train the actor (TD3's delayed steps,
    critic-only steps), so their means are over the actor's updates alone; a key with
    no value in the batch is not logged.
    """
    means = {}
    for key, value in losses.items():
        mean = value.float().nanmean()
        if not torch.isnan(mean):
            means[f"train/{key}"] = mean.item()
    return means
