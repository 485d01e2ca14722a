"""TorchRL samplers over a persistent storage, one kind a module (SLM Lab's memory kinds).

- :mod:`~torchrl_robotmem.samplers.on_policy`: on-policy batch replay, the newest collected batch only.
- :mod:`~torchrl_robotmem.samplers.combined`: combined experience replay, every batch holds the newest rows.
- :mod:`~torchrl_robotmem.samplers.prioritized`: prioritized replay whose priorities persist in the store.
- :mod:`~torchrl_robotmem.samplers.window`: uniform replay over the newest ``window`` rows (a growing memory).
"""
from __future__ import annotations

from .combined import CombinedExperienceSampler, newest_rows
from .on_policy import OnPolicyBatchSampler
from .prioritized import PersistentPrioritizedSampler, PriorityTable
from .window import WindowSampler

__all__ = ["CombinedExperienceSampler", "OnPolicyBatchSampler", "PersistentPrioritizedSampler", "PriorityTable",
           "WindowSampler", "newest_rows"]
