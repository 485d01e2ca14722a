"""A writable ZarrStorage loses nothing, however an ordinary process ends, without close().

Every case runs a real child process that extends a buffer and never calls
``close()``; the parent reopens the store and checks that every row whose
``extend`` returned is there, bit-exact. Rows carry their write number, so a
lost, reordered or torn row is caught.
"""
from __future__ import annotations

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

# The child: `extend_batches(rb, n)` writes n batches of BATCH rows whose
# "obs" is the row's write number, and records the number of completed
# extends in a memory-mapped counter after each one (read by the parent after
# the child is gone).
_PRELUDE = textwrap.dedent(
    f"""
    import os, signal, sys, time
    # as launched from a terminal: a shell starts background jobs (`make test &`) with
    # SIGINT ignored, and an ignored signal stays ignored across exec; Ctrl-C must reach
    # the child. Restored here, not by a preexec_fn in the parent: a preexec_fn makes
    # subprocess fork() the whole pytest worker (ENOMEM on a loaded 24 GiB CI box)
    # where it otherwise uses vfork().
    signal.signal(signal.SIGINT, signal.default_int_handler)
    import numpy as np, torch
    from tensordict import TensorDict
    from torchrl.data import ReplayBuffer, TensorDictReplayBuffer
    from torchrl_robotmem import ZarrStorage
    torch.set_num_threads(1)
    PATH, COUNTER = sys.argv[1], sys.argv[2]
    counter = np.memmap(COUNTER, dtype=np.int64, mode="r+", shape=(1,))
    BATCH = {BATCH}

    def batch(i):
        obs = torch.arange(i * BATCH, (i + 1) * BATCH, dtype=torch.float64).unsqueeze(-1)
        done = torch.zeros(BATCH, 1, dtype=torch.bool)
        done[-1] = True
        return TensorDict({{"obs": obs, ("next", "done"): done}}, [BATCH])

    def extend_batches(rb, n, start=0):
        for i in range(start, start + n):
            rb.extend(batch(i))
            counter[0] = i + 1

    def ready():
        print("ready", flush=True)

    def extend_until_signal(rb, start, cap=5000):
        # extends until a signal ends the process (or its handler says stop); bounded, so that
        # no chunk of ONLY_FLUSH_COMMITS ever fills: past `cap` batches it only waits
        i = start
        while i < cap:
            extend_batches(rb, 1, start=i)
            i += 1
        while True:
            time.sleep(0.01)

    # only a flush commits: no timer (an hour), no complete chunk (10**6 rows)
    ONLY_FLUSH_COMMITS = dict(commit_interval=3600, chunk_rows=10**6)
    """
)


def _run_child(tmp_path: Path, body: str, *, signal_after_ready: int | None = None,
               args: tuple[str, ...] = (), timeout: float = 120) -> tuple[subprocess.CompletedProcess, int, Path]:
    path = tmp_path / "m.zarr"
    counter_path = tmp_path / "counter.bin"
    np.memmap(counter_path, dtype=np.int64, mode="w+", shape=(1,))[:] = 0
    script = tmp_path / "child.py"
    script.write_text(_PRELUDE + textwrap.dedent(body))
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, str(script), str(path), str(counter_path), *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            cwd=tmp_path)
    if signal_after_ready is not None:
        line = proc.stdout.readline()
        assert line.strip() == "ready", f"child did not start: {line!r} {proc.stderr.read()}"
        # inside the extend loop: wait until it has completed three more extends (an event, not a time)
        counter = np.memmap(counter_path, dtype=np.int64, mode="r", shape=(1,))
        at_ready, deadline = int(counter[0]), time.monotonic() + 120
        while int(counter[0]) < at_ready + 3:
            assert proc.poll() is None and time.monotonic() < deadline, "the child stopped extending"
            time.sleep(0.005)
        proc.send_signal(signal_after_ready)
    out, err = proc.communicate(timeout=timeout)
    completed = int(np.memmap(counter_path, dtype=np.int64, mode="r", shape=(1,))[0])
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err), completed, path


def _check_rows(path: Path, completed: int, *, at_most_one_more: bool = False) -> int:
    """Every row of every completed extend is in the store, bit-exact; returns len."""
    s = ZarrStorage(path, read_only=True)
    n = len(s)
    assert n % BATCH == 0, f"a torn batch: {n} rows"
    assert n >= completed * BATCH, f"lost rows: {n} in the store, {completed * BATCH} extended"
    if at_most_one_more:  # an extend in flight when the process was stopped may have landed
        assert n <= (completed + 1) * BATCH
    else:
        assert n == completed * BATCH
    expected = torch.arange(n, dtype=torch.float64).unsqueeze(-1)
    assert torch.equal(s["obs"][:n], expected)
    return n


