"""ZarrStorage honours TorchRL's storage contract: what LazyTensorStorage takes, it takes and persists.

Each test covers one point of the contract directly (TorchRL's own replay-buffer
suite is run against ZarrStorage by ``../shared/conformance/run-torchrl-rb-tests``;
its remaining differences are listed in ``docs/storage.md``).
"""
from __future__ import annotations

import math
import multiprocessing as mp
import pickle

import pytest
import torch
from tensordict import LazyStackedTensorDict, NonTensorData, NonTensorStack, TensorDict, tensorclass
from torchrl.data import (
    LazyTensorStorage,
    ReplayBuffer,
    SliceSampler,
    TensorDictReplayBuffer,
)

from torchrl_robotmem import ZarrStorage


@tensorclass
class Transition:
    obs: torch.Tensor
    reward: torch.Tensor


@tensorclass
class Labelled:
    obs: torch.Tensor
    task: str


def _td(n, start=0, **extra):
    i = torch.arange(start, start + n)
    return TensorDict({"obs": i.float().unsqueeze(-1).expand(n, 3).clone(), ("next", "r"): -i.float(), **extra}, [n])


# -- data kinds -----------------------------------------------------------------------


def test_plain_tensors_round_trip_and_reopen(tmp_path):
    path = tmp_path / "t.zarr"
    rb = ReplayBuffer(storage=ZarrStorage(path, 100), batch_size=8)
    rb.extend(torch.arange(30.0).reshape(10, 3))
    batch = rb.sample()
    assert isinstance(batch, torch.Tensor) and batch.shape == (8, 3)
    assert set((batch[:, 0] / 3).long().tolist()) <= set(range(10))
    rb.add(torch.tensor([90.0, 91.0, 92.0]))
    rb.storage.close()
    st = ZarrStorage(path, read_only=True)
    assert len(st) == 11 and torch.equal(st[10], torch.tensor([90.0, 91.0, 92.0]))
    assert torch.equal(st[:10], torch.arange(30.0).reshape(10, 3))


def test_pytrees_round_trip_and_reopen(tmp_path):
    path = tmp_path / "p.zarr"
    rb = ReplayBuffer(storage=ZarrStorage(path, 100), batch_size=4)
    data = {"obs": torch.randn(6, 2), "pair": (torch.arange(6), torch.ones(6, 1, dtype=torch.bool))}
    rb.extend(data)
    batch = rb.sample()
    assert set(batch) == {"obs", "pair"} and isinstance(batch["pair"], tuple)
    assert batch["pair"][0].dtype == torch.int64 and batch["pair"][1].shape == (4, 1)
    with pytest.raises(ValueError, match="structure"):
        rb.extend({"obs": torch.randn(2, 2)})  # another tree structure
    rb.storage.close()
    st = ZarrStorage(path, read_only=True)
    got = st[torch.arange(6)]
    assert torch.equal(got["obs"], data["obs"]) and torch.equal(got["pair"][0], data["pair"][0])


def test_tensorclasses_round_trip(tmp_path):
    path = tmp_path / "c.zarr"
    rb = ReplayBuffer(storage=ZarrStorage(path, 100), batch_size=4)
    rb.extend(Transition(obs=torch.randn(5, 3), reward=torch.arange(5.0), batch_size=[5]))
    assert isinstance(rb.sample(), Transition)
    rb.storage.close()
    # reopened in a process where the class is imported: the same class comes back
    st = ZarrStorage(path, read_only=True)
    out = st[torch.arange(5)]
    assert isinstance(out, Transition) and torch.equal(out.reward, torch.arange(5.0))


