"""``dumps`` / ``loads`` for a sampler whose ``state_dict`` is plain JSON: no pickle on load."""
from __future__ import annotations

import json
from pathlib import Path

__all__ = ["JsonStateDumps"]


class JsonStateDumps:
    """Mixin: TorchRL's ``Sampler.dumps(path)`` / ``loads(path)`` through ``state_dict`` as JSON.

    The file is TorchRL's own ``sampler_metadata.json``, so ``ReplayBuffer.dumps`` / ``loads`` and
    ``torchrl.checkpoint`` handle it as any sampler's. Put it before ``Sampler`` in the bases.

    Example:
        >>> import tempfile
        >>> from torchrl.data.replay_buffers.samplers import Sampler
        >>> class Counter(JsonStateDumps, Sampler):
        ...     def __init__(self): self.n = 0
        ...     def sample(self, storage, batch_size): ...
        ...     def _empty(self): ...
        ...     def state_dict(self): return {"n": self.n}
        ...     def load_state_dict(self, state): self.n = state["n"]
        >>> a, b, path = Counter(), Counter(), tempfile.mkdtemp()
        >>> a.n = 3; a.dumps(path); b.loads(path); b.n
        3
    """

    def dumps(self, path) -> None:
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        with open(path / "sampler_metadata.json", "w") as f:
            json.dump(self.state_dict(), f)

    def loads(self, path) -> None:
        with open(Path(path) / "sampler_metadata.json") as f:
            self.load_state_dict(json.load(f))
