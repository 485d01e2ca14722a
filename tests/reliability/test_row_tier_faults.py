"""The row file of a local store (``_rows/rows.bin`` and its seal) under crashes, growth and hostile files.

A local store's packed rows are mapped from ``_rows/rows.bin`` (:mod:`torchrl_robotmem.storage.rowfile`);
``_rows/seal.json`` says when that file may be served without reading a chunk. The file is a cache of the
committed chunks: whatever happens to it or to the processes writing it, an open serves exactly the
committed rows. Real stores under ``tmp_path``, real processes (``_row_tier_child.py``, forked from the
forkserver of ``_gen.writer_context``), rows that are functions of their write number (``_gen.make_rows``):

1. a writer SIGKILLed with rows written into the mapped file past its last commit (overwriting committed
   rows of a ring): the reopens serve the committed rows, not the file's, and no seal is left;
2. a writer killed while writing a new store; a reader and a writer killed right after filling the rows
   of a store without a row file; a torn ``rows.bin`` (truncated, seal left in place);
3. a memory without a declared capacity (``ZarrStorage(path)``) killed while it grows, after the grown
   rows were written or between the arrays' growth and the record's: the flushed rows, and it grows on;
4. a reader tailing (``refresh()``) a writer process that grows such a memory;
5. hostile row files: a link, bytes changed after the seal, a seal from another store, and a reader
   mapping the file while a writer writes and closes (or is killed with rows past its commit);
6. an open in a memory cgroup smaller than the rows (v2 at /sys/fs/cgroup, else v1 beside this process's;
   skipped where none can be made): its limit is what the cgroup holds once the child moved in (a
   process's pages stay charged where they were) plus a quarter of the rows' bytes.

Conditions hold by construction, never by timing: a child that kills itself holds its commit engine's
condition from before its uncommitted writes (no commit can start), and reports on a pipe what it did.
Seeds: ``ROBOTMEM_ROW_TIER_SEED`` if set, else ``ROBOTMEM_TEST_SEED`` (default 0), printed where drawn.
"""
from __future__ import annotations

import gc
import hashlib
import json
import os
import runpy
import shutil
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import zarr
from conftest import seed_from_env
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage.errors import LinkError
from torchrl_robotmem.storage.layout import PackedLayout
from torchrl_robotmem.storage.rowfile import rows_layout

from . import _gen
from ._gen import make_rows, torn_or_wrong

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="fork, SIGKILL, flock and /proc")

CHILD = str(Path(__file__).with_name("_row_tier_child.py"))
CHILD_RUN_NAME = "__robotmem_row_tier_child__"
ENV = "FetchPush-v4"
RING = 256  # rows of the rings below (4 chunks of 64)
CHILD_DEADLINE = 300.0  # seconds a child may take (a healthy one takes a few on a loaded machine)


# -- helpers ---------------------------------------------------------------------------------------------


def _seed() -> int:
    return seed_from_env("ROBOTMEM_ROW_TIER_SEED")


def _start(tmp_path: Path, scenario: str, *, duplex: bool = False, **kwargs):
    """Starts a child running ``scenario``; returns ``(process, connection, err_file)``.

    ``duplex``: the child also receives on its connection (a scenario that waits for the test).
    """
    ctx = _gen.writer_context()
    ours, theirs = ctx.Pipe(duplex=duplex)
    err = tmp_path / f"{scenario}.err"
    args = dict(scenario=scenario, err_file=str(err), conn=theirs, **kwargs)
    p = ctx.Process(target=runpy.run_path, args=(CHILD,),
                    kwargs={"init_globals": {"ARGS": args}, "run_name": CHILD_RUN_NAME})
    p.start()
    theirs.close()
    return p, ours, err


def _recv(p, conn, err: Path, deadline: float):
    """The child's next message, or ``None`` once it exited without sending one."""
    while True:
        if conn.poll(0.05):
            try:
                return conn.recv()
            except EOFError:
                return None
        if not p.is_alive() and not conn.poll(0):
            return None
        if time.monotonic() > deadline:
            p.kill()
            pytest.fail(f"the child ran past {CHILD_DEADLINE} s; {_error(err)}")


def _error(err: Path) -> str:
    return err.read_text() if err.exists() else "(no traceback)"


