"""The commit worker process (storage/_commit_worker.py): real stores, real processes."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
import torch
import zarr
from conftest import make_transitions
from torchrl.data import ReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage._commit_worker import CommitWorker

TESTS = Path(__file__).resolve().parents[1]


def _wait_for_worker(storage: ZarrStorage, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not storage._engine._use_worker():
        assert time.monotonic() < deadline, "the commit worker never became ready"
        time.sleep(0.05)


def _rows_equal(a, b) -> bool:
    return all(bool((a.get(k) == b.get(k)).all()) for k in b.keys(True, True))


def test_commits_go_through_the_worker_and_read_back_bit_exact(tmp_path):
    st = ZarrStorage(tmp_path / "m.zarr", 1000, chunk_rows=128, commit_process=True)
    assert st._engine.worker_path == str(tmp_path / "m.zarr")
    _wait_for_worker(st)
    rb = ReplayBuffer(storage=st, batch_size=4)
    data = make_transitions(1500)
    for lo in range(0, 1500, 100):  # wraps the ring: journalled commits in the worker
        rb.extend(data[lo : lo + 100])
    st.flush()
    worker = CommitWorker._instance
    assert worker is not None and worker.proc.poll() is None and worker.proc.pid != os.getpid()
    back = ZarrStorage(tmp_path / "m.zarr", read_only=True)
    assert len(back) == 1000
    idx = torch.arange(1000)
    src = torch.where(idx < 500, idx + 1000, idx)
    assert _rows_equal(back.get(idx), data[src])
    # a key added later (schema evolution: attributes written through the worker)
    extra = data[:10].clone()
    extra["new_key"] = torch.ones(10, 2)
    rb.extend(extra)
    st.close()
    again = ZarrStorage(tmp_path / "m.zarr", read_only=True)
    assert "new_key" in again.schema and bool((again.get(torch.arange(500, 510))["new_key"] == 1).all())


def test_the_worker_by_default_and_in_process_commits_on_request(tmp_path, monkeypatch):
    monkeypatch.delenv("TORCHRL_ROBOTMEM_COMMIT_PROCESS", raising=False)
    st = ZarrStorage(tmp_path / "a.zarr", 100)
    assert st._engine.worker_path == str(tmp_path / "a.zarr")
    monkeypatch.setenv("TORCHRL_ROBOTMEM_COMMIT_PROCESS", "0")
    st2 = ZarrStorage(tmp_path / "b.zarr", 100)
    assert st2._engine.worker_path is None
    st3 = ZarrStorage(tmp_path / "c.zarr", 100, commit_process=True)
    assert st3._engine.worker_path == str(tmp_path / "c.zarr")
    for s in (st, st2, st3):
        ReplayBuffer(storage=s, batch_size=2).extend(make_transitions(30))
        s.close()
        assert len(ZarrStorage(s.path, read_only=True)) == 30


@pytest.mark.parametrize("commit_process", [True, False])
def test_a_failed_write_is_raised_with_its_cause_and_retried_by_flush(tmp_path, commit_process):
    st = ZarrStorage(tmp_path / "m.zarr", 1000, chunk_rows=64, commit_process=commit_process)
    if commit_process:
        _wait_for_worker(st)
    rb = ReplayBuffer(storage=st, batch_size=4)
    rb.extend(make_transitions(10))
    st.flush()
    # a directory where the next chunk file must go: the write fails (in the worker, or here)
    blocker = tmp_path / "m.zarr" / "observation" / "c.1.0"
    blocker.mkdir(parents=True)
    rb.extend(make_transitions(100, start=10))
    with pytest.raises(RuntimeError, match=r"background writer .* failed: \w*Error: .*100 rows \(write "
                                           r"numbers 10 to 109, the same storage indices\) are not durable"):
        st.flush()
    assert len(ZarrStorage(tmp_path / "m.zarr", read_only=True)) == 10  # the commit record did not move
    with pytest.raises(RuntimeError, match="not durable"):
        st.flush()  # the cause is still there: the retry fails the same way
    blocker.rmdir()  # the cause is gone: the next flush writes every row the process held
    st.flush()
    back = ZarrStorage(tmp_path / "m.zarr", read_only=True)
    assert len(back) == 110 and _rows_equal(back.get(torch.arange(110)), make_transitions(110))
    rb.extend(make_transitions(5, start=110))  # and writes go on
    st.close()
    assert len(ZarrStorage(tmp_path / "m.zarr", read_only=True)) == 115


CHILD = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {tests!r})
    import torch
    from conftest import make_transitions
    from torchrl.data import ReplayBuffer
    from torchrl_robotmem import ZarrStorage
    from torchrl_robotmem.storage._commit_worker import CommitWorker

    st = ZarrStorage({path!r}, 1_000_000, chunk_rows=256, commit_process=True)
    while not st._engine._use_worker():
        time.sleep(0.02)
    rb = ReplayBuffer(storage=st, batch_size=4)
    rb.extend(make_transitions(1000))
    st.flush()
    print(CommitWorker._instance.proc.pid, flush=True)
    i = 1000
    while True:
        rb.extend(make_transitions(500, start=i))
        i += 500
    """
)


