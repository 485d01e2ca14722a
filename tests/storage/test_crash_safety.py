"""ZarrStorage crash safety with real SIGKILLs.

A writer process extends a buffer forever with rows whose every column is a
deterministic function of the row's global write number ``w``. The test kills it
with SIGKILL at random moments (while opening the store, replaying a journal,
writing, committing, flushing), reopens the store and checks:

* it opens, and ``len`` / ``write_count`` never go backwards;
* nothing that a returned ``flush()`` made durable is lost;
* every row below ``len`` is bit-exact with what its writer produced, all its
  columns agreeing on one ``w`` (no torn rows), at the position the ring puts it;
* the restored cursor / write count are consistent with the rows, and the next
  writer continues from them (the child checks that ``rb.writer`` was restored);
* the episode interrupted by the kill is closed (its last row is done) and episode
  ids stay monotone in write order, changing exactly after a done row.

Two modes: an append-only store (done-split episodes) and a 300-row ring that wraps
dozens of times (collector ``traj_ids``, journalled overwrites). Writers are forked
from a forkserver with torch/torchrl/zarr preloaded, so a kill cycle takes well under
a second. The schedule is seeded: ``CRASH_SEED`` if set, else ``ROBOTMEM_TEST_SEED``
(default 0), printed and named in every failure; ``CRASH_KILLS`` changes the number of
planned kills per mode (18). After them the loop kills on (bounded) until a third of
them saw committed progress (kills during start-up do not count) and, for the ring, it
has wrapped three times: each extra kill waits for a new commit record on disk first.

The deterministic tests at the end crash the writer at one chosen point each (mid
journalled commit, mid metadata commit, with a commit in flight, with ring rows
ahead of the metadata) and pin the bugs found by the random test.
"""
from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import random
import runpy
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch
import zarr
from conftest import seed_from_env
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem.storage import ZarrStorage
from torchrl_robotmem.storage.integrity import IntegrityError

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="needs fork and SIGKILL")

EPISODE_LEN = 50

# Shared by the writer process (run with runpy) and the checks below (exec'd).
ROWS_SRC = '''
import torch
from tensordict import TensorDict

EPISODE_LEN = 50

def make_rows(w, traj_ids=False):
    """Rows for write numbers ``w`` (int64 [n]); every column is a function of w."""
    w = torch.as_tensor(w, dtype=torch.long)
    n = len(w)
    done = (w % EPISODE_LEN == EPISODE_LEN - 1).unsqueeze(-1)
    td = TensorDict(
        {
            "observation": (w.unsqueeze(-1) + torch.arange(5)).float(),
            "action": torch.stack([-w, w % 7], -1),
            "value": w.double() / 8,
            "flag": (w % 3 == 0).unsqueeze(-1),
            "step_count": (w % EPISODE_LEN).unsqueeze(-1),
            "nested": {"deep": {"x": (w.unsqueeze(-1) * 3 + torch.arange(3)).int()}},
            "next": {
                "observation": (w.unsqueeze(-1) + torch.arange(5) + 1).float(),
                "reward": torch.where(w % 10 == 0, 0.0, -1.0).float().unsqueeze(-1),
                "done": done,
                "truncated": done.clone(),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        [n],
    )
    if traj_ids:
        td["collector", "traj_ids"] = w // EPISODE_LEN
    return td
'''

CHILD_SRC = ROWS_SRC + '''
import random, time, traceback
torch.set_num_threads(1)
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem.storage import ZarrStorage

def child_main(path, max_size, chunk_rows, traj_ids, seed, prog, err_file, pause):
    # prog slots: 0 state (1 opened, 2 first extend returned), 1 write_count at open,
    # 2 len at open, 3 cursor at open, 4 rows written (last extend returned),
    # 5 rows durable (last flush returned)
    try:
        st = ZarrStorage(path, max_size, chunk_rows=chunk_rows, commit_interval=0.05, env="FetchPush-v4")
        rb = TensorDictReplayBuffer(storage=st, batch_size=32)
        w = int(rb.writer._write_count)
        assert w == st.write_count and int(rb.writer._cursor) == st.state_dict()["zarr"]["cursor"], "writer not restored"
        prog[1], prog[2], prog[3] = w, len(st), int(rb.writer._cursor)
        prog[4] = prog[5] = w
        prog[0] = 1
        rng = random.Random(seed * 1_000_003 + w)
        while True:
            b = rng.randint(1, 150)
            rb.extend(make_rows(torch.arange(w, w + b), traj_ids))
            w += b
            prog[4] = w
            prog[0] = 2
            u = rng.random()
            if u < 0.15:
                st.flush()
                prog[5] = w
            elif u < 0.25:
                rb.sample()
            # a rate the background writer can sustain with tiny chunks: otherwise
            # everything written in the last second is still in flight at the kill
            time.sleep(rng.random() * pause)
    except BaseException:
        with open(err_file, "w") as f:
            f.write(traceback.format_exc())
        raise

child_main(**ARGS)
'''

_NS: dict = {}
exec(ROWS_SRC, _NS)
make_rows = _NS["make_rows"]

_CTX = None


