"""A randomized SIGKILL loop against real writer processes.

One store, one writer process at a time: each writer reopens the store, checks
that its ``TensorDictReplayBuffer``'s writer was restored to the stored write
count, and extends deterministic batches (``_gen.make_rows``: every column a
function of the row's write number) with a tiny ``commit_interval`` (20 ms) and
32-row chunks, so that background commits are nearly always in flight. The
store holds 600 rows (the last chunk is partial): the first kills hit an appending store, the rest a ring
that wraps around many times, where every commit overwrites committed rows
through the redo journal.

Each writer is SIGKILLed at a moment drawn from four kinds:

* ``startup``: while it opens the store (journal replay, closing the episode
  the previous writer left open, its first flush);
* ``random``: at a random time while it writes;
* ``commit``: right after a commit replaced ``zarr.json`` (the next commit is
  being prepared or its chunks written);
* ``journal``: while a journalled overwrite is pending (``zarr.json`` names a
  journal), so that the next open must replay it.

After every kill the parent reopens the store, alternately ``read_only=True``
(a pending journal is applied in RAM only) and writable (the journal is
replayed on disk, the open episode closed), and checks:

* ``write_count`` never goes backwards and covers every row a returned
  ``flush()`` made durable; it never exceeds what the writer had extended;
* ``len == min(write_count, max_size)``: slot ``r`` holds the last write number
  below ``write_count`` that maps to it, every column bit-exact (no torn rows, no
  rows newer than the committed metadata);
* episode end flags are the natural ones plus the episodes closed at reopens;
  episode ids change exactly after a done row;
* the next writer opened exactly at that state and appends after it.

It reports the loss window: for each kill, how long before the kill the oldest
lost row's ``extend`` had returned (rows lost = extends that returned, minus the
committed write count).

A ``commit`` or ``journal`` moment that does not come (within a minute: a
healthy writer commits every 20 ms and wraps the ring within a second) is
killed anyway and counted as ``random``; a kill that finds the writer still
starting counts as ``startup``. The counts of the kinds that happened are
reported, and the loop does not end on an unlucky schedule: after the planned
kills it kills on (a bounded number of times) until every kind the schedule
asked for has happened, the ring has wrapped and a third of the planned kills
saw committed progress (kills during start-up never count as progress). Every
run asks for every kind (a schedule shorter than five kills is completed by
extra kills). Only writers that stop committing reach
the bound, and the failure says so.

Kill count: ``ROBOTMEM_KILLS`` (default 8); the full run is
``ROBOTMEM_KILLS=120 python -m pytest -s tests/reliability/test_kill_loop.py``.
The schedule is seeded: ``ROBOTMEM_KILL_SEED`` if set, else
``ROBOTMEM_TEST_SEED`` (default 0); the seed is printed with ``-s`` and named
in every failure.
"""
from __future__ import annotations

import json
import os
import random
import runpy
import signal
import statistics
import sys
import time
from pathlib import Path

import pytest
import torch
import zarr
from conftest import seed_from_env
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage

from . import _gen
from ._gen import EPISODE_END_KEYS, EPISODE_LEN, make_rows, torn_or_wrong

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="needs fork and SIGKILL")

MAX_SIZE = 600
CHUNK_ROWS = 32
COMMIT_INTERVAL = 0.02
KINDS = ("startup", "random", "commit", "journal")


def _kills() -> int:
    return int(os.environ.get("ROBOTMEM_KILLS", 8))


def _seed() -> int:
    return seed_from_env("ROBOTMEM_KILL_SEED")


