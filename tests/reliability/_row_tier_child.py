"""The child processes of ``test_row_tier_faults.py``: writers and readers of a store's row file.

Run with ``runpy.run_path(__file__, init_globals={"ARGS": {...}}, run_name=CHILD_RUN_NAME)`` from the
forkserver of :func:`._gen.writer_context` (torch, torchrl, zarr and the library are loaded already).
``ARGS["scenario"]`` names what the child does; it reports on ``ARGS["conn"]`` (a ``Pipe`` end) as it
goes, and writes its traceback to ``ARGS["err_file"]`` if it fails.

Where a child kills itself (SIGKILL) with rows written past its last commit, it holds its commit
engine's condition (``storage._engine.cv``, reentrant) from before those writes until the kill: the
background commit thread cannot take a commit then, so the committed rows are exactly the ones a returned
``flush()`` made durable, by construction (no timing).
"""
from __future__ import annotations

import hashlib
import os
import random
import runpy
import signal
import traceback

import torch

CHILD_RUN_NAME = "__robotmem_row_tier_child__"
ENV = "FetchPush-v4"


_MAKE_ROWS = []


def make_rows(w):
    """``_gen.make_rows`` (loaded from its file once: this one runs outside the test package)."""
    if not _MAKE_ROWS:
        _MAKE_ROWS.append(runpy.run_path(os.path.join(os.path.dirname(os.path.abspath(__file__)), "_gen.py"))["make_rows"])
    return _MAKE_ROWS[0](w)


def _kill_self() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _buffer(st):
    from torchrl.data import TensorDictReplayBuffer

    return TensorDictReplayBuffer(storage=st, batch_size=4)


def ring_overwrite_kill(path, conn, extra, overwrite, **_):
    """Test 1: opens a sealed ring, overwrites ``extra`` rows and flushes, overwrites ``overwrite`` more
    rows without a commit (in the mapped file), and kills itself."""
    from torchrl_robotmem import ZarrStorage

    st = ZarrStorage(path, commit_interval=3600, env=ENV)
    rb = _buffer(st)
    w = int(rb.writer._write_count)
    conn.send({"opened_at": w, "rows": st.row_file, "sealed_at_open": st.row_file["sealed"],
               "seal_left": os.path.exists(os.path.join(path, "_rows", "seal.json"))})
    rb.extend(make_rows(torch.arange(w, w + extra)))
    st.flush()
    w += extra
    with st._engine.cv:  # no commit from here on (see the module docstring)
        rb.extend(make_rows(torch.arange(w, w + overwrite)))
        conn.send({"flushed": w, "written": w + overwrite, "rows": st.row_file})
        _kill_self()


def fresh_writer_kill(path, conn, flushes, batch, tail, **_):
    """Test 2: writes a new store, ``flushes`` batches each made durable, ``tail`` rows more, then kills itself."""
    from torchrl_robotmem import ZarrStorage

    st = ZarrStorage(path, 1000, chunk_rows=64, commit_interval=3600, env=ENV)
    rb = _buffer(st)
    w = 0
    for _ in range(flushes):
        rb.extend(make_rows(torch.arange(w, w + batch)))
        st.flush()
        w += batch
    with st._engine.cv:
        rb.extend(make_rows(torch.arange(w, w + tail)))
        conn.send({"flushed": w, "written": w + tail, "rows": st.row_file})
        _kill_self()


def fill_kill(path, conn, read_only, cache, **_):
    """Test 2: opens a store with no row file; killed right after the rows were filled from the chunks."""
    from torchrl_robotmem import ZarrStorage
    from torchrl_robotmem.storage import mirror

    os.environ["TORCHRL_ROBOTMEM_CACHE"] = cache
    load = mirror.RamMirror.load

    def load_then_die(self, *args, **kwargs):
        out = load(self, *args, **kwargs)
        rows = self.rows.describe() if self.rows is not None else None
        conn.send({"filled": True, "rows": rows, "cache": sorted(os.listdir(cache))})
        _kill_self()
        return out

    mirror.RamMirror.load = load_then_die
    ZarrStorage(path, read_only=read_only, env=None if read_only else ENV)
    conn.send({"filled": False})  # never reached when the open fills the rows


def background_fill_kill(path, conn, cache, rows, **_):
    """Opens a store with no row file as a reader that fills in the background; reads some rows, then is
    killed with the fill under way or done (whichever: both must leave nothing behind)."""
    from torchrl_robotmem import ZarrStorage

    os.environ["TORCHRL_ROBOTMEM_CACHE"] = cache
    os.environ["TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES"] = "0"
    st = ZarrStorage(path, read_only=True)
    background = st._store.mirror.fill is not None
    got = st.get(torch.tensor(rows))
    conn.send({"background": background, "obs": got["observation"][:, 0].tolist(), "cache": sorted(os.listdir(cache))})
    _kill_self()


def writer_background_fill_kill(path, conn, rewrite, appended, **_):
    """Opens a store with no row file as its writer, the rows filled in the background; rewrites rows
    ``rewrite`` in place and appends ``appended`` rows (``make_rows`` of the write numbers after the
    store's), flushes, then is killed with the fill under way or done (whichever)."""
    from torchrl.data import TensorDictReplayBuffer

    from torchrl_robotmem import ZarrStorage

    os.environ["TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES"] = "0"
    st = ZarrStorage(path, env=ENV)
    background = st.row_file["background"]
    n = len(st)
    st.set(torch.tensor(rewrite), make_rows(torch.arange(n, n + len(rewrite))), set_cursor=False)
    TensorDictReplayBuffer(storage=st, batch_size=4).extend(make_rows(torch.arange(n + len(rewrite), n + len(rewrite) + appended)))
    st.flush()
    conn.send({"background": background, "len": len(st)})
    _kill_self()


