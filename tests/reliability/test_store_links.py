"""Nothing a store holds reaches outside it: symbolic links inside a store are refused everywhere.

A store is a folder, and folders are shared (tarballs, shared drives, NFS). A
link inside one can name any file: another memory's chunk with a valid
checksum, a private file, a directory elsewhere that a writer would write
into. Each case here plants a real link in a real store and runs every path
that reads or writes a store: ``ZarrStorage`` opened read-only and writable,
``verify``, and the ``inspect`` / ``export`` / ``copy`` (local and to S3) /
``repair`` commands. Each must refuse, naming the link; nothing the link names
may appear in a result, and no file anywhere changes (the whole folder, the
link targets included, is hashed before and after).

The root itself may be a link (the path a user typed is followed once), and
hard links are files of the store like any other: ``ZarrCheckpointer`` makes
them, and a write never goes into an existing file, so the other names keep
their bytes.
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
import zipfile

import pytest
import torch
from _s3 import new_bucket, s3_server  # noqa: F401  (pytest fixtures)
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.cli import main
from torchrl_robotmem.samplers import PersistentPrioritizedSampler
from torchrl_robotmem.storage.errors import LinkError
from torchrl_robotmem.storage.integrity import verify

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX symbolic links")

ROWS, CHUNK, MAX = 96, 32, 200
SECRET = b"the private bytes of a file outside every store\n" * 20


def _rows(n: int, offset: float) -> TensorDict:
    i = torch.arange(n, dtype=torch.float32)
    return TensorDict({"observation": i.unsqueeze(-1).expand(n, 3) + offset,
                       "action": -i.unsqueeze(-1) - offset,
                       ("next", "done"): ((i + 1) % 16 == 0).unsqueeze(-1),
                       ("next", "is_success"): (i % 2 == 0).unsqueeze(-1)}, [n])


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    """Two memories of one layout (``b``'s rows are ``a``'s plus 5000), ``a`` with stored priorities."""
    root = tmp_path_factory.mktemp("pristine")
    for name, offset in (("a.zarr", 0.0), ("b.zarr", 5000.0)):
        with ZarrStorage(str(root / name), MAX, chunk_rows=CHUNK, env="FetchPush-v4") as s:
            rb = TensorDictReplayBuffer(storage=s, sampler=PersistentPrioritizedSampler(alpha=0.7, beta=0.5),
                                        batch_size=8)
            rb.extend(_rows(ROWS, offset))
            rb.update_priority(torch.arange(ROWS), torch.linspace(0.5, 3.0, ROWS))
            rb.sampler.flush()
    return root


@pytest.fixture
def folder(pristine, tmp_path):
    """A folder with the two memories, a private file and a spare directory beside them."""
    root = tmp_path / "shared"
    shutil.copytree(pristine, root)
    (root / "secret.txt").write_bytes(SECRET)
    return root


def _hash_tree(path) -> dict:
    out = {}
    for dirpath, dirs, files in os.walk(path):
        for entry in dirs + files:
            full = os.path.join(dirpath, entry)
            rel = os.path.relpath(full, path)
            if os.path.islink(full):
                out[rel] = "link:" + os.readlink(full)
            elif os.path.isfile(full):
                with open(full, "rb") as fh:
                    out[rel] = hashlib.sha256(fh.read()).hexdigest()
            else:
                out[rel] = "dir"
    return out


def _first_file(directory) -> str:
    for dirpath, _, files in sorted(os.walk(directory)):
        for f in sorted(files):
            return os.path.join(dirpath, f)
    raise AssertionError(f"no file under {directory}")


def _link_other_memorys_chunk(a, folder) -> str:
    rel = os.path.join("observation", "c.1.0")
    os.remove(a / rel)
    os.symlink(folder / "b.zarr" / rel, a / rel)
    return "observation/c.1.0"


def _link_chunk_to_secret(a, folder) -> str:
    rel = os.path.join("action", "c.2.0")
    os.remove(a / rel)
    os.symlink(folder / "secret.txt", a / rel)
    return "action/c.2.0"


def _link_extra_file(a, folder) -> str:
    os.symlink(folder / "secret.txt", a / "README")
    return "README"


def _link_array_directory(a, folder) -> str:
    shutil.move(str(a / "observation"), str(folder / "elsewhere"))
    os.symlink(folder / "elsewhere", a / "observation")
    return "observation"


def _link_record(a, folder) -> str:
    shutil.move(str(a / "zarr.json"), str(folder / "record.json"))
    os.symlink(folder / "record.json", a / "zarr.json")
    return "zarr.json"


def _link_priority_chunk(a, folder) -> str:
    chunk = _first_file(a / "_priority" / [d for d in sorted(os.listdir(a / "_priority")) if (a / "_priority" / d).is_dir()][0])
    shutil.move(chunk, str(folder / "priority-chunk"))
    os.symlink(folder / "priority-chunk", chunk)
    return os.path.relpath(chunk, a).replace(os.sep, "/")


CASES = {
    "another memory's chunk, valid checksum": _link_other_memorys_chunk,
    "a chunk naming a private file": _link_chunk_to_secret,
    "an extra file": _link_extra_file,
    "an array directory": _link_array_directory,
    "the commit record zarr.json": _link_record,
    "a chunk of the priority group": _link_priority_chunk,
}


@pytest.mark.parametrize("plant", list(CASES.values()), ids=list(CASES))
def test_a_link_inside_a_store_is_refused_by_every_reader_and_writer(folder, tmp_path, capsys, plant):
    a = folder / "a.zarr"
    key = plant(a, folder)
    before = _hash_tree(folder)

    for read_only in (True, False):
        with pytest.raises(LinkError, match=rf"holds 1 symbolic link \({key} -> "):
            ZarrStorage(str(a), read_only=read_only)
    report = verify(str(a))
    assert not report.ok and [(p.kind, p.key) for p in report.errors] == [("link", key)]

    out_dir = tmp_path / "out"
    out_dir.mkdir()
    capsys.readouterr()
    for argv in (["verify", str(a)], ["inspect", str(a)], ["export", str(a), str(out_dir / "x.npz")],
                 ["copy", str(a), str(out_dir / "c.zarr")], ["repair", str(a)]):
        assert main(argv) == 1, argv
        captured = capsys.readouterr()
        assert key in captured.out + captured.err, argv
        assert SECRET[:40].decode() not in captured.out + captured.err
        if argv[0] != "verify":
            assert len(captured.err.strip().splitlines()) == 1 or argv[0] == "repair", captured.err
    assert os.listdir(out_dir) == []  # nothing exported or copied
    assert _hash_tree(folder) == before  # nothing written anywhere: the store, its sibling, the link targets


def test_a_link_is_never_copied_to_an_object_store(folder, capsys, s3_server, monkeypatch):  # noqa: F811
    for k, v in s3_server.child_env().items():
        if k.startswith("AWS_"):
            monkeypatch.setenv(k, v)
    a = folder / "a.zarr"
    key = _link_chunk_to_secret(a, folder)
    bucket = new_bucket(s3_server)
    capsys.readouterr()
    assert main(["copy", str(a), f"s3://{bucket}/copy.zarr"]) == 1
    assert key in capsys.readouterr().err
    import s3fs

    fs = s3fs.S3FileSystem(**s3_server.storage_options, skip_instance_cache=True, use_listings_cache=False)
    assert fs.find(bucket) == []


def test_removing_the_link_and_repairing_mends_the_store(folder):
    a = folder / "a.zarr"
    _link_chunk_to_secret(a, folder)
    os.remove(a / "action" / "c.2.0")  # what the refusal says to do
    assert main(["repair", str(a)]) == 0
    with ZarrStorage(str(a), read_only=True) as s:
        assert len(s) == 2 * CHUNK  # truncated before the chunk that was a link, never its bytes
        assert torch.equal(s[:][("observation")], _rows(ROWS, 0.0)["observation"][: 2 * CHUNK])


# -- what is not a link inside the store ------------------------------------------------------


def test_a_store_whose_root_is_a_link_opens_and_writes_through_it(folder):
    link = folder / "alias.zarr"
    os.symlink(folder / "a.zarr", link)
    with ZarrStorage(str(link), MAX) as s:
        assert len(s) == ROWS
        s.set(slice(ROWS, ROWS + 4), _rows(4, 100.0))
    with ZarrStorage(str(folder / "a.zarr"), read_only=True) as s:
        assert len(s) == ROWS + 4 and s[ROWS]["observation"].tolist() == [100.0] * 3
    assert verify(str(link)).ok


def test_hard_links_share_no_write(folder):
    """A hard-linked copy (what ``ZarrCheckpointer`` makes) keeps its bytes while the store is written."""
    a, copy = folder / "a.zarr", folder / "snapshot.zarr"
    shutil.copytree(a, copy, copy_function=os.link)
    before = _hash_tree(copy)
    with ZarrStorage(str(a), MAX) as s:
        s.set(slice(0, ROWS), _rows(ROWS, 7.0))  # overwrites every chunk the snapshot shares
    assert _hash_tree(copy) == before
    with ZarrStorage(str(copy), read_only=True) as s:
        assert torch.equal(s[:]["observation"], _rows(ROWS, 0.0)["observation"])


# -- a writer whose open walked no chunk folder ---------------------------------------------------


@pytest.mark.parametrize("read_only", [True, False], ids=["reader", "writer"])
def test_a_link_at_a_chunk_files_name_is_refused_by_a_sealed_open(tmp_path, read_only):
    """A sealed open reads no chunk, but it lists each column's folder, where a store created since 2026-12 keeps
    its chunk files (``c.<c>.0``): a link there is refused at once, naming it, as a link anywhere else is. (In a
    store of a folder a chunk, the sealed open does not walk the ``c/`` folders; a write looks at each folder it
    goes into: test_fast_write.py. A link at a chunk's name is replaced by a write, never followed: same file.)"""
    path, outside = tmp_path / "a.zarr", tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "secret").write_bytes(SECRET)
    with ZarrStorage(str(path), MAX, chunk_rows=CHUNK) as s:
        s.set(slice(0, ROWS), _rows(ROWS, 0.0))
    name = f"observation/c.{ROWS // CHUNK}.0"  # the file of the next chunk
    os.symlink(outside / "secret", path / name)
    before = _hash_tree(path)
    with pytest.raises(LinkError, match=re.escape(name)):
        ZarrStorage(str(path), read_only=read_only)
    assert (outside / "secret").read_bytes() == SECRET and _hash_tree(path) == before