class Expectations:
    """What every reopen must show, accumulated over kills."""

    def __init__(self, path: Path):
        self.path = path
        self.last_w = 0
        self.forced_done: set[int] = set()  # write numbers whose episode a reopen closed
        self.rows_checked = 0
        self.pending_journals = 0
        self.wrapped = False

    def check(self, *, read_only: bool, durable: int, written_at_most: int) -> int:
        """Reopens the store and checks every row; returns the committed write count."""
        attrs = zarr.open_group(self.path, mode="r").attrs.asdict()
        self.pending_journals += bool(attrs.get("journal"))
        st = ZarrStorage(self.path, read_only=read_only)
        try:
            rb = TensorDictReplayBuffer(storage=st, batch_size=4)
            state = st.state_dict()["zarr"]
            W, n, cursor = int(state["write_count"]), len(st), int(state["cursor"])
            assert rb.writer.state_dict() == {"_cursor": cursor, "_write_count": W}
            assert W >= self.last_w, f"write_count went backwards: {self.last_w} -> {W}"
            assert W >= durable, f"rows a returned flush() made durable are lost: write_count {W} < {durable}"
            assert W <= written_at_most, f"write_count {W} is past anything the writer extended ({written_at_most})"
            assert n == min(W, MAX_SIZE) and cursor == W % MAX_SIZE, (
                f"len {n}, cursor {cursor} disagree with write_count {W}; stored attributes "
                f"{ {k: attrs.get(k) for k in ('len', 'cursor', 'write_count', 'journal')} }"
            )
            if n:
                self._check_rows(st, n, W, read_only)
            self.wrapped |= W > MAX_SIZE
            self.last_w = W
            if W and (W - 1) % EPISODE_LEN != EPISODE_LEN - 1:
                self.forced_done.add(W - 1)  # closed now (writable) or by the next writer's open
            return W
        finally:
            st.close()

    def _check_rows(self, st: ZarrStorage, n: int, W: int, read_only: bool) -> None:
        td = st[:n]
        expected = W - 1 - ((W - 1 - torch.arange(n)) % MAX_SIZE)
        bad = torn_or_wrong(td, expected)
        assert not bad, f"rows differ from the generator (write_count {W}): {bad}"
        self.rows_checked += n
        w = expected
        natural = make_rows(w)["next", "done"].squeeze(-1)
        forced = torch.tensor([int(x) in self.forced_done for x in w.tolist()])
        last = w == W - 1
        for key in EPISODE_END_KEYS:
            got = td.get(key).squeeze(-1)
            want = natural | forced
            if not read_only:
                want = want | last  # the writable open closed the last episode
            diff = got != want
            if read_only:
                diff &= ~last  # closed or not, depending on whether a writer opened since
            assert not diff.any(), f"{key} wrong at write numbers {w[diff][:10].tolist()}"
        # episode ids: monotone in write order, new exactly after a done row
        order = torch.argsort(w)
        ep = st["episode"][:n][order]
        done = td["next", "done"].squeeze(-1)[order]
        step = torch.diff(ep)
        assert (step >= 0).all(), "episode ids go backwards in write order"
        assert torch.equal(step > 0, done[:-1]), "an episode id changes where no done flag is set"
        assert (st["env"][:n] == st.env_code("FetchPush-v4")).all()


def _zarr_json_state(path: Path):
    try:
        s = os.stat(path / "zarr.json")
        return s.st_ino, s.st_mtime_ns
    except FileNotFoundError:
        return None


def _journal_pending(path: Path) -> bool:
    try:
        return json.loads((path / "zarr.json").read_text())["attributes"].get("journal") is not None
    except (FileNotFoundError, ValueError, KeyError):
        return False


# seconds to wait for a kind's moment (the first extend, a commit, a pending journal): each
# comes within milliseconds of a healthy writer's start (20 ms commits, a ring that wraps in
# about a second); only a stuck writer misses it
MOMENT_TIMEOUT = 60.0


def _wait_for(moment, p, poll: float) -> bool:
    """Polls until ``moment()`` holds (True), the writer died or ``MOMENT_TIMEOUT`` passed (False)."""
    end = time.monotonic() + MOMENT_TIMEOUT
    while p.is_alive() and time.monotonic() < end:
        if moment():
            return True
        time.sleep(poll)
    return False


