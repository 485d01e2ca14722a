"""The row tier (issue 41): rows mapped from ``_rows/rows.bin``, served without a chunk read when sealed, and a
memory without a declared capacity.

Real stores under ``tmp_path``; crash and cgroup cases are in ``tests/reliability/test_row_tier_faults.py``.
"""
from __future__ import annotations

import copy
import gc
import glob
import json
import os
import re

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer, TensorDictReplayBuffer

from torchrl_robotmem import WindowSampler, ZarrStorage
from torchrl_robotmem.storage.checkpointer import ZarrCheckpointer
from torchrl_robotmem.storage.integrity import IntegrityError, repair, verify
from torchrl_robotmem.storage.integrity.rows import row_file_problems
from torchrl_robotmem.storage.rowfile import ROWS_DIR, SEAL_FILE, remove_rows

CHUNK = 64


def _rows(lo: int, hi: int) -> TensorDict:
    """Rows whose values say which row they are (row ``i`` holds ``i``)."""
    i = torch.arange(lo, hi, dtype=torch.float32)
    return TensorDict({"obs": i[:, None].expand(-1, 3).clone(), "action": -i[:, None],
                       ("next", "done"): torch.zeros(hi - lo, 1, dtype=torch.bool)}, [hi - lo])


def _write(path, n: int, **kwargs) -> None:
    with ZarrStorage(path, kwargs.pop("max_size", 1000), chunk_rows=CHUNK, goal_conditioned=False, **kwargs) as st:
        st.set(torch.arange(n), _rows(0, n))


def _seal(path) -> dict:
    with open(os.path.join(path, ROWS_DIR, SEAL_FILE)) as f:
        return json.load(f)


def test_a_clean_close_seals_the_rows_and_an_open_serves_them_without_a_chunk(tmp_path):
    """Every chunk file moved away after the seal: a sealed open still serves every row (it reads none)."""
    path = str(tmp_path / "m.zarr")
    _write(path, 4 * CHUNK)
    assert _seal(path)["layout"]["shape"] == [1000]
    for node in ("obs", "action", "next/done"):
        for chunk in glob.glob(os.path.join(path, node, "c.*")):  # what is served is the row file, not the chunks
            os.remove(chunk)
    with ZarrStorage(path, read_only=True) as st:
        assert st.row_file == {"file": os.path.join(os.path.realpath(path), ROWS_DIR, "rows.bin"),
                               "sealed": True, "shared": True, "background": False}
        assert torch.equal(st["obs"], _rows(0, 4 * CHUNK)["obs"])
    with ZarrStorage(path) as st:  # a writer neither: it checks the arrays' metadata, lists no chunk
        assert st.row_file["sealed"] is True and torch.equal(st["obs"], _rows(0, 4 * CHUNK)["obs"])
    assert not verify(path).ok  # the damage is verify's to find: it reads every chunk
    remove_rows(path)  # without the row file the chunks are read, and the damage refuses every open
    for read_only in (True, False):
        with pytest.raises(IntegrityError, match="chunk file missing"):
            ZarrStorage(path, read_only=read_only)


def test_without_a_seal_the_open_fills_the_rows_from_the_chunks(tmp_path):
    path = str(tmp_path / "m.zarr")
    _write(path, 3 * CHUNK)
    os.remove(os.path.join(path, ROWS_DIR, SEAL_FILE))
    with ZarrStorage(path, read_only=True) as st:
        assert st.row_file["sealed"] is False and st.row_file["file"] is None  # a private, unlinked file
        assert torch.equal(st["action"], _rows(0, 3 * CHUNK)["action"])


@pytest.mark.parametrize("change", ["bytes", "grown", "record", "layout", "other_store", "garbage"])
def test_a_row_file_that_does_not_match_its_seal_is_filled_again_never_served(tmp_path, change):
    path = str(tmp_path / "m.zarr")
    n = 2 * CHUNK
    _write(path, n)
    rows_bin = os.path.join(path, ROWS_DIR, "rows.bin")
    seal_path = os.path.join(path, ROWS_DIR, SEAL_FILE)
    seal = _seal(path)
    if change == "bytes":  # written since the seal (its modification time moves)
        with open(rows_bin, "r+b") as f:
            f.seek(8)
            f.write(b"\xff" * 64)
        st_ = os.stat(rows_bin)
        os.utime(rows_bin, ns=(st_.st_atime_ns, st_.st_mtime_ns + 1_000_000))
    elif change == "grown":
        with open(rows_bin, "ab") as f:
            f.write(b"\0" * 4096)
    elif change == "record":
        seal["record"] = "0" * 64
    elif change == "layout":
        seal["layout"]["row_bytes"] += 8
    elif change == "other_store":  # the seal of another memory with the same columns, copied over
        other = str(tmp_path / "other.zarr")
        _write(other, n + 1)
        seal = _seal(other)
    if change == "garbage":
        with open(seal_path, "w") as f:
            f.write("{not json")
    elif change in ("record", "layout", "other_store"):
        with open(seal_path, "w") as f:
            json.dump(seal, f)
    with ZarrStorage(path, read_only=True) as st:
        assert st.row_file["sealed"] is False
        assert torch.equal(st["obs"], _rows(0, n)["obs"])
        assert torch.equal(st["action"], _rows(0, n)["action"])


