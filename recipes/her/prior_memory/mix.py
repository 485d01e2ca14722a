"""Prior memories sampled beside the run's own buffer: read-only stores of other runs, tasks or scripted controllers.

``prior.paths=[path, ...]`` opens each store read-only and samples it beside the
run's own buffer, symmetric sampling as in RLPD (Ball et al., 2023): a fixed
share of every batch (``prior.ratio``, 0.5 by default) comes from the prior
memories, the rest from the run's own experience (all of it from the priors
while the run has none yet). Each prior memory is a TorchRL
``HERReplayBuffer`` with the current task's reward function, so its rows are
relabelled like the run's own; the rewards of the rows it returns are then
recomputed with the current task's reward function too (a FetchPush memory
used for FetchPickAndPlace keeps its transitions, not its rewards).

Why not ``torchrl.data.ReplayBufferEnsemble``: the ensemble samples its
buffers' storages through its own sampler and collate, which skips
``HERReplayBuffer.sample`` and hence the relabelling; a batch drawn from each
HER buffer and concatenated keeps it.
"""
from __future__ import annotations

from collections.abc import Iterator

import torch
from tensordict import TensorDictBase

from torchrl_robotmem import make_reward_fn

from .layout import cast_rows, check_prior_layout, key_name

__all__ = ["PRIOR_KEY", "TRANSITION_KEYS", "PriorMix"]

#: bool ``[batch]``: True for the rows a batch drew from a prior memory.
PRIOR_KEY = "from_prior"

#: What the losses read from a transition: batches mixing the run's own rows and
#: prior rows carry exactly these (a prior memory may hold more, e.g. a scripted
#: controller's parameters, or less bookkeeping, e.g. no episode_reward).
TRANSITION_KEYS = [
    "observation", "achieved_goal", "desired_goal", "action",
    ("next", "observation"), ("next", "achieved_goal"), ("next", "desired_goal"),
    ("next", "reward"), ("next", "done"), ("next", "terminated"), ("next", "truncated"),
]


class PriorMix:
    """Draws batches from the run's own HER buffer and its prior memories.

    Args:
        own: the run's own buffer (a ``HERReplayBuffer``).
        priors (list): HER buffers over read-only prior memories.
        ratio (float): share of each batch drawn from the priors (0.5: RLPD's
            symmetric sampling) once the run has transitions of its own.
        env_name (str): the current task; its reward function rewards the prior rows.
        keys (list): the keys a batch must hold (the run's own layout); prior
            memories may hold more (e.g. a scripted controller's parameters).
        example (TensorDictBase, optional): one transition of this task: the prior
            memories' keys, shapes and dtypes are checked against it (:func:`~.layout.check_prior_layout`).
        dtypes (dict, optional): ``{key: dtype}`` to cast the prior rows' keys to, as
            :func:`~.layout.check_prior_layout` returned them (priors already checked).

    Example:
        >>> mix = PriorMix(own, [prior_buffer], 0.5, "FetchPush-v4", TRANSITION_KEYS)
        >>> batch = mix.sample(256)          # 128 own rows, 128 prior rows marked batch["from_prior"]
    """

    def __init__(self, own, priors: list, ratio: float, env_name: str, keys: list, example=None,
                 dtypes: dict | None = None) -> None:
        self.own, self.priors, self.ratio = own, priors, ratio
        self.reward_fn = make_reward_fn(env_name)
        self.keys = keys
        sizes = torch.tensor([float(len(p)) for p in priors])
        self._weights = sizes / sizes.sum() if len(priors) else sizes
        self.dtypes = dict(dtypes or {})  # the run's dtype of each key some prior stores in another float dtype
        for p in priors:  # a prior memory must carry everything the run's batches hold
            if example is not None:  # one transition of this task: keys, shapes and dtypes checked against it
                self.dtypes.update(check_prior_layout(p.storage, example, keys, env_name))
                continue
            have = set(p.storage[0:1].keys(True, True)) if len(p.storage) else set()
            missing = [key_name(k) for k in keys if k not in have]
            if missing:
                raise ValueError(
                    f"the prior memory {p.storage.path!r} was written for another observation layout "
                    f"than {env_name}'s (missing {missing}). Use memories of tasks with the same layout."
                )

    @property
    def ratio(self) -> float:
        """Share of each batch drawn from the priors (settable: an annealing schedule sets it)."""
        return self._ratio

    @ratio.setter
    def ratio(self, value: float) -> None:
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"prior.ratio must be in [0, 1], got {value}.")
        self._ratio = float(value)

    @property
    def rows(self) -> int:
        return sum(len(p) for p in self.priors)

    def prior_rows(self) -> Iterator[TensorDictBase]:
        """Every row of each prior memory, with the keys a batch holds (for the normaliser's statistics)."""
        for buffer in self.priors:
            yield cast_rows(buffer[:].select(*self.keys, strict=False), self.dtypes)

    def sample(self, batch_size: int, query=None) -> TensorDictBase:
        """A batch: ``batch_size * ratio`` rows from the priors, the rest from the run's own buffer.

        ``batch["from_prior"]`` marks the prior rows (for ``prior.bc``).
        """
        n_prior = batch_size if not len(self.own) else int(round(self.ratio * batch_size))
        parts = []
        if batch_size - n_prior:
            batch = self._own(batch_size - n_prior, query).select(*self.keys, strict=False)
            batch.set(PRIOR_KEY, torch.zeros(batch.shape, dtype=torch.bool, device=_device_of(batch)))
            parts.append(batch)
        if n_prior:
            counts = torch.distributions.Multinomial(n_prior, self._weights).sample().long().tolist()
            for buffer, k in zip(self.priors, counts):
                if k:
                    batch = cast_rows(buffer.sample(k).select(*self.keys, strict=False), self.dtypes)
                    batch.set(("next", "reward"), self.reward_fn(batch))  # the current task's reward
                    batch.set(PRIOR_KEY, torch.ones(batch.shape, dtype=torch.bool, device=_device_of(batch)))
                    parts.append(batch)
        return torch.cat(parts, 0)

    def _own(self, n: int, query):
        sampler = getattr(self.own, "sampler", None)
        if query is not None and hasattr(sampler, "query"):
            with sampler.query(query):
                return self.own.sample(n)
        return self.own.sample(n)


def _device_of(batch: TensorDictBase) -> torch.device:
    """Where a batch's rows are (a memory on the GPU draws them there): the device of its first tensor."""
    return next(iter(batch.values(True, True))).device