def _wait_and_kill(p, prog, kind: str, path: Path, rng: random.Random) -> str:
    """Waits for the moment of ``kind``, sends SIGKILL; returns the kind that happened.

    A ``commit`` or ``journal`` moment not seen within ``MOMENT_TIMEOUT`` (the
    writer never committed, or never wrapped) is killed anyway and reported as
    ``random``; a writer that never returned from its first extend as
    ``startup``. The caller retries a requested kind that did not happen.
    """
    if kind == "startup":
        time.sleep(rng.random() * 0.25)
    else:
        deadline = time.monotonic() + MOMENT_TIMEOUT
        while prog[_gen.STATE] < 2 and p.is_alive() and time.monotonic() < deadline:
            time.sleep(0.002)
        if prog[_gen.STATE] < 2:
            kind = "startup"
        elif kind == "random":
            time.sleep(rng.random() * 0.8)
        elif kind == "commit":
            time.sleep(rng.random() * 0.3)
            before = _zarr_json_state(path)
            kind = "commit" if _wait_for(lambda: _zarr_json_state(path) != before, p, 0.0005) else "random"
        elif kind == "journal":
            time.sleep(rng.random() * 0.2)
            kind = "journal" if _wait_for(lambda: _journal_pending(path), p, 0.0002) else "random"
    if p.is_alive():
        os.kill(p.pid, signal.SIGKILL)
    return kind


def _loss_window(prog, stamps, W: int, t_kill: float) -> tuple[int, float]:
    """(rows whose extend returned but that are lost, age of the oldest of them at the kill)."""
    lost = max(0, prog[_gen.W_DONE] - W)
    if not lost:
        return 0, 0.0
    n_ext = prog[_gen.N_EXTENDS]
    oldest = None
    for i in range(max(0, n_ext - _gen.STAMP_SLOTS), n_ext):
        j = 2 * (i % _gen.STAMP_SLOTS)
        if stamps[j] > W:  # the first extend whose rows did not all survive
            oldest = stamps[j + 1]
            break
    return lost, (t_kill - oldest) if oldest is not None else float("nan")


def _schedule(kills: int, rng: random.Random) -> list[str]:
    """The kinds of the planned kills: a ``random`` one first, every kind in the next four, then draws."""
    first = list(KINDS)
    rng.shuffle(first)
    return (["random"] + first + [rng.choice(KINDS) for _ in range(kills)])[:kills]


