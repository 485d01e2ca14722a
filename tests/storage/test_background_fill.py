"""A reader whose row file must be filled opens at once and fills in the background (issue 41).

Real stores on disk; the row file is made unusable for the reader by deleting it (``remove_rows``), as a
crash or an active writer leaves it. ``TORCHRL_ROBOTMEM_BACKGROUND_FILL_BYTES=0`` makes these small
stores fill in the background (by default only rows of 64 MiB and more do).
"""
from __future__ import annotations

import glob
import os
import threading

import numpy as np
import pytest
import torch
import zarr
from tensordict import TensorDict
from torchrl.data import RandomSampler, TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage.background_fill import RowFill
from torchrl_robotmem.storage.fast_read import ChunkReads
from torchrl_robotmem.storage.integrity import IntegrityError
from torchrl_robotmem.storage.loader import BACKGROUND_FILL_ENV
from torchrl_robotmem.storage.rowfile import remove_rows

CHUNK = 64
ROWS = 1000


def _rows(lo: int, hi: int) -> TensorDict:
    """Row ``i`` holds ``i`` in every column (a row whose columns disagree is torn)."""
    i = torch.arange(lo, hi, dtype=torch.float32)
    return TensorDict({"obs": i[:, None].expand(-1, 3).clone(), "action": -i[:, None],
                       ("next", "done"): torch.zeros(hi - lo, 1, dtype=torch.bool)}, [hi - lo])


@pytest.fixture
def store(tmp_path, monkeypatch):
    """A closed store of ``ROWS`` rows whose row file is gone: a reader fills it from the chunks."""
    monkeypatch.setenv(BACKGROUND_FILL_ENV, "0")
    path = str(tmp_path / "m.zarr")
    with ZarrStorage(path, 2 * ROWS, chunk_rows=CHUNK, goal_conditioned=False, env="FetchReach-v4") as st:
        st.set(torch.arange(ROWS), _rows(0, ROWS))
    assert remove_rows(path)
    return path


def _whole(rows: TensorDict) -> bool:
    obs = rows["obs"]
    return bool((obs == obs[:, :1]).all() and (rows["action"][:, 0] == -obs[:, 0]).all())


def test_rows_are_filled_chunk_by_chunk_and_the_asked_ones_first(store):
    """RowFill without its thread: ``ensure`` fills exactly the chunks of the rows asked for, ``wait`` the rest."""
    group = zarr.open_group(store, mode="r")
    out = {p: torch.zeros(ROWS, *group[p].shape[1:], dtype=torch.float32) for p in ("obs", "action")}
    reads = ChunkReads({p: group[p] for p in out}, out, CHUNK, local_dir=store)
    fill = RowFill(reads, ROWS, record_file=os.path.join(store, "zarr.json"), max_size=2 * ROWS,
                   fallback=lambda failure: pytest.fail("nothing here needs the synchronous path"), start=False)
    fill.ensure(np.array([5, 700]))  # chunks 0 and 10
    filled = out["obs"][:, 0] == torch.arange(ROWS, dtype=torch.float32)
    assert filled[:CHUNK].all() and filled[10 * CHUNK: 11 * CHUNK].all()
    assert int(filled.sum()) == 2 * CHUNK  # no other chunk (row 0, which holds 0 either way, is in chunk 0)
    assert not fill.done
    fill.wait()
    assert fill.done and torch.equal(out["obs"][:, 2], torch.arange(ROWS, dtype=torch.float32))
    assert torch.equal(out["action"][:, 0], -torch.arange(ROWS, dtype=torch.float32))