def test_the_worker_dies_with_its_parent_and_the_store_reopens(tmp_path):
    path = tmp_path / "m.zarr"
    proc = subprocess.Popen([sys.executable, "-c", CHILD.format(tests=str(TESTS), path=str(path))],
                            stdout=subprocess.PIPE, text=True)
    try:
        worker_pid = int(proc.stdout.readline())
        time.sleep(1.5)  # commits in flight
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(worker_pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.01)
    else:
        pytest.fail("the commit worker outlived its parent by 10 s")
    st = ZarrStorage(path)  # writable: the lock is free again
    n = len(st)
    assert n >= 1000
    data = make_transitions(n)
    # (the reopen closed the episode the kill interrupted: its last row's done flags changed)
    keys = ["observation", "action", "achieved_goal", ("next", "observation"), ("next", "reward")]
    assert _rows_equal(st.get(torch.arange(n)).select(*keys), data.select(*keys))
    st.close()


@pytest.mark.parametrize("commit_process", [False, True], ids=["in-process", "worker"])
def test_a_row_rewritten_while_its_complete_chunk_is_copied_reaches_the_disk(tmp_path, monkeypatch, commit_process):
    """Complete chunks past the record are copied after the engine's lock is released
    (``RamMirror.copy_chunk(copy=False)``, then ``copied``): a write that lands during that copy
    marks its chunk dirty again, so the rows on disk after ``flush`` are the newest, not the copy's."""
    from torchrl_robotmem.storage.mirror import RamMirror

    path = tmp_path / "m.zarr"
    # no timer commit in the test's time: the complete chunks are committed on their own, unlocked
    st = ZarrStorage(path, 64, chunk_rows=8, commit_interval=3600.0, commit_process=commit_process)
    if commit_process:
        _wait_for_worker(st)
    rb = ReplayBuffer(storage=st, batch_size=4)
    copied, real = threading.Event(), RamMirror.copied
    newer = make_transitions(1, start=1000)

    def a_write_lands_during_the_copy(snapshot):
        out = real(snapshot)  # the copy holds row 3 as first written ...
        if not copied.is_set():
            rb[3] = newer[0]  # ... and the row changes before the copy reaches the disk
            copied.set()
        return out

    monkeypatch.setattr(RamMirror, "copied", staticmethod(a_write_lands_during_the_copy))
    rb.extend(make_transitions(20))  # chunks 0 and 1 complete, chunk 2 not
    assert copied.wait(120), "the complete chunks were never committed on their own"
    st.flush()
    st.close()
    expected = make_transitions(20)
    expected[3] = newer[0]
    group = zarr.open_group(path, mode="r")  # the chunks themselves (a reopen would map the sealed row file)
    for key, value in expected.items(True, True):
        column = key if isinstance(key, str) else "/".join(key)
        assert (torch.from_numpy(group[column][:20]) == value).all(), column


def test_a_complete_chunk_holding_committed_rows_is_copied_under_the_lock(tmp_path, monkeypatch):
    """Found by a review: a chunk some of whose rows a record already covers (a timer commit of the chunk
    half full, then the rest written) was copied after the lock too, so an in-place write of its committed rows
    landing during the copy reached the disk half-done, without the journal, under the old record."""
    import torchrl_robotmem.storage.commit as commit_module
    from torchrl_robotmem.storage.mirror import RamMirror

    path = tmp_path / "m.zarr"
    st = ZarrStorage(path, 64, chunk_rows=8, commit_interval=3600.0, commit_process=False)
    rb = ReplayBuffer(storage=st, batch_size=4)
    rb.extend(make_transitions(5))
    st.flush()  # the record covers rows 0-4 of chunk 0
    real_commit, chunk_written = commit_module.commit_protocol, threading.Event()

    def overtaken(snapshot):  # the memcpy, with one in-place write of rows 1 and 3 landing half-way through
        packed, layout = snapshot
        out = torch.empty(packed.shape, dtype=packed.dtype)
        out[:2] = packed[:2]
        rb[torch.tensor([1, 3])] = make_transitions(2, start=1000)
        out[2:] = packed[2:]
        return out, layout

    def seen(group, arrays, write, payload, meta, **kwargs):
        real_commit(group, arrays, write, payload, meta, **kwargs)
        if meta is None:
            chunk_written.set()

    monkeypatch.setattr(RamMirror, "copied", staticmethod(overtaken))
    monkeypatch.setattr(commit_module, "commit_protocol", seen)
    rb.extend(make_transitions(3, start=5))  # chunk 0 complete: committed on its own, without a record
    assert chunk_written.wait(120), "the complete chunk was never committed on its own"
    on_disk = zarr.open_group(path, mode="r")["observation"][:5]  # the record still names 5 rows, as before
    assert (torch.from_numpy(on_disk) == make_transitions(5)["observation"]).all()
    st.close()