@pytest.mark.parametrize("read_only", [True, False], ids=["reader", "writer"])
def test_a_nested_column_named_like_a_chunk_file_replaced_by_a_link_is_refused(tmp_path, read_only):
    """Found by a review: a link in place of the folder of a nested column named ``c.<...>`` (one moved to another
    disk, a hostile store) was taken for a chunk file by the sealed open's walk and skipped; the open then read
    the column's ``zarr.json`` through it."""
    path, elsewhere = tmp_path / "a.zarr", tmp_path / "other_disk"
    with ZarrStorage(str(path), MAX, chunk_rows=CHUNK, goal_conditioned=False) as s:
        s.set(slice(0, 10), TensorDict({"obs": torch.zeros(10, 2), "next": {"c.x": torch.ones(10, 2)}}, [10]))
    shutil.move(path / "next" / "c.x", elsewhere)
    os.symlink(elsewhere, path / "next" / "c.x")
    with pytest.raises(LinkError, match=re.escape("next/c.x")):
        ZarrStorage(str(path), read_only=read_only)


@pytest.mark.parametrize("key", ["x", "0"], ids=["a node", "a node named by a number"])
@pytest.mark.parametrize("what", ["a link", "a named pipe"])
def test_a_group_named_c_that_lost_its_zarr_json_is_walked_by_a_sealed_open(tmp_path, what, key):
    """Found by two reviews: a folder named ``c`` with no ``zarr.json`` was taken for a column's chunk folder and
    not walked by a sealed open, a group named ``c`` that lost its ``zarr.json`` too, and then the nodes in it
    named by a number (a chunk's name): a link in it was read through, a named pipe there blocked the writable
    open for ever. A ``c/`` folder is a chunk folder only in a folder whose ``zarr.json`` describes an array."""
    from torchrl_robotmem.storage._backend import links_below

    path, elsewhere = tmp_path / "a.zarr", tmp_path / "other_disk"
    with ZarrStorage(str(path), MAX, chunk_rows=CHUNK, goal_conditioned=False) as s:
        s.set(slice(0, 10), TensorDict({"obs": torch.zeros(10, 2), "next": {"c": {key: torch.ones(10, 2)}}}, [10]))
    (path / "next" / "c" / "zarr.json").unlink()
    if what == "a link":
        shutil.move(path / "next" / "c" / key, elsewhere)
        os.symlink(elsewhere, path / "next" / "c" / key)
        name = f"next/c/{key}"
    else:
        (path / "next" / "c" / key / "zarr.json").unlink()
        os.mkfifo(path / "next" / "c" / key / "zarr.json")
        name = f"next/c/{key}/zarr.json"
    assert [k for k, _ in links_below(path, chunks=False)] == [name]
    for read_only in (True, False):
        with pytest.raises(LinkError, match=re.escape(name)):
            ZarrStorage(str(path), read_only=read_only)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("what", ["a link", "a named pipe"])