@pytest.mark.parametrize("record", ['{"attributes": {"write_count": "many"}}', '[1, 2]', '{"attributes": 3}', "{"])
def test_a_hostile_record_during_the_fill_hands_it_to_the_synchronous_load(store, record):
    """A record that changes into something unexpected while rows are filled: the rest of the fill is the
    synchronous load's (which checks the record and names what is wrong), never an error of its own."""
    group = zarr.open_group(store, mode="r")
    out = {"obs": torch.zeros(ROWS, 3)}
    reads = ChunkReads({"obs": group["obs"]}, out, CHUNK, local_dir=store)
    record_file = os.path.join(store, "zarr.json")

    def synchronous(failure):
        raise ValueError("the synchronous load ran")

    fill = RowFill(reads, ROWS, record_file=record_file, max_size=2 * ROWS, fallback=synchronous, start=False)
    fill.ensure(np.array([0]))  # the record as written: chunk 0 filled from its file
    assert torch.equal(out["obs"][:CHUNK, 0], torch.arange(CHUNK, dtype=torch.float32))
    with open(record_file, "w") as f:
        f.write(record)
    for _ in range(2):  # that read, and every later one
        with pytest.raises(ValueError, match="the synchronous load ran"):
            fill.ensure(np.array([500]))
    assert not bool(out["obs"][CHUNK:, 0].any())  # nothing read past chunk 0


def test_a_reader_opens_without_reading_and_serves_only_filled_rows(store):
    """The open reads no chunk; every read after it (a sample, TorchRL's ``_storage``) sees whole, filled rows."""
    gen = torch.Generator().manual_seed(0)
    with ZarrStorage(store, read_only=True) as reader:
        rb = TensorDictReplayBuffer(storage=reader, sampler=RandomSampler(), batch_size=256)
        batch = rb.sample()  # possibly before the background thread got to these chunks
        assert _whole(batch)
        idx = torch.randint(-ROWS, ROWS, (300,), generator=gen)  # negative indices count from len
        rows = reader.get(idx)
        assert torch.equal(rows["obs"][:, 0], (idx % ROWS).float())
        assert torch.equal(reader[10:20]["obs"][:, 0], torch.arange(10, 20, dtype=torch.float32))
        stored = reader._storage  # waits for the whole fill
        assert torch.equal(stored["obs"][:ROWS, 1], torch.arange(ROWS, dtype=torch.float32))
        assert reader.summary()["rows"] == ROWS