def test_non_tensor_entries_are_kept_as_one_value_per_store(tmp_path):
    """A tensorclass's ``str`` field (and a NonTensorData in a TensorDict) is kept, in JSON metadata."""
    path = tmp_path / "t.zarr"
    rb = ReplayBuffer(storage=ZarrStorage(path, 100), batch_size=4)
    rb.extend(Labelled(obs=torch.randn(5, 3), task="push", batch_size=[5]))
    rb.extend(Labelled(obs=torch.randn(2, 3), task="push", batch_size=[2]))
    assert rb.sample().task == "push"
    with pytest.raises(ValueError, match=r"'task' holds 'slide'.*holds 'push'"):
        rb.extend(Labelled(obs=torch.randn(2, 3), task="slide", batch_size=[2]))
    assert len(rb) == 7 and rb.writer._cursor == 7  # the refused write changed nothing
    rb.storage.dumps(tmp_path / "ckpt")
    copy = ZarrStorage(tmp_path / "copy.zarr", 100)
    copy.loads(tmp_path / "ckpt")
    assert copy[torch.arange(7)].task == "push" and torch.equal(copy[torch.arange(7)].obs, rb.storage[:7].obs)
    rb.storage.close()
    again = ZarrStorage(path, read_only=True)
    assert again[torch.arange(3)].task == "push" and again.summary()["constants"] == {"task": "push"}
    assert again["task"] == "push" and again["obs"].shape == (7, 3)  # a column by key, the constant included

    td_rb = ReplayBuffer(storage=ZarrStorage(tmp_path / "d.zarr", 100), batch_size=3)
    td_rb.extend(TensorDict({"x": torch.zeros(4), "tag": NonTensorData("a", batch_size=[4])}, [4]))
    assert td_rb.sample()["tag"] == "a"
    with pytest.raises(KeyError, match=r"missing non-tensor keys \['tag'\]"):
        td_rb.extend(TensorDict({"x": torch.zeros(4)}, [4]))
    rows = NonTensorStack(*[NonTensorData(s) for s in "abab"])
    with pytest.raises(ValueError, match=r"'tag' holds different non-tensor values"):
        td_rb.extend(TensorDict({"x": torch.zeros(4), "tag": rows}, [4]))
    with pytest.raises(TypeError, match=r"'blob' holds a non-tensor value of type dict"):
        td_rb.extend(TensorDict({"x": torch.zeros(4), "tag": NonTensorData("a", batch_size=[4]),
                                 "blob": NonTensorData({"k": 1}, batch_size=[4])}, [4]))
    with pytest.raises(TypeError, match=r"'x' holds a non-tensor value.*tensor of dtype float32"):
        td_rb.extend(TensorDict({"x": NonTensorData("oops", batch_size=[4]), "tag": NonTensorData("a", batch_size=[4])}, [4]))
    assert len(td_rb) == 4


def test_a_nan_constant_is_the_same_constant_at_every_write(tmp_path):
    """Found by a review: ``nan != nan`` refused every write after the first of a NaN constant (and a stack of
    NaN rows as different values)."""
    path = tmp_path / "n.zarr"

    def rows(n, gain=math.nan):
        return TensorDict({"x": torch.zeros(n), "gain": NonTensorData(gain, batch_size=[n])}, [n])

    rb = ReplayBuffer(storage=ZarrStorage(path, 100), batch_size=3)
    rb.extend(rows(4))
    rb.extend(rows(4))
    rb.extend(TensorDict({"x": torch.zeros(2), "gain": NonTensorStack(*[NonTensorData(math.nan)] * 2)}, [2]))
    rb.storage.close()
    st = ZarrStorage(path)  # the NaN read back from the record is the same constant too
    rb = ReplayBuffer(storage=st, batch_size=3)
    rb.extend(rows(4))
    for other in (1.0, 0.0):
        with pytest.raises(ValueError, match=r"'gain' holds"):
            rb.extend(rows(2, other))
    assert len(st) == 14 and math.isnan(st[torch.arange(3)]["gain"])
    st.close()

def test_kinds_do_not_mix(tmp_path):
    rb = ReplayBuffer(storage=ZarrStorage(tmp_path / "k.zarr", 10))
    rb.extend(torch.zeros(3, 2))
    with pytest.raises(TypeError, match="holds tensor data"):
        rb.extend(TensorDict({"a": torch.zeros(3)}, [3]))
    assert len(rb) == 3 and rb.writer._cursor == 3


# -- layouts ---------------------------------------------------------------------------


