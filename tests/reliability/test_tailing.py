"""A reader process tailing a store while a writer process appends, across a ring wrap.

The writer is a real process (``_gen.writer_main``: deterministic batches, 20 ms
commits, 16-row chunks, a 200-row ring, flushes now and then); this test process opens the
store ``read_only=True`` and calls ``refresh()`` in a loop. Every time, it checks:

* ``len`` and the committed ``write_count`` never decrease;
* every row is complete (all its columns from one write, bit-exact to the
  generator), at the slot of its write number, and not older than the
  ``write_count`` the reader saw: before the wrap row ``r`` is write ``r``;
  rows being overwritten may already hold newer writes (docs/storage.md,
  "Concurrency"), also when the writer wraps during the reader's load.

``ROBOTMEM_TAIL_SECONDS`` sets how long the reader tails (default 3). The
writer's batch sizes and pauses are seeded: ``ROBOTMEM_TAIL_SEED`` if set, else
``ROBOTMEM_TEST_SEED`` (default 0); the seed is printed and named in every failure.
"""
from __future__ import annotations

import os
import runpy
import signal
import sys
import time

import pytest
import torch
from conftest import seed_from_env

from torchrl_robotmem import ZarrStorage

from . import _gen
from ._gen import torn_or_wrong

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="needs fork and SIGKILL")

MAX_SIZE = 200


def test_reader_sees_only_complete_rows_while_a_writer_appends_and_wraps(tmp_path):
    path = tmp_path / "tail.zarr"
    seconds = float(os.environ.get("ROBOTMEM_TAIL_SECONDS", 3))
    seed = seed_from_env("ROBOTMEM_TAIL_SEED")
    print(f"tailing: ROBOTMEM_TAIL_SEED={seed}")
    ctx = _gen.writer_context()
    prog = ctx.RawArray("q", _gen.PROGRESS_SLOTS)
    stamps = ctx.RawArray("d", 2 * _gen.STAMP_SLOTS)
    args = dict(path=str(path), max_size=MAX_SIZE, chunk_rows=16, commit_interval=0.02,
                seed=seed, prog=prog, stamps=stamps, err_file=str(tmp_path / "err.txt"),
                max_batch=30, pause=0.01, flush_prob=0.05)
    writer = ctx.Process(target=runpy.run_path, args=(_gen.__file__,),
                         kwargs={"init_globals": {"ARGS": args}, "run_name": _gen.WRITER_RUN_NAME})
    writer.start()
    try:
        deadline = time.monotonic() + 60
        while prog[_gen.W_FLUSHED] == 0 and writer.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert writer.is_alive(), (tmp_path / "err.txt").read_text()
        reader = ZarrStorage(path, read_only=True)
        last_n = last_w = 0
        refreshes = rows_checked = newer_rows = 0
        end = time.monotonic() + seconds
        while time.monotonic() < end or last_w <= MAX_SIZE or refreshes < 3:  # (slow refreshes on a busy box)
            assert time.monotonic() < end + 60, f"the ring never wrapped (write_count {last_w}, ROBOTMEM_TAIL_SEED={seed})"
            n = reader.refresh()
            W = int(reader.state_dict()["zarr"]["write_count"])
            assert n >= last_n and W >= last_w, (
                f"went backwards: len {last_n} -> {n}, write_count {last_w} -> {W} (ROBOTMEM_TAIL_SEED={seed})")
            assert n == min(W, MAX_SIZE), f"len {n}, write_count {W} (ROBOTMEM_TAIL_SEED={seed})"
            td = reader[:n]
            w = -td["action"][:, 0]
            # whole rows at the slot of their write number, none older than write_count says
            # (before the wrap that is row r = write r, unless the writer already wrapped since)
            bad = torn_or_wrong(td)
            slot = (w % MAX_SIZE) != torch.arange(n)
            stale = w < W - MAX_SIZE
            if slot.any() or stale.any():
                bad["slot"] = w[slot | stale][:10].tolist()
            newer_rows += int((w >= W).sum())
            assert not bad, (
                f"refresh {refreshes} (write_count {W}, ROBOTMEM_TAIL_SEED={seed}) read incomplete or wrong rows: {bad}")
            rows_checked += n
            refreshes += 1
            last_n, last_w = n, W
        assert writer.is_alive(), (tmp_path / "err.txt").read_text()
    finally:
        if writer.is_alive():
            os.kill(writer.pid, signal.SIGKILL)
        writer.join(10)
    print(f"tailing: refreshes={refreshes} rows_checked={rows_checked} write_count={last_w} "
          f"wraps={last_w // MAX_SIZE} rows newer than the reader's write_count={newer_rows}")
    assert refreshes >= 3


def test_an_in_place_commit_inside_a_reader_load_is_read_again(tmp_path, monkeypatch):
    """A journalled in-place commit that starts and ends inside a reader's load is caught.

    It leaves ``len``, ``cursor`` and ``write_count`` as they were, so the record before the load
    equals the record after it but for its ``overwrites`` count; a load that read one column
    before that commit and the others after it holds torn rows, which the reader must read again.
    The tear is made by construction: the load is run to its end, the writer rewrites rows 0..9 in
    place and commits, and the reader's ``observation`` column of those rows is then given the new
    values (what a load reading that column after the commit gets).
    """
    from torchrl_robotmem.storage.mirror import RamMirror

    path = tmp_path / "inplace.zarr"
    writer = ZarrStorage(path, 100, chunk_rows=10)
    writer.set(slice(0, 40), _gen.make_rows(torch.arange(40)))
    writer.flush()
    load = RamMirror.load
    overlapped = []

    def load_overlapped_by_a_commit(self, group, n0, *, store_path, read_only, local_dir=None):
        left = load(self, group, n0, store_path=store_path, read_only=read_only, local_dir=local_dir)
        if read_only and not overlapped:
            overlapped.append(n0)
            writer.set(slice(0, 10), _gen.make_rows(torch.arange(100, 110)), set_cursor=False)
            writer.flush()  # a journalled commit: rows 0..9 were committed
            self.columns["observation"][:10] = _gen.make_rows(torch.arange(100, 110))["observation"]
        return left

    monkeypatch.setattr(RamMirror, "load", load_overlapped_by_a_commit)
    try:
        with ZarrStorage(path, read_only=True) as reader:  # a writer is open: no seal, the rows are loaded
            assert overlapped == [40]
            assert len(reader) == 40
            expected = torch.cat([torch.arange(100, 110), torch.arange(10, 40)])
            bad = torn_or_wrong(reader[:40], expected)
            assert not bad, f"torn or stale rows after a load an in-place commit overlapped: {bad}"
    finally:
        writer.close()
    with ZarrStorage(path, read_only=True) as again:  # and the store holds the rewrite
        assert not torn_or_wrong(again[:40], torch.cat([torch.arange(100, 110), torch.arange(10, 40)]))
