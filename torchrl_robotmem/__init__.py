"""torchrl_robotmem: a memory for goal-conditioned TorchRL agents that outlives a training run.

Public surface:

- :class:`ZarrStorage`: a TorchRL storage persisted in a Zarr v3 store.
- :class:`GoalIndex` and :func:`recall`: exact nearest-goal lookup over a storage
  (package :mod:`torchrl_robotmem.goal_index`).
- :class:`GoalSimilaritySampler`: a TorchRL sampler drawing rows near query goals.
- :class:`OnPolicyBatchSampler`, :class:`CombinedExperienceSampler`, :class:`PersistentPrioritizedSampler`:
  SLM Lab's memory kinds over a persistent storage (package :mod:`torchrl_robotmem.samplers`);
  :class:`WindowSampler`: uniform replay over the newest rows of a growing memory.
- :class:`RecallTransform`: an env transform appending the nearest remembered goals.
- :class:`GoalProposer`: an env transform pursuing remembered goals where the memory is sparsest (MEGA).
- :class:`RobotMemory`: robotmem's quick-start API over the same store.
- :func:`make_env` / :func:`make_reward_fn`: Fetch / Shadow Hand envs and HER rewards.
"""
from __future__ import annotations

from ._version import __version__
from .envs import make_env, make_reward_fn
from .goal_index import GoalIndex, recall
from .her import PersistentHERReplayBuffer
from .memory import RobotMemory
from .proposer import GoalProposer
from .sampler import GoalSimilaritySampler
from .samplers import CombinedExperienceSampler, OnPolicyBatchSampler, PersistentPrioritizedSampler, WindowSampler
from .storage import ZarrStorage
from .transform import RecallTransform

__all__ = [
    "CombinedExperienceSampler",
    "GoalIndex",
    "GoalProposer",
    "GoalSimilaritySampler",
    "OnPolicyBatchSampler",
    "PersistentHERReplayBuffer",
    "PersistentPrioritizedSampler",
    "RecallTransform",
    "RobotMemory",
    "WindowSampler",
    "ZarrStorage",
    "make_env",
    "make_reward_fn",
    "recall",
    "__version__",
]
