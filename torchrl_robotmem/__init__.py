"""torchrl_robotmem: a memory for goal-conditioned TorchRL agents that outlives a training run."""
from __future__ import annotations

__version__ = "0.1.0"
