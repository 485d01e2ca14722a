"""What docs/newest_tools.md says of tensordict's Zarr backend and TorchRL's OfflineToOnlineReplayBuffer.

Real parts: ZarrStorage stores on disk and in ``memory://``, tensordict 0.14's
``TensorDict.to_zarr`` / ``from_zarr`` / ``PersistentTensorDict``, TorchRL 0.14.1's
``OfflineToOnlineReplayBuffer`` and ``HERReplayBuffer``. Some tests pin a limitation of
those tools that the page cites as a reason; if one of them fails after an upgrade,
the tool changed: revisit the page's decision, then the test.
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
import zarr
from _rows import EP_LEN, fetch_rows
from omegaconf import OmegaConf
from tensordict import PersistentTensorDict, TensorDict
from torchrl.data import HERReplayBuffer, OfflineToOnlineReplayBuffer, ReplayBuffer, TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

from recipes.her.prior_memory.schedules import prior_ratio  # noqa: E402


def reward_fn(td):
    """FetchPush's sparse reward (5 cm) on ``("next", "achieved_goal")`` and ``desired_goal``."""
    d = (td.get(("next", "achieved_goal")) - td.get("desired_goal")).norm(dim=-1, keepdim=True)
    return -(d > 0.05).float()


def write_memory(path, rows, max_size=1024, **kw) -> ZarrStorage:
    st = ZarrStorage(path, max_size, env="FetchPush-v4", chunk_rows=256, **kw)
    TensorDictReplayBuffer(storage=st).extend(rows)
    st.flush()
    return st


# --------------------------------------------------------------------------
# tensordict's Zarr backend


@pytest.mark.parametrize("where", ["dir", "memory"])
def test_tensordict_reads_a_memory(tmp_path, where):
    """``TensorDict.from_zarr`` opens a ZarrStorage store: [max_size] rows, the first ``len`` are the memory."""
    path = str(tmp_path / "m.zarr") if where == "dir" else "memory://newest-tools-interop"
    rows = fetch_rows(300, torch.Generator().manual_seed(0))
    st = write_memory(path, rows)
    n = zarr.open_group(path, mode="r").attrs["len"]
    ptd = TensorDict.from_zarr(path)
    assert isinstance(ptd, PersistentTensorDict) and ptd.batch_size == (1024,) and n == 300
    got = ptd[:n].to_tensordict()
    for key in rows.keys(True, True):
        assert torch.equal(got[key], rows[key]), key
    assert torch.equal(got["episode"], st["episode"]) and got["env"].eq(st.env_code("FetchPush-v4")).all()
    idx = torch.randint(0, n, (64,))
    assert torch.equal(ptd.get_at(("next", "achieved_goal"), idx), rows["next", "achieved_goal"][idx])
    st.close()


def test_tensordict_reads_a_wrapped_memory(tmp_path):
    """A ring that wrapped: every row valid, ``_journal`` is not rows, oldest row at ``cursor``."""
    gen = torch.Generator().manual_seed(5)
    first, second = fetch_rows(1000, gen), fetch_rows(500, gen, start=1000)
    st = write_memory(str(tmp_path / "m.zarr"), first)
    TensorDictReplayBuffer(storage=st).extend(second)
    st.close()
    attrs = zarr.open_group(str(tmp_path / "m.zarr"), mode="r").attrs
    assert (attrs["len"], attrs["cursor"]) == (1024, 1500 - 1024)
    rows = TensorDict.from_zarr(str(tmp_path / "m.zarr"))[: attrs["len"]].to_tensordict().exclude("_journal")
    in_time_order = rows.roll(-attrs["cursor"], 0)
    expected = torch.cat([first, second])[-1024:]
    for key in expected.keys(True, True):
        assert torch.equal(in_time_order[key], expected[key]), key