def run_kill_loop(tmp_path: Path, kills: int, seed: int, *, max_extra_kills: int = 60) -> dict:
    """``kills`` planned kills, then more until the run shows what it is for.

    After the planned kills the loop goes on (at most ``max_extra_kills``
    more) while a kind the schedule asked for has not happened yet (a
    ``commit`` or ``journal`` moment missed, a writer still starting when
    its kill came), the ring has not wrapped, or fewer than a third of the
    planned kills saw committed progress. An extra kill is of a missing kind,
    else of kind ``commit`` (after a commit: progress). Kills during start-up
    do not count toward progress; they only add kills. The bound is reached
    only if writers stop committing: the failure says so, with the seed.
    """
    path = tmp_path / "store.zarr"
    err_file = tmp_path / "writer_error.txt"
    ctx = _gen.writer_context()
    rng = random.Random(seed)
    exp = Expectations(path)
    schedule = _schedule(kills, rng)
    requested = set(KINDS)  # every run asks for every kind: extra kills add those a short schedule lacks
    kinds_done = {k: 0 for k in KINDS}
    windows, losses = [], []
    progressed = 0
    need_progress = kills // 3

    def missing() -> list[str]:
        return [k for k in KINDS if k in requested and not kinds_done[k]]

    it = 0
    while True:
        if it < kills:
            kind = schedule[it]
        elif missing() or not exp.wrapped or progressed < need_progress:
            if it >= kills + max_extra_kills:
                pytest.fail(
                    f"after {it} kills (seed {seed}) the run still lacks what it is for: kinds that never "
                    f"happened {missing()}, ring wrapped {exp.wrapped} (write_count {exp.last_w}, "
                    f"max_size {MAX_SIZE}), kills with progress {progressed} < {need_progress}; kinds "
                    f"{kinds_done}. Writers that stop committing are a bug."
                )
            kind = (missing() or ["commit"])[0]
        else:
            break
        prog = ctx.RawArray("q", _gen.PROGRESS_SLOTS)
        stamps = ctx.RawArray("d", 2 * _gen.STAMP_SLOTS)
        args = dict(path=str(path), max_size=MAX_SIZE, chunk_rows=CHUNK_ROWS, commit_interval=COMMIT_INTERVAL,
                    seed=seed * 1000 + it, prog=prog, stamps=stamps, err_file=str(err_file))
        p = ctx.Process(target=runpy.run_path, args=(_gen.__file__,),
                        kwargs={"init_globals": {"ARGS": args}, "run_name": _gen.WRITER_RUN_NAME})
        p.start()
        kind = _wait_and_kill(p, prog, kind, path, rng)
        t_kill = time.monotonic()
        p.join(10)
        if p.exitcode != -signal.SIGKILL:
            msg = err_file.read_text() if err_file.exists() else "(no traceback)"
            pytest.fail(f"the writer died on its own (exit {p.exitcode}) at kill {it}, seed {seed}:\n{msg}")
        kinds_done[kind] += 1
        if prog[_gen.STATE] >= 1:  # it opened: at the state the last check saw
            assert prog[_gen.W_OPEN] == exp.last_w, (
                f"kill {it} (seed {seed}): the writer opened at write_count {prog[_gen.W_OPEN]}, "
                f"the check saw {exp.last_w}"
            )
        before = exp.last_w
        try:
            W = exp.check(read_only=it % 2 == 0, durable=prog[_gen.W_FLUSHED],
                          written_at_most=max(exp.last_w, prog[_gen.W_TRYING]))
        except AssertionError as e:
            raise AssertionError(f"after kill {it} ({kind}, seed {seed}): {e}") from e
        progressed += kind != "startup" and W > before
        if prog[_gen.STATE] >= 2:
            lost, window = _loss_window(prog, stamps, W, t_kill)
            losses.append(lost)
            if lost:
                windows.append(window)
        it += 1
    # the last writer's successor appends after everything that survived
    with ZarrStorage(path) as st:
        rb = TensorDictReplayBuffer(storage=st, batch_size=4)
        W = st.state_dict()["zarr"]["write_count"]
        rb.extend(make_rows(torch.arange(W, W + 7)))
    exp.check(read_only=True, durable=W + 7, written_at_most=W + 7)
    return dict(seed=seed, kills=it, kills_planned=kills, kinds=kinds_done, kinds_requested=sorted(requested),
                rows_written=exp.last_w, wraps=exp.last_w // MAX_SIZE, wrapped=exp.wrapped,
                rows_checked=exp.rows_checked, pending_journals_at_reopen=exp.pending_journals,
                kills_with_progress=progressed, episodes_closed_at_reopen=len(exp.forced_done),
                rows_lost_median=statistics.median(losses) if losses else 0, rows_lost_max=max(losses, default=0),
                loss_window_median_s=round(statistics.median(windows), 3) if windows else 0.0,
                loss_window_max_s=round(max(windows), 3) if windows else 0.0)


@pytest.mark.timeout(3600)
def test_sigkill_loop(tmp_path):
    kills = _kills()
    seed = _seed()
    print(f"kill loop: ROBOTMEM_KILL_SEED={seed} ROBOTMEM_KILLS={kills}")
    result = run_kill_loop(tmp_path, kills, seed)
    print("kill loop:", json.dumps(result))
    # (each holds by construction: the loop kills on until it does, or fails saying why)
    assert result["wrapped"] and result["wraps"] >= 1, f"the ring never wrapped: {result}"
    assert all(result["kinds"][k] for k in result["kinds_requested"]), f"a requested kill kind never happened: {result}"
    assert set(result["kinds_requested"]) == set(KINDS), result  # every run asks for every kind
    assert result["kills_with_progress"] >= kills // 3, f"the writers made no progress between kills: {result}"