def _ctx():
    """A forkserver with torch/torchrl/zarr preloaded: a writer starts in ms, not seconds."""
    global _CTX
    if _CTX is None:
        _CTX = mp.get_context("forkserver")
        _CTX.set_forkserver_preload(
            ["torch", "tensordict", "torchrl.data", "zarr", "torchrl_robotmem.storage"]
        )
    return _CTX


def _leftover_partials(path: Path) -> int:
    return sum(1 for _ in path.rglob("*.partial"))


class Tracker:
    """What the store must satisfy at each reopen, accumulated over kills."""

    def __init__(self, path: Path, max_size: int, traj_ids: bool):
        self.path, self.max_size, self.traj_ids = path, max_size, traj_ids
        self.ring = False  # becomes True once the store has wrapped
        self.last_len = 0
        self.last_w = 0
        self.durable_w = 0  # rows a returned flush() guaranteed
        self.forced_done: set[int] = set()  # write numbers whose episode a reopen closed
        self.pending_journals = 0

    def reopen_and_check(self) -> int:
        attrs = zarr.open_group(self.path, mode="r").attrs.asdict()
        self.pending_journals += bool(attrs.get("journal"))
        # a reader (no lock, no writes) must see what the writer will restore
        ro = ZarrStorage(self.path, read_only=True)
        ro_state = (len(ro), ro.write_count, ro.state_dict()["zarr"]["cursor"])
        ro_rows = ro[: len(ro)] if len(ro) else None
        ro.close()
        st = ZarrStorage(self.path)  # writable: replays a journal, closes open episodes
        try:
            rb = TensorDictReplayBuffer(storage=st, batch_size=8)
            n, w_count, cursor = len(st), st.write_count, st.state_dict()["zarr"]["cursor"]
            assert int(rb.writer._write_count) == w_count and int(rb.writer._cursor) == cursor
            assert n >= self.last_len, f"len went backwards: {self.last_len} -> {n}"
            assert w_count >= self.last_w, f"write_count went backwards: {self.last_w} -> {w_count}"
            assert w_count >= self.durable_w, (
                f"rows that a returned flush() made durable were lost: write_count {w_count} "
                f"< {self.durable_w}"
            )
            M = self.max_size
            assert n == min(w_count, M) and cursor == w_count % M, (
                f"len {n}, cursor {cursor} disagree with write_count {w_count} (max_size {M}); "
                f"stored attributes before reopen: { {k: attrs.get(k) for k in ('len', 'cursor', 'write_count', 'journal')} }"
            )
            self.last_len, self.last_w = n, w_count
            assert ro_state == (n, w_count, cursor), f"read_only open saw {ro_state}, writer {(n, w_count, cursor)}"
            if n:
                self._check_rows(st, n, w_count)
                td = st[:n]
                for key in ro_rows.keys(True, True):
                    diff = (ro_rows.get(key) != td.get(key)).reshape(n, -1).any(-1)
                    if key in (("next", "done"), ("next", "truncated")):  # the writer closed an episode
                        diff[(w_count - 1) % self.max_size] = False
                    assert not diff.any(), f"read_only open disagrees on {key} at rows {diff.nonzero()[:5].tolist()}"
            return w_count
        finally:
            st.close()

    def _check_rows(self, st: ZarrStorage, n: int, W: int) -> None:
        M = self.max_size
        td = st[:n].update({k: st[k][:n] for k in ("episode", "run", "env")})  # tags are columns
        w = -td["action"][:, 0]
        r = torch.arange(n)
        # Slot r holds the last write number < W that maps to it: no torn rows, no rows
        # newer than the committed metadata, no mixed laps.
        W_t = max(W, int(w.max()) + 1)
        assert W_t == W, (
            f"slots hold write numbers up to {W_t - 1} but the committed write_count is {W} "
            f"(max_size {M}): rows are newer than the metadata"
        )
        expected = W - 1 - ((W - 1 - r) % M)
        bad = (w != expected).nonzero().squeeze(-1)
        assert len(bad) == 0, (
            f"rows {bad[:10].tolist()} hold write numbers {w[bad[:10]].tolist()}, expected "
            f"{expected[bad[:10]].tolist()} (write_count {W}, max_size {M})"
        )
        if W > M:
            self.ring = True
        # the episode interrupted by the kill is closed at reopen
        last = (W - 1) % M
        assert bool(td["next", "done"][last]), f"episode of the last row (w={W - 1}) was left open"
        assert bool(td["next", "truncated"][last])
        if (W - 1) % EPISODE_LEN != EPISODE_LEN - 1:
            self.forced_done.add(W - 1)
        # bit-exact: every column agrees with the write number in the action column
        ref = make_rows(w, self.traj_ids)
        forced = torch.tensor([int(x) in self.forced_done for x in w.tolist()])
        natural = ref["next", "done"].squeeze(-1)
        got_done = td["next", "done"].squeeze(-1)
        for key in ref.keys(True, True):
            if key in (("next", "done"), ("next", "truncated")):
                continue
            a, b = td.get(key), ref.get(key)
            assert a.dtype == b.dtype and a.shape == b.shape, key
            mism = (a != b).reshape(n, -1).any(-1)
            assert not mism.any(), f"torn/corrupt rows in {key}: {mism.nonzero()[:10].squeeze(-1).tolist()}"
        for key in (("next", "done"), ("next", "truncated")):
            got = td.get(key).squeeze(-1)
            extra = got & ~natural
            # only rows whose episode a reopen closed
            assert not (extra & ~forced).any(), (
                f"{key} is set on rows that end no episode (write numbers "
                f"{w[extra & ~forced][:10].tolist()}): a reopen closed an episode that was not open"
            )
            assert not (natural & ~got).any(), f"{key} lost on rows {w[natural & ~got][:10].tolist()}"
        # tags: episode ids monotone in write order, new exactly after a done row;
        # run ids monotone; env tagged
        order = torch.argsort(w)
        ep, run = td["episode"][order], td["run"][order]
        done_prev = got_done[order][:-1]
        assert (torch.diff(run) >= 0).all()
        step = torch.diff(ep)
        assert (step >= 0).all(), "episode ids not monotone in write order"
        assert torch.equal(step > 0, done_prev), "episode id changes where no done flag is set"
        assert (td["env"] == st.env_code("FetchPush-v4")).all()


