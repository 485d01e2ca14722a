"""Hostile archives, bad key names and writes without room: one error line, nothing at the target, no traceback.

* ``.npz`` files whose headers lie or whose members are damaged: every import
  checks the zip and ``.npy`` headers against the file and the memory it can
  get before allocating, and turns damage found while reading into one line
  naming the file and the member (``torchrl_robotmem/cli/_archive.py``);
* key names a store cannot hold portably: refused at the write that brings
  them, the store keeps every earlier row and keeps opening;
* ``import`` / ``export`` / ``copy`` under ``ulimit -f`` (``RLIMIT_FSIZE``, a real
  subprocess whose writes get ``EFBIG``) and onto a full file system (a small
  tmpfs mounted in a user namespace: skipped, saying why, where that is not
  allowed): one line naming the command, the target and the cause, exit 1,
  nothing at the target, and the same command succeeds once there is room.

Real stores, real files, real processes; nothing is mocked.
"""
from __future__ import annotations

import json
import os
import re
import resource
import shutil
import signal
import struct
import subprocess
import sys
import textwrap
import time
import zipfile
import zlib

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ENV = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _plain(path, n: int = 64, *, seed: int = 0, compressed: bool = False) -> dict[str, np.ndarray]:
    """A plain npz of ``n`` transitions (random floats: they do not compress)."""
    rng = np.random.default_rng(seed)
    arrays = {"observation": rng.random((n, 10), np.float32), "next_observation": rng.random((n, 10), np.float32),
              "action": rng.random((n, 4), np.float32), "reward": rng.random(n, np.float32),
              "done": np.arange(n) % 50 == 49}
    (np.savez_compressed if compressed else np.savez)(path, **arrays)
    return arrays


def _member_data_offset(path, member: str) -> tuple[int, int]:
    """``(offset, size)`` of ``member``'s (compressed) data in the zip ``path``."""
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(member)
    with open(path, "rb") as f:
        f.seek(info.header_offset)
        local = f.read(30)
    name_len, extra_len = struct.unpack("<HH", local[26:30])
    return info.header_offset + 30 + name_len + extra_len, info.compress_size


def _patch(path, offset: int, data: bytes) -> None:
    with open(path, "r+b") as f:
        f.seek(offset)
        f.write(data)


def _npy_header(shape, dtype="<f4") -> bytes:
    """An ``.npy`` version 1.0 header declaring ``shape`` (padded as NumPy pads it)."""
    text = repr({"descr": dtype, "fortran_order": False, "shape": tuple(shape)}).encode()
    pad = 64 - (10 + len(text) + 1) % 64
    body = text + b" " * pad + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(body)) + body


def _write_zip(path, members: list[tuple[str, bytes, int, int]]) -> None:
    """A zip of deflate members ``(name, raw deflate data, crc32, uncompressed size)``, written by hand."""
    local, central = b"", b""
    for name, data, crc, size in members:
        n = name.encode()
        central += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 8, 0, 0x21, crc, len(data), size,
                               len(n), 0, 0, 0, 0, 0, len(local)) + n
        local += struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 8, 0, 0x21, crc, len(data), size, len(n), 0) + n + data
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(members), len(members), len(central), len(local), 0)
    with open(path, "wb") as f:
        f.write(local + central + end)


def _deflated(raw: bytes) -> tuple[bytes, int, int]:
    c = zlib.compressobj(6, zlib.DEFLATED, -15)
    return c.compress(raw) + c.flush(), zlib.crc32(raw), len(raw)


def _zeros_member(name: str, mib: int) -> tuple[str, bytes, int, int]:
    """A real deflate member: an ``.npy`` of ``mib`` MiB of float32 zeros, compressed about 1000:1 (fast: one
    MiB block compressed once and repeated after a full flush, which makes every block alike)."""
    header = _npy_header((mib << 18,))
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    zeros = bytes(1 << 20)
    head = c.compress(header) + c.flush(zlib.Z_FULL_FLUSH)
    block = c.compress(zeros) + c.flush(zlib.Z_FULL_FLUSH)
    assert c.compress(zeros) + c.flush(zlib.Z_FULL_FLUSH) == block
    crc = zlib.crc32(header)
    for _ in range(mib):
        crc = zlib.crc32(zeros, crc)
    return name, head + block * mib + c.flush(), crc, len(header) + (mib << 20)