def test_verify_rows_finds_a_row_file_rewritten_with_its_seal(tmp_path):
    """A row file and seal both rewritten (someone who can write the store): served, and found by verify --rows."""
    path = str(tmp_path / "m.zarr")
    _write(path, 2 * CHUNK)
    rows_bin = os.path.join(path, ROWS_DIR, "rows.bin")
    seal = _seal(path)
    with open(rows_bin, "r+b") as f:
        f.write(b"\x7f" * 8)
    st_ = os.stat(rows_bin)
    seal["file"] = [st_.st_dev, st_.st_ino, st_.st_size, st_.st_mtime_ns]
    with open(os.path.join(path, ROWS_DIR, SEAL_FILE), "w") as f:
        json.dump(seal, f)
    problems = row_file_problems(path)
    assert problems and all(p.kind == "rows" and p.rows == (0, CHUNK) for p in problems)
    report = repair(path)
    assert any("row file" in a for a in report.actions) or not os.path.exists(rows_bin)
    assert row_file_problems(path) == []
    with ZarrStorage(path, read_only=True) as st:
        assert torch.equal(st["obs"], _rows(0, 2 * CHUNK)["obs"])


def test_a_reader_keeps_its_rows_while_a_writer_writes_and_closes(tmp_path):
    """The writer cannot lock the reader's file: it writes its own and renames it over at its close."""
    path = str(tmp_path / "m.zarr")
    _write(path, CHUNK)
    reader = ZarrStorage(path, read_only=True)
    assert reader.row_file["sealed"]
    with ZarrStorage(path) as writer:
        assert writer.row_file["file"] != reader.row_file["file"]
        writer.set(torch.arange(CHUNK), _rows(500, 500 + CHUNK))  # overwrites the reader's rows
        writer.flush()
        assert torch.equal(reader["obs"], _rows(0, CHUNK)["obs"])
    assert torch.equal(reader["obs"], _rows(0, CHUNK)["obs"]) and len(reader) == CHUNK
    assert sorted(os.listdir(os.path.join(path, ROWS_DIR))) == ["rows.bin", SEAL_FILE]
    with ZarrStorage(path, read_only=True) as fresh:
        assert fresh.row_file["sealed"] and torch.equal(fresh["obs"][:CHUNK], _rows(500, 500 + CHUNK)["obs"])
    reader.close()


def test_a_writer_reopening_a_sealed_store_continues_in_place_and_closes_episodes(tmp_path):
    path = str(tmp_path / "m.zarr")
    _write(path, CHUNK)  # one episode, left open (no done)
    with ZarrStorage(path) as st:
        assert st.row_file["sealed"] and st.row_file["file"].endswith("rows.bin")
        assert bool(st["next", "done"][CHUNK - 1])  # the episode the last run left open is ended, from the seal
        st.set(torch.arange(CHUNK, 2 * CHUNK), _rows(CHUNK, 2 * CHUNK))
        assert not os.path.exists(os.path.join(path, ROWS_DIR, SEAL_FILE))  # unsealed before the first write
    with ZarrStorage(path, read_only=True) as st:
        assert len(st) == 2 * CHUNK and torch.equal(st["obs"], _rows(0, 2 * CHUNK)["obs"])


def test_a_new_column_moves_the_rows_to_a_new_file(tmp_path):
    path = str(tmp_path / "m.zarr")
    _write(path, CHUNK)
    with ZarrStorage(path) as st:
        st.set(torch.arange(CHUNK, CHUNK + 4), _rows(CHUNK, CHUNK + 4).update({"extra": torch.ones(4, 2)}))
    with ZarrStorage(path, read_only=True) as st:
        assert st.row_file["sealed"]
        assert torch.equal(st["obs"], _rows(0, CHUNK + 4)["obs"])
        assert st["extra"][:CHUNK].abs().sum() == 0 and bool((st["extra"][CHUNK:] == 1).all())


def test_copies_and_checkpoints_leave_the_row_file_out(tmp_path):
    from torchrl_robotmem.cli.copy_memory import copy_memory

    path = str(tmp_path / "m.zarr")
    _write(path, CHUNK)
    copy_memory(path, str(tmp_path / "copy.zarr"))
    assert not os.path.exists(tmp_path / "copy.zarr" / ROWS_DIR) or not os.path.exists(
        tmp_path / "copy.zarr" / ROWS_DIR / SEAL_FILE)
    rb = ReplayBuffer(storage=ZarrStorage(path))
    rb.dumps(tmp_path / "ckpt")
    rb.storage.close()
    copies = [root for root, dirs, _ in os.walk(tmp_path / "ckpt") if ROWS_DIR in dirs]
    assert copies == []  # a writer writes its row file in place: a hard link to it would change with it
    ZarrCheckpointer  # noqa: B018 - the checkpointer that made the copy


# -- a memory without a declared capacity -------------------------------------------------------


def test_a_memory_without_a_capacity_grows_and_never_wraps(tmp_path):
    path = str(tmp_path / "u.zarr")
    st = ZarrStorage(path, chunk_rows=CHUNK, goal_conditioned=False)
    assert st.bounded is False and st.max_size > 2**40
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    capacities = set()
    for lo in range(0, 60 * CHUNK, 40):
        rb.extend(_rows(lo, lo + 40))
        capacities.add(st.capacity)
    assert len(st) == 60 * CHUNK and len(capacities) > 2  # it grew, several times
    assert torch.equal(st["obs"], _rows(0, 60 * CHUNK)["obs"])  # every row kept: no ring
    st.close()
    with ZarrStorage(path, read_only=True) as r:
        assert r.row_file["sealed"] and not r.bounded and torch.equal(r["action"], _rows(0, 60 * CHUNK)["action"])
    with ZarrStorage(path) as w:
        TensorDictReplayBuffer(storage=w).extend(_rows(60 * CHUNK, 61 * CHUNK))
        assert len(w) == 61 * CHUNK and w.write_count == 61 * CHUNK
    assert ZarrStorage(path, read_only=True).record()["torchrl_robotmem"]["format_version"] == 2
    with pytest.raises(ValueError, match="no declared capacity"):
        ZarrStorage(path, 100)