def _committed_write_count(path: Path) -> int:
    """The write count of the commit record on disk (0 before the first)."""
    try:
        return int(json.loads((path / "zarr.json").read_text())["attributes"].get("write_count", 0))
    except (FileNotFoundError, ValueError, KeyError):
        return 0


def _run_kills(tmp_path: Path, *, max_size, chunk_rows, traj_ids, kills, seed, pause=0.03,
               min_rows=0, max_extra_kills=60):
    """``kills`` kills at drawn moments, then more until the run shows what it is for.

    After the planned kills, the loop kills on (at most ``max_extra_kills``
    more) while fewer than a third of the planned kills saw committed progress
    or fewer than ``min_rows`` rows are committed. Each extra kill waits for the
    event that makes it progress (a commit record on disk past the last
    reopen's write count) and then lands at a drawn moment. Kills during
    start-up never count as progress. Only writers that stop committing reach
    the bound; the failure says so, with the seed.
    """
    path = tmp_path / "store.zarr"
    err_file = tmp_path / "child_error.txt"
    script = tmp_path / "crash_child.py"
    script.write_text(CHILD_SRC)
    ctx = _ctx()
    rng = random.Random(seed)
    tracker = Tracker(path, max_size, traj_ids)
    progressed = 0
    startup_kills = 0
    need_progress = kills // 3
    it = 0
    while it < kills or progressed < need_progress or tracker.last_w < min_rows:
        extra = it >= kills
        if it >= kills + max_extra_kills:
            pytest.fail(
                f"after {it} kills (CRASH_SEED={seed}) only {progressed} saw committed progress (want "
                f"{need_progress}) and {tracker.last_w} rows are committed (want {min_rows}): writers that "
                f"stop committing are a bug"
            )
        prog = ctx.RawArray("q", 6)
        args = dict(path=str(path), max_size=max_size, chunk_rows=chunk_rows, traj_ids=traj_ids,
                    seed=seed * 1000 + it, prog=prog, err_file=str(err_file), pause=pause)
        p = ctx.Process(target=runpy.run_path, args=(str(script),),
                        kwargs={"init_globals": {"ARGS": args}, "run_name": "crash_child"})
        p.start()
        deadline = time.monotonic() + 60
        if not extra and it > 0 and rng.random() < 0.25:
            # kill while the writer opens the store (journal replay, episode close, flush)
            time.sleep(rng.random() * 0.15)
        else:
            while prog[0] < 2 and p.is_alive() and time.monotonic() < deadline:
                time.sleep(0.002)
            if extra:  # until the writer committed something new: this kill makes progress
                while (_committed_write_count(path) <= tracker.last_w and p.is_alive()
                       and time.monotonic() < deadline):
                    time.sleep(0.002)
            time.sleep(rng.random() * 1.0)
        startup = prog[0] < 2  # it had not returned from its first extend
        startup_kills += startup
        alive = p.is_alive()
        if alive:
            os.kill(p.pid, signal.SIGKILL)
        p.join(10)
        if not alive or p.exitcode != -signal.SIGKILL:
            msg = err_file.read_text() if err_file.exists() else "(no traceback)"
            pytest.fail(f"writer died on its own (exit {p.exitcode}) at kill {it}, seed {seed}:\n{msg}")
        if prog[0] >= 1:  # it opened: it saw everything the previous open saw
            assert (prog[1], prog[2]) == (tracker.last_w, tracker.last_len), (
                f"the writer saw another state (CRASH_SEED={seed})")
            assert prog[3] == prog[1] % max_size
        tracker.durable_w = max(tracker.durable_w, prog[5])
        before = tracker.last_w
        try:
            tracker.reopen_and_check()
        except AssertionError as e:
            raise AssertionError(f"after kill {it} (CRASH_SEED={seed}): {e}") from e
        progressed += not startup and tracker.last_w > before
        it += 1
    return tracker, progressed, startup_kills, it


def _seed():
    return seed_from_env("CRASH_SEED")


def _kills(default):
    return int(os.environ.get("CRASH_KILLS", default))


