"""Behaviour cloning of prior rows: the Q-filtered BC term, CRR, and cloning before any RL update.

``prior.bc=w`` (:class:`PriorBC`, Nair et al., 2018) adds to the actor's loss,
for the rows of each batch that came from a prior memory (:class:`recipes.her.prior_memory.PriorMix`
marks them ``from_prior``), the squared distance between the actor's
deterministic action and the stored action::

    loss_bc = w * mean|Q(s, pi(s))| * sum_prior(keep * mean_dims((pi(s) - a)^2)) / n_prior

* **Q filter**: a row counts only where the critics rate the stored action above
  the actor's (``min_i Q_i(s, a) > min_i Q_i(s, pi(s))``), so bad scripted
  actions, and actions that do not suit a relabelled goal, are not imitated,
  and the term fades as the actor overtakes the prior (``train/bc_kept`` logs
  the share kept).
* **Scale**: as TD3+BC (Fujimoto & Gu, 2021) the term is multiplied by the
  batch's mean ``|Q|`` (detached), so ``w`` does not depend on the reward scale
  or horizon: TD3+BC's ``alpha = 2.5`` is ``w = 0.4``.

``prior.actor_update=crr`` (:class:`CRRActorLoss`) regresses the actor onto the
stored actions the critics prefer instead of following their action gradient;
``prior.clone_steps=N`` (:func:`pretrain_actor`) clones the prior's successful
episodes into the actor before the first update.

The scripted controllers behind ``experiments/scripted`` reach the goal precisely
(FetchPush at default parameters: 96.6%), which is what SAC+HER alone plateaus
short of (near misses at 5-10 cm, docs/notes/results_log.md section 9).
"""
from __future__ import annotations

import torch
import tqdm
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import LossModule

from recipes.her.prior_memory.layout import cast_rows
from recipes.her.prior_memory.mix import PRIOR_KEY

from .actor_critic import ActorCritic, loss_device
from .hindsight import ACHIEVED_KEY, EPISODE_KEY, HindsightGoals, numbered_episodes

__all__ = ["CRRActorLoss", "PriorBC", "load_demos", "pretrain_actor"]