def test_a_bounded_memory_keeps_its_ring_and_format_1(tmp_path):
    path = str(tmp_path / "b.zarr")
    with ZarrStorage(path, 2 * CHUNK, chunk_rows=CHUNK, goal_conditioned=False) as st:
        rb = TensorDictReplayBuffer(storage=st)
        rb.extend(_rows(0, 3 * CHUNK))
        assert st.bounded and st.capacity == 2 * CHUNK and len(st) == 2 * CHUNK
        assert st.record()["torchrl_robotmem"]["format_version"] == 1
        assert torch.equal(st["obs"][:CHUNK], _rows(2 * CHUNK, 3 * CHUNK)["obs"])


@pytest.mark.parametrize("arrays_say_so", [True, False], ids=["arrays-say-so", "older-arrays"])
def test_repair_of_a_lost_record_keeps_a_memory_without_a_capacity_growing(tmp_path, arrays_say_so):
    """The record (group ``zarr.json``) of a grown memory lost: its arrays say it had no capacity, and the
    rebuilt memory grows again; arrays of an older version, which do not, come back as a ring, as the report says."""
    path = str(tmp_path / "u.zarr")
    n = 5 * CHUNK + 10  # grown past its first chunk, not to a whole number of chunks
    with ZarrStorage(path, chunk_rows=CHUNK, goal_conditioned=False) as st:
        st.set(torch.arange(n), _rows(0, n))
        allocated = st.capacity
    assert allocated > n
    for node in ("obs", "action", "next/done", "episode", "run", "env"):
        meta_path = os.path.join(path, node, "zarr.json")
        with open(meta_path) as f:
            meta = json.load(f)
        assert meta["attributes"] == {"unbounded": True}, node
        if not arrays_say_so:  # as the arrays of stores written before they said so
            meta["attributes"] = {}
            with open(meta_path, "w") as f:
                json.dump(meta, f)
    os.remove(os.path.join(path, "zarr.json"))
    result = repair(path)
    assert result.ok and result.after.ok
    (action,) = [a for a in result.actions if a.startswith("rebuilt the commit record")]
    with ZarrStorage(path) as st:
        assert len(st) == n and torch.equal(st["obs"], _rows(0, n)["obs"])
        assert st.bounded is not arrays_say_so
        assert st.record()["torchrl_robotmem"]["format_version"] == (2 if arrays_say_so else 1)
        TensorDictReplayBuffer(storage=st).extend(_rows(n, allocated + CHUNK))  # past the rows allocated
        if arrays_say_so:
            assert "as a memory without a declared capacity" in action, action
            assert len(st) == allocated + CHUNK and torch.equal(st["obs"], _rows(0, allocated + CHUNK)["obs"])
        else:
            assert f"as a ring of {allocated:,} rows" in action, action
            assert len(st) == allocated  # wrapped: the first rows overwritten, as the report warned
            assert torch.equal(st["obs"][:CHUNK], _rows(allocated, allocated + CHUNK)["obs"])
    assert verify(path).ok


def test_window_sampler_reads_the_newest_rows_of_a_growing_memory(tmp_path):
    torch.manual_seed(0)
    st = ZarrStorage(str(tmp_path / "w.zarr"), chunk_rows=CHUNK, goal_conditioned=False)
    rb = TensorDictReplayBuffer(storage=st, sampler=WindowSampler(32), batch_size=256)
    for lo in range(0, 10 * CHUNK, 100):
        rb.extend(_rows(lo, lo + 100))
        got = rb.sample()["obs"][:, 0]
        assert got.min() >= len(st) - 32 and got.max() < len(st)
    st.close()


def test_a_tailing_reader_follows_a_growing_memory(tmp_path):
    path = str(tmp_path / "t.zarr")
    writer = ZarrStorage(path, chunk_rows=CHUNK, goal_conditioned=False)
    writer.set(torch.arange(CHUNK), _rows(0, CHUNK))
    writer.flush()
    reader = ZarrStorage(path, read_only=True)
    assert len(reader) == CHUNK
    writer.set(torch.arange(CHUNK, 5 * CHUNK), _rows(CHUNK, 5 * CHUNK))
    writer.flush()
    assert reader.refresh() == 5 * CHUNK
    assert torch.equal(reader["obs"], _rows(0, 5 * CHUNK)["obs"])
    writer.close()
    reader.close()


def test_lazy_tensor_storage_and_an_unbounded_memory_sample_alike(tmp_path):
    """The same rows, extended the same way: the same sampled rows for the same seed."""
    zarr = ZarrStorage(str(tmp_path / "s.zarr"), chunk_rows=CHUNK, goal_conditioned=False)
    out = []
    for storage in (LazyTensorStorage(10_000), zarr):
        torch.manual_seed(3)
        rb = TensorDictReplayBuffer(storage=storage, batch_size=16)
        rb.extend(_rows(0, 300))
        out.append(rb.sample()["obs"])
    assert torch.equal(out[0], out[1])
    zarr.close()


def test_a_sealed_writer_still_refuses_an_array_whose_metadata_disagrees_with_the_record(tmp_path):
    """A writer served by a sealed file reads each array's zarr.json alone (no chunk), and refuses one that
    disagrees with the record's schema, naming both, before it writes anything."""
    path = str(tmp_path / "m.zarr")
    _write(path, 2 * CHUNK)
    meta_file = os.path.join(path, "obs", "zarr.json")
    meta = json.loads(open(meta_file).read())
    meta["data_type"] = "float64"
    with open(meta_file, "w") as f:
        json.dump(meta, f)
    with pytest.raises(IntegrityError, match=r"array is float64 \[1000, 3\] chunked \[64, 3\] \(obs/zarr.json\), but the schema"):
        ZarrStorage(path)
    with ZarrStorage(path, read_only=True) as st:  # a sealed reader opens no array: it serves the sealed rows
        assert st.row_file["sealed"] is True and torch.equal(st["obs"], _rows(0, 2 * CHUNK)["obs"])


