"""The pages of a writer's row file mapped ahead of its writes (storage/prefault.py), on real file mappings."""
from __future__ import annotations

import ctypes
import mmap
import os

import pytest
import torch

from torchrl_robotmem.storage.prefault import STEP, WINDOW, Prefault
from torchrl_robotmem.storage.rowfile import RowFile

pytestmark = pytest.mark.skipif(not Prefault().supported, reason="no madvise through ctypes here (not Linux)")


def _file_map(tmp_path, nbytes: int) -> mmap.mmap:
    fd = os.open(tmp_path / "rows.bin", os.O_RDWR | os.O_CREAT, 0o644)
    os.ftruncate(fd, nbytes)
    m = mmap.mmap(fd, nbytes, access=mmap.ACCESS_WRITE)
    os.close(fd)
    return m


def _resident(m: mmap.mmap) -> int:
    """Bytes of the mapping ``m`` resident in this process (``/proc/self/smaps``)."""
    start = ctypes.addressof(ctypes.c_char.from_buffer(m))
    found = False
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()[0]
            if "-" in head and all(c in "0123456789abcdef-" for c in head):
                found = int(head.split("-")[0], 16) == start
            elif found and line.startswith("Rss:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("the mapping is not in /proc/self/smaps")


def _populates(tmp_path) -> bool:
    """Whether this kernel has MADV_POPULATE_WRITE (5.14+): a first call says so."""
    m = _file_map(tmp_path, 1 << 16)
    ahead = Prefault()
    ahead.mapped(m, len(m))
    ahead.written(0)
    ahead.drain()
    return ahead.supported


def test_the_pages_past_a_write_are_mapped_and_not_one_byte_changes(tmp_path):
    if not _populates(tmp_path / ".."):
        pytest.skip("this kernel has no MADV_POPULATE_WRITE (Linux 5.14+): writes fault as before")
    nbytes = 3 * WINDOW
    m = _file_map(tmp_path, nbytes)
    rows = torch.frombuffer(m, dtype=torch.uint8)
    rows[:4096] = 7  # a write: its page is resident, the window after it is not yet
    before = _resident(m)
    ahead = Prefault()
    ahead.mapped(m, nbytes)
    ahead.written(4096)
    ahead.drain()
    after = _resident(m)
    assert after - before >= WINDOW - STEP, (before, after)  # the window past the write was mapped
    assert after < 2 * WINDOW  # and not the rest of the mapping (a large folio may map a little more)
    assert int(rows[:4096].sum()) == 7 * 4096 and int(rows[4096:].count_nonzero()) == 0  # no byte written
    ahead.stop()


def test_a_write_far_into_a_memory_maps_ahead_of_it_never_the_rows_behind(tmp_path):
    if not _populates(tmp_path / ".."):
        pytest.skip("this kernel has no MADV_POPULATE_WRITE (Linux 5.14+): writes fault as before")
    nbytes = 8 * WINDOW
    m = _file_map(tmp_path, nbytes)
    ahead = Prefault()
    ahead.mapped(m, nbytes)
    ahead.written(6 * WINDOW)  # a reopened memory: the first write is past most of its rows
    ahead.drain()
    assert _resident(m) < 2 * WINDOW  # the window past the write, not the 6 windows before it
    ahead.written(nbytes)  # the end of the mapping: nothing past it is asked for
    ahead.drain()
    ahead.stop()


def test_writes_beside_the_thread_land_exactly(tmp_path):
    """The thread maps the pages the writer is about to write: every written byte is as written."""
    nbytes = 2 * WINDOW + 12345
    m = _file_map(tmp_path, nbytes)
    rows = torch.frombuffer(m, dtype=torch.uint8)
    ahead = Prefault()
    ahead.mapped(m, nbytes)
    gen = torch.Generator().manual_seed(0)
    data = torch.randint(0, 256, (nbytes,), dtype=torch.uint8, generator=gen)
    step = 300_007  # writes that end anywhere in a page
    for lo in range(0, nbytes, step):
        hi = min(nbytes, lo + step)
        rows[lo:hi] = data[lo:hi]
        ahead.written(hi)
    ahead.drain()
    ahead.stop()
    assert torch.equal(rows, data)


def test_a_writers_row_file_maps_ahead_and_a_released_one_stops(tmp_path):
    """RowFile: a writer's mapping is mapped ahead of its writes; released, nothing more is asked."""
    rows = RowFile(tmp_path, read_only=False)
    rows.open({"len": 0}, layout=None)
    packed = rows.map((1000,), 1 << 16)  # 64 MB of rows
    packed[:10] = 1
    rows.written(10 << 16)
    rows.ahead.drain()
    assert rows.ahead.supported is False or rows.ahead.done >= (10 << 16) + WINDOW - 4096
    rows.release()
    rows.ahead.written(20 << 16)  # after the release: nothing asked
    assert rows.ahead.asked <= (10 << 16) + WINDOW + 4096 and not rows.ahead.active