def test_ndim2_storage_with_slice_sampler_survives_reopen(tmp_path):
    """A 2-D storage holds what LazyTensorStorage(ndim=2) holds, and keeps it across a reopen."""
    path = tmp_path / "n.zarr"
    envs, T = 4, 25
    done = torch.zeros(envs, T, 1, dtype=torch.bool)
    done[:, -1] = True
    data = TensorDict({"obs": torch.arange(envs * T).float().reshape(envs, T, 1), ("next", "done"): done,
                       "traj": torch.arange(envs).unsqueeze(-1).expand(envs, T).clone()}, [envs, T])
    ref = LazyTensorStorage(400, ndim=2)
    ref_rb = TensorDictReplayBuffer(storage=ref)
    ref_rb.extend(data)
    storage = ZarrStorage(path, 400, ndim=2)
    rb = TensorDictReplayBuffer(storage=storage, sampler=SliceSampler(slice_len=5, traj_key="traj"), batch_size=20)
    rb.extend(data)
    assert len(rb) == len(ref) == envs * T and storage.shape == ref.shape
    assert torch.equal(storage[:]["obs"], ref[:]["obs"])
    batch = rb.sample().reshape(-1, 5)
    # every slice is 5 consecutive steps of one trajectory
    assert (batch["traj"] == batch["traj"][:, :1]).all()
    assert (batch["obs"].squeeze(-1).diff(dim=1) == 1).all()
    assert storage["episode"].shape == storage.shape
    storage.close()
    st = ZarrStorage(path)
    rb2 = TensorDictReplayBuffer(storage=st, sampler=SliceSampler(slice_len=5, traj_key="traj"), batch_size=20)
    assert len(rb2) == envs * T and st.shape == ref.shape
    assert torch.equal(st[:]["obs"], ref[:]["obs"])
    rb2.extend(data)
    ref_rb.extend(data)
    assert len(rb2) == 2 * envs * T and torch.equal(st[:]["obs"], ref[:]["obs"])
    rb2.sample()
    st.close()


def test_lazy_stacks_and_lists_of_tensordicts(tmp_path):
    rb = ReplayBuffer(storage=ZarrStorage(tmp_path / "l.zarr", 100), batch_size=4)
    rb.extend(LazyStackedTensorDict.lazy_stack([_td(1, i)[0] for i in range(5)], 0))
    rb.extend([_td(1, 5 + i)[0] for i in range(3)])  # a list: one item per element
    assert len(rb) == 8
    assert torch.equal(rb.storage["obs"][:8, 0], torch.arange(8.0))
    rb.storage.close()


# -- schema evolution and in-place writes ----------------------------------------------


def test_keys_added_after_the_first_write_are_recorded(tmp_path):
    path = tmp_path / "e.zarr"
    st = ZarrStorage(path, 100)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    rb.extend(_td(5))
    rev = st._mutation_revision
    rb.extend(_td(3, 5).set(("info", "gap"), torch.full((3, 2), 7.0)))
    assert st._mutation_revision > rev
    assert torch.equal(st[("info", "gap")][:8], torch.tensor([[0.0, 0.0]] * 5 + [[7.0, 7.0]] * 3))
    rb.extend(_td(2, 8).set(("info", "gap"), torch.ones(2, 2)))
    with pytest.raises(KeyError, match="missing keys.*gap"):  # a key the store holds cannot vanish
        rb.extend(_td(1, 10))
    with pytest.raises(ValueError, match="'obs'.*float64"):  # nor change dtype
        rb.extend(TensorDict({"obs": torch.zeros(1, 3, dtype=torch.float64), ("next", "r"): torch.zeros(1),
                              ("info", "gap"): torch.zeros(1, 2)}, [1]))
    st.close()
    st = ZarrStorage(path, read_only=True)
    assert len(st) == 10 and torch.equal(st[("info", "gap")][8:10], torch.ones(2, 2))


def test_in_place_writes_are_durable(tmp_path):
    path = tmp_path / "w.zarr"
    st = ZarrStorage(path, 100)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    rb.extend(_td(10))
    rev = st._mutation_revision
    rb[3] = _td(1, 100)[0]
    rb[torch.tensor([5, 6])] = _td(2, 200)
    assert st._mutation_revision > rev
    assert len(rb) == 10 and rb.writer._cursor == 10
    st.close()
    st = ZarrStorage(path, read_only=True)
    assert st["obs"][:, 0].tolist() == [0, 1, 2, 100, 4, 200, 201, 7, 8, 9]


def test_every_write_path_bumps_the_mutation_revision(tmp_path):
    st = ZarrStorage(tmp_path / "r.zarr", 100)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    seen = [st._mutation_revision]

    def bumped():
        seen.append(st._mutation_revision)
        return seen[-1] > seen[-2]

    rb.extend(_td(4))
    assert bumped()
    rb.add(_td(1, 4)[0])
    assert bumped()
    rb[0] = _td(1, 9)[0]
    assert bumped()
    other = ZarrStorage(tmp_path / "o.zarr", 100)
    TensorDictReplayBuffer(storage=other).extend(_td(3))
    st.load_state_dict(other.state_dict())
    assert bumped()
    rb.empty()
    assert bumped()
    st.close()
    other.close()