def test_end_of_script(tmp_path):
    res, completed, path = _run_child(tmp_path, """
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10_000), batch_size=4)
        extend_batches(rb, 5)
    """)
    assert res.returncode == 0, res.stderr
    assert completed == 5
    _check_rows(path, completed)


def test_sys_exit(tmp_path):
    res, completed, path = _run_child(tmp_path, """
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10_000), batch_size=4)
        extend_batches(rb, 3)
        sys.exit(3)
    """)
    assert res.returncode == 3, res.stderr
    _check_rows(path, completed)
    assert completed == 3


def test_return_from_the_function_that_owned_the_buffer(tmp_path):
    # The buffer and its storage reference each other: only the cycle
    # collector (or the exit hook) ends them.
    res, completed, path = _run_child(tmp_path, """
        def train():
            rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10_000), batch_size=4)
            extend_batches(rb, 4)
        train()
        import gc; gc.collect()
        time.sleep(0.2)  # the script goes on with something else, then ends
    """)
    assert res.returncode == 0, res.stderr
    assert completed == 4
    assert "torchrl_robotmem:" not in res.stderr, res.stderr  # no child reported a flush it could not make
    _check_rows(path, completed)


def test_uncaught_exception(tmp_path):
    res, completed, path = _run_child(tmp_path, """
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10_000), batch_size=4)
        extend_batches(rb, 4)
        raise RuntimeError("training diverged")
    """)
    assert res.returncode == 1 and "training diverged" in res.stderr
    assert "could not flush" not in res.stderr
    _check_rows(path, completed)
    assert completed == 4


def test_prefetching_buffer_and_ring_wrap(tmp_path):
    """prefetch=3 samples from threads (as TorchRL's sota SAC does); the ring wraps (journal path)."""
    res, completed, path = _run_child(tmp_path, """
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 1_000, chunk_rows=256), batch_size=32, prefetch=3)
        extend_batches(rb, 3)
        for _ in range(5):
            rb.sample()
        extend_batches(rb, 10, start=3)   # wraps around 1000 slots
        rb.sample()
    """)
    assert res.returncode == 0, res.stderr
    assert completed == 13
    s = ZarrStorage(path, read_only=True)
    assert len(s) == 1_000
    # the ring holds write numbers 300..1299 at slot (write number % 1000)
    expected = torch.arange(300, 1300, dtype=torch.float64)
    slots = expected.long() % 1000
    assert torch.equal(s["obs"][slots].squeeze(-1), expected)


def test_hydra_main_returning(tmp_path):
    res, completed, path = _run_child(tmp_path, """
        import hydra
        from omegaconf import DictConfig

        @hydra.main(version_base="1.3", config_path=None, config_name=None)
        def main(cfg: DictConfig) -> None:
            rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10_000), batch_size=4)
            extend_batches(rb, 2)

        sys.argv = sys.argv[:1] + ["hydra.run.dir=" + os.getcwd() + "/outputs"]
        main()
    """)
    assert res.returncode == 0, res.stderr
    assert completed == 2
    _check_rows(path, completed)


def test_sigterm_in_a_tight_extend_loop(tmp_path):
    """What SLURM / Kubernetes send before preemption: flush, then die by SIGTERM as before.

    Only a flush commits in this child: without the handler's flush the store would hold 0 rows.
    """
    res, completed, path = _run_child(tmp_path, """
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10**6, **ONLY_FLUSH_COMMITS), batch_size=4)
        extend_batches(rb, 2)
        ready()
        extend_until_signal(rb, 2)
    """, signal_after_ready=signal.SIGTERM)
    assert res.returncode == -signal.SIGTERM, res.stderr  # the default action still happens
    assert completed > 2
    _check_rows(path, completed, at_most_one_more=True)


def test_sigterm_chains_to_the_previous_handler(tmp_path):
    """A handler installed before the store opened still runs (and may keep the process alive)."""
    res, completed, path = _run_child(tmp_path, """
        stop = []
        # runs right after the storage's flush: len(rb) is what that flush had to make durable
        signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(len(rb)))
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10**6, **ONLY_FLUSH_COMMITS), batch_size=4)
        extend_batches(rb, 2)
        ready()
        i = 2
        while not stop:
            if i < 5000:
                extend_batches(rb, 1, start=i)
                i += 1
            else:
                time.sleep(0.01)
        # the handler ran, and the store was already flushed when it did: every row extended
        # before it (only a flush commits here)
        print("stopped", len(ZarrStorage(PATH, read_only=True)), stop[0], flush=True)
        extend_batches(rb, 1, start=i)    # still writable afterwards
    """, signal_after_ready=signal.SIGTERM)
    assert res.returncode == 0, res.stderr
    stopped = [line.split()[1:] for line in res.stdout.splitlines() if line.startswith("stopped")]
    assert len(stopped) == 1 and stopped[0][0] == stopped[0][1], res.stdout
    assert int(stopped[0][0]) >= 5 * BATCH  # 2 before ready, 3 more before the signal was sent
    _check_rows(path, completed)


