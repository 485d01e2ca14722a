"""Damaged stores: detected at open with the array and chunk named, refused for writing, verified, repaired.

Each damage kind is made on a real store on disk (a deleted, truncated or
bit-flipped chunk file, a commit record whose ``len`` points past the written
rows or past ``max_size``, a corrupt or truncated ``zarr.json`` of the group or
of an array, a newer format version). For each: a read-only open raises an
``IntegrityError`` naming the array / chunk / file, a writable open refuses and
leaves every file byte-identical, ``verify`` reports it, and ``repair`` makes
the store openable and writable again with every intact row bit-exact
(see "Integrity" in docs/storage.md).
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
import warnings

import pytest
import torch
import zarr
from tensordict import TensorDict

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.cli import main
from torchrl_robotmem.storage import _backend
from torchrl_robotmem.storage.integrity import IntegrityError, repair, verify

ROWS, CHUNK, MAX = 300, 64, 1000


def _rows(n: int, start: int = 0) -> TensorDict:
    i = torch.arange(start, start + n)
    done = ((i + 1) % 10 == 0).unsqueeze(-1)
    return TensorDict(
        {
            "observation": (i.unsqueeze(-1) + torch.arange(6)).float(),
            "action": -i.float().unsqueeze(-1).expand(n, 4).clone(),
            "desired_goal": torch.zeros(n, 3),  # an all-zero column: its chunks must exist too
            "next": {"observation": (i.unsqueeze(-1) + torch.arange(6) + 1).float(), "done": done,
                     "truncated": done.clone(), "reward": -torch.ones(n, 1)},
        },
        [n],
    )


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    """One intact store (written by the default background writer) and its columns, tags included."""
    path = str(tmp_path_factory.mktemp("pristine") / "m.zarr")
    with ZarrStorage(path, MAX, chunk_rows=CHUNK, env="FetchPush-v4") as s:
        s.set(slice(0, ROWS), _rows(ROWS))
    with ZarrStorage(path, read_only=True) as s:
        return path, {k: s[k][:ROWS].clone() for k in s.view().keys(True, True)}


@pytest.fixture
def store(pristine, tmp_path):
    """A fresh copy of the intact store, and its columns."""
    path = str(tmp_path / "m.zarr")
    shutil.copytree(pristine[0], path)
    return path, pristine[1]


def _hash(path) -> dict:
    out = {}
    for root, _, files in os.walk(path):
        for f in files:
            p = os.path.join(root, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, path)] = hashlib.sha256(fh.read()).hexdigest()
    return out


def _edit(path, rel, fn):
    full = os.path.join(path, rel)
    with open(full, "rb") as f:
        data = f.read()
    with open(full, "wb") as f:
        f.write(fn(data))


def _flip(data: bytes) -> bytes:
    b = bytearray(data)
    b[len(b) // 2] ^= 0x40
    return bytes(b)


def _attr(key, value):
    def fn(data):
        meta = json.loads(data)
        meta["attributes"][key] = value
        return json.dumps(meta).encode()
    return fn


def _newer(data):
    meta = json.loads(data)
    meta["attributes"]["torchrl_robotmem"]["format_version"] = 99
    return json.dumps(meta).encode()


# name: (damage, what the open error must name, rows intact after repair)
DAMAGE = {
    "deleted_chunk": (lambda p: os.remove(os.path.join(p, "observation/c.1.0")),
                      r"array 'observation' chunk 1 \(observation/c.1.0, rows 64-127\): chunk file missing", 64),
    "truncated_chunk": (lambda p: _edit(p, "next/observation/c.2.0", lambda d: d[: len(d) // 2]),
                        r"array 'next/observation' chunk 2 \(next/observation/c.2.0.*checksum", 128),
    "flipped_byte": (lambda p: _edit(p, "action/c.3.0", _flip),
                     r"array 'action' chunk 3 \(action/c.3.0, rows 192-255\): checksum mismatch", 192),
    "len_past_written": (lambda p: _edit(p, "zarr.json", _attr("len", 500)),
                         r"array '\w+' chunk 5 \(\w+/c\.5(\.0)?, rows 320-383\): chunk file missing", ROWS),
    "len_past_max_size": (lambda p: _edit(p, "zarr.json", _attr("len", 5000)),
                          r"attribute 'len' must be an integer in \[0, 1000\], got 5000", ROWS),
    "cursor_past_max_size": (lambda p: _edit(p, "zarr.json", _attr("cursor", 1001)),
                             r"attribute 'cursor' must be an integer in \[0, 1000\], got 1001", ROWS),
    "corrupt_group_json": (lambda p: _edit(p, "zarr.json", lambda d: b"\x00garbage" + d[8:]),
                           r"zarr.json: group metadata unreadable", ROWS),
    "truncated_group_json": (lambda p: _edit(p, "zarr.json", lambda d: d[: len(d) // 2]),
                             r"zarr.json: group metadata unreadable", ROWS),
    "truncated_array_json": (lambda p: _edit(p, "next/observation/zarr.json", lambda d: d[: len(d) // 3]),
                             r"array 'next/observation' \(next/observation/zarr.json\): array metadata unreadable", ROWS),
    "deleted_array_json": (lambda p: os.remove(os.path.join(p, "action/zarr.json")),
                           r"array 'action' \(action/zarr.json\): array metadata missing", ROWS),
}


@pytest.mark.parametrize("kind", sorted(DAMAGE))
def test_damage_detected_refused_verified_repaired(store, kind):
    path, before = store
    damage, named, intact = DAMAGE[kind]
    damage(path)
    digest = _hash(path)

    with pytest.raises(IntegrityError, match=named) as err:
        ZarrStorage(path, read_only=True)
    assert "robotmem repair" in str(err.value)
    with pytest.raises(IntegrityError, match=named) as err:
        ZarrStorage(path)
    assert "Refusing to open it for writing" in str(err.value)
    assert _hash(path) == digest  # nothing was rewritten

    report = verify(path)
    assert not report.ok
    assert any(re.search(named, f"{p}") for p in report.errors), [str(p) for p in report.errors]
    assert _hash(path) == digest

    result = repair(path)
    assert result.ok and result.after.ok and result.actions
    assert os.path.isdir(os.path.join(path, result.backup))  # the metadata backup

    with ZarrStorage(path, read_only=True) as s:  # every intact row bit-exact, nothing invented
        assert len(s) == intact
        for key, column in before.items():
            assert torch.equal(s[key][:intact], column[:intact]), key
        if kind.endswith("group_json"):
            assert s.env_names == ("unknown-env-0",)  # names are lost; codes keep their rows
            # rebuilt as a ring of the arrays' length, in the ring's format (1), and the report says so
            assert s.bounded and s.record()["torchrl_robotmem"]["format_version"] == 1
            assert any("as a ring of 1,000 rows, the arrays' length" in a for a in result.actions), result.actions
    with ZarrStorage(path) as s:  # writable again
        s.set(slice(intact, intact + 20), _rows(20, intact))
        assert len(s) == intact + 20
    with ZarrStorage(path, read_only=True) as s:
        assert torch.equal(s["observation"][intact:intact + 20], _rows(20, intact)["observation"])
    assert verify(path).ok


def test_newer_format_version_is_refused_and_never_repaired(store):
    path, _ = store
    _edit(path, "zarr.json", _newer)
    digest = _hash(path)
    for read_only in (True, False):
        with pytest.raises(ValueError, match="format version 99.*Upgrade torchrl_robotmem"):
            ZarrStorage(path, read_only=read_only)
    report = verify(path)
    assert [p.kind for p in report.errors] == ["format"]
    with pytest.raises(IntegrityError, match="newer format"):
        repair(path)
    assert _hash(path) == digest


def test_intact_store_verifies_clean_and_writes_every_chunk(store):
    path, _ = store
    report = verify(path)
    assert report.ok and not report.problems and report.checksums
    assert report.rows == ROWS and report.chunks == report.arrays * 5
    # the all-zero column has its chunk files (otherwise a deleted one could not be told apart)
    assert sorted(f for f in os.listdir(os.path.join(path, "desired_goal")) if f != "zarr.json") == \
        ["c.0.0", "c.1.0", "c.2.0", "c.3.0", "c.4.0"]
    meta = zarr.open_group(path, mode="r").attrs["torchrl_robotmem"]
    assert meta["integrity"] == {"checksum": "crc32c", "empty_chunks": "written"}
    assert repair(path).actions == []


def test_ring_wraps_through_the_journal_and_stays_intact(tmp_path):
    path = str(tmp_path / "m.zarr")
    with ZarrStorage(path, 256, chunk_rows=CHUNK) as s:
        for start in range(0, 600, 100):
            idx = torch.arange(start, start + 100) % 256
            s.set(idx, _rows(100, start))
    assert verify(path).ok
    with ZarrStorage(path) as s:  # the journal replay and the reopen keep all-zero chunks too
        assert len(s) == 256
    assert verify(path).ok


def test_on_damage_warn_reads_the_intact_rows(store):
    path, before = store
    _edit(path, "action/c.2.0", _flip)
    with pytest.warns(UserWarning, match=r"(?s)array 'action' chunk 2 .*reading the 128 rows"):
        s = ZarrStorage(path, read_only=True, on_damage="warn")
    assert len(s) == 128 and torch.equal(s["action"][:128], before["action"][:128])
    s.close()
    with pytest.raises(ValueError, match="on_damage must be 'raise', or 'warn' with read_only=True"):
        ZarrStorage(path, on_damage="warn")


def _downgrade(path):
    """Rewrites a store as torchrl_robotmem 0.1.0 wrote it: no crc32c, all-zero chunks absent, no marker entry."""
    group = zarr.open_group(path, mode="r+")
    for name in group.attrs["schema"]:
        old = group[name]
        data = old[:]
        new = group.create_array(name, shape=old.shape, chunks=old.chunks, dtype=old.dtype, fill_value=0,
                                 compressors=_backend.make_compressors("blosc", 1, old.dtype.itemsize,
                                                                                 checksum=False),
                                 overwrite=True)
        new[:] = data  # Zarr's default: all-zero chunks are not written
    marker = dict(group.attrs["torchrl_robotmem"])
    marker.pop("integrity")
    group.update_attributes({"torchrl_robotmem": marker})


def test_store_without_checksums_still_opens(store):
    path, before = store
    _downgrade(path)
    assert not os.path.exists(os.path.join(path, "desired_goal/c"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an old store opens without a word
        with ZarrStorage(path, read_only=True) as s:
            assert all(torch.equal(s[k][:ROWS], v) for k, v in before.items())
    report = verify(path)
    assert report.ok and report.checksums is False
    # all-zero columns (run 0, env code 0, zero goals) have no chunk files: a warning, not damage
    assert {p.array for p in report.problems} == {"desired_goal", "run", "env"}
    assert {p.severity for p in report.problems} == {"warning"}
    with ZarrStorage(path) as s:
        s.set(slice(ROWS, ROWS + 10), _rows(10, ROWS))
    # a chunk missing from every array is still damage
    _edit(path, "zarr.json", _attr("len", 500))
    with pytest.raises(IntegrityError, match=r"chunk 5 .*missing from every array"):
        ZarrStorage(path, read_only=True)


def test_cli_verify_and_repair(store, tmp_path, capsys):
    """``robotmem verify`` / ``repair`` as subprocesses (each starts an interpreter: ~20 s on a loaded box)."""
    path, before = store
    _edit(path, "observation/c.2.0", lambda d: d[:-7])
    run = [sys.executable, "-m", "torchrl_robotmem"]
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    out = subprocess.run([*run, "verify", path], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 1, out.stderr
    assert "array 'observation' chunk 2 (observation/c.2.0, rows 128-191)" in out.stdout
    assert main(["repair", path, "--dry-run"]) == 1 and "would repair" in capsys.readouterr().out
    fixed = subprocess.run([*run, "repair", path, "--json"], capture_output=True, text=True, env=env, timeout=300)
    assert fixed.returncode == 0, fixed.stderr
    assert json.loads(fixed.stdout)["after"]["ok"] is True
    assert main(["verify", path]) == 0
    with ZarrStorage(path, read_only=True) as s:
        assert len(s) == 128 and torch.equal(s["observation"], before["observation"][:128])
    capsys.readouterr()
    assert main(["verify", str(tmp_path)]) == 2 and "not a torchrl_robotmem memory" in capsys.readouterr().err


def test_key_added_later_writes_its_older_chunks(store):
    """Schema evolution: older rows of a new key read zeros, from chunk files (so the store verifies clean)."""
    path, _ = store
    with ZarrStorage(path) as s:
        rows = _rows(10, ROWS)
        rows["extra"] = torch.ones(10, 2)
        s.set(slice(ROWS, ROWS + 10), rows)
    assert sorted(f for f in os.listdir(os.path.join(path, "extra")) if f != "zarr.json") == \
        ["c.0.0", "c.1.0", "c.2.0", "c.3.0", "c.4.0"]
    with ZarrStorage(path, read_only=True) as s:
        assert not s["extra"][:ROWS].any() and s["extra"][ROWS:].all()
    assert verify(path).ok


# -- repair and readers ---------------------------------------------------------------------

_HOLD_WRITER = """
import os, sys, time
from torchrl_robotmem import ZarrStorage
s = ZarrStorage(sys.argv[1])  # holds the writer lock until killed
open(sys.argv[2], "w").close()
time.sleep(600)
"""


@pytest.mark.parametrize("damaged", [False, True])
def test_repair_takes_the_writer_lock(store, tmp_path, damaged):
    """A process writing the store: repair refuses before it reads or writes anything, naming the cause."""
    path, _ = store
    ready = tmp_path / "ready"
    env = {**os.environ, "TORCHRL_ROBOTMEM_COMMIT_PROCESS": "0", "PYTHONWARNINGS": "ignore"}
    writer = subprocess.Popen([sys.executable, "-c", _HOLD_WRITER, path, str(ready)], env=env)
    try:
        while not ready.exists():
            assert writer.poll() is None, "the writer process died"
            time.sleep(0.05)
        if damaged:  # damage while it writes (a chunk deleted under it)
            os.remove(os.path.join(path, "action/c.1.0"))
        digest = _hash(path)
        with pytest.raises(RuntimeError, match=rf"(?s)robotmem repair needs the store to itself and did not change "
                                               rf"it: .*is writing to .*pid {writer.pid}.*Stop the writer"):
            repair(path)
        assert _hash(path) == digest
    finally:
        writer.kill()
        writer.wait(60)
    assert repair(path).ok  # the writer gone, repair runs


_READER_PAUSED_AFTER_LISTING = """
import json, os, sys, time
import torch
from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage import integrity

