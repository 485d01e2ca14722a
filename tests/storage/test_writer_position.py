"""A reopen hands TorchRL's writer back the position it had: its own cursor and count, however it moved them.

Each test runs the same buffer on ``LazyTensorStorage`` and on ``ZarrStorage``, reopens the Zarr store
(a fresh handle, or a killed process), and checks the writer state and where the next write lands
against the ``LazyTensorStorage`` buffer that was never closed. Found by a differential review: the
store recorded its own count of rows written, which TorchRL's writers do not keep in these cases
(``write_at`` counts without ``set_cursor``, a consuming buffer moves the cursor itself,
``empty(empty_write_count=False)`` keeps the count, ``dim_extend=1`` counts items, and
``TensorDictMaxValueWriter`` keeps a heap no ``state_dict`` saves).
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictMaxValueWriter, TensorDictReplayBuffer
from torchrl.data.replay_buffers import ConsumingSampler, SliceSampler

from torchrl_robotmem import ZarrStorage


def _rows(start: int, n: int) -> TensorDict:
    return TensorDict({"obs": torch.arange(start, start + n, dtype=torch.float32)}, [n])


def _zarr(path, max_size=None, **kwargs) -> ZarrStorage:
    return ZarrStorage(path, max_size, goal_conditioned=False, env="E", **kwargs)


def _position(rb) -> dict:
    return {k: int(v) for k, v in rb.writer.state_dict().items()}


def test_write_at_and_a_consuming_buffer_keep_the_writer_position_across_a_reopen(tmp_path):
    path = tmp_path / "m.zarr"
    ref = TensorDictReplayBuffer(storage=LazyTensorStorage(4), sampler=ConsumingSampler(), batch_size=1)
    zr = TensorDictReplayBuffer(storage=_zarr(path, 4), sampler=ConsumingSampler(), batch_size=1)
    for rb in (ref, zr):
        rb.extend(_rows(0, 4))
        torch.manual_seed(0)
        rb.sample()  # consumes one row
        rb.extend(_rows(10, 3))  # the consumed row through write_at, then two rows from the cursor it moves itself
        rb.writer.write_at(torch.tensor([0]), _rows(20, 1))  # counted by the writer, not set_cursor
    assert _position(zr) == _position(ref) == {"_cursor": 3, "_write_count": 8}
    zr.storage.close()
    again = TensorDictReplayBuffer(storage=_zarr(path), sampler=ConsumingSampler(), batch_size=1)
    assert _position(again) == _position(ref)
    for rb in (ref, again):
        rb.extend(_rows(50, 1))
    assert again.storage[:]["obs"].tolist() == ref.storage[:]["obs"].tolist()
    again.storage.close()


@pytest.mark.parametrize("dim_extend", [0, 1])
def test_an_ndim_2_writer_gets_back_its_count_of_items(tmp_path, dim_extend):
    path = tmp_path / "m.zarr"
    rows = TensorDict({"obs": torch.arange(12.0).reshape(3, 4)}, [3, 4])
    ref = TensorDictReplayBuffer(storage=LazyTensorStorage(24, ndim=2), batch_size=2, dim_extend=dim_extend)
    zr = TensorDictReplayBuffer(storage=_zarr(path, 24, ndim=2), batch_size=2, dim_extend=dim_extend)
    for rb in (ref, zr):
        rb.extend(rows.clone())
    zr.storage.close()
    again = TensorDictReplayBuffer(storage=_zarr(path), batch_size=2, dim_extend=dim_extend)
    assert _position(again) == _position(ref) == {"_cursor": 3 + dim_extend, "_write_count": 3 + dim_extend}
    assert again.write_count == ref.write_count
    again.storage.close()


def test_an_empty_that_keeps_the_write_count_keeps_it_across_a_reopen(tmp_path):
    path = tmp_path / "m.zarr"
    ref = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=2)
    zr = TensorDictReplayBuffer(storage=_zarr(path, 10), batch_size=2)
    for rb in (ref, zr):
        rb.extend(_rows(0, 5))
        rb.empty(empty_write_count=False)
        rb.extend(_rows(5, 3))
    zr.storage.close()
    again = TensorDictReplayBuffer(storage=_zarr(path), batch_size=2)
    assert _position(again) == _position(ref) == {"_cursor": 3, "_write_count": 8}
    again.storage.close()


def test_a_loaded_state_keeps_the_writer_position_and_no_last_cursor(tmp_path):
    """rb.load_state_dict loads the storage first and the writer after: the position is recorded at the
    next flush; the last cursor is left as TensorStorage.load_state_dict leaves it (none), so a
    SliceSampler samples the loaded buffer as it samples the source."""
    def build(st):
        return TensorDictReplayBuffer(storage=st, batch_size=8,
                                      sampler=SliceSampler(slice_len=4, traj_key="traj", strict_length=False))

    src = build(LazyTensorStorage(10))
    src.extend(TensorDict({"obs": torch.arange(7.0), "traj": torch.zeros(7, dtype=torch.long)}, [7]))
    src.extend(TensorDict({"obs": torch.arange(7.0, 13.0), "traj": torch.ones(6, dtype=torch.long)}, [6]))
    state = src.state_dict()
    ref, zr = build(LazyTensorStorage(10)), build(_zarr(tmp_path / "m.zarr", 10))
    samples = []
    for rb in (ref, zr):
        rb.load_state_dict(state)
        torch.manual_seed(0)
        samples.append(rb.sample()["obs"].tolist())
    assert samples[0] == samples[1]
    assert zr.storage._last_cursor_index is None
    zr.storage.flush()
    zr.storage.close()
    again = build(_zarr(tmp_path / "m.zarr"))
    assert _position(again) == _position(ref) == {"_cursor": 3, "_write_count": 13}
    for rb in (ref, again):
        rb.extend(TensorDict({"obs": torch.tensor([100.0]), "traj": torch.tensor([2])}, [1]))
    assert again.storage[:]["obs"].tolist() == ref.storage[:]["obs"].tolist()
    again.storage.close()


def test_a_max_value_writer_gets_back_its_heap(tmp_path):
    def rows(rewards, tag):
        n = len(rewards)
        return TensorDict({"obs": torch.full((n,), float(tag)),
                           ("next", "reward"): torch.tensor(rewards).unsqueeze(-1)}, [n])

    def build(st):
        return TensorDictReplayBuffer(storage=st, writer=TensorDictMaxValueWriter(rank_key=("next", "reward")),
                                      batch_size=2)

    path = tmp_path / "m.zarr"
    ref, zr = build(LazyTensorStorage(4)), build(_zarr(path, 4))
    for rb in (ref, zr):
        rb.extend(rows([9.0, 1.0, 8.0, 2.0], 0))
    zr.storage.close()
    again = build(_zarr(path))
    assert again.write_count == ref.write_count == 4
    for rb in (ref, again):
        rb.extend(rows([5.0, 6.0], 1))  # replace the two lowest rewards, 1 and 2
        rb.add(rows([0.5], 2)[0])  # lower than every stored reward: not written
    rewards = [rb.storage[:]["next", "reward"].flatten().tolist() for rb in (ref, again)]
    assert rewards[0] == rewards[1] == [9.0, 5.0, 8.0, 6.0]
    again.storage.close()


def test_the_writer_position_is_committed_by_a_flush_and_survives_sigkill(tmp_path):
    path = tmp_path / "m.zarr"
    code = textwrap.dedent(f"""
        import os, signal, torch
        from tensordict import TensorDict
        from torchrl.data import TensorDictReplayBuffer
        from torchrl_robotmem import ZarrStorage
        rb = TensorDictReplayBuffer(storage=ZarrStorage({str(path)!r}, 8, goal_conditioned=False, env="E"), batch_size=2)
        rb.extend(TensorDict({{"obs": torch.arange(5.0)}}, [5]))
        rb.writer.write_at(torch.tensor([1, 2]), TensorDict({{"obs": torch.tensor([7.0, 8.0])}}, [2]))
        rb.storage.flush()
        print("FLUSHED", flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert "FLUSHED" in out.stdout and out.returncode == -9, out.stdout + out.stderr
    again = TensorDictReplayBuffer(storage=_zarr(path), batch_size=2)
    assert _position(again) == {"_cursor": 5, "_write_count": 7}
    assert again.storage[:]["obs"].tolist() == [0.0, 7.0, 8.0, 3.0, 4.0]
    again.storage.close()


@pytest.mark.parametrize("forged", ["x", [3], [-1, 4], [99, 4], [2, -5], [True, 4], {"cursor": 2}])
def test_a_forged_writer_entry_is_ignored_for_the_store_s_own_position(tmp_path, forged):
    path = tmp_path / "m.zarr"
    rb = TensorDictReplayBuffer(storage=_zarr(path, 8), batch_size=2)
    rb.extend(_rows(0, 5))
    rb.storage.close()
    meta_file = path / "zarr.json"
    meta = json.loads(meta_file.read_text())
    assert meta["attributes"]["writer"] == [5, 5]
    meta["attributes"]["writer"] = forged
    meta_file.write_text(json.dumps(meta))
    again = TensorDictReplayBuffer(storage=_zarr(path), batch_size=2)
    assert _position(again) == {"_cursor": 5, "_write_count": 5}  # the store's own cursor and count
    again.storage.close()


@pytest.mark.parametrize("flusher", ["sigterm", "thread"])
def test_a_flush_between_the_writer_s_cursor_move_and_its_set_records_the_last_write(tmp_path, flusher):
    """TorchRL's writer moves its cursor, then calls ``storage.set``: a flush can run between the two (a
    SIGTERM's handler; another thread's ``flush()``, the process then killed). The record must name the rows
    written (cursor 5 of a wrapped ring of 25 after 30 rows), not the move of a batch that never reached the
    store (cursor 15, count 40)."""
    path = tmp_path / "m.zarr"
    code = textwrap.dedent(f"""
        import os, signal, threading, torch
        from tensordict import TensorDict
        from torchrl.data import TensorDictReplayBuffer
        from torchrl_robotmem import ZarrStorage

        def flush_and_kill(storage):  # from another thread, while the main thread waits before its set
            storage.flush()
            print("FLUSHED", flush=True)
            os.kill(os.getpid(), signal.SIGKILL)

        class FlushBeforeTheFourthSet(ZarrStorage):  # lands where the writer has moved and not written
            calls = 0
            def set(self, cursor, data, *, set_cursor=True):
                type(self).calls += 1
                if type(self).calls == 4:
                    print("FLUSH", flush=True)
                    if {flusher!r} == "sigterm":
                        os.kill(os.getpid(), signal.SIGTERM)
                    else:
                        t = threading.Thread(target=flush_and_kill, args=(self,))
                        t.start()
                        t.join()
                return super().set(cursor, data, set_cursor=set_cursor)

        rb = TensorDictReplayBuffer(storage=FlushBeforeTheFourthSet({str(path)!r}, 25, goal_conditioned=False,
                                                                    env="E"), batch_size=2)
        for start in range(0, 40, 10):
            rb.extend(TensorDict({{"obs": torch.arange(start, start + 10.0)}}, [10]))
        print("NOT KILLED", flush=True)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert "FLUSH" in out.stdout and out.returncode == {"sigterm": -15, "thread": -9}[flusher], out.stdout + out.stderr
    reference = TensorDictReplayBuffer(storage=LazyTensorStorage(25), batch_size=2)
    for start in range(0, 30, 10):
        reference.extend(_rows(start, 10))
    again = TensorDictReplayBuffer(storage=_zarr(path), batch_size=2)
    assert _position(again) == _position(reference) == {"_cursor": 5, "_write_count": 30}
    assert again.storage[:]["obs"].tolist() == reference.storage[:]["obs"].tolist()
    again.extend(_rows(100, 10))
    reference.extend(_rows(100, 10))
    assert again.storage[:]["obs"].tolist() == reference.storage[:]["obs"].tolist()  # the next batch lands at row 5
    again.storage.close()


@pytest.mark.parametrize("max_size", [None, 1000])
def test_rows_appended_without_a_buffer_move_the_position_the_next_buffer_gets(tmp_path, max_size):
    """Found by a review: the record kept the last buffer's writer position after rows were appended with
    ``storage.set`` alone, so the next buffer's writer overwrote those rows and counted unwritten ones."""
    path = tmp_path / "m.zarr"
    rb = TensorDictReplayBuffer(storage=_zarr(path, max_size), batch_size=2)
    rb.extend(_rows(0, 100))
    rb.storage.close()
    alone = _zarr(path)
    alone.set(torch.arange(100, 110), _rows(100, 10))
    alone.close()
    again = TensorDictReplayBuffer(storage=_zarr(path), batch_size=2)
    assert _position(again) == {"_cursor": 110, "_write_count": 110}
    again.extend(_rows(110, 5))
    assert again.storage[:]["obs"].tolist() == list(range(115))
    again.storage.close()