def _run(tmp_path: Path, scenario: str, *, killed: bool, **kwargs) -> list[dict]:
    """Runs a child to its end; checks how it ended (SIGKILLed itself, or exit 0); returns its messages."""
    p, conn, err = _start(tmp_path, scenario, **kwargs)
    deadline = time.monotonic() + CHILD_DEADLINE
    msgs = []
    while (m := _recv(p, conn, err, deadline)) is not None:
        msgs.append(m)
    p.join(60)
    want = -signal.SIGKILL if killed else 0
    assert p.exitcode == want, f"{scenario}: exit {p.exitcode}, expected {want}; messages {msgs}\n{_error(err)}"
    return msgs


def _ring_w(W: int, size: int = RING) -> torch.Tensor:
    """The write number each slot of a ring of ``size`` rows holds after ``W`` writes."""
    n = min(W, size)
    return W - 1 - ((W - 1 - torch.arange(n)) % size)


def _make_store(path: Path, w: torch.Tensor, max_size: int | None = RING) -> None:
    """A store holding the rows ``make_rows(w)``, closed cleanly (so its row file is sealed)."""
    with ZarrStorage(str(path), max_size, chunk_rows=64, env=ENV) as st:
        TensorDictReplayBuffer(storage=st, batch_size=4).extend(make_rows(w))
    assert (path / "_rows" / "seal.json").exists(), "a clean close left no seal"


def _rows_info(st: ZarrStorage) -> dict:
    return st.row_file


def _check(path: Path, expected_w: torch.Tensor, *, read_only: bool, sealed: bool | None) -> dict:
    """Opens the store, checks it holds exactly the rows ``make_rows(expected_w)``; returns where they came from."""
    st = ZarrStorage(str(path), read_only=read_only, **({} if read_only else {"env": ENV}))
    try:
        info = _rows_info(st)
        if sealed is not None:
            assert info["sealed"] is sealed, (
                f"rows {'not ' if sealed else ''}served from a sealed file, expected otherwise: {info}")
        assert len(st) == len(expected_w), f"len {len(st)}, expected {len(expected_w)} ({info})"
        if len(expected_w):
            bad = torn_or_wrong(st[: len(st)], expected_w)
            assert not bad, f"rows differ from the committed ones ({info}): {bad}"
        return info
    finally:
        st.close()


def _committed(path: Path) -> dict:
    return zarr.open_group(str(path), mode="r").attrs.asdict()


def _file_column(path: Path, key: str, rows: slice) -> np.ndarray:
    """The bytes of column ``key`` in ``_rows/rows.bin`` (whatever its seal says), laid out as the record says."""
    attrs = _committed(path)
    layout = rows_layout(PackedLayout(attrs["schema"]), (int(attrs["max_size"]),))
    field = next(f for f in layout["fields"] if f[0] == key)
    _, off, nbytes, dtype, _shape = field
    raw = np.fromfile(path / "_rows" / "rows.bin", dtype=np.uint8).reshape(-1, layout["row_bytes"])
    return raw[rows, off:off + nbytes].copy().view(dtype)


def _in_store_folder(file: str | None, path: Path) -> bool:
    """Whether a writer's row file is the store's (``_rows/rows.bin``) or one of its own beside it."""
    return file is not None and Path(file).parent == path / "_rows" and Path(file).name.startswith("rows.")


def _row_folder(path: Path) -> list[str]:
    return sorted(p.name for p in (path / "_rows").iterdir())


def _hash_tree(root: Path) -> dict[str, str]:
    """``{relative path: sha256, or "-> target" for a link}`` of every file below ``root`` (no link followed)."""
    out = {}
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            out[rel] = f"-> {os.readlink(p)}" if p.is_symlink() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


# -- 1. a writer killed with rows past its commit in the mapped file -------------------------------------