def _export(tmp_path, name: str = "exp.npz") -> str:
    """A small memory exported by ``robotmem export``."""
    mem = tmp_path / "mem.zarr"
    st = ZarrStorage(mem, 100, env="FetchPush-v4")
    TensorDictReplayBuffer(storage=st, batch_size=4).extend(TensorDict({
        "observation": torch.arange(40.0).reshape(20, 2),
        "next": {"done": (torch.arange(20) % 5 == 4).unsqueeze(-1)}}, [20]))
    st.close()
    out = str(tmp_path / name)
    assert main(["export", str(mem), out]) == 0
    return out


def _rewrite_record(src: str, **changes) -> None:
    z = dict(np.load(src, allow_pickle=False))
    meta = json.loads(str(z["__robotmem__"]))
    meta.update(changes)
    z["__robotmem__"] = np.array(json.dumps(meta))
    np.savez(src, **z)


def _listing(directory) -> list[str]:
    return sorted(os.listdir(directory))


def _assert_one_line(err: str, command: str, *needles: str) -> None:
    assert "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 and err.startswith(f"robotmem {command}: error: "), err
    for needle in needles:
        assert needle in err, (needle, err)


# -- hostile archives ----------------------------------------------------------------------------------


def _header_declares_8_tib(src):
    """observation.npy's header declares 2**41 float32 (8 TiB); the member holds 1 KiB."""
    _plain(src)
    z = dict(np.load(src))
    with zipfile.ZipFile(src, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, a in z.items():
            data = _npy_header((1 << 41,)) + bytes(1024) if k == "observation" else None
            if data is None:
                with zf.open(k + ".npy", "w") as f:
                    np.lib.format.write_array(f, a)
            else:
                zf.writestr(k + ".npy", data)
    return "observation.npy", (r"declares an array of shape \[2199023255552\] float32 \(8\.0 TiB: 8,796,093,022,208 "
                               r"bytes\), but the member holds 1,024")


def _central_entry(path, member: str) -> int:
    """The offset of ``member``'s entry in the zip's central directory (sizes at +20 and +24)."""
    with open(path, "rb") as f:
        raw = f.read()
    start = raw.index(b"PK\x01\x02")
    while True:
        name_len = struct.unpack("<H", raw[start + 28:start + 30])[0]
        if raw[start + 46:start + 46 + name_len] == member.encode():
            return start
        start = raw.index(b"PK\x01\x02", start + 4)


def _zip_declares_more_than_deflate_expands(src):
    """The zip directory says observation.npy inflates to 3,000x its compressed size (deflate: at most 1032x)."""
    _plain(src, compressed=True)
    with zipfile.ZipFile(src) as zf:
        declared = zf.getinfo("observation.npy").compress_size * 3000
    _patch(src, _central_entry(src, "observation.npy") + 24, struct.pack("<I", declared))
    return "observation.npy", r"more than deflate can expand"


def _bad_crc(src):
    _plain(src)
    offset, size = _member_data_offset(src, "observation.npy")
    with open(src, "rb") as f:
        f.seek(offset + size - 8)
        byte = f.read(1)
    _patch(src, offset + size - 8, bytes([byte[0] ^ 0xFF]))  # inside the array data, past the .npy header
    return "observation.npy", r"BadZipFile: Bad CRC-32 for file 'observation\.npy'"


def _corrupt_deflate(src):
    _plain(src, 2000, compressed=True)
    offset, size = _member_data_offset(src, "next_observation.npy")
    _patch(src, offset + size // 2, b"\xff" * 64)  # mid-stream: past the header, inside the array data
    return "next_observation.npy", r"(zlib\.error|BadZipFile|EOF)"


def _corrupt_deflate_block(src):
    _plain(src, compressed=True)
    offset, _ = _member_data_offset(src, "action.npy")
    _patch(src, offset, b"\xff")  # the first deflate block's type: 11, reserved
    return "action.npy", r"zlib\.error: .*invalid block type"


def _bad_npy_header(src):
    _plain(src, 2000)  # a member larger than zipfile's read-ahead: the header is read before the member's CRC
    offset, _ = _member_data_offset(src, "action.npy")
    _patch(src, offset, b"\x93NUMPZ")  # not the .npy magic
    return "action.npy", r"array 'action' cannot be read \(ValueError: the magic string is not correct.* from member 'action\.npy'"


def _cut_off_member(src):
    """observation.npy's sizes in the zip directory are 100 bytes short of its array (a member cut off)."""
    _plain(src, 2000)
    with zipfile.ZipFile(src) as zf:
        small = zf.getinfo("observation.npy").file_size - 100
    _patch(src, _central_entry(src, "observation.npy") + 20, struct.pack("<II", small, small))
    return "observation.npy", (r"declares an array of shape \[2000, 10\] float32 \(78\.1 KiB: 80,000 bytes\), but "
                               r"the member holds 79,900")


def _max_size_1e13(src, tmp_path):
    exported = _export(tmp_path, "exp.npz")
    shutil.move(exported, src)
    _rewrite_record(src, max_size=1e13)
    return "'__robotmem__' record's max_size", r"max_size 10,000,000,000,000 rows .*more than the .* leaves this"


HOSTILE = [
    ("npy-header-8-TiB", _header_declares_8_tib),
    ("zip-size-past-deflate", _zip_declares_more_than_deflate_expands),
    ("bad-crc", _bad_crc),
    ("corrupt-deflate", _corrupt_deflate),
    ("corrupt-deflate-block", _corrupt_deflate_block),
    ("bad-npy-header", _bad_npy_header),
    ("cut-off-member", _cut_off_member),
    ("max-size-1e13", _max_size_1e13),
]


@pytest.mark.parametrize("case", HOSTILE, ids=[c[0] for c in HOSTILE])
def test_a_hostile_npz_is_one_line_naming_file_and_member_and_creates_nothing(case, tmp_path, capsys):
    _, make = case
    src = str(tmp_path / "src.npz")
    member, match = make(src, tmp_path) if make is _max_size_1e13 else make(src)
    capsys.readouterr()
    before = _listing(tmp_path)
    target = tmp_path / "new" / "m.zarr"
    assert main(["import", src, str(target)]) == 2
    err = capsys.readouterr().err
    _assert_one_line(err, "import", "src.npz", member, "nothing was created")
    assert re.search(match, err), err
    assert not target.exists() and _listing(tmp_path) == before


def test_a_small_zip_declaring_more_than_the_address_space_limit_is_refused_before_allocating(tmp_path):
    """1.5 MiB of real deflate data inflating to a 1.5 GiB array, imported under ``ulimit -v`` (what the process
    maps already + 1 GiB): refused from the headers, one line, nothing created (before: numpy's MemoryError)."""
    src = tmp_path / "big.npz"
    plain = {k: v[:4] for k, v in _plain(tmp_path / "small.npz", 4).items() if k != "observation"}
    members = [_zeros_member("observation.npy", 1536)]
    for k, a in plain.items():
        import io

        buf = io.BytesIO()
        np.lib.format.write_array(buf, a)
        members.append((k + ".npy", *_deflated(buf.getvalue())))
    _write_zip(src, members)
    assert os.path.getsize(src) < 4 << 20
    with zipfile.ZipFile(src) as zf:
        assert zf.getinfo("observation.npy").file_size > 1536 << 20  # what the directory declares
    target = tmp_path / "m.zarr"
    code = textwrap.dedent(f"""
        import resource, sys
        import tensordict, torch, torchrl, zarr  # what the import loads, loaded before the limit
        import torchrl_robotmem.cli.npz_io, torchrl_robotmem.cli.plain_npz, torchrl_robotmem.cli.transfer
        from torchrl_robotmem.cli import main
        size = int(next(l for l in open("/proc/self/status") if l.startswith("VmSize:")).split()[1]) * 1024
        resource.setrlimit(resource.RLIMIT_AS, (size + (1 << 30), resource.getrlimit(resource.RLIMIT_AS)[1]))
        sys.exit(main(["import", {str(src)!r}, {str(target)!r}]))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=600)
    assert proc.returncode == 2, proc.stderr
    _assert_one_line(proc.stderr, "import", "big.npz", "observation.npy", "the address-space limit (ulimit -v)",
                     "nothing was created")
    assert not target.exists() and _listing(tmp_path) == ["big.npz", "small.npz"]


# -- key names -----------------------------------------------------------------------------------------

BAD_NAMES = [
    ("backslash", "a\\b", r"holds a path separator \('\\\\'\)"),
    ("tab", "tab\tkey", r"holds a control character \('\\t'\)"),
    ("newline-nested", ("next", "x\ny"), r"holds a control character \('\\n'\)"),
    ("too-long", "k" * 300, r"is 300 bytes long in UTF-8, over the 255"),
    ("too-long-utf8", "é" * 130, r"is 260 bytes long in UTF-8"),
    ("colon", "a:b", r"holds a character Windows file names cannot hold \(':'\)"),
    ("trailing-dot", "obs.", r"ends in '\.'"),
    ("device-name", "nul", r"is a Windows device name"),
    ("case-twin", "Observation", r"'Observation' differs from 'observation'.*only in letter case"),
    ("lone-surrogate", "bad\udc80", r"not valid Unicode text"),
]


def _rows(start: int, n: int) -> TensorDict:
    w = torch.arange(start, start + n)
    return TensorDict({"observation": w.float().unsqueeze(-1) * torch.tensor([1.0, -1.0]),
                       "next": {"done": (w % 5 == 4).unsqueeze(-1)}}, [n])


@pytest.mark.parametrize("case", BAD_NAMES, ids=[c[0] for c in BAD_NAMES])
def test_a_key_name_a_store_cannot_hold_is_refused_at_its_first_write(case, tmp_path):
    _, name, match = case
    path = tmp_path / "m.zarr"
    st = ZarrStorage(path, 100, env="FetchPush-v4")
    rb = TensorDictReplayBuffer(storage=st, batch_size=4)
    before = _rows(0, 20)
    rb.extend(before)
    st.flush()
    bad = _rows(20, 5)
    bad.set(name, torch.ones(5))
    with pytest.raises(ValueError, match=re.compile(match, re.S)) as info:
        rb.extend(bad)
    assert "cannot be stored" in str(info.value) and "nothing was written" in str(info.value)
    rb.extend(_rows(20, 5))  # the same handle writes on
    st.close()
    for read_only in (True, False):  # the store opens, every earlier row bit-exact
        again = ZarrStorage(path, read_only=read_only)
        try:
            assert len(again) == 25
            got = again[:20]
            for key in before.keys(True, True):
                assert got.get(key).numpy().tobytes() == before.get(key).numpy().tobytes(), key
        finally:
            again.close()
    assert main(["verify", str(path)]) == 0


def test_a_bad_key_name_at_a_first_write_creates_no_array(tmp_path):
    path = tmp_path / "m.zarr"
    st = ZarrStorage(path, 100)
    td = _rows(0, 5)
    td.set("tab\tkey", torch.ones(5))
    with pytest.raises(ValueError, match="'tab\\\\tkey' cannot be stored"):
        TensorDictReplayBuffer(storage=st, batch_size=4).extend(td)
    assert not st.initialized and [p for p in os.listdir(path) if p != "zarr.json" and not p.startswith(".")] == []
    st.close()


def test_an_import_of_a_key_name_a_store_cannot_hold_is_one_line(tmp_path, capsys):
    src = _export(tmp_path, "exp.npz")
    z = dict(np.load(src, allow_pickle=False))
    meta = json.loads(str(z["__robotmem__"]))
    z["a\\b"] = z["observation"]
    meta["schema"]["a\\b"] = meta["schema"]["observation"]
    z["__robotmem__"] = np.array(json.dumps(meta))
    np.savez(src, **z)
    capsys.readouterr()
    target = tmp_path / "m.zarr"
    assert main(["import", src, str(target)]) == 2
    _assert_one_line(capsys.readouterr().err, "import", "exp.npz", "'a\\\\b' cannot be stored", "path separator")
    assert not target.exists() and not [p for p in os.listdir(tmp_path) if ".partial-" in p]


# -- no room: ulimit -f and a full file system ----------------------------------------------------------

_DRIVER = textwrap.dedent("""
    import contextlib, io, json, sys
    from torchrl_robotmem.cli import main
    out = []
    for args in json.loads(sys.argv[1]):
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            rc = main(args)
        out.append({"args": args, "rc": rc, "err": err.getvalue()})
    print("RESULTS" + json.dumps(out))
""")


def _results(stdout: str) -> list[dict]:
    assert "RESULTS" in stdout, stdout
    return json.loads(stdout.split("RESULTS", 1)[1])


def _partials(directory) -> list[str]:
    return [p for p in os.listdir(directory) if ".partial-" in p]


def test_import_export_and_copy_under_a_file_size_limit(tmp_path, capsys):
    """``ulimit -f`` below what each command writes: one line (command, target, ``File too large``), exit 1,
    nothing at the target; then the same commands without the limit succeed."""
    src = tmp_path / "t.npz"
    _plain(src, 20_000)
    mem = tmp_path / "mem.zarr"
    assert main(["import", str(src), str(mem)]) == 0  # the source of export and copy
    biggest = max(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(mem) for f in fs)
    limit = min(biggest // 2, 64 << 10)
    out = tmp_path / "out"
    out.mkdir()
    commands = [["import", str(src), str(out / "m.zarr")], ["export", str(mem), str(out / "e.npz")],
                ["copy", str(mem), str(out / "c.zarr")]]

    def limited():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write gets EFBIG instead of the signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    proc = subprocess.run([sys.executable, "-c", _DRIVER, json.dumps(commands)], capture_output=True, text=True,
                          env=ENV, preexec_fn=limited, timeout=600)
    assert proc.returncode == 0, proc.stderr
    for r in _results(proc.stdout):
        command, target = r["args"][0], r["args"][-1]
        assert r["rc"] == 1, r
        _assert_one_line(r["err"], command, repr(target), "File too large", "ulimit -f", "nothing was left at")
    assert _listing(out) == [], "a failed command left a file or its build"
    capsys.readouterr()
    for args in commands:  # with room: the same commands succeed
        assert main(args) == 0, capsys.readouterr().err
    assert _listing(out) == ["c.zarr", "e.npz", "m.zarr"]
    assert main(["verify", str(out / "m.zarr")]) == 0 and main(["verify", str(out / "c.zarr")]) == 0


_FULL_DISK = textwrap.dedent("""
    set -u
    mount -t tmpfs -o size=256k tmpfs "$1" || exit 77
    "$2" -c "$3" "$4" > "$5"
    ls -A "$1" > "$6"
    mount -o remount,size=64m "$1"
    "$2" -c "$3" "$4" > "$7"
    ls -A "$1" > "$8"
""")


def test_import_export_and_copy_onto_a_full_file_system(tmp_path):
    """A 256 KiB tmpfs (mounted in a user namespace): each command fails with one line naming ``No space left``,
    exit 1, nothing left; the tmpfs grown to 64 MiB, the same commands succeed."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare(1) to mount a small tmpfs in a user namespace")
    src = tmp_path / "t.npz"
    _plain(src, 20_000)
    mem = tmp_path / "mem.zarr"
    assert main(["import", str(src), str(mem)]) == 0
    disk = tmp_path / "disk"
    disk.mkdir()
    commands = [["import", str(src), str(disk / "m.zarr")], ["export", str(mem), str(disk / "e.npz")],
                ["copy", str(mem), str(disk / "c.zarr")]]
    files = [str(tmp_path / n) for n in ("full.json", "full.ls", "room.json", "room.ls")]
    proc = subprocess.run(["unshare", "-rm", "sh", "-c", _FULL_DISK, "sh", str(disk), sys.executable, _DRIVER,
                           json.dumps(commands), *files], capture_output=True, text=True, env=ENV, timeout=600)
    if proc.returncode == 77 or (proc.returncode != 0 and not os.path.exists(files[0])):
        pytest.skip(f"cannot mount a tmpfs in a user namespace here: {proc.stderr.strip()[:200]}")
    assert proc.returncode == 0, proc.stderr
    with open(files[0]) as f:
        full = _results(f.read())
    with open(files[2]) as f:
        room = _results(f.read())
    for r in full:
        command, target = r["args"][0], r["args"][-1]
        assert r["rc"] == 1, r
        _assert_one_line(r["err"], command, repr(target), "No space left on device", "nothing was left at")
    assert open(files[1]).read().split() == [], "a failed command left a file or its build on the full disk"
    for r in room:
        assert r["rc"] == 0, r
    assert sorted(open(files[3]).read().split()) == ["c.zarr", "e.npz", "m.zarr"]


_FORGED = {"a list": "[]", "null": "null", "attributes a list": json.dumps(
    {"zarr_format": 3, "node_type": "group", "attributes": ["torchrl_robotmem"]}),
    "nested 100k deep": "[" * 100_000 + "]" * 100_000}


@pytest.mark.parametrize("case", sorted(_FORGED))
def test_a_forged_record_or_a_truncated_zip_is_one_line_exit_2(case, tmp_path, capsys):
    """Found by a review: a zarr.json that is valid JSON but not a node's metadata (or nested past the recursion
    limit), and a *.zip memory cut half-way, ended in a traceback (AttributeError, TypeError, BadZipFile)."""
    forged = tmp_path / "forged.zarr"
    forged.mkdir()
    (forged / "zarr.json").write_text(_FORGED[case])
    src = str(tmp_path / "src.zarr")
    with ZarrStorage(src, 100, env="E", goal_conditioned=False) as st:
        st.set(slice(0, 10), TensorDict({"obs": torch.arange(10.0)}, [10]))
    assert main(["export", src, str(tmp_path / "m.npz")]) == 0
    assert main(["import", str(tmp_path / "m.npz"), str(tmp_path / "m.zip")]) == 0
    data = (tmp_path / "m.zip").read_bytes()
    (tmp_path / "cut.zip").write_bytes(data[: len(data) // 2])  # a download cut half-way
    capsys.readouterr()
    for target in (forged, tmp_path / "cut.zip"):
        for args in (["inspect", str(target)], ["export", str(target), str(tmp_path / "x.npz")],
                     ["copy", str(target), str(tmp_path / ("c.zip" if target.suffix == ".zip" else "c.zarr"))]):
            assert main(args) == 2, args
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and "is not a torchrl_robotmem memory" in err and "Traceback" not in err, (args, err)
    assert not os.path.exists(tmp_path / "x.npz") and not os.path.exists(tmp_path / "c.zarr")


def test_an_export_of_a_ring_a_writer_wraps_is_in_write_order_or_refused(tmp_path, capsys):
    """Found by a review: an export while a writer wrapped a full ring rolled rows re-read at later commits by the
    cursor of the record read at the open: the newest rows came first. Every export is now in write order
    (each row's observation is its write number) or refused, saying why and what to do."""
    path = str(tmp_path / "ring.zarr")
    writer = textwrap.dedent(f"""
        import time, torch
        from tensordict import TensorDict
        from torchrl.data import TensorDictReplayBuffer
        from torchrl_robotmem import ZarrStorage
        st = ZarrStorage({path!r}, max_size=300, chunk_rows=32, env="E", goal_conditioned=False,
                         commit_interval=0.02)
        rb = TensorDictReplayBuffer(storage=st, batch_size=4)
        k = 0
        while True:
            rb.extend(TensorDict({{"observation": torch.arange(k, k + 7).float().unsqueeze(-1),
                                   "next": {{"done": (torch.arange(k, k + 7) % 10 == 9).unsqueeze(-1)}}}}, [7]))
            k += 7
            if k > 600:
                open({path!r} + ".wrapped", "w").close()
            time.sleep(0.002)
    """)
    proc = subprocess.Popen([sys.executable, "-c", writer], env=ENV)
    try:
        while not os.path.exists(path + ".wrapped"):  # full, and wrapped twice: every export is of a wrapping ring
            assert proc.poll() is None, "the writer died"
            time.sleep(0.05)
        outcomes = []
        for attempt in range(6):
            out = str(tmp_path / f"e{attempt}.npz")
            code = main(["export", path, out])
            err = capsys.readouterr().err
            if code == 0:
                w = np.load(out)["observation"][:, 0].astype(np.int64)
                assert len(w) == 300 and (np.diff(w) == 1).all(), f"not in write order: {w.tolist()}"
                outcomes.append("exported")
            else:
                assert code == 1 and "overwrote rows of this full ring while it was read" in err, err
                assert "writer is stopped or paused" in err and not os.path.exists(out)
                outcomes.append("refused")
        print("outcomes:", outcomes)
    finally:
        proc.kill()
        proc.wait()
    out = str(tmp_path / "after.npz")  # the writer gone (killed): the committed rows, in write order
    assert main(["export", path, out]) == 0
    w = np.load(out)["observation"][:, 0].astype(np.int64)
    assert (np.diff(w) == 1).all(), [(int(w[i]), int(w[i + 1])) for i in np.flatnonzero(np.diff(w) != 1)]


@pytest.mark.parametrize("key, value", [("episode", np.iinfo(np.int64).max), ("run", 2**62), ("episode", -5)])
def test_an_npz_whose_episode_or_run_ids_cannot_be_counted_on_is_refused_naming_the_key(tmp_path, capsys, key, value):
    """Found by a review: ids at the int64 limit imported and verified, and the memory's first write raised
    OverflowError (the next id is the largest + 1)."""
    src = str(tmp_path / "a.zarr")
    with ZarrStorage(src, 100, env="E", goal_conditioned=False) as st:
        st.set(slice(0, 10), TensorDict({"obs": torch.arange(10.0)}, [10]))
    assert main(["export", src, str(tmp_path / "a.npz")]) == 0
    arrays = dict(np.load(tmp_path / "a.npz"))
    arrays[key][3] = value  # an edited (or hostile) export
    np.savez(tmp_path / "b.npz", **arrays)
    capsys.readouterr()
    assert main(["import", str(tmp_path / "b.npz"), str(tmp_path / "b.zarr")]) != 0
    err = capsys.readouterr().err
    assert f"the state's {key!r} ids must be in [0, 2**62)" in err and err.count("\n") == 1, err
    assert not os.path.exists(tmp_path / "b.zarr")


def test_repair_of_a_damaged_zip_memory_changes_nothing_and_says_how(tmp_path, capsys):
    """Found by a review: repair appended a backup to the zip, then raised BadZipFile reading the damaged member."""
    src = str(tmp_path / "a.zarr")
    with ZarrStorage(src, 100, env="E", goal_conditioned=False) as st:
        st.set(slice(0, 10), TensorDict({"obs": torch.arange(10.0), "act": torch.ones(10, 2)}, [10]))
    assert main(["export", src, str(tmp_path / "a.npz")]) == 0
    zpath = str(tmp_path / "m.zip")
    assert main(["import", str(tmp_path / "a.npz"), zpath]) == 0
    with zipfile.ZipFile(zpath) as z:
        info = z.getinfo("act/zarr.json")
    data = bytearray(open(zpath, "rb").read())
    data[info.header_offset + 30 + len(info.filename) + 5] ^= 0xFF  # one byte of act/zarr.json's data
    open(zpath, "wb").write(bytes(data))
    capsys.readouterr()
    assert main(["verify", zpath]) == 1
    assert "Bad CRC-32" in capsys.readouterr().out
    assert main(["repair", zpath]) == 1
    err = capsys.readouterr().err
    assert "repair does not write into a *.zip memory" in err and "python -m zipfile -e" in err, err
    assert "Traceback" not in err and open(zpath, "rb").read() == bytes(data)