def _row_file_flags(path) -> list[set[str]]:
    """The ``VmFlags`` of this process's mappings of ``path`` (``/proc/self/smaps``)."""
    out, current, target = [], False, os.path.realpath(path)
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()
            if re.match(r"[0-9a-f]+-[0-9a-f]+ ", line):  # a mapping's header (an anonymous one names no file)
                current = len(head) >= 6 and os.path.realpath(" ".join(head[5:])) == target
            elif line.startswith("VmFlags:") and current:
                out.append(set(head[1:]))
    return out


@pytest.mark.skipif(not os.path.exists("/proc/self/smaps"), reason="reads the kernel's VmFlags of each mapping")
@pytest.mark.parametrize("read_only", [True, False])
def test_the_row_file_is_mapped_for_samples_and_scans_turn_readahead_on(tmp_path, read_only):
    """``rr`` (MADV_RANDOM: a fault reads only its page) outside a scan; the kernel's readahead inside one."""
    path = str(tmp_path / "m.zarr")
    _write(path, 4 * CHUNK)
    rows_bin = os.path.join(path, ROWS_DIR, "rows.bin")
    gc.collect()  # the closed writer's views (a reference cycle) go, and the mapping they kept with them
    with ZarrStorage(path, read_only=read_only) as st:
        st.get(torch.arange(3))  # a sample: the mapping is in use
        flags = _row_file_flags(rows_bin)
        assert flags and all("rr" in f for f in flags), flags
        with st.scanning():
            with st.scanning():  # nested: readahead stays on until the outer scan ends
                pass
            assert all("rr" not in f for f in _row_file_flags(rows_bin))
        assert all("rr" in f for f in _row_file_flags(rows_bin))


@pytest.mark.parametrize("max_size", [None, 300])  # a memory that grows, and a ring that wraps
def test_a_clean_close_reads_only_the_appended_rows_and_seals_the_episodes_a_full_scan_finds_open(tmp_path, max_size):
    """The seal's open episode ends, read from this session's rows alone, equal a scan of every row."""
    path = str(tmp_path / "m.zarr")
    gen = torch.Generator().manual_seed(0)
    written = 0
    for session in range(4):
        st = ZarrStorage(path, max_size, chunk_rows=CHUNK, goal_conditioned=False)
        for _ in range(3):  # batches of random length whose last episode is often left open
            n = int(torch.randint(1, 90, (1,), generator=gen))
            rows = _rows(written, written + n)
            rows["next", "done"] = torch.rand(n, 1, generator=gen) < 0.1
            st.set(torch.arange(written, written + n) % (max_size or 10**9), rows)
            written += n
        st.close()
        with ZarrStorage(path, read_only=True) as reader:
            store = reader._store
            n = len(reader)
            full = n >= store.mirror.max_size
            scan = store.mirror.open_episode_ends(n, store.cursor, full=full).tolist()
        assert sorted(_seal(path)["open_ends"]) == sorted(scan), f"session {session}"
    with ZarrStorage(path, max_size) as st:  # a writer that appends nothing seals no open end
        pass
    assert _seal(path)["open_ends"] == []


@pytest.mark.parametrize("how", ["set", "update_"])  # ZarrStorage.set in place; TorchRL's in-place write of the rows
def test_an_in_place_write_that_reopens_an_old_episode_is_sealed_open(tmp_path, how):
    """A session that clears an older row's done flag (appending nothing) seals that episode as open."""
    path = str(tmp_path / "m.zarr")
    rows = _rows(0, 20)
    rows["next", "done"][[9, 19]] = True  # two whole episodes
    with ZarrStorage(path, 100, chunk_rows=CHUNK, goal_conditioned=False) as st:
        st.set(torch.arange(20), rows)
    assert _seal(path)["open_ends"] == []
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 100, chunk_rows=CHUNK, goal_conditioned=False))
    if how == "set":
        row = rows[9:10].clone()
        row["next", "done"][:] = False
        rb.storage.set(torch.tensor([9]), row, set_cursor=False)
    else:
        done = rb.storage[:]["next", "done"].clone()
        done[9] = False
        rb.update_(TensorDict({("next", "done"): done}, [len(rb)]))
    rb.storage.close()
    assert _seal(path)["open_ends"] == [9]
    with ZarrStorage(path, 100, chunk_rows=CHUNK, goal_conditioned=False) as st:  # the next writer closes it
        assert bool(st[9]["next", "done"])