def test_ctrl_c_in_a_tight_extend_loop(tmp_path):
    """Only a flush commits in this child: the exit hook's flush is what keeps the rows."""
    res, completed, path = _run_child(tmp_path, """
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10**6, **ONLY_FLUSH_COMMITS), batch_size=4)
        extend_batches(rb, 2)
        ready()
        extend_until_signal(rb, 2)
    """, signal_after_ready=signal.SIGINT)
    # Python ends an uncaught KeyboardInterrupt by re-raising SIGINT after its normal exit path;
    # with ray installed (torchrl.envs imports it), the process exits with status 1 instead
    assert res.returncode in (-signal.SIGINT, 1) and "KeyboardInterrupt" in res.stderr, res.stderr
    assert completed > 2
    # an interrupt is handled between writes: the extend in flight either
    # landed whole or not at all
    _check_rows(path, completed, at_most_one_more=True)


def test_second_writer_process_is_refused_and_a_reader_process_follows(tmp_path):
    """Two processes never write one store; a read_only process sees only committed rows."""
    path = tmp_path / "m.zarr"
    counter_path = tmp_path / "counter.bin"
    np.memmap(counter_path, dtype=np.int64, mode="w+", shape=(1,))[:] = 0
    script = tmp_path / "writer.py"
    script.write_text(_PRELUDE + textwrap.dedent("""
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10_000_000, commit_interval=0.05), batch_size=4)
        extend_batches(rb, 2)
        rb.storage.flush()
        ready()
        extend_batches(rb, 10**9, start=2)
    """))
    proc = subprocess.Popen([sys.executable, str(script), str(path), str(counter_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
        with pytest.raises(RuntimeError, match="Another process .* is writing"):
            ZarrStorage(path)
        reader = ZarrStorage(path, read_only=True)
        seen = [len(reader)]
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and len(seen) < 4:
            time.sleep(0.1)
            n = reader.refresh()
            if n > seen[-1]:
                seen.append(n)
        assert len(seen) >= 4, f"the reader saw no new commits: {seen}"
        for n in seen:
            assert n % BATCH == 0
        n = len(reader)
        assert torch.equal(reader["obs"][:n], torch.arange(n, dtype=torch.float64).unsqueeze(-1))
    finally:
        proc.terminate()
        proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGTERM
    completed = int(np.memmap(counter_path, dtype=np.int64, mode="r", shape=(1,))[0])
    _check_rows(path, completed, at_most_one_more=True)
    ZarrStorage(path).close()  # the writer's lock died with it


def test_exit_hook_reports_a_commit_it_cannot_make(tmp_path):
    """The exit path does not swallow errors: a store made unwritable is reported on stderr."""
    res, completed, path = _run_child(tmp_path, """
        import shutil
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10_000), batch_size=4)
        extend_batches(rb, 1)
        rb.storage.flush()
        extend_batches(rb, 1, start=1)
        shutil.rmtree(PATH)                 # the store vanishes under the writer
        open(PATH, "w").write("not a dir")  # and a file stands in its way
    """)
    assert res.returncode == 0, res.stderr
    assert "torchrl_robotmem: could not flush" in res.stderr and "m.zarr" in res.stderr


def test_a_forked_child_exits_reads_and_is_refused_writes_and_the_parent_loses_nothing(tmp_path):
    """A child forked while rows are uncommitted (``multiprocessing`` with fork, DataLoader workers) is not the writer.

    Its exit runs no flush (it used to block for ever on a lock inherited mid-use, and the parent on it), it reads
    the rows it inherited, and a write through the inherited handle is a clear error. Every row stays the
    parent's to commit: they are all in the store after the parent's own exit.
    """
    res, completed, path = _run_child(tmp_path, """
        import multiprocessing as mp
        from torchrl_robotmem.samplers import PersistentPrioritizedSampler
        rb = TensorDictReplayBuffer(storage=ZarrStorage(PATH, 10_000, **ONLY_FLUSH_COMMITS), batch_size=4,
                                    sampler=PersistentPrioritizedSampler())
        extend_batches(rb, 3)  # uncommitted: only a flush commits
        rb.update_priority(torch.arange(10), torch.full((10,), 5.0))  # unwritten priorities too

        def child(mode):
            if mode == "read":
                assert rb.storage[250]["obs"].item() == 250.0
            elif mode == "write":
                try:
                    extend_batches(rb, 1, start=3)
                except RuntimeError as err:
                    print("refused:", err, flush=True)
                    sys.exit(7)
            elif mode == "flush":
                try:
                    rb.storage.flush()
                except RuntimeError as err:
                    print("refused:", err, flush=True)
                    sys.exit(8)

        for mode in ("exit", "read", "write", "flush"):
            p = mp.get_context("fork").Process(target=child, args=(mode,))
            p.start()
            p.join(60)  # the child's exit is what is tested: a hang is a failure, not a wait
            print(mode, p.exitcode, flush=True)
            if p.exitcode is None:
                p.kill()
        extend_batches(rb, 1, start=3)  # the parent is still the writer
    """)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert [ln for ln in lines if not ln.startswith("refused")] == ["exit 0", "read 0", "write 7", "flush 8"]
    refusals = [ln for ln in lines if ln.startswith("refused")]
    assert len(refusals) == 2 and all("is a forked child of it" in r and "read_only=True" in r for r in refusals)
    assert completed == 4
    assert "torchrl_robotmem:" not in res.stderr, res.stderr  # no child reported a flush it could not make
    _check_rows(path, completed)


def test_a_writer_collected_inside_another_store_s_zarr_io_is_closed_without_a_deadlock(tmp_path):
    """Found in TorchRL's own test suite with ZarrStorage swapped in: a writer left in a reference cycle was
    collected by the garbage collector while another store's open waited on Zarr's event loop, inside
    ``concurrent.futures.wait``, which holds the lock of the future that loop must take. Its ``__del__`` closed
    it there, and the close's own Zarr call waited on the blocked loop for ever. Made to happen exactly there:
    a profile hook on that wait runs the collection once Zarr's loop thread is blocked on the lock. The
    writer is closed all the same, its rows committed (before: the process hung)."""
    first, second = tmp_path / "cycle.zarr", tmp_path / "other.zarr"
    code = textwrap.dedent(f"""
        import concurrent.futures._base as futures, gc, sys, threading, time, torch, weakref
        from tensordict import TensorDict
        from torchrl_robotmem import ZarrStorage
        rows = TensorDict({{"obs": torch.arange(10.0)}}, [10])
        a = ZarrStorage({str(first)!r}, 100, goal_conditioned=False, env="E")
        a.set(torch.arange(10), rows)
        a.flush()
        while any(t.name.startswith("ZarrStorage-writer") for t in threading.enumerate()):
            time.sleep(0.01)  # its commit thread goes once idle: nothing but the cycle holds the storage
        a.cycle, gone = a, weakref.ref(a)
        gc.disable()
        del a

        def loop_waits_on_us():  # Zarr's loop thread blocked on the lock of a future this thread holds
            me = threading.get_ident()
            return any(tid != me and f.f_code.co_name == "__enter__" and f.f_back is not None
                       and f.f_back.f_code.co_filename == futures.__file__
                       for tid, f in sys._current_frames().items())

        fired = []

        def collect_in_the_wait(frame, event, arg):
            if event == "call" and frame.f_code.co_filename == futures.__file__ and frame.f_code.co_name == "<genexpr>":
                sys.setprofile(None)
                fired.append(True)
                while not loop_waits_on_us():
                    time.sleep(0.001)
                gc.collect()
                print("COLLECTED", gone() is None, flush=True)

        # the hook fires in a wait that finds its future not done yet (concurrent.futures.wait counts the
        # pending ones in that genexpr); on a loaded box every wait of one open can find its future done
        # already: the store is opened again until one waits
        for attempt in range(500):
            sys.setprofile(collect_in_the_wait)
            b = ZarrStorage({str(second)!r}, 100, goal_conditioned=False, env="E")  # its open waits on Zarr's loop
            sys.setprofile(None)
            if fired:
                break
            b.close()
        gc.enable()
        b.set(torch.arange(5), rows[:5])
        b.close()
        print("DONE", flush=True)
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:  # the deadlock: SIGTERM would wait on it too
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"the process hung (deadlock):\n{out}\n{err[-3000:]}")
    assert proc.returncode == 0 and "COLLECTED True" in out and "DONE" in out, out + err
    with ZarrStorage(first, read_only=True) as st:
        assert st["obs"].tolist() == list(range(10))
    with ZarrStorage(second, read_only=True) as st:
        assert len(st) == 5