def unbounded_grow_kill(path, conn, flush_at, last, kill_at, **_):
    """Test 3: a memory without a declared capacity grows (``chunk_rows=64``), flushing at ``flush_at``;
    then one extend to ``last`` rows that grows it again, and a kill: after the grown rows were written
    (``kill_at="written"``) or between the arrays' growth and the record's (``"record"``)."""
    from torchrl_robotmem import ZarrStorage

    st = ZarrStorage(path, chunk_rows=64, commit_interval=3600, env=ENV)
    rb = _buffer(st)
    assert st.bounded is False, "ZarrStorage(path) without max_size made a bounded memory"
    w, capacities = 0, [st.capacity]
    for stop in flush_at:
        rb.extend(make_rows(torch.arange(w, stop)))
        st.flush()
        w = stop
        capacities.append(st.capacity)
    conn.send({"flushed": w, "capacities": capacities})
    engine = st._engine
    if kill_at == "record":
        update = engine.update_attrs

        def update_then_die(attrs):
            if "max_size" in attrs:  # the arrays were resized; the record is not written
                conn.send({"killed": "record", "arrays_to": int(attrs["max_size"])})
                _kill_self()
            return update(attrs)

        engine.update_attrs = update_then_die
    with engine.cv:  # (released while the growth's own flush waits: everything before it is committed)
        rb.extend(make_rows(torch.arange(w, last)))
        conn.send({"killed": "written", "capacity": st.capacity, "written": last,
                   "rows": st.row_file})
        _kill_self()


def tail_writer(path, conn, seed, total, **_):
    """Test 4: grows a memory without a declared capacity to ``total`` rows; after each ``flush()``
    sends the rows flushed and waits for the reader's go (it has refreshed: it sees every step, by
    construction); flushes at least once at every capacity; closes and sends ``"closed"``."""
    from torchrl_robotmem import ZarrStorage

    rng = random.Random(seed)
    st = ZarrStorage(path, chunk_rows=64, commit_interval=0.05, env=ENV)
    rb = _buffer(st)
    w, told = 0, None
    while w < total:
        b = min(rng.randint(50, 700), total - w)
        rb.extend(make_rows(torch.arange(w, w + b)))
        w += b
        if rng.random() < 0.7 or w == total or st.capacity != told:
            st.flush()
            told = st.capacity
            conn.send({"flushed": w, "capacity": told})
            conn.recv()  # the reader refreshed
    st.close()
    conn.send({"closed": w})


def ring_writer(path, conn, n, **_):
    """Test 5d: opens a sealed ring writable, writes ``n`` rows (overwriting the oldest), closes."""
    from torchrl_robotmem import ZarrStorage

    st = ZarrStorage(path, commit_interval=3600, env=ENV)
    rb = _buffer(st)
    w = int(rb.writer._write_count)
    conn.send({"opened_at": w, "rows": st.row_file})
    rb.extend(make_rows(torch.arange(w, w + n)))
    st.close()
    conn.send({"closed": w + n})


def _status(pid: int | str = "self") -> dict:
    out = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            k, _, v = line.partition(":")
            if k in ("VmRSS", "RssAnon", "RssFile"):
                out[k] = int(v.split()[0]) * 1024
    return out


def cgroup_reader(path, conn, cgroup, version, rows_bytes, batch, **_):
    """Test 6: moves itself into the memory cgroup ``cgroup``, limits it to what it holds plus a quarter of
    the rows' bytes, opens the store read-only and reads every row in batches; sends a sha256 of them."""
    from torchrl_robotmem import ZarrStorage

    def read(name):
        with open(os.path.join(cgroup, name)) as f:
            return f.read()

    rss = _status()["VmRSS"]
    with open(os.path.join(cgroup, "cgroup.procs"), "w") as f:
        f.write(str(os.getpid()))
    # a process's pages stay charged where they were when it moves: the limit is what the cgroup holds
    # now (this process's new pages) plus a quarter of the rows
    usage = int(read("memory.current" if version == "v2" else "memory.usage_in_bytes"))
    limit = usage + rows_bytes // 4
    with open(os.path.join(cgroup, "memory.max" if version == "v2" else "memory.limit_in_bytes"), "w") as f:
        f.write(str(limit))
    st = ZarrStorage(path, read_only=True)
    rows = st.row_file
    n = len(st)
    digest = hashlib.sha256()
    for a in range(0, n, batch):
        digest.update(st[a:min(a + batch, n)]["image"].numpy().tobytes())
    after = _status()
    if version == "v2":
        events = dict(line.split() for line in read("memory.events").splitlines())
        hits = int(events.get("max", 0))
        peak = int(read("memory.peak")) if os.path.exists(os.path.join(cgroup, "memory.peak")) else None
    else:
        hits = int(read("memory.failcnt"))
        peak = int(read("memory.max_usage_in_bytes"))
    conn.send({"sha256": digest.hexdigest(), "rows": rows, "len": n, "rss_before": rss, "usage_at_move": usage,
               "limit": limit, "limit_hits": hits, "peak": peak, "after": after})
    st.close()


SCENARIOS = {f.__name__: f for f in (ring_overwrite_kill, fresh_writer_kill, fill_kill, background_fill_kill,
                                     writer_background_fill_kill,
                                     unbounded_grow_kill,
                                     tail_writer, ring_writer, cgroup_reader)}


def main(scenario: str, err_file: str, **kwargs) -> None:
    torch.set_num_threads(1)
    try:
        SCENARIOS[scenario](**kwargs)
    except BaseException:
        with open(err_file, "w") as f:
            f.write(traceback.format_exc())
        raise


if __name__ == CHILD_RUN_NAME:
    main(**ARGS)  # noqa: F821 - ARGS is injected by runpy.run_path(init_globals=...)
