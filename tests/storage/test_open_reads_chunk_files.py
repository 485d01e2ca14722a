"""Opening a store reads its chunk files straight into the RAM mirror (``storage/fast_read.py``).

What an open reads must be bit-exact to what was written (many chunks, a
partial last chunk, columns of several dtypes and shapes, ``ndim=2``, each
codec), the same as Zarr's own read, and damage must still be an error that
names the array and the chunk: a changed byte, a truncated file, a chunk file
that disappears between the open's listing and the read.
"""
from __future__ import annotations

import os
import re

import numpy as np
import pytest
import torch
import zarr
from tensordict import TensorDict

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage import handle, integrity
from torchrl_robotmem.storage.fast_read import ChunkPlan, read_into
from torchrl_robotmem.storage.integrity import IntegrityError
from torchrl_robotmem.storage.rowfile import remove_rows

CHUNK = 64


def _rows(n: int, start: int = 0, *, batch: tuple = ()) -> TensorDict:
    """Rows of many dtypes and shapes; every value a function of the row index (seeded noise for the floats)."""
    g = torch.Generator().manual_seed(start)
    i = torch.arange(start, start + n).reshape(n, *([1] * len(batch))).expand(n, *batch)
    done = (i + 1) % 7 == 0
    return TensorDict(
        {
            "observation": torch.randn(n, *batch, 25, generator=g),
            "action": torch.randn(n, *batch, 4, generator=g).double(),
            "pixels": ((i.unsqueeze(-1).unsqueeze(-1) + torch.arange(6).reshape(2, 3)) % 251).to(torch.uint8),
            "step": (i % 50).to(torch.int16).unsqueeze(-1),
            "count": i.clone(),  # int64, no trailing dims
            "next": {"done": done.unsqueeze(-1), "reward": -(i % 3).float().unsqueeze(-1),
                     "value": torch.randn(n, *batch, 1, generator=g).half()},
        },
        [n, *batch],
    )


def _columns(s: ZarrStorage, n: int) -> dict:
    return {k: s[k][:n].clone() for k in s.view().keys(True, True)}


@pytest.mark.parametrize("compressor", ["blosc", "zstd", None])
@pytest.mark.parametrize("ndim", [1, 2])
def test_open_reads_every_row_bit_exact(tmp_path, compressor, ndim):
    """Many chunks and a partial last one, several dtypes and shapes: the open reads back exactly what was written."""
    batch = (3,) if ndim == 2 else ()
    n = 5 * CHUNK + 17  # partial last chunk
    path = str(tmp_path / "m.zarr")
    data = _rows(n, batch=batch)
    with ZarrStorage(path, 1000 * (3 if ndim == 2 else 1), chunk_rows=CHUNK, ndim=ndim, compressor=compressor,
                     env="e") as s:
        for lo in range(0, n, 50):  # several writes, chunks committed across them
            s.set(slice(lo, min(lo + 50, n)), data[lo:min(lo + 50, n)])
        written = _columns(s, n)
    group = zarr.open_group(path, mode="r")
    for p in group.attrs["schema"]:  # what was written is what Zarr itself reads
        key = tuple(p.split("/")) if "/" in p else p
        assert np.array_equal(group[p][:n], written[key].numpy()), p
    for read_only in (True, False):
        with ZarrStorage(path, read_only=read_only) as s:
            assert len(s) == n * (3 if ndim == 2 else 1)
            got = _columns(s, n)
        assert got.keys() == written.keys()
        for k in written:
            if not read_only and k in (("next", "done"), ("next", "truncated")):
                continue  # a writable open closes the episodes the last run left open (a write, not a read)
            assert got[k].dtype == written[k].dtype and torch.equal(got[k], written[k]), k