def test_a_column_in_a_forged_arrays_chunk_folder_is_refused_before_it_is_read(tmp_path, what):
    """Found by a third review: a group's ``zarr.json`` replaced by an array's made its ``c/<digits>/`` folders
    chunk folders, which a sealed open does not walk; the writable open then read a column's ``zarr.json`` in one
    (through a link, or blocking for ever on a named pipe). A record naming a column in an array's chunk folder
    is refused before any of its files is read (Zarr keeps no node below an array)."""
    from torchrl_robotmem.storage.errors import IntegrityError

    path, elsewhere = tmp_path / "a.zarr", tmp_path / "other_disk"
    with ZarrStorage(str(path), MAX, chunk_rows=CHUNK, goal_conditioned=False) as s:
        s.set(slice(0, 10), TensorDict({"obs": torch.zeros(10, 2), "next": {"c": {"0": torch.ones(10, 2)}}}, [10]))
    shutil.copy(path / "obs" / "zarr.json", path / "next" / "zarr.json")  # "next" now claims to be an array
    column = path / "next" / "c" / "0" / "zarr.json"
    if what == "a link":
        elsewhere.mkdir()
        shutil.move(column, elsewhere / "zarr.json")
        os.symlink(elsewhere / "zarr.json", column)
    else:
        column.unlink()
        os.mkfifo(column)
    for read_only in (False, True):
        with pytest.raises(IntegrityError, match=r"next/c/0.*lies in the chunk folder of the array 'next'"):
            ZarrStorage(str(path), read_only=read_only)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("what", ["a column folder linked", "a named pipe at the record",
                                  "a named pipe at the seal", "a named pipe at a column's description"])
