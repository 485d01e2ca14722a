"""The commit worker fails, the disk fills: nothing the writer process still holds is lost.

Real writer processes, a real commit worker process killed (SIGKILL) or
stopped (SIGSTOP), a writer killed while its worker is stopped (an orphan that
holds the lock), a real file-size limit (``RLIMIT_FSIZE``: what a full disk
looks like to a writer) lifted again in the same process. Each child writes
rows whose ``obs`` is the row's write number and whose ``noise`` is a seeded
function of it (incompressible), so a lost, reordered or torn row is caught.
The tests wait for events (a file the test writes, a line the child prints, a
process state in ``/proc``, a process exit); nothing is timed.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from torchrl_robotmem import ZarrStorage

BATCH = 100

_PRELUDE = textwrap.dedent(
    f"""
    import json, os, resource, signal, sys, time, warnings
    import numpy as np, torch
    from tensordict import TensorDict
    from torchrl.data import TensorDictReplayBuffer
    from torchrl_robotmem import ZarrStorage
    from torchrl_robotmem.storage._commit_worker import CommitWorker
    torch.set_num_threads(1)
    PATH, DIR, MODE = sys.argv[1], sys.argv[2], sys.argv[3]
    counter = np.memmap(os.path.join(DIR, "counter.bin"), dtype=np.int64, mode="r+", shape=(1,))
    BATCH = {BATCH}

    caught = []
    warnings.simplefilter("always")
    _show = warnings.showwarning
    def _record(message, category, *args, **kwargs):
        caught.append(str(message))
        _show(message, category, *args, **kwargs)
    warnings.showwarning = _record

    def batch(i):
        w = torch.arange(i * BATCH, (i + 1) * BATCH)
        noise = torch.randn(BATCH, 8, generator=torch.Generator().manual_seed(i))
        return TensorDict({{"obs": w.double().unsqueeze(-1), "noise": noise}}, [BATCH])

    def wait_file(name, timeout=300):
        deadline = time.monotonic() + timeout
        while not os.path.exists(os.path.join(DIR, name)):
            assert time.monotonic() < deadline, "the test never wrote " + name
            time.sleep(0.01)

    def committed_len():
        with open(os.path.join(PATH, "zarr.json")) as f:
            return int(json.load(f)["attributes"]["len"])

    def open_with_worker(**kw):
        st = ZarrStorage(PATH, **kw)
        deadline = time.monotonic() + 120
        while not st._engine._use_worker():
            assert time.monotonic() < deadline, "the commit worker never became ready"
            time.sleep(0.02)
        return st

    def worker_warnings():
        return [w for w in caught if "commit worker" in w]
    """
)


def _start(tmp_path: Path, body: str, mode: str = "", env: dict | None = None) -> tuple[subprocess.Popen, Path]:
    path = tmp_path / "m.zarr"
    np.memmap(tmp_path / "counter.bin", dtype=np.int64, mode="w+", shape=(1,))[:] = 0
    script = tmp_path / "child.py"
    script.write_text(_PRELUDE + textwrap.dedent(body))
    proc = subprocess.Popen([sys.executable, str(script), str(path), str(tmp_path), mode],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
    return proc, path


def _line(proc: subprocess.Popen, prefix: str) -> str:
    """The child's next stdout line, which must start with ``prefix``."""
    line = proc.stdout.readline()
    if not line.startswith(prefix):
        proc.kill()
        out, err = proc.communicate(timeout=60)
        pytest.fail(f"expected {prefix!r} from the child, got {line!r}\n{out}\n{err}")
    return line[len(prefix):].strip()


def _state(pid: int) -> str | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None


