"""torchrl_robotmem: a memory for goal-conditioned TorchRL agents that outlives a training run.

Public surface:

- :class:`ZarrStorage`: a TorchRL storage persisted in a Zarr v3 store.
- :func:`make_env`: Gymnasium-Robotics Fetch / Shadow Hand envs ready for TorchRL collectors.
"""
from __future__ import annotations

__version__ = "0.1.0"

from .envs import make_env, make_reward_fn
from .storage import ZarrStorage

__all__ = ["ZarrStorage", "make_env", "make_reward_fn", "__version__"]