# -- state, copies and processes ----------------------------------------------------------


def test_state_dict_carries_the_rows_between_storages(tmp_path):
    src = TensorDictReplayBuffer(storage=ZarrStorage(tmp_path / "a.zarr", 100, env="FetchPush-v4"), batch_size=4)
    src.extend(_td(12))
    sd = src.state_dict()
    # into a ZarrStorage on another path: rows, length and the writer's position come along
    dst = TensorDictReplayBuffer(storage=ZarrStorage(tmp_path / "b.zarr", 100), batch_size=4)
    dst.load_state_dict(sd)
    assert len(dst) == 12 and dst.writer._cursor == 12
    assert torch.equal(dst.storage["obs"][:12], src.storage["obs"][:12])
    assert dst.storage.env_names == ("FetchPush-v4",) and (dst.storage["env"][:12] == 0).all()
    dst.storage.close()
    assert len(ZarrStorage(tmp_path / "b.zarr", read_only=True)) == 12  # durable, not a pointer
    # and into TorchRL's own LazyTensorStorage
    lts = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=4)
    lts.load_state_dict(sd)
    assert len(lts) == 12 and torch.equal(lts.storage[:12]["obs"], src.storage["obs"][:12])
    # and from it
    back = TensorDictReplayBuffer(storage=ZarrStorage(tmp_path / "c.zarr", 100), batch_size=4)
    back.load_state_dict(lts.state_dict())
    assert len(back) == 12 and torch.equal(back.storage["obs"][:12], src.storage["obs"][:12])
    src.storage.close()
    back.storage.close()


def test_constructor_takes_torchrl_storage_arguments(tmp_path):
    st = ZarrStorage(tmp_path / "a.zarr", 10, ndim=1, compilable=True, device="cpu")
    TensorDictReplayBuffer(storage=st).extend(_td(3))
    assert len(st) == 3
    st.close()
    with pytest.raises(ValueError, match="shared_init=True. is not supported"):
        ZarrStorage(tmp_path / "b.zarr", 10, shared_init=True)
    with pytest.raises(TypeError, match="first argument is the store's path"):
        ZarrStorage(1000)  # functools.partial(LazyTensorStorage, ...) with only the class changed


def _child_reads(storage, queue):
    try:
        queue.put((storage.read_only, len(storage), storage["obs"][:, 0].tolist()))
        storage.set(0, _td(1)[0])
    except RuntimeError as err:
        queue.put(str(err))


def test_pickled_into_another_process_it_is_a_read_only_handle(tmp_path):
    st = ZarrStorage(tmp_path / "m.zarr", 100)
    TensorDictReplayBuffer(storage=st).extend(_td(6))  # not flushed: pickling flushes
    assert pickle.loads(pickle.dumps(st)).read_only
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_child_reads, args=(st, queue))
    proc.start()
    read_only, n, obs = queue.get(timeout=120)
    err = queue.get(timeout=60)
    proc.join(60)
    assert read_only and n == 6 and obs == [0, 1, 2, 3, 4, 5]
    assert "read_only" in err
    st.close()


def test_a_subclass_with_its_own_constructor_loads_another_stores_checkpoint(tmp_path):
    """rb.loads builds the checkpoint's copy as a ZarrStorage, not as type(storage) (whose arguments may differ)."""
    made = []

    class Sized(ZarrStorage):  # a LazyTensorStorage-like signature: max_size first, the path chosen inside
        def __init__(self, max_size, **kwargs):
            made.append(tmp_path / f"store{len(made)}.zarr")
            super().__init__(str(made[-1]), max_size, **kwargs)

    rows = TensorDict({"obs": torch.arange(20.0).reshape(10, 2)}, [10])
    rb = ReplayBuffer(storage=Sized(100))
    rb.extend(rows)
    rb.dumps(tmp_path / "checkpoint")
    other = ReplayBuffer(storage=Sized(100))
    other.loads(tmp_path / "checkpoint")
    assert len(other) == 10 and torch.equal(other.storage[:10]["obs"], rows["obs"])
    rb.storage.close()
    other.storage.close()
