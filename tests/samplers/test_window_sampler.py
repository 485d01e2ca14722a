"""WindowSampler: uniform replay over the newest ``window`` rows, before and after a ring wraps.

Real TorchRL buffers over ``LazyTensorStorage`` and ``ZarrStorage`` (a store under ``tmp_path``). Every
row carries its write number ``t``, so "the newest rows" is checked on the data itself, not only on
indices. Reachability holds by construction: a window of 8 rows and 2,048 seeded draws (a given row is
missed with probability (7/8)**2048 < 1e-118).
"""
from __future__ import annotations

import itertools

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer, TensorDictReplayBuffer

from torchrl_robotmem import WindowSampler, ZarrStorage
from torchrl_robotmem.samplers.combined import CombinedExperienceSampler

CAPACITY, WINDOW, DRAWS = 50, 8, 2048


def _rows(start: int, n: int) -> TensorDict:
    t = torch.arange(start, start + n)
    return TensorDict({"t": t, "obs": t.float().unsqueeze(-1).expand(n, 3).clone()}, [n])


def _lazy(path, capacity=CAPACITY):
    return LazyTensorStorage(capacity)


def _zarr(path, capacity=CAPACITY):
    return ZarrStorage(path, capacity, env="FetchPush-v4", goal_conditioned=False)


STORAGES = pytest.mark.parametrize("make_storage", [_lazy, _zarr], ids=["lazy", "zarr"])


def _buffer(storage, window=WINDOW, seed=0):
    return TensorDictReplayBuffer(storage=storage, sampler=WindowSampler(window), batch_size=DRAWS,
                                  generator=torch.Generator().manual_seed(seed))


def _close(storage):
    if isinstance(storage, ZarrStorage):
        storage.close()


def _assert_samples_exactly(rb, written: int, window: int = WINDOW):
    """Every draw is one of the newest ``window`` rows, and every one of them is drawn."""
    newest_t = set(range(max(written - window, 0), written))
    newest_rows = {t % CAPACITY for t in newest_t}  # round-robin writes: write number t lands in row t % capacity
    batch = rb.sample()
    assert set(batch["t"].tolist()) == newest_t
    assert set(batch["index"].tolist()) == newest_rows
    assert torch.equal(batch["t"] % CAPACITY, batch["index"])
    assert set(rb.sampler.window_rows(rb.storage).tolist()) == newest_rows


@STORAGES
def test_every_draw_is_among_the_newest_rows_before_and_after_the_ring_wraps(tmp_path, make_storage):
    rb = _buffer(make_storage(tmp_path / "w.zarr"))
    written = 0
    # not wrapped; full to the brim (no wrap yet); wrapped (newest rows 2..9); window across the wrap (46..49, 0..3)
    for n in (20, 30, 10, 44):
        rb.extend(_rows(written, n))
        written += n
        _assert_samples_exactly(rb, written)
    assert rb.sampler.window_rows(rb.storage).tolist() == [46, 47, 48, 49, 0, 1, 2, 3]
    _close(rb.storage)


def test_plain_replay_buffer_over_tensors_samples_the_newest_values():
    rb = ReplayBuffer(storage=LazyTensorStorage(CAPACITY), sampler=WindowSampler(WINDOW), batch_size=DRAWS,
                      generator=torch.Generator().manual_seed(0))
    rb.extend(torch.arange(70))  # wrapped: 50..69 in rows 0..19 (and 20..49 hold 20..49)
    assert set(rb.sample().tolist()) == set(range(62, 70))
    for t in range(70, 75):  # single adds
        rb.add(torch.tensor(t))
    assert set(rb.sample().tolist()) == set(range(67, 75))


@STORAGES
def test_a_window_larger_than_the_storage_samples_every_row(tmp_path, make_storage):
    rb = _buffer(make_storage(tmp_path / "w.zarr"), window=1000, seed=1)
    rb.extend(_rows(0, 5))
    assert set(rb.sample()["t"].tolist()) == set(range(5))
    rb.extend(_rows(5, 60))  # wrapped: every row is among the newest 1000
    assert set(rb.sample()["index"].tolist()) == set(range(CAPACITY))
    _close(rb.storage)


def test_a_reopened_zarr_store_samples_its_newest_rows(tmp_path):
    path = tmp_path / "w.zarr"
    rb = _buffer(_zarr(path))
    rb.extend(_rows(0, 73))  # wrapped: the newest rows 15..22 hold 65..72
    rb.storage.close()
    rb = _buffer(ZarrStorage(path), seed=2)  # no write in this process: the store's write_count says where
    assert rb.storage.write_count == 73
    _assert_samples_exactly(rb, 73)
    rb.extend(_rows(73, 3))
    _assert_samples_exactly(rb, 76)
    rb.storage.close()


def test_the_window_and_last_row_survive_state_dict_and_dumps(tmp_path):
    rb = _buffer(LazyTensorStorage(CAPACITY), window=5)
    rb.extend(_rows(0, 62))  # wrapped: newest rows 7..11
    assert rb.sampler.state_dict() == {"window": 5, "last_written": 11}
    state = rb.state_dict()
    rb.dumps(tmp_path / "ckpt")
    # TorchRL's load_state_dict / loads leave the storage's _last_cursor_index unset (a new storage) or stale (one
    # written before): the sampler's restored record of the last write places the window until the next write
    restores = (lambda b: b.load_state_dict(state), lambda b: b.loads(tmp_path / "ckpt"))
    for restore, written_before in itertools.product(restores, (False, True)):
        restored = _buffer(LazyTensorStorage(CAPACITY), window=99)
        if written_before:
            restored.extend(_rows(0, 1))  # its _last_cursor_index: row 0
        restore(restored)
        assert restored.sampler.window == 5
        assert set(restored.sample()["t"].tolist()) == set(range(57, 62))
        restored.extend(_rows(62, 2))  # writes go on at the writer's restored cursor
        assert set(restored.sample()["t"].tolist()) == set(range(59, 64))


def test_combined_replay_over_the_window():
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(CAPACITY), batch_size=64,
                                sampler=CombinedExperienceSampler(WindowSampler(WINDOW), newest=2))
    rb.extend(_rows(0, 80))
    for _ in range(5):
        t = set(rb.sample()["t"].tolist())
        assert {78, 79} <= t <= set(range(72, 80))


def test_built_from_a_hydra_config():
    from hydra.utils import instantiate

    sampler = instantiate({"_target_": "torchrl_robotmem.samplers.WindowSampler", "window": 16})
    assert isinstance(sampler, WindowSampler) and sampler.window == 16


@pytest.mark.parametrize("window", [0, -3, True, 2.5, "8", None])
def test_bad_windows_are_refused(window):
    with pytest.raises(ValueError, match="window must be a positive integer"):
        WindowSampler(window)
    with pytest.raises(ValueError, match="window must be a positive integer"):
        WindowSampler(4).load_state_dict({"window": window})


def test_storages_it_cannot_serve_are_refused_with_the_reason():
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(CAPACITY), sampler=WindowSampler(4), batch_size=8)
    with pytest.raises(RuntimeError, match="empty storage"):
        rb.sample()
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100, ndim=2), sampler=WindowSampler(4), batch_size=8)
    rb.extend(TensorDict({"t": torch.zeros(4, 5)}, [4, 5]))
    with pytest.raises(RuntimeError, match=r"ndim=2.*reshape\(-1\)"):
        rb.sample()
