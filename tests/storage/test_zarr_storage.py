"""ZarrStorage on real Zarr stores: persistence, resume, schema, tags, TorchRL buffers."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch
import zarr
from tensordict import TensorDict
from torchrl.data import (
    HERReplayBuffer,
    LazyTensorStorage,
    ReplayBuffer,
    TensorDictPrioritizedReplayBuffer,
    TensorDictReplayBuffer,
)

from torchrl_robotmem.storage import ZarrStorage


def _rb(storage, **kw):
    return TensorDictReplayBuffer(storage=storage, batch_size=8, **kw)


def _assert_td_equal(a, b):
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for k in a.keys(True, True):
        assert torch.equal(a.get(k), b.get(k)), k


# -- persistence --------------------------------------------------------------


def test_reopen_restores_rows_len_and_cursor(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    rb = _rb(ZarrStorage(path, 1000, env="FetchPush-v4", chunk_rows=64))
    rb.extend(transitions(130))
    before = rb.storage[:130].clone()
    rb.storage.close()

    rb2 = _rb(ZarrStorage(path))
    assert len(rb2) == 130
    assert rb2.writer._cursor == 130 and rb2.writer._write_count == 130
    _assert_td_equal(rb2.storage[:130], before)
    rb2.extend(transitions(20, start=130))
    assert len(rb2) == 150
    assert torch.equal(rb2.storage["observation"][130:150, 0], torch.arange(130, 150).float())
    assert torch.equal(rb2.storage["observation"][:130], before["observation"])
    rb2.storage.close()


def test_ring_wraps_across_restart_like_without_restart(tmp_path, transitions):
    ref = _rb(LazyTensorStorage(100))
    rb = _rb(ZarrStorage(tmp_path / "m.zarr", 100, chunk_rows=16))
    for k in range(3):
        ref.extend(transitions(45, start=45 * k))
        rb.extend(transitions(45, start=45 * k))
    rb.storage.close()
    rb = _rb(ZarrStorage(tmp_path / "m.zarr"))
    for k in range(3, 5):
        ref.extend(transitions(45, start=45 * k))
        rb.extend(transitions(45, start=45 * k))
    assert len(rb) == len(ref) == 100
    assert rb.writer._cursor == ref.writer._cursor
    assert torch.equal(rb.storage["observation"][:], ref.storage["observation"][:])
    assert torch.equal(rb.storage["action"][:], ref.storage["action"][:])
    rb.storage.close()
    # and the disk agrees with RAM after the journalled overwrites
    on_disk = zarr.open_group(str(tmp_path / "m.zarr"), mode="r")
    np.testing.assert_array_equal(on_disk["observation"][:], ref.storage["observation"][:].numpy())
    assert on_disk.attrs["journal"] is None


def test_reopen_in_fresh_process(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    rb = _rb(ZarrStorage(path, 500))
    rb.extend(transitions(77))
    rb.storage.close()
    code = textwrap.dedent(
        f"""
        import torch, sys
        from tensordict import TensorDict
        from torchrl.data import TensorDictReplayBuffer
        from torchrl_robotmem import ZarrStorage
        rb = TensorDictReplayBuffer(storage=ZarrStorage({str(path)!r}), batch_size=4)
        assert len(rb) == 77, len(rb)
        data = rb.storage[:77]
        rb.extend(data.exclude("episode", "run", "env")[:5].clone())
        print(len(rb), rb.writer._cursor, int(rb.storage["run"][80]))
        rb.storage.close()
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["82", "82", "1"]