@pytest.mark.timeout(600)
def test_sigkill_append_store(tmp_path):
    """A store larger than everything written: rows only ever appended."""
    seed = _seed()
    print(f"CRASH_SEED={seed}")
    tracker, progressed, startup, kills = _run_kills(
        tmp_path, max_size=1_000_000, chunk_rows=64, traj_ids=False, kills=_kills(18), seed=seed
    )
    print(f"seed={seed} kills={kills} rows={tracker.last_w} kills with progress={progressed} kills while opening="
          f"{startup} episodes closed at reopen={len(tracker.forced_done)} "
          f"leftover .partial files={_leftover_partials(tmp_path / 'store.zarr')}")
    # (holds by construction: the loop kills on until it does, or fails saying why)
    assert progressed >= _kills(18) // 3, "the writer made no durable progress between most kills"
    assert not tracker.ring


@pytest.mark.full
@pytest.mark.timeout(600)
def test_sigkill_ring_store(tmp_path):
    """A small ring (300 rows, chunks of 64: the last chunk is partial) wrapping many times."""
    seed = _seed()
    print(f"CRASH_SEED={seed}")
    tracker, progressed, startup, kills = _run_kills(
        tmp_path, max_size=300, chunk_rows=64, traj_ids=True, kills=_kills(18), seed=seed, min_rows=3 * 300 + 1
    )
    print(f"seed={seed} kills={kills} rows={tracker.last_w} wraps={tracker.last_w // 300} kills while opening="
          f"{startup} episodes closed at reopen={len(tracker.forced_done)} "
          f"pending journals at reopen={tracker.pending_journals} "
          f"leftover .partial files={_leftover_partials(tmp_path / 'store.zarr')}")
    # (both hold by construction: the loop kills on until they do, or fails saying why)
    assert tracker.ring and tracker.last_w > 3 * 300  # wrapped several times
    assert progressed >= _kills(18) // 3


# -- deterministic reproductions of crash-safety bugs -------------------------

_TORN_CHILD = ROWS_SRC + '''
import json, os, signal, sys, threading, time
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem.storage import ZarrStorage, fast_write
path = sys.argv[1]
# in-process commits: the chunk file writer is patched in this process only, and a commit worker that
# finished starting before the wrap would write the chunks where the patch cannot see them
st = ZarrStorage(path, 128, chunk_rows=64, commit_interval=60, commit_process=False)
rb = TensorDictReplayBuffer(storage=st, batch_size=4)
rb.extend(make_rows(torch.arange(128))); st.flush()
orig_write = fast_write.write_file
written, lock = [], threading.Lock()
def write_file(root, key, buffers, check=None):
    # the first of these arrays' wrap chunks gets written, the others never do
    if "/c." in key and key.split("/c.")[0] in ("action", "value", "observation"):
        with open(os.path.join(path, "zarr.json")) as f:
            if json.load(f)["attributes"].get("journal"):  # the wrap commit writes its rows
                with lock:
                    first = not written
                    written.append(key)
                if not first:
                    time.sleep(60)  # no other array gets there before the crash
                orig_write(root, key, buffers, check)
                os.kill(os.getpid(), signal.SIGKILL)  # one array's chunk written, then crash
    return orig_write(root, key, buffers, check)
fast_write.write_file = write_file
rb.extend(make_rows(torch.arange(128, 192))); st.flush()
'''