def test_an_unbounded_memory_counts_rows_written_again_as_torchrl_does_and_reopens(tmp_path):
    """Found by a review: TorchRL adds every row a set names to len (rows written again too); the memory grew
    only to the highest row written, so len passed the rows allocated, reads raised, and the record committed
    made every later open refuse the store."""
    path = str(tmp_path / "again.zarr")
    st, reference = ZarrStorage(path, chunk_rows=CHUNK, goal_conditioned=False), LazyTensorStorage(100_000)
    for s in (st, reference):
        s.set(torch.arange(10), _rows(0, 10))
    first = st.capacity  # what the first write allocated (1,024 rows)
    for s in (st, reference):
        for _ in range(first // 10 + 2):
            s.set(torch.arange(10), _rows(0, 10))  # rows 0..9 again and again: len past the rows allocated
    n = len(reference)
    assert n > first and len(st) == n and st.capacity >= n
    assert torch.equal(st.get(torch.arange(10))["obs"], reference.get(torch.arange(10))["obs"])
    assert st.get(torch.arange(n)).shape == (n,)
    st.close()
    with ZarrStorage(path, read_only=True) as r:
        assert len(r) == n and torch.equal(r["obs"][:10], _rows(0, 10)["obs"])


@pytest.mark.parametrize("n", [1024, 2048])
def test_a_state_that_fills_the_rows_of_an_unbounded_memory_appends_after_them(tmp_path, n):
    """Found by a review: a loaded state of exactly as many rows as the memory had allocated (1,024 or 2,048
    here) put its cursor at row 0 (the modulo of a ring), so the next write overwrote the first rows."""
    path = str(tmp_path / "fill.zarr")
    source = LazyTensorStorage(n)
    source.set(torch.arange(n), _rows(0, n))
    st = ZarrStorage(path, chunk_rows=CHUNK, goal_conditioned=False)
    st.load_state_dict(source.state_dict())
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    rb.extend(_rows(n, n + 5))
    assert len(st) == n + 5 and torch.equal(st["obs"], _rows(0, n + 5)["obs"])
    st.close()
    with ZarrStorage(path) as again:
        TensorDictReplayBuffer(storage=again).extend(_rows(n + 5, n + 10))
        assert torch.equal(again["obs"], _rows(0, n + 10)["obs"])


@pytest.mark.parametrize("max_size", [None, 1000])
def test_loads_of_an_older_checkpoint_of_the_same_store_restores_it_as_lazy_tensor_storage_does(tmp_path, max_size):
    """Found by a review: the store kept its newer rows while TorchRL then loaded the checkpoint's writer (after
    the storage), so the next extend overwrote rows and counted rows never written into len."""
    path = str(tmp_path / "self.zarr")
    buffers = {"zarr": TensorDictReplayBuffer(storage=ZarrStorage(path, max_size, chunk_rows=CHUNK,
                                                                  goal_conditioned=False), batch_size=4),
               "lazy": TensorDictReplayBuffer(storage=LazyTensorStorage(100_000), batch_size=4)}
    for name, rb in buffers.items():
        rb.extend(_rows(0, 300))
        rb.dumps(tmp_path / f"ckpt-{name}")
        rb.extend(_rows(300, 400))
        rb.loads(tmp_path / f"ckpt-{name}")
        rb.extend(_rows(1000, 1010))
    zarr, lazy = buffers["zarr"], buffers["lazy"]
    assert len(zarr) == len(lazy) == 310
    assert torch.equal(zarr.storage[:]["obs"], lazy.storage[:]["obs"])
    assert zarr.writer.state_dict() == lazy.writer.state_dict()
    zarr.storage.close()
    again = TensorDictReplayBuffer(storage=ZarrStorage(path, goal_conditioned=False), batch_size=4)
    assert len(again) == 310 and int(again.writer._cursor) == 310
    again.storage.close()


@pytest.mark.parametrize("max_size", [None, 130])
def test_load_state_dict_of_an_older_state_of_the_same_store_restores_it_as_lazy_tensor_storage_does(
        tmp_path, max_size):
    """Found by a review: the store kept its newer rows and only put the writer back where the store stood, then
    TorchRL loaded the state's writer (after the storage): the newest rows were past the writer's cursor, and
    HER's episode ends (the last written row) said another episode's."""
    path = str(tmp_path / "self.zarr")
    buffers = {"zarr": TensorDictReplayBuffer(storage=ZarrStorage(path, max_size, chunk_rows=16,
                                                                  goal_conditioned=False), batch_size=4),
               "lazy": TensorDictReplayBuffer(storage=LazyTensorStorage(max_size or 100_000), batch_size=4)}
    for rb in buffers.values():
        rb.extend(_rows(0, 170))  # the ring wrapped
        state = copy.deepcopy(rb.state_dict())  # a copy (as torch.save makes one)
        rb.extend(_rows(170, 237))
        rb.load_state_dict(state)
        rb.extend(_rows(1000, 1010))
    zarr, lazy = buffers["zarr"], buffers["lazy"]
    assert len(zarr) == len(lazy) == (130 if max_size else 180)
    assert torch.equal(zarr.storage[:]["obs"], lazy.storage[:]["obs"])
    assert zarr.writer.state_dict() == lazy.writer.state_dict()
    zarr.storage.close()
    with ZarrStorage(path, goal_conditioned=False) as again:
        assert torch.equal(again[:]["obs"], lazy.storage[:]["obs"])


def test_load_state_dict_of_the_same_store_s_live_rows_after_it_moved_on_is_refused_and_changes_nothing(tmp_path):
    path = str(tmp_path / "live.zarr")
    with ZarrStorage(path, 100, chunk_rows=16, goal_conditioned=False) as st:
        rb = TensorDictReplayBuffer(storage=st)
        rb.extend(_rows(0, 40))
        live = rb.state_dict()  # the storage's own tensors: no copy
        rb.load_state_dict(live)  # nothing moved: the writer goes back where the store is
        rb.extend(_rows(40, 50))
        with pytest.raises(ValueError, match=r"moved on since \(len 40 -> 50, rows written 40 -> 50\).*not a copy"):
            rb.load_state_dict(live)
        assert len(st) == 50 and torch.equal(st["obs"], _rows(0, 50)["obs"]) and st.write_count == 50
        rb.extend(_rows(50, 55))
        assert torch.equal(st["obs"], _rows(0, 55)["obs"])


def _obs(lo: int, n: int, **extra) -> TensorDict:
    return TensorDict({"obs": torch.arange(lo, lo + n, dtype=torch.float32).unsqueeze(-1), **extra}, [n])


@pytest.mark.parametrize("how", ["load_state_dict", "dumps/loads"])
@pytest.mark.parametrize("change", ["written again in place", "emptied and refilled"])
def test_a_rollback_to_a_state_with_the_same_counts_restores_its_rows_as_lazy_tensor_storage_does(
        tmp_path, how, change):
    """Found by a review: the store was taken as the state left it whenever len and write_count matched, and
    in-place writes (rb[i] = x) and an empty() then as many rows again keep both counts: the newer rows stayed."""
    out = {}
    for name, st in (("lazy", LazyTensorStorage(10)), ("zarr", ZarrStorage(str(tmp_path / "m.zarr"), 10,
                                                                            goal_conditioned=False))):
        rb = TensorDictReplayBuffer(storage=st, batch_size=2)
        rb.extend(_obs(0, 4))
        ckpt = tmp_path / f"ckpt-{name}"
        state = copy.deepcopy(rb.state_dict()) if how == "load_state_dict" else rb.dumps(ckpt)
        if change == "written again in place":
            rb[1] = _obs(100, 1)[0]
        else:
            rb.empty()
            rb.extend(_obs(50, 4))
        rb.load_state_dict(state) if how == "load_state_dict" else rb.loads(ckpt)
        out[name] = (rb.storage[:]["obs"].flatten().tolist(), rb.writer.state_dict())
    assert out["zarr"] == out["lazy"] and out["lazy"][0] == [0.0, 1.0, 2.0, 3.0]
    rb.storage.close()
    with ZarrStorage(str(tmp_path / "m.zarr"), read_only=True) as again:
        assert again["obs"].flatten().tolist() == [0.0, 1.0, 2.0, 3.0]


_ROLLBACK_KILLED = """
import copy, os, signal, sys, torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem import ZarrStorage
from torchrl.data import LazyTensorStorage
path, max_size, source = sys.argv[1], (int(sys.argv[2]) or None), sys.argv[3]
obs = lambda lo, n: TensorDict({"obs": torch.arange(lo, lo + n, dtype=torch.float32).unsqueeze(-1)}, [n])
st = ZarrStorage(path, max_size, goal_conditioned=False)
rb = TensorDictReplayBuffer(storage=st, batch_size=2)
rb.extend(obs(0, 30))
state = copy.deepcopy(rb.state_dict())
if source == "a state with a column the store lacks":
    other = LazyTensorStorage(30)
    other.set(torch.arange(30), TensorDict({"obs": -obs(0, 30)["obs"], "extra": torch.ones(30, 1)}, [30]))
    state = other.state_dict()
if source == "a state with a constant the store lacks":
    other = ZarrStorage(path + "-other", 30, goal_conditioned=False)
    other.set(torch.arange(30), TensorDict({"obs": -obs(0, 30)["obs"], "label": "scripted"}, [30]))
    state = copy.deepcopy(other.state_dict())
    other.close()
rb.extend(obs(100, 30))
st.flush()  # 60 rows durable
real = ZarrStorage._set
def then_killed(self, *args, **kwargs):  # the state's rows written (in RAM), the load not finished
    real(self, *args, **kwargs)
    os.kill(os.getpid(), signal.SIGKILL)
ZarrStorage._set = then_killed
(rb if source == "the store's own older state" else st).load_state_dict(state)
"""


@pytest.mark.parametrize("source", ["the store's own older state", "a state with a column the store lacks",
                                    "a state with a constant the store lacks"])
@pytest.mark.parametrize("max_size", [64, None], ids=["ring", "unbounded"])
def test_a_rollback_killed_before_it_ends_leaves_the_rows_of_before_it(tmp_path, max_size, source):
    """``load_state_dict`` that replaces the rows (a rollback) emptied the store durably first, then wrote the
    state's rows: a SIGKILL in between left an empty memory. The whole replacement is now one commit. Found by a
    review of that fix: a state adding a column committed the emptied store while adding it (now added first).
    Found by the next review: a state adding a constant wrote it to the record at once, so the rows of before
    came back with it, and a write without it was refused (the constants now go in the commit's record)."""
    import subprocess
    import sys

    path = str(tmp_path / "m.zarr")
    proc = subprocess.run([sys.executable, "-c", _ROLLBACK_KILLED, path, str(max_size or 0), source],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr[-2000:]
    with ZarrStorage(path, read_only=True) as back:
        assert back["obs"].flatten().tolist() == list(range(30)) + list(range(100, 130))
        assert "label" not in back[:2].keys()
    # it goes on, with the rows of before (a column the load added first stays: older rows read zeros there)
    extra = {"extra": torch.ones(2, 1)} if source == "a state with a column the store lacks" else {}
    with ZarrStorage(path, goal_conditioned=False) as back:
        back.set(torch.arange(60, 62), _obs(200, 2, **extra))
        assert back["obs"].flatten().tolist()[-3:] == [129.0, 200.0, 201.0]


@pytest.mark.parametrize("max_size", [64, None], ids=["ring", "unbounded"])
def test_a_rollback_that_fails_half_way_commits_none_of_it(tmp_path, monkeypatch, max_size):
    """An error inside the rows' replacement (after the store's rows were emptied and the state's written in
    RAM) left that half-done RAM to the next commit: the memory of before was lost. Now none of it is committed,
    the rows of before (also those not yet committed when the load began) stay, the handle closes saying so."""
    from torchrl_robotmem.storage.store import MemoryStore

    path = str(tmp_path / "m.zarr")
    st = ZarrStorage(path, max_size, goal_conditioned=False, commit_interval=3600.0)
    rb = TensorDictReplayBuffer(storage=st, batch_size=2)
    rb.extend(_obs(0, 30))
    state = copy.deepcopy(rb.state_dict())
    rb.extend(_obs(100, 30))  # not committed yet (no flush, the timer an hour away)

    def fails(self, *args, **kwargs):  # the state's rows are in RAM by now
        raise OSError("injected")

    monkeypatch.setattr(MemoryStore, "load_position", fails)
    with pytest.raises(RuntimeError, match="Nothing of it was committed: the store holds the rows of before"):
        rb.load_state_dict(state)
    monkeypatch.undo()
    with pytest.raises(RuntimeError, match="is closed"):
        rb.extend(_obs(7, 1))
    before = list(range(30)) + list(range(100, 130))
    with ZarrStorage(path, read_only=True) as back:
        assert back["obs"].flatten().tolist() == before
    again = ZarrStorage(path, goal_conditioned=False)  # the state loads once the cause is gone
    rb = TensorDictReplayBuffer(storage=again, batch_size=2)
    assert again["obs"].flatten().tolist() == before
    rb.load_state_dict(state)
    again.close()
    with ZarrStorage(path, read_only=True) as back:
        assert back["obs"].flatten().tolist() == list(range(30))


_ROLLBACK_FAILS_UNDER_SIGTERM = """
import copy, os, signal, sys, torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem import ZarrStorage
obs = lambda lo, n: TensorDict({"obs": torch.arange(lo, lo + n, dtype=torch.float32).unsqueeze(-1)}, [n])
st = ZarrStorage(sys.argv[1], 64, goal_conditioned=False)
rb = TensorDictReplayBuffer(storage=st, batch_size=2)
rb.extend(obs(0, 30))
state = copy.deepcopy(rb.state_dict())
rb.extend(obs(100, 30))
def fails(self, *args, **kwargs):  # the rows emptied in RAM; a SIGTERM arrives (held back), then an error
    os.kill(os.getpid(), signal.SIGTERM)
    raise OSError("injected")
ZarrStorage._set = fails
rb.load_state_dict(state)
"""


def test_a_rollback_that_fails_while_a_sigterm_waits_commits_none_of_it(tmp_path):
    """Found by a review: the load gave up only after its hold and critical section ended, where the SIGTERM
    they held back flushed the half-replaced rows first (the store emptied on disk)."""
    import subprocess
    import sys

    path = str(tmp_path / "m.zarr")
    proc = subprocess.run([sys.executable, "-c", _ROLLBACK_FAILS_UNDER_SIGTERM, path], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode != 0 and "Traceback" not in proc.stdout, proc.stderr[-2000:]
    with ZarrStorage(path, read_only=True) as back:
        assert back["obs"].flatten().tolist() == list(range(30)) + list(range(100, 130)), proc.stderr[-2000:]


def test_a_state_larger_than_a_fresh_store_is_refused_before_anything_changes(tmp_path):
    """Found by a review: the capacity was checked only on a store that had had a first write; before it, a
    state of 12 rows into a store of 10 failed inside the load (torch's shape error before, the handle closed
    and an empty store after e5a91ad)."""
    lts = LazyTensorStorage(12)
    lts.set(torch.arange(12), _obs(0, 12))
    path = str(tmp_path / "m.zarr")
    st = ZarrStorage(path, 10, goal_conditioned=False)
    with pytest.raises(ValueError, match="The state holds 12 rows .* holds at most 10 .* Nothing was changed"):
        st.load_state_dict(lts.state_dict())
    st.set(torch.arange(3), _obs(0, 3))  # it goes on
    st.close()
    # found by TorchRL's own tests: a row with batch dimensions of its own counts once (10 rows of [10, 3] fit 10)
    lts = LazyTensorStorage(10)
    lts.set(torch.arange(10), TensorDict({"x": torch.ones(10, 3, 2)}, [10, 3]))
    fresh = ZarrStorage(str(tmp_path / "rows.zarr"), 10, goal_conditioned=False)
    fresh.load_state_dict(lts.state_dict())
    assert len(fresh) == 10 and fresh[0]["x"].shape == (3, 2)
    fresh.close()
    with ZarrStorage(path, read_only=True) as back:
        assert back["obs"].flatten().tolist() == [0.0, 1.0, 2.0]


@pytest.mark.parametrize("case", ["a column added since", "other columns", "more rows than the capacity"])
def test_a_state_the_store_cannot_hold_is_refused_before_anything_changes(tmp_path, case):
    """Found by a review: load_state_dict emptied the store (durably) before the state's rows were checked."""
    path = str(tmp_path / "m.zarr")
    st = ZarrStorage(path, 10, goal_conditioned=False)
    rb = TensorDictReplayBuffer(storage=st, batch_size=2)
    rb.extend(_obs(0, 4))
    if case == "a column added since":
        state = copy.deepcopy(st.state_dict())
        rb.extend(_obs(7, 2, extra=torch.ones(2, 1)))
        said = "missing keys \\['extra'\\]"
    else:
        src = TensorDict({"other": torch.zeros(3, 1)}, [3]) if case == "other columns" else _obs(0, 20)
        lts = LazyTensorStorage(len(src))
        lts.set(torch.arange(len(src)), src)
        state = lts.state_dict()
        said = "missing keys \\['obs'\\]" if case == "other columns" else "holds at most 10 .* Nothing was changed"
    before = (len(st), st.write_count, st["obs"].clone(), rb.writer.state_dict())
    with pytest.raises((KeyError, ValueError), match=said):
        st.load_state_dict(state)
    assert (len(st), st.write_count) == before[:2] and torch.equal(st["obs"], before[2])
    rb.extend(_obs(30, 1, **({"extra": torch.ones(1, 1)} if case == "a column added since" else {})))  # it goes on
    st.close()
    with ZarrStorage(path, read_only=True) as again:
        assert len(again) == before[0] + 1 and torch.equal(again["obs"][:before[0]], before[2])


def test_the_state_of_a_buffer_before_its_first_write_loads_as_lazy_tensor_storage_loads_it(tmp_path):
    """Found by a review: it was refused as a live state (it holds no rows at all)."""
    out = {}
    for name, st in (("lazy", LazyTensorStorage(10)), ("zarr", ZarrStorage(str(tmp_path / "m.zarr"), 10,
                                                                            goal_conditioned=False))):
        rb = TensorDictReplayBuffer(storage=st, batch_size=2)
        state = copy.deepcopy(rb.state_dict())
        rb.extend(_obs(0, 5))
        rb.load_state_dict(state)
        out[name] = (len(rb), rb.writer.state_dict())
    assert out["zarr"] == out["lazy"] == (0, {"_cursor": 0, "_write_count": 0})
    rb.storage.close()


def test_window_sampler_after_a_lazy_tensor_storage_state_is_loaded_into_a_ring(tmp_path):
    """Found by a review: the window was placed by the store's count of rows written (the rows the load wrote),
    not by the last row written, so after a load of a wrapped buffer it held the wrong rows, also after a
    reopen."""
    source = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), sampler=WindowSampler(50), batch_size=8)
    source.extend(_rows(0, 1300))  # wrapped: rows 250..299 hold the newest, 1250..1299
    path = str(tmp_path / "win.zarr")
    out = {}
    for name, storage in (("lazy", LazyTensorStorage(1000)),
                          ("zarr", ZarrStorage(path, 1000, chunk_rows=CHUNK, goal_conditioned=False))):
        rb = TensorDictReplayBuffer(storage=storage, sampler=WindowSampler(50), batch_size=8)
        rb.load_state_dict(source.state_dict())
        first = storage.get(rb.sampler.window_rows(storage))["obs"][:, 0]
        rb.extend(_rows(5000, 5005))
        out[name] = (first, storage.get(rb.sampler.window_rows(storage))["obs"][:, 0])
    assert torch.equal(out["zarr"][0], out["lazy"][0]) and out["lazy"][0].tolist() == list(range(1250, 1300))
    assert torch.equal(out["zarr"][1], out["lazy"][1]) and out["lazy"][1][-5:].tolist() == list(range(5000, 5005))
    rb.storage.close()
    with ZarrStorage(path, read_only=True) as reader:
        rows = WindowSampler(50).window_rows(reader)
        assert torch.equal(reader.get(rows)["obs"][:, 0], out["lazy"][1])


@pytest.mark.parametrize("cursor, data", [(-1, _rows(100, 101)[0]), (slice(-3, None), _rows(100, 103)),
                                          (torch.tensor([5, -2]), _rows(100, 102))])
def test_a_negative_index_into_a_memory_without_a_capacity_is_refused_and_changes_nothing(tmp_path, cursor, data):
    """Found by a review: -1 named the last row allocated (a row that moves as the memory grows), len counted
    a row of zeros, and the next buffer appended past len. Such a memory has no last row to count from."""
    path = str(tmp_path / "neg.zarr")
    with ZarrStorage(path, chunk_rows=CHUNK, goal_conditioned=False) as st:
        st.set(torch.arange(40), _rows(0, 40))
        with pytest.raises(IndexError, match="no declared capacity.*negative index"):
            st.set(cursor, data)
        assert len(st) == 40 and torch.equal(st["obs"], _rows(0, 40)["obs"])
        assert torch.equal(st.get(-1)["obs"], _rows(39, 40)["obs"][0])  # reading from the end still works
    with ZarrStorage(path) as again:
        TensorDictReplayBuffer(storage=again).extend(_rows(40, 45))
        assert torch.equal(again["obs"], _rows(0, 45)["obs"])


def test_a_checkpoint_of_a_store_with_a_constant_column_restores(tmp_path):
    """Found by a review of the check before a load: it checked the state's rows without their constant columns
    (the write adds them), and refused a checkpoint of a store holding one."""
    path = str(tmp_path / "m.zarr")
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 50, goal_conditioned=False), batch_size=2)
    rb.extend(_obs(0, 4, label="x"))
    rb.dumps(tmp_path / "ckpt")
    rb.extend(_obs(10, 2, label="x"))
    rb.loads(tmp_path / "ckpt")
    assert len(rb) == 4 and rb.storage[:]["obs"].flatten().tolist() == [0.0, 1.0, 2.0, 3.0]
    other = ZarrStorage(str(tmp_path / "b.zarr"), 50, goal_conditioned=False)
    other.set(torch.arange(2), _obs(20, 2, label="x"))
    other.load_state_dict(rb.storage.state_dict())
    assert len(other) == 4 and other[:]["label"] == "x"
    other.close()
    rb.storage.close()


def test_a_store_holding_nan_holds_its_own_unchanged_state(tmp_path):
    """Found by a review: NaN != NaN made an unchanged store look changed: a read-only handle refused to load its
    own state, and a writer rewrote every row."""
    path = str(tmp_path / "m.zarr")
    with ZarrStorage(path, 50, goal_conditioned=False) as st:
        st.set(torch.arange(4), TensorDict({"obs": torch.tensor([[0.0], [float("nan")], [2.0], [3.0]])}, [4]))
    with ZarrStorage(path, read_only=True) as ro:
        then = copy.deepcopy(ro.state_dict())
        assert ro.holds(then)
        ro.load_state_dict(then)  # only the writer position: a reader may do it
        assert len(ro) == 4


def test_a_local_path_with_a_double_colon_in_a_folder_name_is_a_path(tmp_path):
    """Found by a review: any '::' made a name an fsspec chain, refused (naming the wrong path)."""
    folder = tmp_path / "run::2024"
    folder.mkdir()
    with ZarrStorage(str(folder / "m.zarr"), 10, goal_conditioned=False) as st:
        st.set(torch.arange(3), _obs(0, 3))
    with ZarrStorage(str(folder / "m.zarr"), read_only=True) as ro:
        assert len(ro) == 3
