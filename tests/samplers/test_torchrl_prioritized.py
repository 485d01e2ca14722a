"""TorchRL's prioritized replay over ``ZarrStorage``, wherever TorchRL's C++ extension loads.

``PrioritizedSampler`` keeps its sum/min trees in ``torchrl._torchrl``, a C++
extension built against one torch release: torchrl 0.14.1's loads with torch
2.14 and not with 2.10 to 2.13 (docs/install.md, "Supported versions"; the CPU torch
2.13.0 that CI installs is one of those), so these tests skip there and run
in the Python 3.12 suite (torch 2.14.1).
"""
from __future__ import annotations

import pytest
import torch
from _rows import fetch_rows
from torchrl.data import TensorDictPrioritizedReplayBuffer

from torchrl_robotmem import ZarrStorage

try:
    import torchrl._torchrl  # noqa: F401

    EXTENSION_ERROR = None
except ImportError as err:  # undefined symbols: built against another torch
    EXTENSION_ERROR = str(err).splitlines()[0][:160]

pytestmark = pytest.mark.skipif(
    EXTENSION_ERROR is not None,
    reason=f"torchrl's C++ extension (prioritized replay) does not load with torch {torch.__version__}: "
    f"{EXTENSION_ERROR}",
)


def _buffer(path, **kw):
    return TensorDictPrioritizedReplayBuffer(alpha=0.7, beta=0.5, storage=ZarrStorage(path, max_size=512, **kw),
                                             batch_size=64, priority_key="td_error")


def test_prioritized_buffer_over_zarr_storage_samples_by_priority(tmp_path):
    rb = _buffer(tmp_path / "per.zarr", env="FetchPush-v4")
    rows = fetch_rows(300, torch.Generator().manual_seed(0))
    index = rb.extend(rows)
    assert index.tolist() == list(range(300))
    # every row but 5 made (almost) impossible to draw: with alpha 0.7 the 5 carry 1.6e11 times the others'
    # probability, so 640 draws hit another row with a chance of about 2e-7 (and the draw is seeded)
    favoured = torch.tensor([3, 77, 150, 222, 299])
    priority = torch.full((300,), 1e-8)
    priority[favoured] = 1e8
    rb.update_priority(torch.arange(300), priority)
    drawn = torch.cat([rb.sample()["index"] for _ in range(10)])
    assert set(drawn.tolist()) <= set(favoured.tolist())
    batch = rb.sample()
    assert batch["priority_weight"].shape == (64,)  # importance weights, TorchRL 0.14's key
    assert torch.equal(batch["observation"], rows["observation"][batch["index"]])
    rb.storage.close()


def test_prioritized_buffer_reopens_the_memory(tmp_path):
    path = tmp_path / "per.zarr"
    rb = _buffer(path, env="FetchPush-v4")
    rows = fetch_rows(200, torch.Generator().manual_seed(1))
    rb.extend(rows)
    rb.storage.close()
    # a new process (here: a new buffer) on the same path: every row is back, sampled with fresh priorities
    rb = _buffer(path)
    assert len(rb) == 200
    batch = rb.sample()
    assert torch.equal(batch["action"], rows["action"][batch["index"]])
    rb.update_tensordict_priority(batch.set("td_error", torch.ones(64)))
    rb.storage.close()