def test_writer_killed_with_uncommitted_rows_in_the_mapped_file(tmp_path):
    path = tmp_path / "ring.zarr"
    _make_store(path, torch.arange(RING))
    msgs = _run(tmp_path, "ring_overwrite_kill", killed=True, path=str(path), extra=64, overwrite=100)
    opened, last = msgs[0], msgs[-1]
    assert opened["opened_at"] == RING and opened["sealed_at_open"], f"the writer did not open the sealed file: {opened}"
    assert not opened["seal_left"], f"the writer kept the seal while it could write the file: {opened}"
    assert last["rows"]["file"] == str(path / "_rows" / "rows.bin"), f"not written in place: {last}"
    W, written = last["flushed"], last["written"]
    assert (W, written) == (RING + 64, RING + 164)
    # the scenario: the killed writer's uncommitted rows are in rows.bin, the record is at its flush, no seal
    assert not (path / "_rows" / "seal.json").exists(), "a killed writer left a seal"
    assert _committed(path)["write_count"] == W
    in_file = -_file_column(path, "action", slice(64, 164))[:, 0]
    assert np.array_equal(in_file, np.arange(W, written)), "the uncommitted rows never reached rows.bin"
    # every open serves the committed rows (refilled from the chunks), never the file's
    _check(path, _ring_w(W), read_only=True, sealed=False)
    _check(path, _ring_w(W), read_only=False, sealed=False)
    # and the next writer appends after them; its clean close seals again
    with ZarrStorage(str(path), env=ENV) as st:
        TensorDictReplayBuffer(storage=st, batch_size=4).extend(make_rows(torch.arange(W, W + 10)))
    _check(path, _ring_w(W + 10), read_only=True, sealed=True)


# -- 2. killed while a store is written or its rows filled; a torn row file ------------------------------


def test_writer_of_a_new_store_killed_after_flushes(tmp_path):
    path = tmp_path / "new.zarr"
    msgs = _run(tmp_path, "fresh_writer_kill", killed=True, path=str(path), flushes=3, batch=50, tail=30)
    W = msgs[-1]["flushed"]
    assert W == 150 and _in_store_folder(msgs[-1]["rows"]["file"], path), msgs[-1]
    assert not (path / "_rows" / "seal.json").exists(), "a killed writer left a seal"
    _check(path, torch.arange(W), read_only=True, sealed=False)
    _check(path, torch.arange(W), read_only=False, sealed=False)
    assert _row_folder(path) == ["rows.bin", "seal.json"], "the next writer left the dead writer's files"
    _check(path, torch.arange(W), read_only=True, sealed=True)  # the writable open above closed cleanly


@pytest.mark.parametrize("read_only", [True, False], ids=["reader", "writer"])
def test_killed_right_after_filling_the_rows(tmp_path, read_only):
    """A store without ``_rows/``: the open fills the rows from the chunks; the process dies right after."""
    path, cache = tmp_path / "store.zarr", tmp_path / "cache"
    cache.mkdir()
    _make_store(path, torch.arange(200))
    shutil.rmtree(path / "_rows")
    before = _hash_tree(path)
    msgs = _run(tmp_path, "fill_kill", killed=True, path=str(path), read_only=read_only, cache=str(cache))
    assert msgs and msgs[0]["filled"], f"the child never filled the rows: {msgs}"
    filled = msgs[0]
    assert filled["cache"] == [], f"a reader's private row file has a name: {filled}"
    assert list(cache.iterdir()) == [], "the killed process left a row file in the cache directory"
    if read_only:
        assert filled["rows"]["file"] is None, f"a reader filled a file others can see: {filled}"
        assert _hash_tree(path) == before, "a reader changed the store"
    else:
        assert _in_store_folder(filled["rows"]["file"], path), filled
        assert not (path / "_rows" / "seal.json").exists(), "a killed writer left a seal"
    # the writer's open closed no episode before the kill: the rows are the committed ones, as written
    _check(path, torch.arange(200), read_only=True, sealed=False)
    _check(path, torch.arange(200), read_only=False, sealed=False)
    assert _row_folder(path) == ["rows.bin", "seal.json"], "the next writer left the dead writer's files"
    _check(path, torch.arange(200), read_only=True, sealed=True)


def test_killed_while_filling_in_the_background(tmp_path):
    """A reader that fills in the background, killed after its first read: it served the committed rows, left
    nothing in the cache directory or the store, and the next opens serve the committed rows."""
    path, cache = tmp_path / "store.zarr", tmp_path / "cache"
    cache.mkdir()
    _make_store(path, torch.arange(200))
    shutil.rmtree(path / "_rows")
    before = _hash_tree(path)
    asked = [199, 0, 70, 130]
    msgs = _run(tmp_path, "background_fill_kill", killed=True, path=str(path), cache=str(cache), rows=asked)
    assert msgs and msgs[0]["background"], f"the reader did not fill in the background: {msgs}"
    expected = make_rows(torch.arange(200))["observation"][asked, 0].tolist()
    assert msgs[0]["obs"] == expected, msgs[0]
    assert msgs[0]["cache"] == [], f"a reader's private row file has a name: {msgs[0]}"
    assert list(cache.iterdir()) == [], "the killed reader left a row file in the cache directory"
    assert _hash_tree(path) == before, "a reader changed the store"
    _check(path, torch.arange(200), read_only=True, sealed=False)
    _check(path, torch.arange(200), read_only=False, sealed=False)