def test_flush_makes_rows_visible_to_a_reader(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    writer = _rb(ZarrStorage(path, 1000, chunk_rows=32, commit_interval=3600))
    writer.extend(transitions(10))
    writer.storage.flush()
    reader = ZarrStorage(path, read_only=True)
    assert len(reader) == 10
    writer.extend(transitions(50, start=10))
    writer.storage.flush()
    assert reader.refresh() == 60
    assert torch.equal(reader["observation"][:60], writer.storage["observation"][:60])
    with pytest.raises(RuntimeError, match="read_only"):
        _rb(reader).extend(transitions(1))
    writer.storage.close()


def test_reader_sees_a_consistent_prefix_while_writing(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    writer = _rb(ZarrStorage(path, 10_000, chunk_rows=64, commit_interval=0.01))
    writer.extend(transitions(100))
    writer.storage.flush()
    for k in range(1, 20):
        writer.extend(transitions(100, start=100 * k))
        reader = ZarrStorage(path, read_only=True)
        n = len(reader)
        assert n % 100 == 0 and n >= 100
        expected = transitions(n)
        assert torch.equal(reader["observation"][:n], expected["observation"])
        assert torch.equal(reader["next", "done"][:n], expected["next", "done"])
    writer.storage.close()


def test_second_writable_handle_in_one_process_takes_the_writer_over(tmp_path, transitions):
    """A notebook cell re-run: the earlier handle (still referenced) hands its writer over."""
    path = tmp_path / "m.zarr"
    rb1 = _rb(ZarrStorage(path, 100))
    rb1.extend(transitions(10))  # not flushed yet: the handover must flush it
    keep = rb1.storage  # e.g. a GoalIndex still refers to it
    rb2 = _rb(ZarrStorage(path))
    assert len(rb2) == 10
    assert torch.equal(rb2.storage["observation"][:10], transitions(10)["observation"])
    rb2.extend(transitions(5, 10))
    assert len(rb2) == 15
    # the old handle is a read-only snapshot now; writing through it says why
    assert len(keep) == 10 and torch.equal(keep["observation"][:10], transitions(10)["observation"])
    with pytest.raises(RuntimeError, match="handed its writer"):
        rb1.extend(transitions(1))
    assert len(rb1) == 10  # the refused write did not move the old buffer either
    keep.close()  # closing the retired handle does not touch the new writer
    rb2.extend(transitions(5, 15))
    rb2.storage.close()
    assert len(ZarrStorage(path, read_only=True)) == 20


def test_failed_second_open_hands_the_writer_back(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    rb = _rb(ZarrStorage(path, 100))
    rb.extend(transitions(10))
    with pytest.raises(ValueError, match="shrink"):
        ZarrStorage(path, 50)
    rb.extend(transitions(10, 10))  # the first handle still writes
    rb.storage.close()
    assert len(ZarrStorage(path, read_only=True)) == 20


def test_context_manager_and_background_false(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    with ZarrStorage(path, 100, background=False) as s:
        rb = _rb(s)
        rb.extend(transitions(7))
        # durable before extend returned: a reader sees it without flush()
        assert len(ZarrStorage(path, read_only=True)) == 7
    with ZarrStorage(path) as s:
        assert len(s) == 7


# -- schema -------------------------------------------------------------------


def test_nested_keys_and_dtypes_round_trip(tmp_path):
    path = tmp_path / "m.zarr"
    td = TensorDict(
        {
            "f32": torch.randn(6, 2),
            "f64": torch.randn(6, 3, dtype=torch.float64),
            "i32": torch.arange(6, dtype=torch.int32),
            "i64": torch.arange(6).unsqueeze(-1),
            "u8": torch.arange(6, dtype=torch.uint8),
            "b": torch.tensor([True, False] * 3),
            "next": {"deep": {"x": torch.randn(6, 2, 2)}},
        },
        [6],
    )
    with ZarrStorage(path, 10) as s:
        _rb(s).extend(td.clone())
    with ZarrStorage(path) as s:
        back = s[:6]
        for key in td.keys(True, True):
            assert back.get(key).dtype == td.get(key).dtype, key
            assert torch.equal(back.get(key), td.get(key)), key
    g = zarr.open_group(str(path), mode="r")
    assert g["next/deep/x"].shape == (10, 2, 2)
    schema = g.attrs["schema"]
    assert schema["f64"] == {"dtype": "float64", "shape": [3]}
    assert g.attrs["torchrl_robotmem"]["format_version"] == 1


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda td: td.exclude("action"), "missing keys.*action"),
        (lambda td: td.set("action", td["action"].double()), "'action'.*float64"),
        (lambda td: td.set("action", torch.zeros(td.shape[0], 5)), "'action'.*shape \\[5\\]"),
        (lambda td: td.set(("next", "reward"), torch.zeros(td.shape[0], 1, dtype=torch.int64)), "reward"),
    ],
)
def test_schema_mismatch_leaves_store_untouched(tmp_path, transitions, mutate, match):
    path = tmp_path / "m.zarr"
    rb = _rb(ZarrStorage(path, 100, chunk_rows=16))
    rb.extend(transitions(20))
    rb.storage.flush()
    ram_before = rb.storage[:].clone()
    disk_before = {k: v[:] for k, v in zarr.open_group(str(path), mode="r").arrays()}
    attrs_before = dict(zarr.open_group(str(path), mode="r").attrs)
    with pytest.raises((KeyError, ValueError), match=match):
        rb.extend(mutate(transitions(5, start=20)))
    assert len(rb) == 20 and rb.writer._cursor == 20 and rb.writer._write_count == 20
    _assert_td_equal(rb.storage[:], ram_before)
    rb.storage.flush()
    g = zarr.open_group(str(path), mode="r")
    assert dict(g.attrs) == attrs_before
    for k, v in g.arrays():
        np.testing.assert_array_equal(v[:], disk_before[k])
    # the next good write lands right after the old rows: no hole
    rb.extend(transitions(5, start=20))
    assert torch.equal(rb.storage["observation"][20:25, 0], torch.arange(20, 25).float())
    rb.storage.close()


@pytest.mark.parametrize(
    "mutate, error, match",
    [
        (lambda td: td.set(("next", "reward"), td["next", "reward"].double()), ValueError, "'reward'.*float64"),
        (lambda td: td.set(("next", "observation"), torch.zeros(td.shape[0], 24)), ValueError, "shape \\[24\\]"),
        (lambda td: td.exclude(("next", "done")), KeyError, "missing keys.*done"),
        (lambda td: td.set("episode", torch.zeros(td.shape[0], dtype=torch.long)), ValueError, "'episode' is a tag"),
        (lambda td: td.set("env", torch.full((td.shape[0],), 5)), ValueError, "codes \\[5\\] unknown"),
        (lambda td: td.set("_journal", torch.zeros(td.shape[0])), ValueError, "'_journal' is reserved"),
    ],
)
def test_repeat_appends_still_check_every_batch(tmp_path, transitions, monkeypatch, mutate, error, match):
    """The one-pass plan of a repeat append (planner._plan_append) hides no bad batch: it falls back to the
    full checks, which name the key and leave the store as it was."""
    from torchrl_robotmem.storage import planner

    full = []
    normalise = planner._normalise
    monkeypatch.setattr(planner, "_normalise", lambda *a, **k: full.append(1) or normalise(*a, **k))
    with ZarrStorage(tmp_path / "m.zarr", 100, chunk_rows=16, env="FetchPush-v4") as s:
        rb = _rb(s)
        for k in range(3):
            rb.extend(transitions(10, start=10 * k))
        assert len(full) == 1  # the first write is planned in full; the repeats in one pass
        before, attrs = s[:].clone(), dict(s.schema)
        with pytest.raises(error, match=match):
            rb.extend(mutate(transitions(5, start=30)))
        assert len(full) == 2
        assert len(rb) == 30 and rb.writer._cursor == 30 and rb.writer._write_count == 30
        assert s.schema == attrs and s.env_names == ("FetchPush-v4",)
        _assert_td_equal(s[:], before)
        rb.extend(transitions(5, start=30))  # a good batch after it: one pass again, right after the old rows
        assert len(full) == 2 and torch.equal(s["observation"][30:35, 0], torch.arange(30, 35).float())


def test_repeat_appends_follow_new_keys_and_env_names(tmp_path, transitions):
    """What a write changes (a column added, an env name registered, the storage's env) holds for the next."""
    from tensordict import NonTensorData

    with ZarrStorage(tmp_path / "m.zarr", 100, chunk_rows=16, env="FetchPush-v4") as s:
        rb = _rb(s)
        rb.extend(transitions(5))
        rb.extend(transitions(5, start=5))
        wider = transitions(5, start=10)
        wider.set(("next", "extra"), torch.ones(5, 2))
        rb.extend(wider)  # a new key: a new column, whose older rows read zeros
        assert "next/extra" in s.schema and s["next", "extra"][:10].abs().sum() == 0
        with pytest.raises(KeyError, match="missing keys.*extra"):
            rb.extend(transitions(5, start=15))  # the column is held now: every write carries it
        wider = transitions(5, start=15)
        wider.set(("next", "extra"), torch.ones(5, 2))
        wider.set("env", NonTensorData("FetchReach-v4", batch_size=[5]))
        rb.extend(wider)  # a new env name, from the data
        assert s.env_names == ("FetchPush-v4", "FetchReach-v4")
        wider = transitions(5, start=20)
        wider.set(("next", "extra"), torch.ones(5, 2))
        rb.extend(wider)  # no env entry: the storage's env
        s.env = "FetchSlide-v4"
        wider = transitions(5, start=25)
        wider.set(("next", "extra"), torch.ones(5, 2))
        rb.extend(wider)
        assert s["env"][:30].tolist() == [0] * 15 + [1] * 5 + [0] * 5 + [2] * 5
        assert s["run"][:30].unique().tolist() == [0] and len(rb) == 30


def test_batched_collector_output_warns_with_a_fix(tmp_path, transitions):
    """[num_envs, T] data in an ndim=1 store: items stored whole (as LazyTensorStorage), with advice."""
    with ZarrStorage(tmp_path / "m.zarr", 100) as s:
        rb = _rb(s)
        with pytest.warns(UserWarning, match="reshape\\(-1\\).*ndim=2"):
            rb.extend(transitions(20).reshape(2, 10))
        assert len(rb) == 2 and rb.sample(3).batch_size == (3, 10)
        assert s["episode"][:2].tolist() == [[0] * 10, [1] * 10]  # one episode id per item
    with ZarrStorage(tmp_path / "m.zarr") as s:
        assert torch.equal(s[:2]["observation"], transitions(20).reshape(2, 10)["observation"])


def test_bad_paths_and_versions(tmp_path, transitions):
    with ZarrStorage(tmp_path / "new.zarr") as grows:  # no max_size: a memory without a declared capacity
        assert not grows.bounded
    with pytest.raises(ValueError, match="max_size"):
        ZarrStorage(tmp_path / "nd.zarr", ndim=2)  # one that grows stores a transition a row
    (tmp_path / "not_a_store").mkdir()
    (tmp_path / "not_a_store" / "data.txt").write_text("hello")
    with pytest.raises(ValueError, match="not a Zarr store"):
        ZarrStorage(tmp_path / "not_a_store", 10)
    (tmp_path / "file.bin").write_bytes(b"x")
    with pytest.raises(ValueError, match="is a file"):
        ZarrStorage(tmp_path / "file.bin", 10)
    with pytest.raises(FileNotFoundError):
        ZarrStorage(tmp_path / "missing.zarr", read_only=True)
    # the instant between a writer creating the group and writing its commit record
    zarr.open_group(str(tmp_path / "being_created.zarr"), mode="w", zarr_format=3)
    with pytest.raises(ValueError, match="empty Zarr group, not yet a torchrl_robotmem store.*open it again"):
        ZarrStorage(tmp_path / "being_created.zarr", read_only=True)
    foreign = zarr.open_group(str(tmp_path / "foreign.zarr"), mode="w")
    foreign.create_array("x", shape=(3,), dtype="f4")
    with pytest.raises(ValueError, match="not a torchrl_robotmem store"):  # a group with members: foreign
        ZarrStorage(tmp_path / "foreign.zarr", read_only=True)
    with pytest.raises(ValueError, match="not written by torchrl_robotmem"):
        ZarrStorage(tmp_path / "foreign.zarr", 10)
    with ZarrStorage(tmp_path / "future.zarr", 10) as s:
        _rb(s).extend(transitions(3))
    g = zarr.open_group(str(tmp_path / "future.zarr"), mode="a")
    g.attrs["torchrl_robotmem"] = {"format_version": 99, "library_version": "9.9"}
    with pytest.raises(ValueError, match="format version 99"):
        ZarrStorage(tmp_path / "future.zarr")


def test_a_new_store_appears_with_its_commit_record(tmp_path, transitions):
    """A new store's zarr.json is first written with the format marker in it: no reader sees a bare group."""
    from torchrl_robotmem.storage.handle import StoreHandle

    path = tmp_path / "m.zarr"
    h = StoreHandle(str(path), read_only=False)
    h.open()  # the writer has the store open (and its lock): nothing a reader could open yet
    assert not (path / "zarr.json").exists()
    with pytest.raises(FileNotFoundError, match="no zarr.json"):
        ZarrStorage(path, read_only=True)
    h.create({}, max_size=10, chunk_rows=None, ndim=1)
    attrs = json.loads((path / "zarr.json").read_text())["attributes"]
    assert attrs["torchrl_robotmem"]["format_version"] >= 1 and attrs["len"] == 0 and attrs["max_size"] == 10
    h.release()
    with ZarrStorage(path, read_only=True) as s:
        assert len(s) == 0
    # an empty group, as an older version killed between the group and its record left it: a writer adopts it
    zarr.open_group(str(tmp_path / "old.zarr"), mode="w", zarr_format=3)
    with ZarrStorage(tmp_path / "old.zarr", 10) as s:
        _rb(s).extend(transitions(3))
    with ZarrStorage(tmp_path / "old.zarr", read_only=True) as s:
        assert len(s) == 3


def test_nothing_is_unpickled_on_open(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    with ZarrStorage(path, 10) as s:
        _rb(s).extend(transitions(3))
    # the metadata is plain JSON, readable without this library
    meta = json.loads((path / "zarr.json").read_text())
    assert meta["attributes"]["len"] == 3
    # pickling gives a read-only handle on the same store (what a worker process gets)
    import pickle

    with ZarrStorage(path) as s:
        clone = pickle.loads(pickle.dumps(s))
    assert clone.read_only and len(clone) == 3 and clone is not s


def test_max_size_mismatch_and_growth(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    with ZarrStorage(path, 50, chunk_rows=16) as s:
        _rb(s).extend(transitions(30))
    with pytest.raises(ValueError, match="shrink"):
        ZarrStorage(path, 40)
    with ZarrStorage(path, 80) as s:  # not wrapped yet: grows
        rb = _rb(s)
        assert s.max_size == 80 and len(s) == 30
        rb.extend(transitions(50, start=30))
        assert len(s) == 80 and rb.writer._cursor == 0
        rb.extend(transitions(5, start=80))  # wraps now
    with ZarrStorage(path) as s:
        assert s.max_size == 80
        assert torch.equal(s["observation"][:5, 0], torch.arange(80, 85).float())
    with pytest.raises(ValueError, match="wrapped"):
        ZarrStorage(path, 100)


# -- tags ---------------------------------------------------------------------


def test_episode_run_env_tags_across_runs(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    with ZarrStorage(path, 1000, env="FetchPush-v4") as s:
        _rb(s).extend(transitions(25))  # episodes 0, 1 and an open 2
    with ZarrStorage(path, env="FetchSlide-v4") as s:
        # the interrupted episode was closed at reopen
        assert bool(s["next", "done"][24]) and bool(s["next", "truncated"][24])
        assert not bool(s["next", "done"][23])
        _rb(s).extend(transitions(20, start=100))
        assert s.env_names == ("FetchPush-v4", "FetchSlide-v4")
        ep = s["episode"][:45]
        assert ep[:25].tolist() == [0] * 10 + [1] * 10 + [2] * 5
        assert ep[25:].tolist() == [3] * 10 + [4] * 10  # never merged with episode 2
        assert s["run"][:45].tolist() == [0] * 25 + [1] * 20
        assert s["env"][:45].tolist() == [0] * 25 + [1] * 20
    with ZarrStorage(path) as s:  # keeps the last env by default
        assert s.env == "FetchSlide-v4"


def test_episode_ids_from_collector_traj_ids(tmp_path, transitions):
    td = transitions(40, episode_len=20)
    # two envs interleaved, as a batched collector's output after reshape(-1)
    td.set(("collector", "traj_ids"), torch.tensor([0] * 20 + [1] * 20))
    with ZarrStorage(tmp_path / "m.zarr", 1000) as s:
        rb = _rb(s)
        rb.extend(td[:10].clone())
        rb.extend(td[20:30].clone())
        rb.extend(td[10:20].clone())
        rb.extend(td[30:40].clone())
        ep = s["episode"][:40]
        assert ep.tolist() == [0] * 10 + [1] * 10 + [0] * 10 + [1] * 10
    td2 = transitions(10, episode_len=20)  # a new collector restarts traj ids at 0
    td2.set(("collector", "traj_ids"), torch.zeros(10, dtype=torch.long))
    with ZarrStorage(tmp_path / "m.zarr") as s:
        _rb(s).extend(td2)
        assert s["episode"][40:50].unique().tolist() == [2]


def test_env_names_from_data(tmp_path, transitions):
    with ZarrStorage(tmp_path / "m.zarr", 100) as s:
        code = s.env_code("HandReach-v3", create=True)
        td = transitions(4)
        td.set("env", torch.full((4,), code))
        _rb(s).extend(td)
        assert s["env"][:4].tolist() == [code] * 4
        td = transitions(4)
        td.set("env", torch.full((4,), 7))
        with pytest.raises(ValueError, match="codes \\[7\\] unknown"):
            _rb(s).extend(td)


# -- TorchRL buffers ----------------------------------------------------------


def test_plain_buffer(tmp_path, transitions):
    """A plain ReplayBuffer over ZarrStorage (the prioritized one: test_prioritized_buffer)."""
    with ZarrStorage(tmp_path / "a.zarr", 100) as s:
        rb = ReplayBuffer(storage=s, batch_size=4)
        rb.extend(transitions(10))
        rb.add(transitions(1, start=10)[0])
        assert len(rb) == 11
        want = transitions(11)
        assert torch.equal(s[:11]["observation"], want["observation"])
        batch, info = rb.sample(return_info=True)
        assert batch.shape == (4,)
        assert torch.equal(batch["observation"], want["observation"][torch.as_tensor(info["index"])])


def test_prioritized_buffer(tmp_path, transitions):
    try:
        TensorDictPrioritizedReplayBuffer(alpha=0.7, beta=0.5, storage=LazyTensorStorage(4))
    except RuntimeError as err:  # torchrl's C++ segment trees do not load against this torch
        pytest.skip(f"PrioritizedSampler unavailable: torchrl's C++ extension does not load against torch "
                    f"{torch.__version__} ({err})")
    with ZarrStorage(tmp_path / "b.zarr", 100) as s:
        rb = TensorDictPrioritizedReplayBuffer(alpha=0.7, beta=0.5, storage=s, batch_size=16)
        rb.extend(transitions(50))
        # every row gets a priority (rows left out of an update keep the initial one): row 3 carries ~1e8 times the
        # others' probability, so a batch of 16 is row 3 but for a ~1e-6 chance, by construction
        index = torch.arange(50)
        batch = rb.storage.get(index).set("index", index)
        batch.set("td_error", torch.where(index == 3, 1e4, 1e-8))
        rb.update_tensordict_priority(batch)
        assert (rb.sample()["index"] == 3).float().mean() > 0.5


def test_her_never_relabels_across_a_run_boundary(tmp_path, transitions):
    path = tmp_path / "m.zarr"

    def reward_fn(td):
        d = (td["next", "achieved_goal"] - td["desired_goal"]).norm(dim=-1, keepdim=True)
        return -(d > 0.05).float()

    with ZarrStorage(path, 1000) as s:
        rb = HERReplayBuffer(reward_fn=reward_fn, storage=s, batch_size=256, her_ratio=1.0,
                             strategy="final", achieved_goal_key=("next", "achieved_goal"))
        rb.extend(transitions(15))  # episode 1 is interrupted at row 14
    with ZarrStorage(path) as s:
        rb = HERReplayBuffer(reward_fn=reward_fn, storage=s, batch_size=256, her_ratio=1.0,
                             strategy="final", achieved_goal_key=("next", "achieved_goal"))
        rb.extend(transitions(20, start=1000))
        for _ in range(5):
            batch = rb.sample()
            rows = batch["index"]
            # "final" relabels with the last achieved goal of the row's own episode
            ep_of_row = s["episode"][rows]
            last_row = torch.stack([(s["episode"][:35] == e).nonzero().max() for e in ep_of_row])
            expected = s["next", "achieved_goal"][last_row]
            assert torch.allclose(batch["desired_goal"], expected)
            interrupted = rows >= 10
            interrupted &= rows < 15
            if interrupted.any():
                assert (last_row[interrupted] == 14).all()


def test_dumps_loads_and_checkpoint(tmp_path, transitions):
    from torchrl.checkpoint import Checkpoint

    path = tmp_path / "m.zarr"
    s = ZarrStorage(path, 10_000)
    rb = _rb(s)
    rb.extend(transitions(300))
    rb.dumps(tmp_path / "ckpt")
    # a self-contained copy made of hard links: no chunk is copied
    chunks = [p for p in (tmp_path / "ckpt" / "storage" / "store.zarr").rglob("c.*") if p.is_file()]
    assert chunks and all(p.stat().st_nlink >= 2 for p in chunks)
    assert json.loads((tmp_path / "ckpt" / "storage" / "zarr_storage.json").read_text())["len"] == 300
    Checkpoint(replay_buffer=rb).save(tmp_path / "ck2")
    s.close()
    rb2 = _rb(ZarrStorage(path))
    rb2.loads(tmp_path / "ckpt")
    assert len(rb2) == 300 and rb2.writer._cursor == 300
    # a writer moved elsewhere is put back by Checkpoint.load (the store is the newest state)
    rb2.writer._cursor, rb2.writer._write_count = 7, 7
    Checkpoint(replay_buffer=rb2).load(tmp_path / "ck2")
    assert (rb2.writer._cursor, rb2.writer._write_count) == (300, 300)
    rb2.extend(transitions(10, 300))  # appends after the old rows
    assert len(rb2) == 310 and torch.equal(rb2.storage["observation"][300:310], transitions(10, 300)["observation"])
    rb2.storage.close()
    # into a buffer on another store: the rows are copied (as TorchRL's storages do)
    other = _rb(ZarrStorage(tmp_path / "other.zarr", 1000))
    other.loads(tmp_path / "ckpt")
    assert len(other) == 300 and other.writer._cursor == 300
    assert torch.equal(other.storage["observation"][:300], transitions(300)["observation"])
    other.storage.close()
    assert len(ZarrStorage(tmp_path / "other.zarr", read_only=True)) == 300


def test_empty_is_persisted(tmp_path, transitions):
    path = tmp_path / "m.zarr"
    with ZarrStorage(path, 100) as s:
        rb = _rb(s)
        rb.extend(transitions(10))
        rb.empty()
        assert len(rb) == 0
    with ZarrStorage(path) as s:
        assert len(s) == 0


# -- store URLs ---------------------------------------------------------------


def test_memory_url_and_zip_store(tmp_path, transitions):
    with ZarrStorage("memory://robotmem-test/m", 100) as s:
        _rb(s).extend(transitions(12))
    with ZarrStorage("memory://robotmem-test/m", read_only=True) as s:
        assert len(s) == 12
        assert torch.equal(s["observation"][:12], transitions(12)["observation"])

    zpath = str(tmp_path / "m.zarr.zip")
    with ZarrStorage(zpath, 100) as s:
        _rb(s).extend(transitions(12))
    with ZarrStorage(zpath, read_only=True) as s:
        assert len(s) == 12
        assert torch.equal(s["action"][:12], transitions(12)["action"])
    # the integrity check reads keys before any group is opened: the zip store is opened for it (it used to raise
    # AttributeError: 'ZipStore' object has no attribute '_lock')
    from torchrl_robotmem.storage.integrity import verify

    report = verify(zpath)
    assert report.ok, str(report)


def test_summary(tmp_path, transitions):
    with ZarrStorage(tmp_path / "m.zarr", 100, env="FetchPush-v4") as s:
        _rb(s).extend(transitions(35))
        s.flush()
        info = s.summary()
    assert info["rows"] == 35 and info["episodes"] == 4 and info["runs"] == 1
    assert info["envs"] == ("FetchPush-v4",)
    assert abs(info["success_rate"] - 5 / 35) < 1e-6
    assert info["bytes_on_disk"] > 0


def test_a_one_row_slice_with_its_stop_left_out_is_committed_and_closes(tmp_path):
    """``set(slice(9, None), one_row)``: committed like ``LazyTensorStorage`` counts it (len 4, last cursor 9);
    the open slice used to kill the writer thread in the commit record, and ``close()`` waited for it forever."""
    path = str(tmp_path / "m.zarr")
    st = ZarrStorage(path, 10, goal_conditioned=False, env="FetchReach-v4")
    st.set(slice(0, 3), TensorDict({"a": torch.arange(3.0)}, [3]))
    st.set(slice(9, None), TensorDict({"a": torch.tensor([9.0])}, [1]))
    ref = LazyTensorStorage(10)
    ref.set(slice(0, 3), TensorDict({"a": torch.arange(3.0)}, [3]))
    ref.set(slice(9, None), TensorDict({"a": torch.tensor([9.0])}, [1]))
    st.close()
    with ZarrStorage(path, read_only=True) as reader:
        assert len(reader) == len(ref) == 4
        assert reader.record()["last_cursor"] == 9


def test_a_strided_slice_with_its_stop_left_out_is_committed_as_torchrl_counts_it(tmp_path):
    """``set(slice(0, None, 2), five_rows)``: the commit record's last row is TorchRL's own resolution of the
    cursor (row 8), not ``stop - 1`` of an open slice (a ``TypeError`` in every commit, and nothing committed)."""
    path = str(tmp_path / "m.zarr")
    rows = TensorDict({"a": torch.arange(5.0) + 10}, [5])
    st = ZarrStorage(path, 10, goal_conditioned=False, env="FetchReach-v4")
    st.set(0, TensorDict({"a": torch.tensor(1.0)}, []))
    st.set(slice(0, None, 2), rows)
    ref = LazyTensorStorage(10)
    ref.set(0, TensorDict({"a": torch.tensor(1.0)}, []))
    ref.set(slice(0, None, 2), rows)
    st.flush()
    st.close()
    with ZarrStorage(path, read_only=True) as reader:
        assert len(reader) == len(ref)
        assert reader.record()["last_cursor"] == ref._last_cursor_index == 8
        assert reader[[0, 2, 4]]["a"].tolist() == [10.0, 11.0, 12.0]


def test_negative_cursors_reach_the_chunks(tmp_path):
    """``set(-1, row)``, a tensor of indices with a negative one and a negative range write the rows they name
    (counted from the end, as TorchRL's storages index) into the Zarr chunks, not only into the row file: the
    rows read back with the row file deleted, and through Zarr itself, are the rows written (they used to mark a
    chunk ``-1`` dirty, so the chunks kept the old rows; through the commit worker, the empty snapshot of that
    chunk failed the commit)."""
    import shutil

    from torchrl_robotmem.storage.rowfile import ROWS_DIR

    path = str(tmp_path / "m.zarr")
    with ZarrStorage(path, 100, chunk_rows=10, goal_conditioned=False, env="FetchReach-v4") as st:
        st.set(slice(0, 100), TensorDict({"a": torch.arange(100.0)}, [100]))
    with ZarrStorage(path, goal_conditioned=False) as st:
        st.set(-1, TensorDict({"a": torch.tensor(777.0)}, []))
        st.set(torch.tensor([-12, 5]), TensorDict({"a": torch.tensor([555.0, 5.5])}, [2]))
        st.set(range(-30, -28), TensorDict({"a": torch.tensor([70.5, 71.5])}, [2]))
        st.flush()
        assert zarr.open_group(path, mode="r")["a"][[88, 99, 5, 70, 71]].tolist() == [555.0, 777.0, 5.5, 70.5, 71.5]
    shutil.rmtree(tmp_path / "m.zarr" / ROWS_DIR)  # the rows come from the chunks alone
    with ZarrStorage(path, read_only=True) as reader:
        assert reader[[88, 99, 5, 70, 71, 98]]["a"].tolist() == [555.0, 777.0, 5.5, 70.5, 71.5, 98.0]


def _random_cursor(rng, n: int):
    """A cursor of one of the kinds a TorchRL storage's ``set`` takes, rows of a storage of ``n``."""
    kind = rng.choice(["int", "negative int", "slice", "open slice of one", "strided slice", "open strided slice",
                       "tensor", "negative tensor", "list", "range"])
    a = rng.randrange(n)
    b = rng.randrange(a + 1, n + 1)
    if kind == "int":
        return a
    if kind == "negative int":
        return -rng.randrange(1, n + 1)
    if kind == "slice":
        return slice(a, b)
    if kind == "open slice of one":
        return slice(n - 1, None)
    if kind == "strided slice":
        return slice(a, b, rng.randrange(2, 4))
    if kind == "open strided slice":
        return slice(a, None, rng.randrange(2, 4))
    picked = rng.sample(range(n), rng.randrange(1, n // 2))
    if kind == "tensor":
        return torch.tensor(picked)
    if kind == "negative tensor":
        return torch.tensor([i - n for i in picked])
    return picked if kind == "list" else range(a, b)


def test_any_cursor_is_written_committed_and_reopened_as_lazy_tensor_storage_counts_it(tmp_path):
    """A differential test: 10 runs of 40 ``set`` calls with random cursors of every kind TorchRL's storages take,
    on ``ZarrStorage`` and ``LazyTensorStorage`` side by side. After each call both have the same length, last
    cursor and written rows (those below the length); after ``close()``, the reopened store (row file deleted: the chunks alone) has them
    too. Seeded by ``ROBOTMEM_TEST_SEED`` (the failure names the seed, run and call)."""
    import random
    import shutil

    from conftest import suite_seed

    from torchrl_robotmem.storage.rowfile import ROWS_DIR

    n = 12
    for run in range(10):
        seed = suite_seed() * 1000 + run
        rng = random.Random(seed)
        path = str(tmp_path / f"m{run}.zarr")
        st, ref = ZarrStorage(path, n, chunk_rows=4, goal_conditioned=False, env="FetchReach-v4"), LazyTensorStorage(n)
        written = torch.zeros(n, dtype=torch.bool)
        for call in range(40):
            cursor = _random_cursor(rng, n)
            rows = torch.arange(n)[cursor if not isinstance(cursor, (list, range)) else list(cursor)].reshape(-1)
            value = torch.full((len(rows),), float(call)) if not isinstance(cursor, int) else torch.tensor(float(call))
            data = TensorDict({"a": value}, value.shape)
            ref.set(cursor, data)
            st.set(cursor, data)
            written[rows] = True
            where = f"seed {seed} (ROBOTMEM_TEST_SEED={suite_seed()}, run {run}), call {call}, cursor {cursor!r}"
            assert (len(st), st._last_cursor_index) == (len(ref), ref._last_cursor_index), where
            seen = written[: len(ref)].nonzero().reshape(-1)  # rows past the length are not read (an IndexError)
            assert torch.equal(st[seen]["a"], ref[seen]["a"]), where
        st.close()
        shutil.rmtree(tmp_path / f"m{run}.zarr" / ROWS_DIR)
        with ZarrStorage(path, read_only=True) as reader:
            assert (len(reader), reader._last_cursor_index) == (len(ref), ref._last_cursor_index), f"seed {seed}"
            assert torch.equal(reader[seen]["a"], ref[seen]["a"]), f"seed {seed}, reopened from the chunks"


def test_any_first_dim_cursor_of_an_ndim_2_storage_matches_lazy_tensor_storage(tmp_path):
    """The differential test on ``ndim=2`` storages (8 trajectories of 3 steps, chunks of 3 trajectories): whole
    trajectories written at random first-dimension cursors of every kind; after each call the same length, last
    cursor and contents as ``LazyTensorStorage(24, ndim=2)``, and after ``close()`` the same from the chunks alone."""
    import random
    import shutil

    from conftest import suite_seed

    from torchrl_robotmem.storage.rowfile import ROWS_DIR

    n, steps = 8, 3
    for run in range(5):
        seed = suite_seed() * 1000 + run
        rng = random.Random(seed)
        path = str(tmp_path / f"m{run}.zarr")
        st = ZarrStorage(path, n * steps, ndim=2, chunk_rows=3, goal_conditioned=False, env="FetchReach-v4")
        ref = LazyTensorStorage(n * steps, ndim=2)
        start = TensorDict({"a": torch.zeros(n, steps)}, [n, steps])
        st.set(slice(0, n), start)
        ref.set(slice(0, n), start)
        for call in range(30):
            cursor = _random_cursor(rng, n)
            shape = (steps,) if isinstance(cursor, int) else (
                len(torch.arange(n)[cursor if not isinstance(cursor, (list, range)) else list(cursor)].reshape(-1)), steps)
            data = TensorDict({"a": torch.full(shape, float(call + 1))}, shape)
            ref.set(cursor, data)
            st.set(cursor, data)
            where = f"seed {seed} (ROBOTMEM_TEST_SEED={suite_seed()}, run {run}), call {call}, cursor {cursor!r}"
            assert (len(st), st._last_cursor_index) == (len(ref), ref._last_cursor_index), where
            assert torch.equal(st[:]["a"], ref[:]["a"]), where
        st.close()
        shutil.rmtree(tmp_path / f"m{run}.zarr" / ROWS_DIR)
        with ZarrStorage(path, read_only=True) as reader:
            assert len(reader) == len(ref) and torch.equal(reader[:]["a"], ref[:]["a"]), f"seed {seed}, from the chunks"