class PriorBC:
    """The Q-filtered behaviour-cloning term of the actor, on a batch's prior rows.

    Args:
        loss_module: the run's SAC / TD3 / DDPG loss (its live actor and critic parameters are used).
        weight (float): ``w`` above, in units of the batch's mean ``|Q|``; ``0`` disables the term.
        q_filter (bool): imitate only where the critics prefer the stored action.
        demos (TensorDictBase, optional): imitate these rows (original goals, :func:`load_demos`)
            instead of the batch's prior rows, as many as the batch holds.

    Example:
        >>> bc = PriorBC(loss_module, weight=0.4)
        >>> extra = bc(batch)            # {"loss_bc": ..., "bc_kept": ...}, zeros without prior rows
        >>> (loss_td["loss_actor"] + extra["loss_bc"]).backward()
    """

    def __init__(self, loss_module: LossModule, weight: float, q_filter: bool = True,
                 demos: TensorDictBase | None = None) -> None:
        if weight < 0:
            raise ValueError(f"prior.bc must be >= 0, got {weight}.")
        self.weight, self.q_filter, self.demos = float(weight), bool(q_filter), demos
        self.nets = ActorCritic(loss_module)

    def __call__(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        mask = batch.get(PRIOR_KEY, None)
        if not self.weight or mask is None or not mask.any():  # nothing to imitate in this batch
            zero = torch.zeros((), device=self.nets.device)
            return {"loss_bc": zero, "bc_kept": zero}
        if self.demos is not None:  # as many rows as the batch's prior share, with their original goals
            prior = self.demos[torch.randint(self.demos.shape[0], (int(mask.sum()),))]
        else:
            prior = batch[mask]
        mse, keep, q_pi = self.filtered_mse(prior)
        loss = self.weight * q_pi.abs().mean() * (keep * mse).sum() / prior.shape[0]
        return {"loss_bc": loss, "bc_kept": keep.mean()}

    def filtered_mse(self, rows: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per row: squared distance of the actor's deterministic action to the stored one, the Q filter, Q(s, pi(s))."""
        pi = self.nets.action(rows)
        stored = rows.get(self.nets.action_key)
        if self.q_filter:
            q_pi, q_stored = self.nets.min_q(rows, pi.detach(), stored)
            keep = (q_stored > q_pi).float()
        else:
            (q_pi,) = self.nets.min_q(rows, pi.detach())
            keep = torch.ones_like(q_pi)
        return (pi - stored).pow(2).mean(-1), keep, q_pi


class CRRActorLoss(PriorBC):
    """The actor's loss as critic-regularised regression (CRR, Wang et al. 2020, binary filter).

    ``prior.actor_update=crr`` replaces the algorithm's own actor loss (the
    critics' action gradient, ``-Q(s, pi(s))``) by regression onto the batch's
    stored actions that the critics rate above the actor's, on every row (the
    run's own and the prior's, with their relabelled goals)::

        loss_actor = sum(keep * mean_dims((pi(s) - a)^2)) / batch,   keep = 1[min_i Q_i(s, a) > min_i Q_i(s, pi(s))]

    The actor only ever moves towards actions that were taken, so a critic
    that is wrong between them cannot pull it off the data (the TD3+BC anchor
    leaves an equilibrium offset proportional to the critics' action gradient:
    enough to undo a precise cloned policy, docs/notes/results_log.md section 11). The
    critics are trained by the algorithm's own loss, unchanged. Measured: it
    did not keep the cloned FetchPush actor either (0.95 to 0.05-0.11 in 2500
    frames, section 12): regression targets that are not the clone's own
    actions move its weights past what its precision tolerates.

    Args:
        loss_module: the run's SAC / TD3 / DDPG loss.

    Example:
        >>> crr = CRRActorLoss(loss_module)
        >>> out = crr(batch)                 # {"loss_actor": ..., "crr_kept": ...}
        >>> (loss_td["loss_qvalue"] + out["loss_actor"]).backward()
    """

    def __init__(self, loss_module: LossModule) -> None:
        super().__init__(loss_module, weight=1.0, q_filter=True)

    def __call__(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        mse, keep, _ = self.filtered_mse(batch)
        return {"loss_actor": (keep * mse).sum() / batch.shape[0], "crr_kept": keep.mean()}


def pretrain_actor(
    loss_module: LossModule,
    storages: list,
    steps: int,
    batch_size: int = 256,
    lr: float = 1e-3,
    success_only: bool = True,
    seed: int = 0,
    demos: TensorDictBase | None = None,
    horizon: int = 0,
) -> float:
    """Clone the prior memories' actions into the actor before any RL update (behaviour cloning).

    The actor's deterministic action is regressed onto the stored action (squared
    error, actions clipped to the action box) over the prior rows with their
    **original** goals (no relabelling: the stored action was aimed at that goal).
    ``success_only`` keeps the episodes whose ``episode_success`` (written by
    ``experiments.scripted``) is set, where the memory records it. A separate Adam
    is used, so the run's optimiser state is untouched.

    Args:
        loss_module: the run's SAC / TD3 / DDPG loss; its live actor parameters are trained.
        storages (list): prior memories (``ZarrStorage``), read once.
        steps (int): gradient steps.
        batch_size (int): rows a step.
        lr (float): Adam learning rate.
        success_only (bool): only the rows of successful episodes (when the memory says which).
        seed (int): seed of the row draws.
        demos (TensorDictBase, optional): the rows of :func:`load_demos`, when already read.
        horizon (int): ``> 0``: hindsight goals (``prior.clone_goals=hindsight``): every row, its goal
            replaced at each draw by an achieved goal of its episode at most ``horizon`` steps on
            (:class:`~.hindsight.HindsightGoals`; ``demos`` from ``load_demos(..., hindsight=True)``).

    Returns:
        the mean squared error of the last 100 steps.

    Example:
        >>> storage = ZarrStorage("memory/scripted/push.zarr", read_only=True)
        >>> pretrain_actor(loss_module, [storage], steps=4000)   # FetchPush: 0.94 evaluated success, no env frame
    """
    actor = loss_module.actor_network
    action_key = getattr(loss_module.tensor_keys, "action", "action")
    data = demos if demos is not None else load_demos(loss_module, storages, success_only, hindsight=horizon > 0)
    low, high = -1.0, 1.0
    spec = getattr(actor, "spec", None)
    if spec is not None and action_key in spec.keys():
        low, high = spec[action_key].space.low, spec[action_key].space.high
    target = data.get(action_key).clamp(low, high)
    params = loss_module.actor_network_params
    opt = torch.optim.Adam(list(params.values(True, True)), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    draw = HindsightGoals(data, horizon, generator=gen) if horizon > 0 else data.__getitem__
    losses = []
    for _ in tqdm.trange(steps, desc="cloning the prior's actions", leave=False):
        idx = torch.randint(data.shape[0], (batch_size,), generator=gen)
        with set_exploration_type(ExplorationType.DETERMINISTIC), params.to_module(actor):
            pi = actor(draw(idx).exclude(action_key)).get(action_key)
        loss = (pi - target[idx]).pow(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    opt.zero_grad(set_to_none=True)  # no stale gradient for the run's own optimiser to step on
    return float(sum(losses[-100:]) / len(losses[-100:]))


def load_demos(loss_module: LossModule, storages: list, success_only: bool = True,
               dtypes: dict | None = None, hindsight: bool = False) -> TensorDictBase:
    """The prior memories' rows an actor can imitate: what the actor reads and the action, original goals.

    ``success_only`` keeps the episodes whose ``episode_success`` is set, where the memory records it;
    ``dtypes`` (``{key: dtype}``, :func:`~.layout.check_prior_layout`) casts the keys a prior stores
    in another floating dtype (float64 from a raw Gymnasium env) to the run's. ``hindsight``: every
    row (``success_only`` ignored), with ``("next", "achieved_goal")`` and an episode number
    (:data:`~.hindsight.EPISODE_KEY`, unique across the memories) for :class:`~.hindsight.HindsightGoals`.

    Example:
        >>> demos = load_demos(loss_module, [ZarrStorage("memory/scripted/push.zarr", read_only=True)])
    """
    actor = loss_module.actor_network
    action_key = getattr(loss_module.tensor_keys, "action", "action")
    keys = [*actor.in_keys, action_key, *([ACHIEVED_KEY] if hindsight else [])]
    parts, episodes = [], 0
    for storage in storages:
        rows = storage[: len(storage)]
        if hindsight:
            ids = numbered_episodes(rows, first=episodes)  # unique across the memories
            episodes = int(ids.max()) + 1 if ids.numel() else episodes
        if success_only and not hindsight and "episode_success" in rows.keys():
            rows = rows[rows.get("episode_success").reshape(rows.shape[0]) > 0.5]
        missing = [k for k in keys if k not in rows.keys(True)]
        if missing:
            raise KeyError(f"a prior memory holds no {missing}: the actor reads {actor.in_keys} "
                           "(prior.clone_steps, prior.bc_original_goals).")
        part = cast_rows(rows.select(*keys).clone(), dtypes)
        if hindsight:
            part.set(EPISODE_KEY, ids)
        parts.append(part)
    data = torch.cat(parts, 0) if len(parts) > 1 else parts[0]
    if not data.shape[0]:
        raise ValueError("no prior rows to imitate (no successful episodes in prior.paths?).")
    return data.to(loss_device(loss_module))  # where the actor trains (device=cuda)