def test_a_tailing_readers_refresh_refuses_a_link_or_special_file_made_since_its_open(tmp_path, what):
    """Found by an audit of every file an open reads: ``refresh()`` read the store again without the walk its open
    made, so a link made since (a column folder linked to another store's) served rows from outside, and a named
    pipe at the record, the seal or a column's description blocked it for ever. It walks the store first."""
    path, outside = tmp_path / "a.zarr", tmp_path / "other"
    with ZarrStorage(str(path), MAX, chunk_rows=CHUNK) as s:
        s.set(slice(0, ROWS), _rows(ROWS, 0.0))
    reader = ZarrStorage(str(path), read_only=True)
    if what == "a column folder linked":
        shutil.copytree(path / "observation", outside)
        shutil.rmtree(path / "observation")
        os.symlink(outside, path / "observation")
        name = "observation"
    else:
        name = {"a named pipe at the record": "zarr.json", "a named pipe at the seal": "_rows/seal.json",
                "a named pipe at a column's description": "observation/zarr.json"}[what]
        os.remove(path / name)
        os.mkfifo(path / name)
    with pytest.raises(LinkError, match=re.escape(name)):
        reader.refresh()
    assert len(reader) == ROWS  # what it served before
    reader.close()


@pytest.mark.parametrize("target", ["a file", "a folder"])
def test_a_checkpoint_of_a_store_holding_a_link_is_refused(tmp_path, target):
    """Found by a review: ``ZarrCheckpointer`` copied the store with ``shutil.copytree``, which followed a link made
    after the open (a folder's files, or across filesystems a file's bytes, landed in the checkpoint as the
    store's own). A store holding a link anywhere is refused, naming it, and nothing is copied."""
    path, outside = tmp_path / "a.zarr", tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "secret").write_bytes(SECRET)
    storage = ZarrStorage(str(path), MAX, chunk_rows=CHUNK)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=4)
    rb.extend(_rows(ROWS, 0.0))
    storage.flush()
    name = f"observation/c.{ROWS // CHUNK + 1}" + (".0" if target == "a file" else "")
    os.symlink(outside / "secret" if target == "a file" else outside, path / name)
    with pytest.raises(LinkError, match=re.escape(name)):
        rb.dumps(tmp_path / "ckpt")
    copied = [p for p in (tmp_path / "ckpt").rglob("*")] if (tmp_path / "ckpt").exists() else []
    assert not [p for p in copied if p.is_file() and p.read_bytes() == SECRET], copied
    os.remove(path / name)
    storage.close()


