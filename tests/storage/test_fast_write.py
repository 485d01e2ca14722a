"""storage/fast_write.py: chunk files written directly are the files Zarr writes, and stay inside the store."""
from __future__ import annotations

import errno
import os
import sys

import numpy as np
import pytest
import torch
import zarr

from torchrl_robotmem.storage import _backend
from torchrl_robotmem.storage.contained import ContainedStore, FolderCheck
from torchrl_robotmem.storage.fast_write import ChunkCodec, plan_array, write_chunks
from torchrl_robotmem.storage.format import ARRAY_CONFIG
from torchrl_robotmem.storage.schema import create_arrays

CHUNK, ROWS = 16, 40  # the last chunk (rows 32..39) is the array's edge chunk, padded to 16 rows

DTYPES = [torch.float16, torch.float32, torch.float64, torch.int8, torch.int16, torch.int32, torch.int64,
          torch.uint8, torch.bool]
CODECS = [("blosc", 1), ("zstd", 1), ("zstd", 3), (None, 1)]


def _values(dtype: np.dtype, shape: tuple, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if dtype == np.bool_:
        return rng.random(shape) < 0.5
    if dtype.kind == "f":
        return (rng.standard_normal(shape) * 100).astype(dtype)
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, shape, dtype=dtype, endpoint=True)


def _chunk_files(root, path: str) -> dict[str, bytes]:
    """The chunk files of array ``path`` (``c/<c>/0`` or ``c.<c>.0``) by name: none is an empty dict."""
    out = {}
    base = os.path.join(root, path)
    for folder, _, files in os.walk(base):
        for name in files:
            full = os.path.join(folder, name)
            if full != os.path.join(base, "zarr.json"):
                out[os.path.relpath(full, base)] = open(full, "rb").read()
    return out


def _groups(tmp_path):
    return [zarr.open_group(str(tmp_path / name), mode="w", zarr_format=3) for name in ("zarr.zarr", "direct.zarr")]


