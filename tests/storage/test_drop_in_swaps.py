"""Drop-in swaps keep their meaning: a stock TorchRL script with ``ZarrStorage`` in place of its storage.

TorchRL's sota scripts build ``LazyMemmapStorage(size, scratch_dir=...)`` over a plain
``GymEnv`` (no ``is_success``, no env name). Swapping the storage for
``ZarrStorage(path, size, scratch_dir=...)`` must run, say once that ``scratch_dir`` is
ignored, say once what the memory lacks (and how to add it), and keep the rows.
"""
from __future__ import annotations

import inspect
import warnings

import gymnasium as gym
import gymnasium_robotics
import pytest
import torch
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import GymEnv, default_info_dict_reader

from torchrl_robotmem import ZarrStorage, recall

gym.register_envs(gymnasium_robotics)


def _collect(rb, env_fn, frames=100):
    """The sota scripts' loop: a Collector, flat transitions into the buffer."""
    collector = Collector(env_fn, policy=None, frames_per_batch=50, total_frames=frames)
    for data in collector:
        rb.extend(data.reshape(-1))
    collector.shutdown()


def _caught(record, text):
    return [w for w in record if issubclass(w.category, UserWarning) and text in str(w.message)]


def test_stock_sota_script_swapped_to_zarr_keeps_scratch_dir(tmp_path):
    path, scratch = str(tmp_path / "rb.zarr"), str(tmp_path / "scratch")
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        # was (sota sac/utils.py): TensorDictReplayBuffer(pin_memory=False, prefetch=3,
        #     storage=LazyMemmapStorage(1000, scratch_dir=scratch, device="cpu"), batch_size=32)
        rb = TensorDictReplayBuffer(pin_memory=False, prefetch=3, batch_size=32,
                                    storage=ZarrStorage(path, 1000, scratch_dir=scratch, device="cpu"))
        _collect(rb, lambda: GymEnv("FetchReach-v4"))
        batch = rb.sample()
    scratch_warnings = _caught(record, "scratch_dir is ignored")
    assert len(scratch_warnings) == 1 and path in str(scratch_warnings[0].message)
    context = _caught(record, "the rows written have")
    assert len(context) == 1, "the missing success / env advice is given once, at the first write"
    message = str(context[0].message)
    for fix in ("('next', 'is_success') column and no env name", "torchrl_robotmem.make_env(",
                "default_info_dict_reader(['is_success'])", "env='FetchReach-v4'"):
        assert fix in message
    assert context[0].filename == __file__, "the warning points at the script's rb.extend line"
    assert len(rb) == 100 and batch.batch_size == (32,) and ("next", "achieved_goal") in batch.keys(True)
    assert not (tmp_path / "scratch").exists(), "nothing is written to scratch_dir"
    # the recall errors say what is missing and how to add it
    with pytest.raises(KeyError, match=r"success_only needs the column \('next', 'is_success'\).*make_env"):
        recall(rb, torch.zeros(3), 3, success_only=True)
    with pytest.raises(ValueError, match=r"cannot filter on env 'FetchReach-v4'.*env='FetchReach-v4'"):
        recall(rb, torch.zeros(3), 3, env="FetchReach-v4")
    goals = rb.storage["next", "achieved_goal"][:100].clone()
    rb.storage.close()
    # the next process: the rows are there, the writer appends after them
    reopened = TensorDictReplayBuffer(storage=ZarrStorage(path, max_size=1000, scratch_dir=scratch), batch_size=32)
    assert len(reopened) == 100 and torch.equal(reopened.storage["next", "achieved_goal"][:100], goals)
    reopened.storage.close()


def test_with_the_fixes_the_memory_has_its_context(tmp_path):
    """GymEnv + default_info_dict_reader(["is_success"]) and env=: no advice, and recall filters work."""

    def env_fn():
        env = GymEnv("FetchReach-v4")
        env.set_info_dict_reader(default_info_dict_reader(["is_success"]))
        return env

    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        rb = TensorDictReplayBuffer(storage=ZarrStorage(tmp_path / "rb.zarr", 1000, env="FetchReach-v4"))
        _collect(rb, env_fn, frames=50)
    assert not _caught(record, "the rows written have")
    out = recall(rb, torch.zeros(3), 3, success_only=True, env="FetchReach-v4")  # no error: the columns exist
    assert out.batch_size == (3,)
    rb.storage.close()


def test_every_keyword_of_the_replaced_storages_is_accepted(tmp_path):
    """LazyMemmapStorage / LazyTensorStorage keyword arguments (TorchRL 0.14): accepted, plain values only."""
    params = set(inspect.signature(ZarrStorage).parameters)
    for cls in (LazyMemmapStorage, LazyTensorStorage):
        theirs = set(inspect.signature(cls).parameters) - {"max_size"}
        assert theirs <= params, f"ZarrStorage lacks {cls.__name__}'s {sorted(theirs - params)}"
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        st = ZarrStorage(tmp_path / "a.zarr", 10, device="cpu", ndim=1, compilable=True, consolidated=True,
                         cleanup_memmap=False, existsok=False, auto_cleanup=False, shared_init=False)
    assert not [w for w in record if issubclass(w.category, UserWarning)]  # same meaning: silent
    st.close()
    with pytest.warns(UserWarning, match="existsok=True: .*appends after its rows"):
        ZarrStorage(tmp_path / "b.zarr", 10, existsok=True).close()
    with pytest.warns(UserWarning, match="auto_cleanup=True: .*never deleted"):
        ZarrStorage(tmp_path / "c.zarr", 10, auto_cleanup=True).close()
    with pytest.raises(ValueError, match="shared_init=True"):
        ZarrStorage(tmp_path / "d.zarr", 10, shared_init=True)
    # a Hydra config: _target_ and plain values, as the sota configs' replay_buffer section
    from hydra.utils import instantiate

    with pytest.warns(UserWarning, match="scratch_dir is ignored"):
        st = instantiate({"_target_": "torchrl_robotmem.ZarrStorage", "path": str(tmp_path / "e.zarr"),
                          "max_size": 10, "scratch_dir": str(tmp_path / "scratch"), "device": "cpu"})
    assert isinstance(st, ZarrStorage) and st.max_size == 10
    st.close()