# -- found by a review of every command (2026-11-29): writes that left the store ------------------------------


def test_a_seal_name_hard_linked_to_a_file_outside_is_never_written(folder):
    """A writer's clean close writes its seal to a temporary file of its own (``O_EXCL | O_NOFOLLOW``): names the
    store already holds (here every name the old code used, hard links to a private file) are never opened."""
    a = folder / "a.zarr"
    (a / "_rows").mkdir(exist_ok=True)
    for pid in {os.getpid(), *range(os.getpid() - 3, os.getpid() + 4)}:
        os.link(folder / "secret.txt", a / "_rows" / f"seal.{pid}.tmp")
    with ZarrStorage(str(a), MAX) as s:
        s.set(slice(ROWS, ROWS + 4), _rows(4, 100.0))
    assert (folder / "secret.txt").read_bytes() == SECRET
    assert (a / "_rows" / "seal.json").exists()


@pytest.mark.parametrize("spelling", ["dotdot", "link"])
def test_a_copy_into_its_own_source_is_refused_however_the_path_is_spelled(folder, spelling, capsys):
    a = folder / "a.zarr"
    if spelling == "dotdot":
        (folder / "x").mkdir()
        dst = folder / "x" / ".." / "a.zarr" / "sub.zarr"
    else:
        os.symlink(a, folder / "alias")
        dst = folder / "alias" / "sub.zarr"
    before = _hash_tree(a)
    assert main(["copy", str(a), str(dst)]) != 0
    assert "inside it" in capsys.readouterr().err
    assert _hash_tree(a) == before


def test_a_copy_from_an_object_store_never_writes_a_key_outside_the_copy(folder, tmp_path, capsys, s3_server,  # noqa: F811
                                                                          monkeypatch):
    """An object store's keys are any strings: ``m.zarr/action/../../..`` names a place outside the copy."""
    for k, v in s3_server.child_env().items():
        if k.startswith("AWS_"):
            monkeypatch.setenv(k, v)
    bucket = new_bucket(s3_server)
    assert main(["copy", str(folder / "a.zarr"), f"s3://{bucket}/m.zarr"]) == 0
    import s3fs

    fs = s3fs.S3FileSystem(**s3_server.storage_options, skip_instance_cache=True, use_listings_cache=False)
    outside = tmp_path / "outside" / "planted.txt"
    depth = len((tmp_path / "dst" / "copy.zarr").parts)
    fs.pipe(f"{bucket}/m.zarr/action/" + "../" * (depth + 2) + str(outside).lstrip("/"), SECRET)
    capsys.readouterr()
    assert main(["copy", f"s3://{bucket}/m.zarr", str(tmp_path / "dst" / "copy.zarr")]) != 0
    assert "outside the copy" in capsys.readouterr().err
    assert not outside.exists() and not (tmp_path / "dst" / "copy.zarr").exists()