def test_a_tensordict_store_is_not_a_memory_but_imports_into_one(tmp_path):
    """``to_zarr`` writes no commit record: ZarrStorage refuses it, and takes its rows through ``extend``."""
    rows = fetch_rows(200, torch.Generator().manual_seed(1))
    rows.to_zarr(str(tmp_path / "td.zarr"))
    with pytest.raises(ValueError, match="not a torchrl_robotmem store"):
        ZarrStorage(str(tmp_path / "td.zarr"), read_only=True)
    with pytest.raises(ValueError, match="not written by torchrl_robotmem"):
        ZarrStorage(str(tmp_path / "td.zarr"), 512)
    st = write_memory(str(tmp_path / "m.zarr"), TensorDict.from_zarr(str(tmp_path / "td.zarr")).to_tensordict())
    assert len(st) == 200 and torch.equal(st[:]["next", "achieved_goal"], rows["next", "achieved_goal"])
    st.close()


def test_persistent_tensordict_does_not_grow(tmp_path):
    """No append: a larger batch size is ignored without a word, the arrays keep their rows."""
    ptd = fetch_rows(100, torch.Generator().manual_seed(2)).to_zarr(str(tmp_path / "td.zarr"))
    ptd.batch_size = [150]
    assert ptd.batch_size == (100,)
    assert not hasattr(ptd, "extend") and not hasattr(ptd, "append")
    assert zarr.open_group(str(tmp_path / "td.zarr"), mode="r")["observation"].shape == (100, 25)


def test_tensordict_in_place_writes_take_no_writer_lock(tmp_path):
    """``from_zarr(mode="r+")`` opens a memory a ZarrStorage is writing: read with mode="r" only."""
    st = write_memory(str(tmp_path / "m.zarr"), fetch_rows(100, torch.Generator().manual_seed(3)))
    writable = PersistentTensorDict.from_zarr(str(tmp_path / "m.zarr"), mode="r+")
    assert writable.batch_size == (1024,)  # no lock refused it
    st.close()


class _Loud:
    def __reduce__(self):
        return (print, ("unpickled: code ran",))


def test_tensordict_unpickles_non_tensor_entries_on_read(tmp_path, capsys):
    """Opening and tensor reads run nothing; reading a non-tensor entry marked "pickle" runs ``pickle.loads``."""
    path = str(tmp_path / "td.zarr")
    td = TensorDict({"observation": torch.zeros(4, 2)}, [4])
    td.set_non_tensor("note", _Loud())  # not JSON: tensordict stores pickle.dumps of it
    td.to_zarr(path)
    capsys.readouterr()
    assert zarr.open_group(path, mode="r")["note"].attrs["__tensordict_non_tensor__"] == {"encoding": "pickle"}
    ptd = TensorDict.from_zarr(path)
    ptd["observation"], ptd[:2].get("observation")
    assert "code ran" not in capsys.readouterr().out
    ptd.to_tensordict()
    assert "code ran" in capsys.readouterr().out


# --------------------------------------------------------------------------
# OfflineToOnlineReplayBuffer


class PriorSource:
    """The offline side of an ``OfflineToOnlineReplayBuffer``: HER over a prior memory, this task's rewards.

    ``OfflineToOnlineReplayBuffer`` only calls ``sample(n)`` and ``len()`` on it. ``select`` drops the
    ``"index"`` a ``HERReplayBuffer`` adds (the online ``ReplayBuffer`` adds none, and ``torch.cat`` of
    the two halves needs the same keys).
    """

    def __init__(self, her: HERReplayBuffer, keys: list):
        self.her, self.keys = her, keys

    def __len__(self) -> int:
        return len(self.her)

    def sample(self, n: int):
        batch = self.her.sample(n).select(*self.keys)
        batch.set(("next", "reward"), reward_fn(batch))
        return batch


@pytest.fixture
def two_memories(tmp_path):
    gen = torch.Generator().manual_seed(4)
    prior_rows, own_rows = fetch_rows(500, gen), fetch_rows(500, gen)
    write_memory(str(tmp_path / "prior.zarr"), prior_rows).close()
    prior = ZarrStorage(str(tmp_path / "prior.zarr"), read_only=True)
    own = ZarrStorage(str(tmp_path / "own.zarr"), 1024, env="FetchPush-v4", chunk_rows=256)
    yield prior, own, prior_rows, own_rows
    prior.close()
    own.close()