path, listed, moved = sys.argv[1:4]
real = integrity.check_open


def paused(*args, **kwargs):  # the open's checks (its listing of the chunk files) done, the rows not read yet
    out = real(*args, **kwargs)
    open(listed, "w").close()
    deadline = time.monotonic() + 300
    while not os.path.exists(moved):
        assert time.monotonic() < deadline, "repair never finished"
        time.sleep(0.01)
    return out


integrity.check_open = paused
try:
    with ZarrStorage(path, read_only=True) as s:
        n = len(s)
        obs = s["observation"][:n]
        zero = (obs == 0).all(-1)
        print(json.dumps({"rows": n, "zero_rows": zero.nonzero().flatten().tolist()[:5], "obs": obs.tolist()}))
except integrity.IntegrityError as err:
    print(json.dumps({"error": str(err)}))
"""


def test_reader_is_never_served_zeros_for_a_chunk_repair_moves_away(store, tmp_path):
    """A read-only open lists the chunk files, repair moves a damaged one to its backup, then the rows are read.

    The order holds by construction: the reader process pauses right after the
    open's checks (a hook wrapping ``integrity.check_open``) until ``repair`` has
    finished. Zarr reads the moved chunk as zeros; the reader must raise an
    ``IntegrityError`` naming it (or serve the right rows), never serve zeros.
    """
    path, before = store
    _edit(path, "observation/c.2.0", _flip)  # damage repair will move away
    listed, moved = tmp_path / "listed", tmp_path / "moved"
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    reader = subprocess.Popen([sys.executable, "-c", _READER_PAUSED_AFTER_LISTING, path, str(listed), str(moved)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        while not listed.exists():
            assert reader.poll() is None, reader.stderr.read()
            time.sleep(0.02)
        result = repair(path)
        assert any("moved the damaged chunk observation/c.2.0" in a for a in result.actions), str(result)
        moved.touch()
        out, err = reader.communicate(timeout=300)
    finally:
        if reader.poll() is None:
            reader.kill()
    assert reader.returncode == 0, err
    got = json.loads(out.strip().splitlines()[-1])
    if "error" in got:
        assert re.search(r"array 'observation' chunk 2 \(observation/c.2.0, rows 128-191\): chunk file missing",
                         got["error"]), got["error"]
        assert "robotmem repair" in got["error"]
    else:  # the right rows (what the store held when the reader's open checked it), nothing invented
        assert not got["zero_rows"], f"served zero rows {got['zero_rows']} where data was"
        assert torch.equal(torch.tensor(got["obs"]), before["observation"][:got["rows"]])
    with ZarrStorage(path, read_only=True) as s:  # after the repair: the intact rows
        assert len(s) == 128 and torch.equal(s["observation"], before["observation"][:128])


def test_refresh_runs_the_checks_an_open_runs(store):
    """A tailing reader's refresh after a commit record claiming more rows than written: an error, not zeros."""
    path, before = store
    reader = ZarrStorage(path, read_only=True)
    assert reader.refresh() == ROWS
    _edit(path, "zarr.json", _attr("len", 390))  # rows 300-389 were never written
    with pytest.raises(IntegrityError, match=r"array '\w+' chunk 5 \(\w+/c\.5(\.0)?, rows 320-383\): chunk file missing"):
        ZarrStorage(path, read_only=True)
    with pytest.raises(IntegrityError, match=r"array '\w+' chunk 5 \(\w+/c\.5(\.0)?, rows 320-383\): chunk file missing"):
        reader.refresh()
    # the handle keeps what it had
    assert len(reader) == ROWS and torch.equal(reader["observation"][:ROWS], before["observation"])
    _edit(path, "zarr.json", _attr("len", ROWS))
    assert reader.refresh() == ROWS
    reader.close()


_GROW = """
import sys, torch
from torchrl_robotmem import ZarrStorage
sys.path.insert(0, sys.argv[3])
from test_integrity import _rows
path, new_max = sys.argv[1], int(sys.argv[2])
with ZarrStorage(path, new_max) as s:  # grows the store (it has not wrapped), then writes past the old size
    n = len(s)
    s.set(slice(n, n + 900), _rows(900, n))
"""


def test_refresh_after_the_writer_grew_the_store(store):
    """A writer process reopens the store with a larger max_size and writes past the old size; a reader refreshes."""
    path, before = store
    reader = ZarrStorage(path, read_only=True)
    assert reader.refresh() == ROWS and reader.max_size == MAX
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    subprocess.run([sys.executable, "-c", _GROW, path, str(2 * MAX), os.path.dirname(__file__)], env=env,
                   check=True, timeout=300)
    assert reader.refresh() == ROWS + 900 > MAX
    assert reader.max_size == 2 * MAX
    assert torch.equal(reader["observation"][:ROWS], before["observation"])
    assert torch.equal(reader["observation"][ROWS:ROWS + 900], _rows(900, ROWS)["observation"])
    reader.close()