@pytest.mark.parametrize("where", ["observation/c.1.0", "zarr.json"], ids=["a chunk", "the record"])
def test_a_named_pipe_in_a_store_is_refused_never_read(folder, where):
    """A FIFO (``tar`` and ``cp -a`` carry them) blocked every reader for ever: each command now names it and stops.

    Each command runs in a child process with a deadline, so a regression fails the test instead of hanging it.
    """
    a = folder / "a.zarr"
    os.remove(a / where)
    os.mkfifo(a / where)
    before = _hash_tree(folder)
    for argv in (["verify", str(a)], ["inspect", str(a)], ["copy", str(a), str(folder / "copy.zarr")]):
        out = subprocess.run([sys.executable, "-m", "torchrl_robotmem", *argv], capture_output=True, text=True,
                             timeout=240)
        assert out.returncode != 0, (argv, out.stdout, out.stderr)
        assert "named pipe" in out.stderr + out.stdout or "not a regular file" in out.stderr + out.stdout, (argv, out.stderr)
    code = f"from torchrl_robotmem import ZarrStorage\nZarrStorage({str(a)!r}, read_only=True)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=240)
    assert out.returncode != 0 and "named pipe" in out.stderr, out.stderr[-2000:]
    assert not (folder / "copy.zarr").exists()
    assert _hash_tree(folder) == before


def test_a_local_url_is_walked_for_links_as_a_path_is(folder):
    a = folder / "a.zarr"
    key = _link_other_memorys_chunk(a, folder)
    for name in (f"local://{a}", f"file://{a}", str(a)):
        with pytest.raises(LinkError, match=key):
            ZarrStorage(name, read_only=True)


@pytest.mark.parametrize("chain", ["simplecache::file://", "filecache::file://", "simplecache::"])
def test_a_local_store_reached_through_an_fsspec_chain_is_refused_naming_its_path(folder, chain, capsys):
    """Found by a review: ``simplecache::file://PATH`` was a URL, never walked for links: copy wrote the bytes of a
    file a link below the store named into the copy, and verify said intact."""
    a = folder / "a.zarr"
    (folder / "private.txt").write_text("not the memory's\n")
    os.symlink(folder / "private.txt", a / "README")
    before = _hash_tree(folder)
    name = f"{chain}{a}"
    for read_only in (True, False):
        with pytest.raises(ValueError, match=re.escape(f"open {str(a)!r} instead")):
            ZarrStorage(name, read_only=read_only)
    capsys.readouterr()
    for argv in (["verify", name], ["inspect", name], ["copy", name, str(folder / "copy.zarr")],
                 ["export", name, str(folder / "x.npz")]):
        assert main(argv) != 0, argv
        assert f"open {str(a)!r} instead" in capsys.readouterr().err, argv
    assert not (folder / "copy.zarr").exists() and not (folder / "x.npz").exists()
    assert _hash_tree(folder) == before


def test_a_zip_path_is_never_created_by_repair_nor_written_when_it_holds_no_store(tmp_path, capsys):
    typo = tmp_path / "typo.zip"
    assert main(["repair", str(typo)]) != 0
    assert "does not exist" in capsys.readouterr().err
    assert not typo.exists()
    photos = tmp_path / "photos.zip"
    with zipfile.ZipFile(photos, "w") as z:
        z.writestr("holiday.jpg", b"\xff\xd8 not a store")
    before = photos.read_bytes()
    with pytest.raises(ValueError, match="holds no Zarr store"):
        ZarrStorage(str(photos), 100)
    assert photos.read_bytes() == before