def test_writer_killed_while_filling_in_the_background(tmp_path):
    """A writer whose rows are filled in the background rewrites rows in chunks it has not filled, appends,
    flushes and is killed: the committed store holds the rewrite and the appends over the old rows, whole."""
    path = tmp_path / "store.zarr"
    _make_store(path, torch.arange(200))
    shutil.rmtree(path / "_rows")
    rewrite = [70, 71, 130, 199]
    msgs = _run(tmp_path, "writer_background_fill_kill", killed=True, path=str(path), rewrite=rewrite, appended=30)
    assert msgs and msgs[0]["background"] and msgs[0]["len"] == 230, f"the writer did not fill in the background: {msgs}"
    expected = torch.cat([torch.arange(200), torch.arange(204, 234)])
    expected[rewrite] = torch.arange(200, 204)
    assert not (path / "_rows" / "seal.json").exists(), "a killed writer left a seal"
    _check(path, expected, read_only=True, sealed=False)
    _check(path, expected, read_only=False, sealed=False)
    _check(path, expected, read_only=True, sealed=True)


def test_torn_row_file_with_its_seal_is_filled_again(tmp_path):
    path = tmp_path / "store.zarr"
    _make_store(path, torch.arange(RING + 40))  # a ring that wrapped
    rows_bin = path / "_rows" / "rows.bin"
    size = rows_bin.stat().st_size
    os.truncate(rows_bin, size // 2)  # torn: the seal stays, binding the whole file
    assert (path / "_rows" / "seal.json").exists()
    W = RING + 40
    _check(path, _ring_w(W), read_only=True, sealed=False)
    assert rows_bin.stat().st_size == size // 2, "a reader wrote the store's row file"
    _check(path, _ring_w(W), read_only=False, sealed=False)
    assert rows_bin.stat().st_size == size
    _check(path, _ring_w(W), read_only=True, sealed=True)


# -- 3. a memory without a declared capacity killed while it grows ---------------------------------------


@pytest.mark.parametrize("kill_at", ["written", "record"])
def test_unbounded_memory_killed_while_growing(tmp_path, kill_at):
    path = tmp_path / "grow.zarr"
    flush_at, last = [700, 1500, 3000], 4500
    msgs = _run(tmp_path, "unbounded_grow_kill", killed=True, path=str(path), flush_at=flush_at, last=last,
                kill_at=kill_at)
    caps, F = msgs[0]["capacities"], msgs[0]["flushed"]
    assert F == flush_at[-1] and caps == sorted(caps) and len(set(caps)) >= 3 and caps[-1] < last, (
        f"the memory did not grow twice before the last extend: capacities {caps}")
    assert msgs[-1]["killed"] == kill_at, msgs[-1]
    if kill_at == "written":
        assert msgs[-1]["capacity"] >= last > caps[-1], msgs[-1]
    attrs = _committed(path)
    assert attrs.get("unbounded") is True and attrs["len"] == F, {k: attrs.get(k) for k in ("len", "max_size")}
    assert not (path / "_rows" / "seal.json").exists(), "a killed writer left a seal"
    st = ZarrStorage(str(path), read_only=True)
    try:
        assert st.bounded is False and st.capacity >= F and len(st) == F
        assert not torn_or_wrong(st[:F], torch.arange(F))
    finally:
        st.close()
    # the writer goes on from the flushed rows and grows further
    with ZarrStorage(str(path), env=ENV) as st:
        assert st.bounded is False and len(st) == F, (st.bounded, len(st))
        assert not torn_or_wrong(st[:F], torch.arange(F))
        before = st.capacity
        target = max(before, last) + 500
        rb = TensorDictReplayBuffer(storage=st, batch_size=4)
        for a in range(F, target, 1000):
            rb.extend(make_rows(torch.arange(a, min(a + 1000, target))))
        assert len(st) == target and st.capacity >= target > before, (len(st), st.capacity, before)
    _check(path, torch.arange(target), read_only=True, sealed=True)
    _check(path, torch.arange(target), read_only=False, sealed=True)


# -- 4. a reader tailing a memory that grows ------------------------------------------------------------


def test_reader_tails_a_growing_memory(tmp_path):
    path = tmp_path / "tail.zarr"
    seed = _seed()
    print(f"row tier tailing: ROBOTMEM_ROW_TIER_SEED={seed}")
    total = 6000  # the capacity grows 1024 -> 2048 -> 4096 -> 8192
    p, conn, err = _start(tmp_path, "tail_writer", duplex=True, path=str(path), seed=seed, total=total)
    deadline = time.monotonic() + CHILD_DEADLINE
    reader, checks, capacities = None, 0, set()
    try:
        while (m := _recv(p, conn, err, deadline)) is not None:
            if reader is None:
                assert "flushed" in m, m
                reader = ZarrStorage(str(path), read_only=True)
                assert reader.bounded is False
            n = reader.refresh()
            flushed = m.get("flushed", m.get("closed"))
            assert n >= flushed and len(reader) == n, (
                f"refresh gave {n} rows after the writer flushed {flushed} (seed {seed})")
            assert reader.capacity >= n
            capacities.add(reader.capacity)
            bad = torn_or_wrong(reader[:n], torch.arange(n))
            assert not bad, f"rows wrong after refresh to {n} (seed {seed}): {bad}"
            checks += 1
            if "closed" in m:
                assert n == total
                break
            conn.send("go")  # the writer waits for it: every flush is refreshed to before it goes on
        p.join(60)
        assert p.exitcode == 0, _error(err)
        assert len(capacities) >= 3, f"the reader saw the memory grow only to {sorted(capacities)} (seed {seed})"
    finally:
        if reader is not None:
            reader.close()
        if p.is_alive():
            p.kill()
    print(f"row tier tailing: {checks} refreshes, capacities {sorted(capacities)}")
    _check(path, torch.arange(total), read_only=True, sealed=True)


# -- 5. hostile row files ----------------------------------------------------------------------------------


def test_row_file_that_is_a_link_is_refused(tmp_path):
    path, outside = tmp_path / "store.zarr", tmp_path / "outside.bin"
    _make_store(path, torch.arange(200))
    rows_bin = path / "_rows" / "rows.bin"
    shutil.copyfile(rows_bin, outside)  # the very rows, outside the store
    rows_bin.unlink()
    rows_bin.symlink_to(outside)
    outside_hash, before = hashlib.sha256(outside.read_bytes()).hexdigest(), _hash_tree(path)
    for read_only in (True, False):
        with pytest.raises(LinkError) as info:
            ZarrStorage(str(path), read_only=read_only)
        assert "_rows/rows.bin" in str(info.value), str(info.value)
        assert [p.key for p in info.value.problems] == ["_rows/rows.bin"], info.value.problems
    assert hashlib.sha256(outside.read_bytes()).hexdigest() == outside_hash, "the file outside the store changed"
    assert _hash_tree(path) == before, "the refused opens changed the store"


def test_row_file_changed_after_its_seal_is_filled_again(tmp_path):
    path = tmp_path / "store.zarr"
    _make_store(path, torch.arange(200))
    rows_bin, seal_file = path / "_rows" / "rows.bin", path / "_rows" / "seal.json"
    seal = json.loads(seal_file.read_text())
    st0 = rows_bin.stat()
    assert seal["file"][1:] == [st0.st_ino, st0.st_size, st0.st_mtime_ns]
    # file times tick with the kernel's clock: wait until it has moved past the seal's, so that a write shows
    while time.time_ns() < st0.st_mtime_ns + 50_000_000:
        time.sleep(0.01)
    row_bytes = seal["layout"]["row_bytes"]
    with open(rows_bin, "r+b") as f:  # flip every byte of rows 10-19, in place
        f.seek(10 * row_bytes)
        chunk = f.read(10 * row_bytes)
        f.seek(10 * row_bytes)
        f.write(bytes(b ^ 0xFF for b in chunk))
    st1 = rows_bin.stat()
    assert (st1.st_ino, st1.st_size) == (st0.st_ino, st0.st_size) and st1.st_mtime_ns != st0.st_mtime_ns
    assert seal_file.read_text() == json.dumps(seal), "the seal changed"
    _check(path, torch.arange(200), read_only=True, sealed=False)
    _check(path, torch.arange(200), read_only=False, sealed=False)
    _check(path, torch.arange(200), read_only=True, sealed=True)


def test_a_folder_where_the_row_file_goes_is_a_warning_at_close_and_the_rows_are_kept(tmp_path):
    """Found by a review: a directory planted at ``_rows/rows.bin`` made a writer's clean close raise a bare
    ``IsADirectoryError`` (its rows were committed all the same). The close warns, naming it, and ends."""
    path = tmp_path / "store.zarr"
    _make_store(path, torch.arange(100))
    rows_bin = path / "_rows" / "rows.bin"
    rows_bin.unlink()
    rows_bin.mkdir()
    st = ZarrStorage(str(path), env=ENV)
    TensorDictReplayBuffer(storage=st, batch_size=4).extend(make_rows(torch.arange(100, 150)))
    with pytest.warns(RuntimeWarning, match="row file was not sealed.*every row is committed"):
        st.close()
    _check(path, torch.arange(150), read_only=True, sealed=False)


def test_seal_of_another_store_is_not_trusted(tmp_path):
    a, b = tmp_path / "a.zarr", tmp_path / "b.zarr"
    _make_store(a, torch.arange(200))
    _make_store(b, torch.arange(1000, 1200))  # the same layout, other rows
    shutil.copyfile(a / "_rows" / "seal.json", b / "_rows" / "seal.json")
    _check(b, torch.arange(1000, 1200), read_only=True, sealed=False)
    _check(b, torch.arange(1000, 1200), read_only=False, sealed=False)
    _check(b, torch.arange(1000, 1200), read_only=True, sealed=True)
    _check(a, torch.arange(200), read_only=True, sealed=True)


def test_reader_keeps_its_rows_while_a_writer_writes_and_closes(tmp_path):
    path = tmp_path / "ring.zarr"
    _make_store(path, torch.arange(RING))
    rows_bin = path / "_rows" / "rows.bin"
    reader = ZarrStorage(str(path), read_only=True)
    try:
        info = _rows_info(reader)
        assert info["sealed"] and info["shared"] and info["file"] == str(rows_bin), info
        seen = reader[:RING].clone()
        inode = rows_bin.stat().st_ino
        msgs = _run(tmp_path, "ring_writer", killed=False, path=str(path), n=100)
        assert msgs[0]["opened_at"] == RING, msgs
        own = msgs[0]["rows"]["file"]
        assert own != str(rows_bin) and Path(own).parent == rows_bin.parent, (
            f"the writer wrote the file a reader maps: {msgs[0]}")
        assert msgs[-1]["closed"] == RING + 100
        assert rows_bin.stat().st_ino != inode and not Path(own).exists(), "the writer's file was not renamed in"
        assert (reader[:RING] == seen).all(), "the reader's rows changed under it"
        assert not torn_or_wrong(reader[:RING], torch.arange(RING))
        _check(path, _ring_w(RING + 100), read_only=True, sealed=True)  # a new reader: the new rows
        assert reader.refresh() == RING
        assert not torn_or_wrong(reader[:RING], _ring_w(RING + 100)), "a refresh kept the old rows"
    finally:
        reader.close()


def test_writer_killed_while_a_reader_maps_the_file(tmp_path):
    """The writer writes a file of its own (a reader maps ``rows.bin``) and dies with rows past its commit:
    the reader's rows stay, the store's sealed file is not served for the newer record, the dead writer's
    file is removed by the next writer."""
    path = tmp_path / "ring.zarr"
    _make_store(path, torch.arange(RING))
    rows_bin = path / "_rows" / "rows.bin"
    reader = ZarrStorage(str(path), read_only=True)
    try:
        assert _rows_info(reader)["shared"]
        seen, inode = reader[:RING].clone(), rows_bin.stat().st_ino
        msgs = _run(tmp_path, "ring_overwrite_kill", killed=True, path=str(path), extra=64, overwrite=100)
        own = msgs[-1]["rows"]["file"]
        assert own != str(rows_bin) and not msgs[0]["sealed_at_open"], msgs
        W = msgs[-1]["flushed"]
        assert Path(own).exists() and rows_bin.stat().st_ino == inode
        assert (reader[:RING] == seen).all(), "the reader's rows changed under it"
        _check(path, _ring_w(W), read_only=True, sealed=False)  # the seal binds the older record
        _check(path, _ring_w(W), read_only=False, sealed=False)
        assert not Path(own).exists(), "the next writer left the dead writer's row file"
        assert _row_folder(path) == ["rows.bin", "seal.json"]
        _check(path, _ring_w(W), read_only=True, sealed=True)
        assert reader.refresh() == RING and not torn_or_wrong(reader[:RING], _ring_w(W))
    finally:
        reader.close()


# -- 6. an open in a memory cgroup smaller than the rows ------------------------------------------------


def _own_cgroup(version: str) -> str:
    for line in Path("/proc/self/cgroup").read_text().splitlines():
        _, controllers, rel = line.split(":", 2)
        if version == "v2" and controllers == "":
            return rel
        if version == "v1" and "memory" in controllers.split(","):
            return rel
    raise OSError(f"no {version} memory line in /proc/self/cgroup")


def _memory_cgroup(tag: str) -> tuple[Path, str]:
    """A new memory cgroup (v2 at /sys/fs/cgroup, else v1 beside this process's); skips saying why there is none."""
    tried = []
    for version, parent in (("v2", "/sys/fs/cgroup"), ("v1", None)):
        try:
            if version == "v2":
                if "memory" not in Path(parent, "cgroup.controllers").read_text().split():
                    raise OSError(f"{parent}: not a cgroup v2 root with the memory controller")
            else:
                parent = "/sys/fs/cgroup/memory" + _own_cgroup("v1")
            d = Path(parent) / tag
            d.mkdir()
            if not (d / ("memory.max" if version == "v2" else "memory.limit_in_bytes")).exists():
                d.rmdir()
                raise OSError(f"{d}: no memory limit file")
            return d, version
        except OSError as e:
            tried.append(f"cgroup {version}: {e}")
    pytest.skip("no memory cgroup can be made here: " + "; ".join(tried))


def _remove_cgroup(d: Path) -> None:
    for _ in range(100):
        try:
            d.rmdir()
            return
        except FileNotFoundError:
            return
        except OSError:
            time.sleep(0.05)  # the child's exit is still being accounted
    d.rmdir()


def test_open_in_a_memory_cgroup_smaller_than_the_rows(tmp_path):
    path = tmp_path / "images.zarr"
    seed = _seed()
    n, side, batch = 20_000, 64, 1000
    print(f"row tier cgroup: ROBOTMEM_ROW_TIER_SEED={seed}, {n} rows of {side}x{side}x3 uint8 noise")
    cgroup, version = _memory_cgroup(f"robotmem-test-{os.getpid()}")
    try:
        g = torch.Generator().manual_seed(seed)
        digest = hashlib.sha256()
        st = ZarrStorage(str(path), n, env="NoiseImages-v0", goal_conditioned=False)
        rb = TensorDictReplayBuffer(storage=st, batch_size=4)
        for a in range(0, n, 2000):
            image = torch.randint(0, 256, (2000, side, side, 3), dtype=torch.uint8, generator=g)
            rb.extend(TensorDict({"image": image, "step": torch.arange(a, a + 2000)}, [2000]))
            digest.update(image.numpy().tobytes())
        st.close()
        del st, rb
        gc.collect()
        rows_bin = path / "_rows" / "rows.bin"
        rows_bytes = rows_bin.stat().st_size
        assert rows_bytes >= n * side * side * 3 and (path / "_rows" / "seal.json").exists()
        fd = os.open(rows_bin, os.O_RDONLY)  # out of the page cache: the child's reads are charged to its cgroup
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)
        msgs = _run(tmp_path, "cgroup_reader", killed=False, path=str(path), cgroup=str(cgroup), version=version,
                    rows_bytes=rows_bytes, batch=batch)
    finally:
        _remove_cgroup(cgroup)
    out = msgs[-1]
    print(f"row tier cgroup ({version}): " + json.dumps({k: v for k, v in out.items() if k != "sha256"}))
    assert out["len"] == n and out["rows"]["sealed"] and out["rows"]["shared"], out
    assert out["sha256"] == digest.hexdigest(), "the rows read in the cgroup differ from the rows written"
    assert out["limit_hits"] > 0, f"the rows fitted under the limit: the cgroup did not bound the open ({out})"
    assert out["peak"] is None or out["peak"] <= out["limit"], out