def test_a_damaged_chunk_is_refused_at_the_first_read_never_served(store):
    """A flipped byte in a chunk: the open returns, and every read of the rows raises the error a synchronous
    open raises (naming the array and the chunk), the sample's and every later one."""
    target = os.path.join(store, "action", "c.3.0")
    data = bytearray(open(target, "rb").read())
    data[len(data) // 2] ^= 0x40
    open(target, "wb").write(bytes(data))
    named = r"array 'action' chunk 3 \(action/c.3.0, rows 192-255\): checksum mismatch"
    reader = ZarrStorage(store, read_only=True)
    try:
        with pytest.raises(IntegrityError, match=named):
            reader.get(torch.tensor([200]))
        with pytest.raises(IntegrityError, match=named):
            reader.get(torch.tensor([0]))  # a chunk that reads fine: the store is refused all the same
        with pytest.raises(IntegrityError, match=named):
            _ = reader._storage
    finally:
        reader.close()
    os.environ[BACKGROUND_FILL_ENV] = str(1 << 40)  # the synchronous open says the same
    with pytest.raises(IntegrityError, match=named):
        ZarrStorage(store, read_only=True)


def test_a_missing_chunk_file_is_refused_by_the_open_itself(store):
    """The open lists the chunk files of a store it will read (metadata only): a missing one refuses the open."""
    os.remove(os.path.join(store, "obs", "c.1.0"))
    with pytest.raises(IntegrityError, match=r"array 'obs' chunk 1 \(obs/c.1.0, rows 64-127\): chunk file missing"):
        ZarrStorage(store, read_only=True)


def test_a_fill_beside_a_writer_that_appends_and_wraps_serves_whole_committed_rows(store):
    """A writer appends (the last chunk rewritten) and then wraps the ring (overwrites, journalled) while the
    reader fills: the appends are read as they are, the wrap hands the fill to the synchronous path; every row
    served is whole, and every row is one the store held (the open's, or one written since)."""
    reader = ZarrStorage(store, read_only=True)
    try:
        first = reader.get(torch.arange(0, CHUNK))  # chunk 0, before the writer's commits
        assert torch.equal(first["obs"][:, 0], torch.arange(CHUNK, dtype=torch.float32))
        with ZarrStorage(store, chunk_rows=CHUNK, goal_conditioned=False) as writer:
            writer.set(torch.arange(ROWS, ROWS + 10), _rows(ROWS, ROWS + 10))  # appends into the open chunk
            writer.flush()
            writer.set(torch.arange(ROWS + 10, 2 * ROWS), _rows(ROWS + 10, 2 * ROWS))
            writer.flush()
            writer.set(torch.arange(0, 200), _rows(5000, 5200))  # the ring wraps: rows 0-199 overwritten
            writer.flush()
        rows = reader.get(torch.arange(ROWS))
        assert _whole(rows)
        held = rows["obs"][:, 0]
        i = torch.arange(ROWS, dtype=torch.float32)
        assert bool(((held == i) | ((i < 200) & (held == i + 5000))).all())
        assert len(reader) == ROWS  # the open's length, until a refresh
        assert reader.refresh() == 2 * ROWS
        assert torch.equal(reader.get(torch.arange(200))["obs"][:, 0], torch.arange(5000, 5200, dtype=torch.float32))
    finally:
        reader.close()


def test_close_during_a_fill_stops_its_thread(store):
    before = {t.ident for t in threading.enumerate()}
    reader = ZarrStorage(store, read_only=True)
    reader.close()
    assert not [t for t in threading.enumerate() if t.name == "robotmem-fill" and t.ident not in before]


def test_a_forked_child_fills_what_is_left_itself(store):
    """A DataLoader-style fork right after the open: the child reads every row, whole, whatever the parent's
    thread had filled at the fork."""
    reader = ZarrStorage(store, read_only=True)
    try:
        pid = os.fork()
        if pid == 0:  # the child: exit code 0 if every row is right
            ok = False
            try:
                rows = reader.get(torch.arange(ROWS))
                ok = _whole(rows) and torch.equal(rows["obs"][:, 0], torch.arange(ROWS, dtype=torch.float32))
            finally:
                os._exit(0 if ok else 1)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        assert torch.equal(reader.get(torch.arange(ROWS))["obs"][:, 0], torch.arange(ROWS, dtype=torch.float32))
    finally:
        reader.close()


def test_below_the_threshold_the_open_reads_every_row(store, monkeypatch):
    monkeypatch.setenv(BACKGROUND_FILL_ENV, str(1 << 40))
    with ZarrStorage(store, read_only=True) as reader:
        assert reader._store.mirror.fill is None
    assert glob.glob(os.path.join(store, "obs", "c.*"))


# -- the writer's fill (after a crash, or any open that finds no usable row file) ----------------------------------


@pytest.fixture
def writer_fill(monkeypatch):
    """The writer's fill without its background thread: only what the open and each write ask for is filled,
    then the rest at the first read of every row. What the thread would race is made to happen by construction."""
    import functools

    import torchrl_robotmem.storage.mirror as mirror_module

    monkeypatch.setattr(mirror_module, "RowFill", functools.partial(RowFill, start=False))


def _open_writer(path: str) -> ZarrStorage:
    writer = ZarrStorage(path, chunk_rows=CHUNK, goal_conditioned=False)
    assert writer.row_file["background"] and writer._store.mirror.fill is not None  # the open read only what it needs
    return writer


def test_a_writers_open_fills_in_the_background_and_a_write_below_the_length_is_kept(store, writer_fill):
    """Rows rewritten in place right after the open, in a chunk not filled yet: the chunk is filled first, so
    the fill never writes the old rows over the new ones (a reopen reads the rewrite)."""
    writer = _open_writer(store)
    try:
        assert not writer._store.mirror.fill.ready(np.array([320]))  # chunk 5: not read by the open
        writer.set(torch.arange(320, 330), _rows(7000, 7010))
        writer.set(slice(640, 650), _rows(8000, 8010))  # a slice too (the append path's copy)
        rows = writer.get(torch.arange(ROWS))  # every chunk filled now
        expected = torch.arange(ROWS, dtype=torch.float32)
        expected[320:330] += 6680
        expected[640:650] += 7360
        assert _whole(rows) and torch.equal(rows["obs"][:, 0], expected)
    finally:
        writer.close()
    with ZarrStorage(store, read_only=True) as reader:
        assert reader.row_file["sealed"]  # the close waited for the fill: the file holds every row
        assert torch.equal(reader.get(torch.arange(ROWS))["obs"][:, 0], expected)


def test_a_writers_open_closes_the_episode_left_open_and_appends_after_it(store, writer_fill):
    """The store's one episode was left open (its rows were never ended): the open ends it on its last row,
    from the tag columns it read before the fill; the fill does not undo the flag; new rows get a new episode."""
    writer = _open_writer(store)
    try:
        writer.set(torch.arange(ROWS, ROWS + 10), _rows(ROWS, ROWS + 10))
        last = writer.get(torch.tensor([ROWS - 1, ROWS]))
        rows = writer.get(torch.arange(ROWS + 10))  # every chunk filled
        assert bool(last["next", "done"][0]) and not bool(last["next", "done"][1])
        assert int(rows["next", "done"].sum()) == 1
        episodes = writer["episode"][: ROWS + 10].reshape(-1)
        assert int(episodes[ROWS]) > int(episodes[:ROWS].max())  # an id not in use
    finally:
        writer.close()
    with ZarrStorage(store, read_only=True) as reader:
        assert bool(reader.get(torch.tensor([ROWS - 1]))["next", "done"][0])
        assert torch.equal(reader.get(torch.arange(ROWS + 10))["obs"][:, 0], torch.arange(ROWS + 10, dtype=torch.float32))


def test_a_writers_fill_refuses_a_damaged_chunk_and_keeps_what_it_writes_elsewhere(store, writer_fill):
    """A flipped byte in chunk 3: the open returns; a read or write of that chunk raises, naming it; rows written
    past the opened length are committed all the same (the chunk they go into was filled at the open)."""
    target = os.path.join(store, "action", "c.3.0")
    data = bytearray(open(target, "rb").read())
    data[len(data) // 2] ^= 0x40
    open(target, "wb").write(bytes(data))
    writer = _open_writer(store)
    try:
        with pytest.raises(IntegrityError, match=r"array 'action' chunk 3 \(action/c.3.0, rows 192-255\): checksum mismatch"):
            writer.get(torch.tensor([200]))
        with pytest.raises(IntegrityError, match=r"array 'action' chunk 3"):
            writer.set(torch.tensor([201]), _rows(9000, 9001))
        writer.set(torch.arange(ROWS, ROWS + 10), _rows(ROWS, ROWS + 10))
        writer.flush()
    finally:
        writer.close()
    group = zarr.open_group(store, mode="r")
    assert group.attrs["len"] == ROWS + 10
    assert np.array_equal(group["obs"][ROWS:ROWS + 10, 0], np.arange(ROWS, ROWS + 10, dtype=np.float32))
    assert not os.path.exists(os.path.join(store, "_rows", "seal.json"))  # not sealed: the next open reads again


def test_a_commit_of_a_chunk_the_writers_fill_cannot_read_is_an_error_not_a_hang(store, writer_fill):
    """Every row marked for a commit again (what TorchRL's in-place writes do) while chunk 3 cannot be filled:
    the commit's snapshot of chunk 3 raises; ``flush`` and ``close`` say so (the writer thread used to die there,
    and ``flush`` waited for it forever)."""
    target = os.path.join(store, "action", "c.3.0")
    data = bytearray(open(target, "rb").read())
    data[len(data) // 2] ^= 0x40
    open(target, "wb").write(bytes(data))
    writer = _open_writer(store)
    writer._store.mark_rows_dirty(ROWS)
    with pytest.raises(RuntimeError, match=r"array 'action' chunk 3 \(action/c.3.0, rows 192-255\): checksum mismatch"):
        writer.flush()
    with pytest.raises(RuntimeError, match="chunk 3"):
        writer.close()