def test_read_into_fills_strided_columns_and_leaves_nothing_for_zarr(tmp_path):
    """``read_into`` writes into views of a packed buffer, reading every array from its files."""
    path = str(tmp_path / "m.zarr")
    n = 3 * CHUNK + 5
    with ZarrStorage(path, 1000, chunk_rows=CHUNK) as s:
        s.set(slice(0, n), _rows(n))
    group = zarr.open_group(path, mode="r")
    paths = ["observation", "pixels", "next/done", "count"]
    widths = [group[p][:1].nbytes for p in paths]
    packed = torch.zeros(1000, sum(-(-w // 8) * 8 for w in widths), dtype=torch.uint8)  # 8-aligned columns
    columns, off = {}, 0
    for p, w in zip(paths, widths):
        arr = group[p]
        dtype = torch.from_numpy(np.zeros(0, arr.dtype)).dtype
        columns[p] = packed[:, off:off + w].view(dtype).view(1000, *arr.shape[1:])
        off += -(-w // 8) * 8
    assert read_into({p: group[p] for p in paths}, columns, n, CHUNK, local_dir=path) == set()
    for p in paths:
        assert np.array_equal(columns[p][:n].numpy(), group[p][:n]), p
    assert not packed[n:].any()  # nothing past the rows asked for
    # a store that is not a local directory is left to Zarr
    assert read_into({p: group[p] for p in paths}, columns, n, CHUNK, local_dir=None) == set(paths)


def test_a_chunk_file_gone_is_left_to_zarr_and_a_changed_one_too(tmp_path):
    """A missing or changed chunk file is never decoded here: the array is handed back for Zarr (and its checks)."""
    path = str(tmp_path / "m.zarr")
    n = 3 * CHUNK
    with ZarrStorage(path, 1000, chunk_rows=CHUNK) as s:
        s.set(slice(0, n), _rows(n))
    group = zarr.open_group(path, mode="r")
    os.remove(os.path.join(path, "observation/c.1.0"))
    chunk = os.path.join(path, "action/c.2.0")
    raw = bytearray(open(chunk, "rb").read())
    raw[len(raw) // 2] ^= 0x10
    open(chunk, "wb").write(bytes(raw))
    columns = {p: torch.zeros(1000, *group[p].shape[1:], dtype=torch.from_numpy(np.zeros(0, group[p].dtype)).dtype)
               for p in ("observation", "action", "count")}
    assert read_into({p: group[p] for p in columns}, columns, n, CHUNK, local_dir=path) == {"observation", "action"}
    with pytest.raises(ValueError, match="checksum"):
        plan = ChunkPlan(group["action"], "action", path)
        plan.decode(np.frombuffer(bytes(raw), np.uint8), np.empty(plan.nbytes, np.uint8))


@pytest.mark.parametrize("read_only", [True, False])
@pytest.mark.parametrize("damage, message", [
    ("flip", r"array 'action' chunk 2 \(action/c.2.0, rows 128-191\): checksum mismatch"),
    ("truncate", r"array 'observation' chunk 1 \(observation/c.1.0, rows 64-127\).*(checksum|does not decode)"),
])
def test_damaged_chunk_still_fails_the_open_naming_it(tmp_path, read_only, damage, message):
    path = str(tmp_path / "m.zarr")
    n = 4 * CHUNK
    with ZarrStorage(path, 1000, chunk_rows=CHUNK) as s:
        s.set(slice(0, n), _rows(n))
    remove_rows(path)  # the open reads the chunks (a sealed row file serves without them: tests/storage/test_row_tier.py)
    rel = "action/c.2.0" if damage == "flip" else "observation/c.1.0"
    full = os.path.join(path, rel)
    raw = bytearray(open(full, "rb").read())
    if damage == "flip":
        raw[len(raw) // 2] ^= 0x40
    else:
        raw = raw[: len(raw) // 2]
    open(full, "wb").write(bytes(raw))
    with pytest.raises(IntegrityError) as err:
        ZarrStorage(path, read_only=read_only)
    assert re.search(message, str(err.value)), str(err.value)


@pytest.mark.parametrize("read_only", [True, False])
def test_chunk_gone_after_the_listing_is_an_error_not_zeros(tmp_path, monkeypatch, read_only):
    """A chunk file removed after the open's listing, before the read: an error naming it, never zero rows.

    The removal happens at that moment by construction: a hook wrapping the real ``integrity.check_open``.
    """
    path = str(tmp_path / "m.zarr")
    n = 4 * CHUNK
    with ZarrStorage(path, 1000, chunk_rows=CHUNK) as s:
        s.set(slice(0, n), _rows(n))
    remove_rows(path)  # the open reads the chunks
    check_open = integrity.check_open

    def then_remove(*args, **kwargs):
        out = check_open(*args, **kwargs)
        os.remove(os.path.join(path, "next/reward/c.3.0"))
        return out

    monkeypatch.setattr(integrity, "check_open", then_remove)
    assert handle.integrity is integrity  # the module the open checks through
    with pytest.raises(IntegrityError, match=r"array 'next/reward' chunk 3 \(next/reward/c.3.0, rows 192-255\): "
                                             r"chunk file missing"):
        ZarrStorage(path, read_only=read_only)