def _wait_state(pid: int, states: tuple, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while _state(pid) not in states:
        assert time.monotonic() < deadline, f"process {pid} never reached state {states}: {_state(pid)}"
        time.sleep(0.01)


def _touch(tmp_path: Path, name: str) -> None:
    (tmp_path / name).write_text("")


def _expected(n_batches: int) -> tuple[torch.Tensor, torch.Tensor]:
    obs = torch.arange(n_batches * BATCH, dtype=torch.float64).unsqueeze(-1)
    noise = torch.cat([torch.randn(BATCH, 8, generator=torch.Generator().manual_seed(i)) for i in range(n_batches)])
    return obs, noise


def _check_rows(path: Path, n_batches: int) -> None:
    """The store holds exactly ``n_batches`` batches, every row bit-exact."""
    s = ZarrStorage(path, read_only=True)
    assert len(s) == n_batches * BATCH, f"{len(s)} rows in the store, {n_batches * BATCH} extended"
    obs, noise = _expected(n_batches)
    assert torch.equal(s["obs"][: len(s)], obs)
    assert torch.equal(s["noise"][: len(s)], noise)


def _counter(tmp_path: Path) -> int:
    return int(np.memmap(tmp_path / "counter.bin", dtype=np.int64, mode="r", shape=(1,))[0])


def _finish(proc: subprocess.Popen, timeout: float = 240) -> tuple[str, str]:
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate(timeout=60)
        pytest.fail(f"the writer process did not finish within {timeout} s\n{out}\n{err}")


# -- the worker killed --------------------------------------------------------------------------

_KILLED = """
    st = open_with_worker(max_size=1_000_000, chunk_rows=256)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    i = 0
    for _ in range(10):
        rb.extend(batch(i)); i += 1
    st.flush()
    print("worker", CommitWorker._instance.proc.pid, flush=True)
    if MODE == "busy":   # extending while the kill lands (bounded: the ring never wraps)
        while not os.path.exists(os.path.join(DIR, "killed")) and i < 5000:
            rb.extend(batch(i)); i += 1
    wait_file("killed")
    for _ in range(20):  # extends after the worker's death
        rb.extend(batch(i)); i += 1
    # noticed without a flush(): the background writer commits on its own, in-process
    deadline = time.monotonic() + 120
    while committed_len() < i * BATCH:
        assert time.monotonic() < deadline, f"rows never committed: {committed_len()} of {i * BATCH}"
        time.sleep(0.05)
    rb.extend(batch(i)); i += 1
    st.close()
    print("batches", i, flush=True)
    print("warnings", json.dumps(worker_warnings()), flush=True)
"""


@pytest.mark.parametrize("mode", ["busy", "idle"])
def test_a_killed_worker_loses_nothing_the_writer_holds(tmp_path, mode):
    """SIGKILL of the commit worker, while the writer extends and while it is idle."""
    proc, path = _start(tmp_path, _KILLED, mode)
    worker = int(_line(proc, "worker "))
    os.kill(worker, signal.SIGKILL)
    _wait_state(worker, (None, "Z"))  # dead (a zombie until its parent reaps it)
    _touch(tmp_path, "killed")
    batches = int(_line(proc, "batches "))
    warned = json.loads(_line(proc, "warnings "))
    out, err = _finish(proc)
    assert proc.returncode == 0, err
    assert len(warned) == 1, warned  # warned once, naming the worker and the cause
    assert f"pid {worker}" in warned[0] and "SIGKILL" in warned[0], warned[0]
    _check_rows(path, batches)


_STOPPED = """
    st = open_with_worker(max_size=1_000_000, chunk_rows=256)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    i = 0
    for _ in range(10):
        rb.extend(batch(i)); i += 1
    st.flush()
    print("worker", CommitWorker._instance.proc.pid, flush=True)
    wait_file("stopped")
    for _ in range(20):
        rb.extend(batch(i)); i += 1
    st.flush()  # returns: the silent worker is killed after its reply deadline
    print("batches", i, flush=True)
    wait_file("checked")
    rb.extend(batch(i)); i += 1
    st.close()
    print("batches", i, flush=True)
    print("warnings", json.dumps(worker_warnings()), flush=True)
"""


def test_a_stopped_worker_is_killed_after_its_deadline_and_flush_returns(tmp_path):
    """SIGSTOP of the commit worker: flush() returns (a bounded reply deadline), every row lands."""
    proc, path = _start(tmp_path, _STOPPED, env={"TORCHRL_ROBOTMEM_WORKER_TIMEOUT": "2"})
    worker = int(_line(proc, "worker "))
    os.kill(worker, signal.SIGSTOP)
    _wait_state(worker, ("T", "t"))
    _touch(tmp_path, "stopped")
    flushed = int(_line(proc, "batches "))
    # the flush that returned made everything durable (the worker has been killed by then)
    assert _state(worker) in (None, "Z")
    _check_rows(path, flushed)
    _touch(tmp_path, "checked")
    batches = int(_line(proc, "batches "))
    warned = json.loads(_line(proc, "warnings "))
    out, err = _finish(proc)
    assert proc.returncode == 0, err
    assert len(warned) == 1 and f"pid {worker}" in warned[0] and "did not answer" in warned[0], warned
    _check_rows(path, batches)


_ENDING = """
    # commits only on flush: no timer (an hour), no complete chunk (1,000 rows of 100,000)
    st = open_with_worker(max_size=200_000, chunk_rows=100_000, commit_interval=3600)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    i = 0
    for _ in range(10):
        rb.extend(batch(i)); i += 1
        counter[0] = i
    st.flush()
    print("worker", CommitWorker._instance.proc.pid, flush=True)
    wait_file("stopped")
    if MODE == "sigterm":
        while True:  # extending until SIGTERM arrives (bounded: then it only waits)
            if i < 900:
                rb.extend(batch(i)); i += 1
                counter[0] = i
            else:
                time.sleep(0.01)
    for _ in range(20):
        rb.extend(batch(i)); i += 1
        counter[0] = i
    # the script ends with the worker stopped
"""


@pytest.mark.parametrize("how", ["sigterm", "exit"])
def test_sigterm_and_exit_with_a_stopped_worker_finish_and_keep_every_row(tmp_path, how):
    """The process ends (SIGTERM, end of script) while its worker is stopped: it ends, nothing lost.

    The bound docs/storage.md states is the reply deadline (5 s here) plus one in-process
    commit; the test only waits for the exit (generously), it times nothing.
    """
    proc, path = _start(tmp_path, _ENDING, how)
    worker = int(_line(proc, "worker "))
    os.kill(worker, signal.SIGSTOP)
    _wait_state(worker, ("T", "t"))
    _touch(tmp_path, "stopped")
    if how == "sigterm":
        deadline = time.monotonic() + 120
        while _counter(tmp_path) < 30:  # the child is extending after the stop
            assert time.monotonic() < deadline and proc.poll() is None, "the writer stopped extending"
            time.sleep(0.01)
        proc.send_signal(signal.SIGTERM)
    out, err = _finish(proc, timeout=120)
    completed = _counter(tmp_path)
    if how == "sigterm":
        assert proc.returncode == -signal.SIGTERM, err
        n = len(ZarrStorage(path, read_only=True)) // BATCH
        assert completed <= n <= completed + 1, (n, completed)  # an extend in flight may have landed
        _check_rows(path, n)
    else:
        assert proc.returncode == 0, err
        assert completed == 30
        _check_rows(path, completed)
    assert "did not answer" in err  # the warning, on stderr
    _wait_state(worker, (None, "Z"))


# -- the writer killed while its worker is stopped: an orphan holds the lock ------------------------

_HOLDER = """
    st = open_with_worker(max_size=10_000, chunk_rows=256)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    for i in range(10):
        rb.extend(batch(i))
    st.flush()
    print("worker", CommitWorker._instance.proc.pid, flush=True)
    while True:
        time.sleep(1)
"""


def test_the_lock_error_names_the_writer_and_its_worker(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_ROBOTMEM_LOCK_WAIT", "0.2")
    proc, path = _start(tmp_path, _HOLDER)
    try:
        worker = int(_line(proc, "worker "))
        with pytest.raises(RuntimeError, match="Another process .* is writing") as err:
            ZarrStorage(path)
        assert f"pid {proc.pid}:" in str(err.value), str(err.value)
        assert f"pid {worker}: the commit worker of writer pid {proc.pid} (alive)" in str(err.value)
        assert proc.poll() is None and _state(worker) not in (None, "Z")  # nobody was killed
    finally:
        proc.kill()
        proc.communicate(timeout=60)


def test_an_orphaned_worker_of_a_dead_writer_is_killed_and_the_lock_taken_over(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_ROBOTMEM_LOCK_WAIT", "0.2")
    proc, path = _start(tmp_path, _HOLDER)
    try:
        worker = int(_line(proc, "worker "))
        os.kill(worker, signal.SIGSTOP)  # it cannot notice its writer's death
        _wait_state(worker, ("T", "t"))
        proc.kill()
        proc.wait(60)  # (not communicate(): the stopped worker still has its stdout open)
        assert _state(worker) in ("T", "t")  # the orphan, still holding the writer lock
        st = ZarrStorage(path)  # takes the lock over
        assert _state(worker) in (None, "Z")
        assert len(st) == 10 * BATCH
        st.close()
        _check_rows(path, 10)
    finally:
        if _state(worker) not in (None, "Z"):
            os.kill(worker, signal.SIGKILL)


# -- a full disk: the rows stay in memory, and are written once there is room -----------------------

_DISK_FULL = """
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
    worker = MODE.startswith("worker")
    # one chunk for every row and no commit timer: the only commits are the explicit flushes, so
    # no background commit can fail (and refuse an extend) while the rows are extended
    kw = dict(max_size=10_000, chunk_rows=10_000, commit_interval=3600)
    st = open_with_worker(**kw) if worker else ZarrStorage(PATH, commit_process=False, **kw)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    for i in range(4):
        rb.extend(batch(i))
    st.flush()

    def limit(n):  # the soft limit: this process may raise it again
        soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.setrlimit(resource.RLIMIT_FSIZE, (n, hard))
        if worker:  # the process that writes the chunks
            resource.prlimit(CommitWorker._instance.proc.pid, resource.RLIMIT_FSIZE, (n, hard))
        return soft

    def attempt(what, fn):
        try:
            fn()
            print(what, "OK", flush=True)
        except Exception as err:
            print(what, "ERROR", type(err).__name__, str(err).replace("\\n", " "), flush=True)
            return err

    unlimited = limit(64)  # the disk is full: no file grows past 64 bytes
    for i in range(4, 8):
        rb.extend(batch(i))
    e1 = attempt("flush", st.flush)
    e2 = attempt("extend", lambda: rb.extend(batch(8)))  # refused: nothing written
    if MODE.endswith("flush"):
        limit(unlimited)  # room again
        attempt("flush", st.flush)
        rb.extend(batch(8))
        st.close()
    elif MODE.endswith("reopen"):
        # the advice, followed literally in the same process, with the error still referenced
        e3 = attempt("reopen", lambda: ZarrStorage(PATH))
        e4 = attempt("reopen", lambda: ZarrStorage(PATH))
        limit(unlimited)
        st2 = ZarrStorage(PATH)
        print("reopened", len(st2), flush=True)
        TensorDictReplayBuffer(storage=st2).extend(batch(8))
        st2.close()
    else:  # close while the disk is still full
        attempt("close", st.close)
        limit(unlimited)
        st3 = ZarrStorage(PATH)
        print("reopened", len(st3), flush=True)
        st3.close()
    print("done", flush=True)
"""


def _outcomes(out: str) -> list[str]:
    return [line for line in out.splitlines() if line.split(" ")[0] in ("flush", "extend", "reopen", "close")]


@pytest.mark.parametrize("path_kind", ["worker", "in_process"])
@pytest.mark.parametrize("then", ["flush", "reopen", "close"])
def test_a_full_disk_keeps_the_rows_until_there_is_room(tmp_path, path_kind, then):
    """RLIMIT_FSIZE: errors say which rows are not durable; once the limit is lifted they land."""
    proc, path = _start(tmp_path, _DISK_FULL, f"{path_kind}-{then}")
    out, err = _finish(proc)
    assert proc.returncode == 0 and "done" in out, out + err
    lines = _outcomes(out)
    not_durable = "400 rows (write numbers 400 to 799, the same storage indices) are not durable"
    assert lines[0].startswith("flush ERROR RuntimeError") and "File too large" in lines[0], lines
    assert not_durable in lines[0] and "call flush()" in lines[0], lines[0]
    assert lines[1].startswith("extend ERROR RuntimeError") and not_durable in lines[1], lines
    if then == "flush":
        assert lines[2:] == ["flush OK"], lines
        _check_rows(path, 9)
    elif then == "reopen":
        # the cause is still there: a clear error, twice (no half-registered handle)
        assert len(lines) == 4, lines
        for line in lines[2:]:
            assert line.startswith("reopen ERROR RuntimeError") and not_durable in line, line
        assert "reopened 800" in out  # the old handle's rows were written at the handover
        _check_rows(path, 9)
    else:
        assert len(lines) == 3 and lines[2].startswith("close ERROR RuntimeError"), lines
        assert "400 rows (write numbers 400 to 799, the same storage indices) could not be written and are lost" \
            in lines[2], lines[2]
        assert "reopened 400" in out
        _check_rows(path, 4)