def _crash_mid_wrap(tmp_path):
    path = tmp_path / "ring.zarr"
    script = tmp_path / "torn_child.py"
    script.write_text(_TORN_CHILD)
    out = subprocess.run([sys.executable, str(script), str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == -signal.SIGKILL, out.stderr
    g = zarr.open_group(path, mode="r")
    assert g.attrs["journal"], "the crash did not leave a pending journal"
    raw = {k: torch.from_numpy(g[k][:]) for k in ("action", "value", "observation")}
    w = -raw["action"][:, 0]
    torn = (raw["value"] != w.double() / 8) | (raw["observation"][:, 0] != w.float())
    assert torn.any(), "the crash left no torn rows on disk: the scenario is not exercised"
    return path


def _torn_rows(st):
    td = st[: len(st)]
    w = -td["action"][:, 0]
    ref = make_rows(w)
    keys = [k for k in ref.keys(True, True) if k not in (("next", "done"), ("next", "truncated"))]
    return sum(int((td.get(k) != ref.get(k)).reshape(len(w), -1).any(-1).sum()) for k in keys)


def test_crash_mid_journaled_commit_writable_reopen_replays(tmp_path):
    path = _crash_mid_wrap(tmp_path)
    with ZarrStorage(path) as st:
        assert len(st) == 128 and _torn_rows(st) == 0


def test_crash_mid_journaled_commit_read_only_open(tmp_path):
    path = _crash_mid_wrap(tmp_path)
    st = ZarrStorage(path, read_only=True)
    assert _torn_rows(st) == 0


def _end_journal(path, *, next_journal=False):
    """What a writer does at a journalled commit's end: the rows in place, the record, and (``next_journal``)
    the next journalled commit's record; or its journal arrays replaced by the next one's (deleted here)."""
    from torchrl_robotmem.storage.format import writing_config
    from torchrl_robotmem.storage.journal import replay_journal

    g = zarr.open_group(path, mode="r+")
    journal = g.attrs["journal"]
    with writing_config():  # as a writer replays it: every chunk written, an all-zero one too
        replay_journal(g, journal)
    if next_journal:  # the same chunks journalled again (the arrays hold their rows): a new pending journal
        meta = {**journal["meta"], "overwrites": int(journal["meta"].get("overwrites", 0)) + 1}
        g.update_attributes({"journal": {"chunks": journal["chunks"], "meta": meta}})
    else:
        import shutil

        shutil.rmtree(os.path.join(path, "_journal"))


@pytest.mark.parametrize("when", ["applying it", "reading its chunks again"])
def test_a_reader_whose_pending_journal_ends_during_its_open_serves_whole_rows(tmp_path, monkeypatch, when):
    """Found by looping an export beside a writer that wraps a ring: a read-only open read a pending journal's
    arrays after the writer had ended that commit and its next journal had replaced them, and raised
    ``KeyError: '_journal/observation'`` (``robotmem export`` said the store was not a memory). A journal array
    that is gone while the record has moved on is read again from the record of now."""
    from torchrl_robotmem.storage import _backend
    from torchrl_robotmem.storage.mirror import RamMirror

    path = str(_crash_mid_wrap(tmp_path))
    load, open_group, calls = RamMirror.load, _backend.open_group, []

    def load_then_write(self, *args, **kwargs):
        left = load(self, *args, **kwargs)
        if when == "applying it":
            _end_journal(path)
        else:
            calls.append("loaded")
        return left

    def open_group_then_write(*args, **kwargs):  # the reader's looks at the record, once its rows are loaded
        group = open_group(*args, **kwargs)
        if calls:
            calls.append("record")
            if len(calls) == 2:  # before the reread: the journal ended, the next one pending (same chunks)
                _end_journal(path, next_journal=True)
                group = open_group(*args, **kwargs)
            elif len(calls) == 3:  # the reread saw it pending; it ends, and its arrays are replaced
                _end_journal(path)
        return group

    monkeypatch.setattr(RamMirror, "load", load_then_write)
    monkeypatch.setattr(_backend, "open_group", open_group_then_write)
    st = ZarrStorage(path, read_only=True)
    assert len(st) == 128 and _torn_rows(st) == 0
    assert not os.path.exists(os.path.join(path, "_journal")), "the scenario was not exercised"
    assert when == "applying it" or len(calls) > 3
    st.close()


@pytest.mark.parametrize("commit_process", [False, True], ids=["in-process commits", "the commit worker"])
def test_the_journal_arrays_are_kept_across_writer_sessions(tmp_path, commit_process):
    """Found by a review: each writer session (and the commit worker's first commit) created the journal arrays
    anew (``overwrite=True``), deleting them for some milliseconds: the window in which a reader of a pending
    journal found them gone. An array that fits is reused, never deleted."""
    path = str(tmp_path / "r.zarr")
    inodes = []
    for _ in range(3):
        with ZarrStorage(path, 16, chunk_rows=4, goal_conditioned=False, commit_process=commit_process) as st:
            for k in range(0, 40, 8):  # wraps the ring: journalled commits
                st.set(torch.arange(k, k + 8) % 16, TensorDict({"obs": torch.arange(k, k + 8.0)[:, None]}, [8]))
                st.flush()
        meta = os.stat(os.path.join(path, "_journal", "obs", "zarr.json"))
        inodes.append((meta.st_ino, meta.st_mtime_ns))  # a new array writes its zarr.json anew
    assert len(set(inodes)) == 1, inodes
    with ZarrStorage(path, read_only=True) as st:
        assert st["obs"].flatten().tolist() == [*range(32, 40), *range(24, 32)]


def test_a_pending_journal_whose_arrays_are_gone_is_damage(tmp_path, monkeypatch):
    """With the record unchanged (no writer moved on), a missing journal array is damage, named as such."""
    from torchrl_robotmem.storage.mirror import RamMirror

    path = str(_crash_mid_wrap(tmp_path))
    load = RamMirror.load

    def load_then_lose(self, *args, **kwargs):  # after the open's checks, before the journal is read
        left = load(self, *args, **kwargs)
        import shutil

        shutil.rmtree(os.path.join(path, "_journal"))
        return left

    monkeypatch.setattr(RamMirror, "load", load_then_lose)
    with pytest.raises(IntegrityError, match=r"_journal/\w+.*journal array missing"):
        ZarrStorage(path, read_only=True)


_CONSTANT_JOURNAL_CHILD = """
import json, os, signal, sys, torch
from tensordict import NonTensorData, TensorDict
from torchrl_robotmem.storage import ZarrStorage, fast_write
path, extra, label = sys.argv[1], json.loads(sys.argv[2]), json.loads(sys.argv[3])
st = ZarrStorage(path, 8, chunk_rows=4, goal_conditioned=False, commit_interval=3600, commit_process=False)
st.set(torch.arange(8), TensorDict({"obs": torch.arange(8.0)[:, None], "label": NonTensorData(label, batch_size=[8])}, [8]))
st.flush()
orig = fast_write.write_file
def write_file(root, key, buffers, check=None):  # the journal written, then killed before the rows' own write
    if not key.startswith("_journal/"):
        with open(os.path.join(path, "zarr.json")) as f:
            if json.load(f)["attributes"].get("journal"):
                os.kill(os.getpid(), signal.SIGKILL)
    return orig(root, key, buffers, check)
fast_write.write_file = write_file
st.set(torch.arange(2), TensorDict({"obs": torch.full((2, 1), 50.0), "label": NonTensorData(label, batch_size=[2]), **extra}, [2]))
st.flush()  # rewrites committed rows: through the journal
"""


@pytest.mark.parametrize("extra, label", [({}, "scripted"), ({"source": "replay"}, "scripted"), ({}, math.nan)],
                         ids=["same constants", "a constant added", "a NaN constant"])
def test_a_store_with_constants_killed_mid_journal_reopens_with_the_journalled_rows(tmp_path, extra, label):
    """Found by a review: with the constants in every commit record, a journal of a store holding one recorded
    them, which the journal's check refuses (a journal never rewrites the structure): readers beside the writer
    and every open after a kill there were refused, and `repair` then cut the memory to 0 rows. A record now
    carries constants only when it adds one; a journal may add constants, never change or drop one. A NaN
    constant is the same constant at every write (``nan != nan`` refused its second write)."""
    path = str(tmp_path / "m.zarr")
    out = subprocess.run([sys.executable, "-c", _CONSTANT_JOURNAL_CHILD, path, json.dumps(extra), json.dumps(label)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == -signal.SIGKILL, out.stderr[-2000:]
    g = zarr.open_group(path, mode="r")
    assert g.attrs["journal"], "the kill left no pending journal: the scenario is not exercised"
    assert ("constants" in g.attrs["journal"]["meta"]) == bool(extra)
    for read_only in (True, False):  # the writable open replays the journal
        with ZarrStorage(path, read_only=read_only) as st:
            assert st["obs"].flatten().tolist() == [50.0, 50.0, 2, 3, 4, 5, 6, 7]
            row = st[0]
            assert row["label"] == label or isinstance(label, float) and math.isnan(row["label"])
            assert (row["source"] if "source" in row.keys() else None) == extra.get("source")


@pytest.mark.parametrize("forged", [{"label": "forged"}, {}, {"label": "scripted", "n": True}],
                         ids=["changed", "dropped", "another type"])
def test_a_journal_that_changes_a_constant_is_refused(tmp_path, forged):
    """A journal may add constants, never change or drop one (found by a review: ``1 == True`` passed)."""
    path = str(tmp_path / "m.zarr")
    with ZarrStorage(path, 8, chunk_rows=4, goal_conditioned=False) as st:
        st.set(torch.arange(8), TensorDict({"obs": torch.arange(8.0)[:, None], "label": "scripted"}, [8]))
    g = zarr.open_group(path, mode="r+")
    g.update_attributes({"constants": {"label": "scripted", "n": 1}})  # as a write of n=1 records it
    meta = {k: g.attrs[k] for k in ("len", "cursor", "write_count")}
    g.update_attributes({"journal": {"chunks": [0], "meta": {**meta, "constants": forged}}})
    with pytest.raises(IntegrityError, match=r"pending journal rewrites \['constants'\]"):
        ZarrStorage(path, read_only=True)


_CONSTANT_GROWTH_CHILD = """
import os, signal, sys, torch
from tensordict import TensorDict
from torchrl_robotmem.storage import ZarrStorage
from torchrl_robotmem.storage.store import MemoryStore
st = ZarrStorage(sys.argv[1], goal_conditioned=False, chunk_rows=4, commit_interval=3600)  # no capacity
st.set(torch.arange(4), TensorDict({"obs": torch.arange(4.0)[:, None]}, [4]))
n = st.capacity
st.set(torch.arange(4, n), TensorDict({"obs": torch.arange(4.0, n)[:, None]}, [n - 4]))  # not committed yet
def grow_for(self, need):  # killed after the growth's flush of the rows before, before the new rows
    os.kill(os.getpid(), signal.SIGKILL)
MemoryStore.grow_for = grow_for
st.set(torch.arange(n, n + 4), TensorDict({"obs": torch.zeros(4, 1), "label": "new"}, [4]))
"""


def test_a_constant_whose_write_grows_the_memory_is_committed_with_its_rows(tmp_path, monkeypatch):
    """Found by a review: the constant was added before the growth, whose flush of the rows before committed it
    without any row carrying it (a kill there, or a growth that failed, left a store refusing writes without it)."""
    from torchrl_robotmem.storage.store import MemoryStore

    path = str(tmp_path / "killed.zarr")
    out = subprocess.run([sys.executable, "-c", _CONSTANT_GROWTH_CHILD, path], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == -signal.SIGKILL, out.stderr[-2000:]
    with ZarrStorage(path, goal_conditioned=False) as st:
        n = len(st)
        assert n > 4 and "label" not in st[0].keys(), "the flush before the growth did not run: not exercised"
        st.set(torch.arange(n, n + 2), TensorDict({"obs": torch.zeros(2, 1)}, [2]))  # no constant to carry

    path = str(tmp_path / "failed.zarr")  # the growth fails (a full disk): the write changes nothing
    st = ZarrStorage(path, goal_conditioned=False, chunk_rows=4, commit_interval=3600)
    st.set(torch.arange(4), TensorDict({"obs": torch.arange(4.0)[:, None]}, [4]))
    n = st.capacity
    st.set(torch.arange(4, n), TensorDict({"obs": torch.arange(4.0, n)[:, None]}, [n - 4]))

    def full(self, need):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(MemoryStore, "grow_for", full)
    with pytest.raises(OSError, match="No space left"):
        st.set(torch.arange(n, n + 4), TensorDict({"obs": torch.zeros(4, 1), "label": "new"}, [4]))
    monkeypatch.undo()
    st.set(torch.arange(n, n + 2), TensorDict({"obs": torch.zeros(2, 1)}, [2]))  # no constant to carry
    st.close()
    assert "constants" not in zarr.open_group(path, mode="r").attrs


def test_flush_waits_for_an_in_flight_commit(tmp_path, monkeypatch):
    """flush() called while the background writer is mid-commit returns only once it committed.

    The commit's chunk write is held (a slow disk or object store) until the test
    releases it: the commit is in flight for as long as the test needs, however
    loaded the machine. flush() runs in a thread that notes whether the write was
    still held when flush() returned; the write is released only after that
    thread has had a second to return on its own.
    """
    from torchrl_robotmem.storage import fast_write

    orig = fast_write.write_file
    started, release = threading.Event(), threading.Event()

    def held(root, key, buffers, check=None):  # a slow disk
        started.set()
        release.wait()
        return orig(root, key, buffers, check)

    monkeypatch.setattr(fast_write, "write_file", held)
    path = tmp_path / "m.zarr"
    # in-process commits: the patched write runs in this process (the worker process has
    # the same wait: flush() returns when the worker's reply to the commit arrives)
    st = ZarrStorage(path, 1000, chunk_rows=64, commit_interval=0.05, commit_process=False)
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    rb.extend(make_rows(torch.arange(10)))
    try:
        assert started.wait(60), "the timer commit never started"
        assert not st._engine.dirty and st._engine.inflight == 1, "the commit is not in flight: the scenario is not exercised"
        returned = []

        def flush():
            st.flush()
            returned.append("while the write was held" if not release.is_set() else "after the write")

        t = threading.Thread(target=flush)
        t.start()
        t.join(1.0)  # a flush() that does not wait returns while the write is held
    finally:
        release.set()
    t.join(60)
    assert returned == ["after the write"], f"flush() returned {returned}"
    assert len(ZarrStorage(path, read_only=True)) == 10, "flush() returned before the rows were committed"
    st.close()


_LEAD_CHILD = ROWS_SRC + '''
import os, signal, sys, time
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem.storage import ZarrStorage
st = ZarrStorage(sys.argv[1], 128, chunk_rows=64, commit_interval=60)
rb = TensorDictReplayBuffer(storage=st, batch_size=4)
rb.extend(make_rows(torch.arange(128))); st.flush()   # committed: write_count 128
rb.extend(make_rows(torch.arange(128, 328)))          # 1.5 more laps, not flushed
import json
def committed():
    with open(os.path.join(sys.argv[1], "zarr.json")) as f:
        return json.load(f)["attributes"]["write_count"]
deadline = time.monotonic() + 60                      # until the writer committed past the first lap
while time.monotonic() < deadline and committed() <= 128:
    time.sleep(0.05)
print("committed", committed(), flush=True)
rb.extend(make_rows(torch.arange(328, 360)))          # and more rows in RAM only
os.kill(os.getpid(), signal.SIGKILL)
'''


def test_ring_rows_never_lead_the_metadata(tmp_path):
    path = tmp_path / "ring.zarr"
    script = tmp_path / "lead_child.py"
    script.write_text(_LEAD_CHILD)
    out = subprocess.run([sys.executable, str(script), str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == -signal.SIGKILL, out.stderr
    committed = int(out.stdout.split()[-1])
    assert 128 < committed <= 328, f"the child committed nothing past the first lap: {out.stdout}"
    with ZarrStorage(path) as st:
        W = st.write_count
        assert committed <= W < 360
        w = -st[: len(st)]["action"][:, 0]
        # every slot holds the last write < write_count that maps to it
        expected = W - 1 - ((W - 1 - torch.arange(len(st))) % 128)
        assert torch.equal(w, expected), f"write_count {W}, slots hold {int(w.min())}..{int(w.max())}"


# Every process started with _ATTRS_HOOK's directory on PYTHONPATH (the writer and, through
# the environment it inherits, its commit worker, a script of its own) imports it at start-up
# (Python's ``sitecustomize`` hook): after every ``Group.update_attributes`` on the store it
# reads the commit record back from disk, logs it, and if the record is half-written (len,
# cursor and write_count disagree: no ring here, they are equal in every whole record) kills
# the writer and its worker on the spot, as a crash at that moment would.
_ATTRS_HOOK = r"""
import os
if os.environ.get("ROBOTMEM_TEST_ATTRS_LOG"):
    import json, signal, sys
    import zarr
    _log, _store = os.environ["ROBOTMEM_TEST_ATTRS_LOG"], os.environ["ROBOTMEM_TEST_ATTRS_STORE"]
    _role = "worker" if os.path.basename(sys.argv[0]) == "_commit_worker.py" else "writer"
    _orig = zarr.Group.update_attributes

    def update_attributes(self, new):
        out = _orig(self, new)
        root = getattr(self.store, "root", None)
        if root is None or os.path.realpath(root) != _store:
            return out
        with open(os.path.join(_store, "zarr.json")) as f:
            a = json.load(f)["attributes"]
        record = {k: a.get(k) for k in ("len", "cursor", "write_count")}
        ok = None in record.values() or record["len"] == record["cursor"] == record["write_count"]
        with open(_log, "a") as f:
            f.write(json.dumps({"role": _role, "pid": os.getpid(), "keys": sorted(new), "record": record,
                                "ok": ok}) + "\n")
        if not ok:  # this half-written commit is what a crash leaves
            if _role == "worker":
                os.kill(os.getppid(), signal.SIGKILL)
            os.kill(os.getpid(), signal.SIGKILL)
        return out

    zarr.Group.update_attributes = update_attributes
"""

_ATTRS_CHILD = ROWS_SRC + """
import json, os, sys, time
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem.storage import ZarrStorage
path, mode, log = sys.argv[1], sys.argv[2], os.environ["ROBOTMEM_TEST_ATTRS_LOG"]

def records_by(role):
    # commit records (attribute writes that carry len) the hook checked in that role
    if not os.path.exists(log):
        return 0
    with open(log) as f:
        return sum(1 for line in f if json.loads(line)["role"] == role and "len" in json.loads(line)["keys"])

# room for every row the loop writes (no ring: a whole record has len == cursor == write_count), however
# many rows in-process commits write before the worker has started
st = ZarrStorage(path, 100_000, chunk_rows=64, commit_interval=60, commit_process=mode == "worker")
rb = TensorDictReplayBuffer(storage=st, batch_size=4)
w = 0
# the worker takes commits over once it has started: commit until it has written three records, however long
# a loaded machine takes to start it (no deadline: a worker that never commits is a bug, and the test's timeout)
while True:
    rb.extend(make_rows(torch.arange(w, w + 50))); st.flush(); w += 50
    if w >= 150 and (mode != "worker" or records_by("worker") >= 3):
        break
print("rows", w, flush=True)
"""


@pytest.mark.parametrize("mode", ["worker", "in-process"])
def test_commit_metadata_is_written_atomically(tmp_path, mode):
    """Every commit record on disk is whole, whichever process writes it (the commit worker or the writer)."""
    path = tmp_path / "m.zarr"
    script, hook, log = tmp_path / "attrs_child.py", tmp_path / "hook", tmp_path / "attrs.log"
    script.write_text(_ATTRS_CHILD)
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_ATTRS_HOOK)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(hook), os.environ.get("PYTHONPATH")])),
           "ROBOTMEM_TEST_ATTRS_LOG": str(log), "ROBOTMEM_TEST_ATTRS_STORE": os.path.realpath(path)}
    out = subprocess.run([sys.executable, str(script), str(path), mode], capture_output=True, text=True,
                         timeout=540, env=env)
    lines = [json.loads(x) for x in log.read_text().splitlines()] if log.exists() else []
    bad = [x for x in lines if not x["ok"]]
    assert not bad, f"half-written commit records on disk: {bad[:3]}"
    # the child is killed at the first half-written record it sees; it saw none
    assert out.returncode == 0, (out.returncode, out.stderr[-3000:])
    records = {role: sum(1 for x in lines if x["role"] == role and "len" in x["keys"]) for role in ("worker", "writer")}
    print(f"{mode}: commit records checked on disk after each write, by the process that wrote them: {records}")
    # the hook ran, in the process that writes the records in this mode
    if mode == "worker":
        assert records["worker"] > 0, f"no commit record went through the commit worker: {records}"
    else:
        assert records["worker"] == 0 and records["writer"] > 0, records
    rows = int(out.stdout.split()[-1])
    assert rows >= 150
    with ZarrStorage(path) as st:
        assert len(st) == rows
        assert (len(st), st.state_dict()["zarr"]["cursor"]) == (st.write_count, st.write_count), (
            f"len {len(st)}, cursor {st.state_dict()['zarr']['cursor']}, write_count {st.write_count}"
        )


def test_episode_continues_across_extend_batches(tmp_path):
    # no traj_ids: episodes are split at done flags (w % 50 == 49)
    with ZarrStorage(tmp_path / "m.zarr", 1000) as st:
        rb = TensorDictReplayBuffer(storage=st, batch_size=4)
        rb.extend(make_rows(torch.arange(40, 60)))  # ends episode 40..49, starts 50..
        rb.extend(make_rows(torch.arange(60, 70)))  # continues it
        ep = st["episode"][:30]
        assert ep[:10].unique().numel() == 1 and ep[10:].unique().numel() == 1, ep.tolist()
        assert ep[10] != ep[9]