def _write_both(tmp_path, make_arrays, data: dict[str, np.ndarray], prefix: str = ""):
    """Writes ``data`` chunk by chunk through Zarr (one store) and through write_chunks (the other)."""
    by_zarr, direct = (make_arrays(g) for g in _groups(tmp_path))
    for path, values in data.items():
        arr = by_zarr[path].with_config(ARRAY_CONFIG)
        for lo in range(0, len(values), CHUNK):
            arr[lo : lo + CHUNK] = values[lo : lo + CHUNK]
    handles = {prefix + p: a.with_config(ARRAY_CONFIG) for p, a in direct.items()}
    payload = {c: {p: v[c * CHUNK : (c + 1) * CHUNK] for p, v in data.items()} for c in range(-(-ROWS // CHUNK))}
    write_chunks(handles.__getitem__, payload, CHUNK, prefix, threads=2)
    return by_zarr, direct


@pytest.mark.parametrize("compressor, level", CODECS)
@pytest.mark.parametrize("inner_shape, shape", [((), []), ((), [3]), ((), [2, 5]), ((4,), [3])])
def test_chunk_files_are_the_bytes_zarr_writes(tmp_path, compressor, level, inner_shape, shape):
    """Every dtype, row shape and codec the library creates: byte-identical files, read back equal by Zarr."""
    schema = {_backend.key_to_path(("next", f"x{i}")) if i % 2 else f"x{i}": {
        "dtype": _backend.torch_dtype_name(t), "shape": shape} for i, t in enumerate(DTYPES)}
    data = {p: _values(_backend.numpy_dtype(_backend.torch_dtype(s["dtype"])), (ROWS, *inner_shape, *shape), i)
            for i, (p, s) in enumerate(schema.items())}
    data["x1" if "x1" in data else next(iter(data))][:CHUNK] = 0  # an all-zero chunk is written too

    def make(group):
        return create_arrays(group, schema, rows=ROWS, inner_shape=inner_shape, chunk_rows=CHUNK,
                             compressor=compressor, level=level)

    by_zarr, direct = _write_both(tmp_path, make, data)
    for path in schema:
        plan = plan_array(direct[path])
        assert plan is not None, f"{path}: the library's pipeline {direct[path].metadata.codecs} is not written directly"
        assert plan[1].checksum and plan[1].compressor == compressor
        expected, got = _chunk_files(by_zarr[path].store.root, path), _chunk_files(direct[path].store.root, path)
        assert sorted(got) == sorted(expected) and len(got) == 3, (path, sorted(got), sorted(expected))
        for key in expected:
            assert got[key] == expected[key], f"{path} chunk {key}: bytes differ from Zarr's"
        back = zarr.open_group(direct[path].store.root, mode="r")[path][:]
        np.testing.assert_array_equal(back, data[path])
    assert not [f for f in _all_files(tmp_path) if f.endswith(".partial")]


def test_journal_arrays_zarr_default_pipeline_are_the_bytes_zarr_writes(tmp_path):
    """The journal's arrays (Zarr's default codecs: zstd level 0, no checksum) are written directly too."""
    data = {"obs": _values(np.dtype("f4"), (ROWS, 3), 0), "done": _values(np.dtype(bool), (ROWS, 1), 1)}

    def make(group):
        return {p: group.create_array(f"_journal/{p}", shape=v.shape, chunks=(CHUNK, *v.shape[1:]), dtype=v.dtype,
                                      fill_value=0, overwrite=True) for p, v in data.items()}

    by_zarr, direct = _write_both(tmp_path, make, data, prefix="_journal/")
    for p in data:
        codec = ChunkCodec(direct[p])
        assert (codec.compressor, codec.checksum) == ("zstd", False)
        assert _chunk_files(direct[p].store.root, f"_journal/{p}") == _chunk_files(by_zarr[p].store.root, f"_journal/{p}")
        np.testing.assert_array_equal(direct[p][:], data[p])


def test_what_it_does_not_encode_goes_through_zarr(tmp_path):
    """Another store (memory), or a write that does not cover its chunk: Zarr's setitem, as before."""
    mem = zarr.create_array(zarr.storage.MemoryStore(), shape=(ROWS, 2), chunks=(CHUNK, 2), dtype="f4", fill_value=0)
    assert plan_array(mem) is None
    write_chunks(lambda p: mem, {1: {"m": np.ones((CHUNK, 2), "f4")}}, CHUNK)
    assert mem[CHUNK : 2 * CHUNK].tolist() == [[1.0, 1.0]] * CHUNK
    group = zarr.open_group(str(tmp_path / "s.zarr"), mode="w", zarr_format=3)
    arr = create_arrays(group, {"a": {"dtype": "float32", "shape": [2]}}, rows=ROWS, inner_shape=(), chunk_rows=CHUNK,
                        compressor="blosc", level=1)["a"].with_config(ARRAY_CONFIG)
    arr[:] = np.full((ROWS, 2), 7, "f4")
    write_chunks(lambda p: arr, {1: {"a": np.ones((3, 2), "f4")}}, CHUNK)  # 3 of the chunk's 16 rows: merged
    assert arr[CHUNK : CHUNK + 4].tolist() == [[1.0, 1.0]] * 3 + [[7.0, 7.0]]


def _all_files(root) -> list[str]:
    return [os.path.join(d, f) for d, _, files in os.walk(root) for f in files]


def _store(path, kind: str):
    """A plain LocalStore (fast_write checks its folders with a FolderCheck of its own) or the writer's ContainedStore."""
    return str(path) if kind == "local" else ContainedStore(str(path))


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX symbolic links")
@pytest.mark.parametrize("kind", ["local", "contained"])
@pytest.mark.parametrize("link", ["obs/c", "obs/c/1"])
def test_a_chunk_folder_that_links_outside_the_store_is_refused(tmp_path, link, kind):
    outside = tmp_path / "outside"
    outside.mkdir()
    (tmp_path / "s.zarr").mkdir()
    group = zarr.open_group(_store(tmp_path / "s.zarr", kind), mode="w", zarr_format=3)
    arr = create_arrays(group, {"obs": {"dtype": "float32", "shape": [3]}}, rows=ROWS, inner_shape=(4,),
                        chunk_rows=CHUNK, compressor="zstd", level=1,
                        separator="/")["obs"].with_config(ARRAY_CONFIG)  # a folder a chunk (stores before 2026-12)
    os.makedirs(tmp_path / "s.zarr" / os.path.dirname(link), exist_ok=True)
    os.symlink(outside, tmp_path / "s.zarr" / link)
    rows = np.ones((CHUNK, 4, 3), "f4")
    with pytest.raises(OSError) as info:
        write_chunks(lambda p: arr, {0: {"obs": rows}, 1: {"obs": rows}}, CHUNK)
    assert info.value.errno == errno.ELOOP and link in str(info.value)
    check = plan_array(arr)[2]  # the store's own check where it has one, else one of its root
    assert check is arr.store.check if kind == "contained" else isinstance(check, FolderCheck)
    assert os.listdir(outside) == [], "a file was written through the link"


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX symbolic links")
@pytest.mark.parametrize("kind", ["local", "contained"])
@pytest.mark.parametrize("separator", ["/", "."], ids=["c/<c>/0", "c.<c>.0"])
def test_a_chunk_file_that_is_a_link_is_replaced_not_written_through(tmp_path, kind, separator):
    secret = tmp_path / "secret"
    secret.write_bytes(b"private")
    (tmp_path / "s.zarr").mkdir()
    group = zarr.open_group(_store(tmp_path / "s.zarr", kind), mode="w", zarr_format=3)
    arr = create_arrays(group, {"obs": {"dtype": "float32", "shape": [3]}}, rows=ROWS, inner_shape=(),
                        chunk_rows=CHUNK, compressor=None, level=1, separator=separator)["obs"].with_config(ARRAY_CONFIG)
    chunk = tmp_path / "s.zarr" / "obs" / ("c/0/0" if separator == "/" else "c.0.0")
    os.makedirs(chunk.parent, exist_ok=True)
    os.symlink(secret, chunk)
    write_chunks(lambda p: arr, {0: {"obs": np.ones((CHUNK, 3), "f4")}}, CHUNK)
    assert secret.read_bytes() == b"private"
    assert not os.path.islink(chunk) and chunk.is_file()
    assert arr[:CHUNK].tolist() == [[1.0] * 3] * CHUNK


@pytest.mark.parametrize("separator", ["/", "."], ids=["c/<c>/0", "c.<c>.0"])
def test_every_write_ends_before_the_first_error_is_raised(tmp_path, separator):
    group = zarr.open_group(str(tmp_path / "s.zarr"), mode="w", zarr_format=3)
    arrays = create_arrays(group, {p: {"dtype": "float32", "shape": [3]} for p in ("a", "b", "c")}, rows=ROWS,
                           inner_shape=(), chunk_rows=CHUNK, compressor="blosc", level=1, separator=separator)
    name = "c/{}/0" if separator == "/" else "c.{}.0"
    (tmp_path / "s.zarr" / "b" / name.format(0)).mkdir(parents=True)  # a folder where b's chunk 0 must go
    payload = {c: {p: np.full((CHUNK, 3), c, "f4") for p in arrays} for c in range(2)}
    with pytest.raises(OSError):
        write_chunks(lambda p: arrays[p].with_config(ARRAY_CONFIG), payload, CHUNK, threads=3)
    for p in ("a", "c"):
        assert sorted(_chunk_files(tmp_path / "s.zarr", p)) == [name.format(0), name.format(1)]
    assert not [f for f in _all_files(tmp_path) if f.endswith(".partial")]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/PID/maps")
def test_the_commit_worker_imports_it_without_torch():
    """The worker (a script) imports fast_write as a top-level module: no package import, no torch (its start time)."""
    import time

    from torchrl_robotmem.storage._commit_worker import CommitWorker

    worker = CommitWorker()
    try:
        deadline = time.monotonic() + 120
        while not worker.ready():  # fast_write is imported before the worker says it is ready
            assert time.monotonic() < deadline, "the commit worker never became ready"
            time.sleep(0.02)
        maps = open(f"/proc/{worker.proc.pid}/maps").read()
    finally:
        worker.discard()
    assert "blosc" in maps, "fast_write's codecs are not loaded in the worker"
    assert "libtorch" not in maps, "the commit worker loaded torch"