def final_goals(rows):
    """The achieved goal at the end of every episode (what HER's "final" strategy relabels with)."""
    return rows["next", "achieved_goal"][EP_LEN - 1::EP_LEN]


def rows_in(goals, pool):
    return (goals.unsqueeze(1) == pool.unsqueeze(0)).all(-1).any(1)


def test_offline_to_online_over_zarr_storages(two_memories):
    """Prior rows (offline: HER over a read-only ZarrStorage) relabelled; the run's rows (online) never."""
    prior, own, prior_rows, own_rows = two_memories
    keys = list(own_rows.keys(True, True))
    her = HERReplayBuffer(reward_fn, storage=prior, her_ratio=1.0, strategy="final",
                          achieved_goal_key=("next", "achieved_goal"))
    rb = OfflineToOnlineReplayBuffer(PriorSource(her, keys), online_storage=own, offline_fraction=0.25, batch_size=64)
    assert rb.sample().batch_size == (64,)  # no own rows yet: all from the prior
    rb.extend(own_rows)
    own.flush()
    assert len(own) == 500 and zarr.open_group(own.path, mode="r").attrs["len"] == 500
    batch = rb.sample()
    off, on = batch[:16], batch[16:]  # round(0.25 * 64) prior rows first
    assert rows_in(off["desired_goal"], final_goals(prior_rows)).all()
    assert torch.equal(off["next", "reward"], reward_fn(off))
    assert rows_in(on["desired_goal"], own_rows["desired_goal"]).all()
    assert not rows_in(on["desired_goal"], final_goals(own_rows)).any()  # HER never saw them
    assert type(rb.online_buffer) is ReplayBuffer and rb.online_buffer.storage is own


def test_offline_to_online_with_a_her_buffer_as_is(two_memories):
    """A ``HERReplayBuffer`` passed straight as the offline dataset: its "index" key breaks the concatenation."""
    prior, own, _, own_rows = two_memories
    her = HERReplayBuffer(reward_fn, storage=prior, achieved_goal_key=("next", "achieved_goal"))
    rb = OfflineToOnlineReplayBuffer(her, online_storage=own, batch_size=32)
    rb.extend(own_rows)
    with pytest.raises(KeyError):
        rb.sample()


def test_offline_fraction_bounds_and_the_recipes_schedule(two_memories):
    """``offline_fraction`` refuses 0 and 1; ``anneal`` reproduces ``prior.ratio -> prior.ratio_final`` for a lower end."""
    prior, own, _, _ = two_memories
    for f in (0.0, 1.0):
        with pytest.raises(ValueError, match="offline_fraction"):
            OfflineToOnlineReplayBuffer(prior, online_storage=own, offline_fraction=f)
    start, final, horizon = 0.5, 0.1, 1000
    cfg = OmegaConf.create({"prior": {"ratio": start, "ratio_final": final, "anneal_frames": horizon}})
    rb = OfflineToOnlineReplayBuffer(prior, online_storage=own, offline_fraction=start)
    for frames in (0, 250, 1000, 4000):
        rb.anneal(min(frames, horizon), horizon * start / (start - final))
        assert rb.offline_fraction == pytest.approx(prior_ratio(cfg, frames))


def test_offline_to_online_online_side_resumes(two_memories, tmp_path):
    """The online ``ReplayBuffer`` over a reopened ZarrStorage appends after the last run's rows."""
    prior, own, _, own_rows = two_memories
    OfflineToOnlineReplayBuffer(prior, online_storage=own).extend(own_rows[:300])
    own.close()
    again = ZarrStorage(own.path)
    OfflineToOnlineReplayBuffer(prior, online_storage=again).extend(own_rows[300:])
    assert len(again) == 500 and torch.equal(again[:]["observation"], own_rows["observation"])
    assert again["run"].unique().tolist() == [0, 1]
    again.close()
