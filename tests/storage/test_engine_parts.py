"""Unit tests of the storage engine's parts, each on its own (no ZarrStorage, no commit thread).

- ``rowfile``: the row file, its seal (what it binds, when it is served), the locks, ``remove_rows``;
- ``format``: how an unbounded memory grows (``grown_size``) and the record's dimensions (``dims``);
- ``planner``: the rows a cursor touches (``cursor_rows``) and the write span (``write_span``);
- ``tags.EpisodeTagger``: episode ids of a done-split stream, against a row-by-row reference;
- ``mirror``: the packed RAM mirror (``RamMirror``): views, writes, growth, chunk snapshots, episode ends;
- ``_backend.links_below``: which symbolic links below a store each mode reports; ``remove_partial_files``:
  where a killed writer's partial files are removed; ``contained``: writes that refuse a linked folder.

Real files under ``tmp_path``; deterministic; no timing.
"""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from tensordict import LazyStackedTensorDict, TensorDict

from torchrl_robotmem.storage._backend import links_below, remove_partial_files
from torchrl_robotmem.storage.contained import ContainedStore, FolderCheck
from torchrl_robotmem.storage.format import dims, grown_size
from torchrl_robotmem.storage.layout import PackedLayout
from torchrl_robotmem.storage.mirror import RamMirror
from torchrl_robotmem.storage.planner import cursor_rows, write_span
from torchrl_robotmem.storage.rowfile import (
    CACHE_ENV,
    ROWS_DIR,
    ROWS_FILE,
    SEAL_FILE,
    RowFile,
    record_digest,
    remove_rows,
    rows_layout,
)
from torchrl_robotmem.storage.tags import EpisodeTagger

RECORD = {"len": 3, "cursor": 3, "write_count": 3}
LAYOUT = {"row_bytes": 8, "fields": [["x", 0, 8, "float32", [2]]], "shape": [4]}


@pytest.fixture(autouse=True)
def _private_files_under_tmp(tmp_path, monkeypatch):
    """A reader's private row file goes to the test's own folder."""
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))


def _sealed_store(directory, *, fill: int = 7, open_ends=()) -> None:
    """A writer maps 4 rows of 8 bytes, fills them with ``fill`` and seals them for ``RECORD``."""
    rows = RowFile(directory, read_only=False)
    assert rows.open(RECORD, layout=LAYOUT) is False  # nothing sealed yet
    rows.map((4,), 8)[:] = fill
    rows.seal(RECORD, layout=LAYOUT, open_ends=list(open_ends))
    rows.release()


def _files(directory) -> list[str]:
    return sorted(os.listdir(os.path.join(directory, ROWS_DIR)))


# -- rowfile: digests and layouts ------------------------------------------------------------


def test_record_digest_ignores_key_order_and_changes_with_any_value():
    assert record_digest({"len": 3, "cursor": 1}) == record_digest({"cursor": 1, "len": 3})
    assert record_digest({"len": 3, "cursor": 1}) != record_digest({"len": 3, "cursor": 2})
    assert record_digest({"len": 3}) != record_digest({"len": 3, "journal": None})
    assert len(record_digest({})) == 64  # a sha256 in hex


def test_rows_layout_names_row_bytes_each_field_and_the_rows_shape():
    layout = PackedLayout({"x": {"dtype": "float32", "shape": [2]}, "n": {"dtype": "int64", "shape": []}})
    out = rows_layout(layout, (10, 3))
    assert out["row_bytes"] == layout.row_bytes == 16
    assert out["shape"] == [10, 3]
    assert sorted(f[0] for f in out["fields"]) == ["n", "x"]
    by_path = {f[0]: f for f in out["fields"]}
    assert by_path["x"][2:] == [8, "float32", [2]] and by_path["n"][2:] == [8, "int64", []]
    assert sorted(f[1] for f in out["fields"]) == [0, 8]  # packed side by side, no overlap


def test_remove_rows_deletes_the_row_folder_and_says_whether_there_was_one(tmp_path):
    assert remove_rows(tmp_path) is False
    _sealed_store(tmp_path)
    assert _files(tmp_path) == [ROWS_FILE, SEAL_FILE]
    assert remove_rows(tmp_path) is True
    assert not (tmp_path / ROWS_DIR).exists()
    assert remove_rows(tmp_path) is False


# -- rowfile: when a sealed file is served ---------------------------------------------------


def test_a_reader_is_served_the_sealed_file_for_the_record_it_was_sealed_for(tmp_path):
    _sealed_store(tmp_path, fill=7, open_ends=[1, 3])
    reader = RowFile(tmp_path, read_only=True)
    try:
        assert reader.open(RECORD, layout=LAYOUT) is True
        assert reader.describe() == {"file": str(tmp_path / ROWS_DIR / ROWS_FILE), "sealed": True, "shared": True}
        assert reader.open_ends == [1, 3]  # the seal's open episode ends come back with it
        assert reader.map((4,), 8).tolist() == [[7] * 8] * 4
    finally:
        reader.release()


@pytest.mark.parametrize("change", ["record", "layout", "no layout"])
def test_a_seal_for_another_record_or_layout_is_not_served(tmp_path, change):
    _sealed_store(tmp_path)
    attrs = {**RECORD, "len": 4} if change == "record" else RECORD
    layout = {"no layout": None, "layout": {**LAYOUT, "row_bytes": 16}}.get(change, LAYOUT)
    reader = RowFile(tmp_path, read_only=True)
    try:
        assert reader.open(attrs, layout=layout) is False
        assert reader.describe() == {"file": None, "sealed": False, "shared": False}  # a private, unlinked file
        assert reader.map((4,), 8).tolist() == [[0] * 8] * 4  # to be filled from the chunks, not the seal's rows
    finally:
        reader.release()
    assert _files(tmp_path) == [ROWS_FILE, SEAL_FILE]  # a reader changes nothing in the store


def test_a_file_changed_after_its_seal_is_not_served(tmp_path):
    _sealed_store(tmp_path)
    with open(tmp_path / ROWS_DIR / ROWS_FILE, "ab") as f:
        f.write(b"\0" * 8)  # one row more than the seal bound (size and mtime differ)
    reader = RowFile(tmp_path, read_only=True)
    try:
        assert reader.open(RECORD, layout=LAYOUT) is False
    finally:
        reader.release()


def test_a_missing_or_unreadable_seal_serves_nothing(tmp_path):
    _sealed_store(tmp_path)
    seal = tmp_path / ROWS_DIR / SEAL_FILE
    seal.write_text("{not json")
    reader = RowFile(tmp_path, read_only=True)
    try:
        assert reader.open(RECORD, layout=LAYOUT) is False
        seal.unlink()
        assert reader.open(RECORD, layout=LAYOUT) is False
    finally:
        reader.release()


def test_a_store_without_a_directory_maps_a_private_unlinked_file(tmp_path):
    rows = RowFile(None, read_only=False)
    try:
        assert rows.open(RECORD, layout=LAYOUT) is False
        packed = rows.map((2, 3), 8)
        assert packed.shape == (2, 3, 8) and packed.dtype == torch.uint8
        assert rows.describe()["file"] is None
        rows.seal(RECORD, layout=LAYOUT)  # nothing to seal: no store folder
        assert rows.describe()["sealed"] is False
    finally:
        rows.release()
    assert os.listdir(tmp_path / "cache") == []  # unlinked as soon as it was made


# -- rowfile: a writer ------------------------------------------------------------------------


def test_a_writer_reopens_the_sealed_file_in_place_and_claim_removes_the_seal(tmp_path):
    _sealed_store(tmp_path, fill=5)
    writer = RowFile(tmp_path, read_only=False)
    try:
        assert writer.open(RECORD, layout=LAYOUT) is True
        assert writer.describe() == {"file": str(tmp_path / ROWS_DIR / ROWS_FILE), "sealed": True, "shared": False}
        assert _files(tmp_path) == [ROWS_FILE, SEAL_FILE]  # nothing written by the open itself
        writer.claim()
        assert _files(tmp_path) == [ROWS_FILE]  # unsealed before the first write into the file
        assert writer.map((4,), 8).tolist() == [[5] * 8] * 4  # the sealed rows, in place
    finally:
        writer.release()


def test_a_writer_does_not_write_in_place_a_file_a_reader_maps(tmp_path):
    _sealed_store(tmp_path, fill=7)
    reader = RowFile(tmp_path, read_only=True)
    writer = RowFile(tmp_path, read_only=False)
    try:
        assert reader.open(RECORD, layout=LAYOUT) is True
        seen = reader.map((4,), 8)
        assert writer.open(RECORD, layout=LAYOUT) is False  # the reader's shared lock: a file of its own
        writer.map((4,), 8)[:] = 9
        own = writer.describe()["file"]
        assert os.path.basename(own).startswith("rows.") and own.endswith(".bin") and own != ROWS_FILE
        writer.seal({**RECORD, "len": 4}, layout=LAYOUT)
        assert _files(tmp_path) == [ROWS_FILE, SEAL_FILE]  # renamed over rows.bin at the clean close
        assert seen.tolist() == [[7] * 8] * 4  # the reader keeps the rows (and the inode) it mapped
    finally:
        writer.release()
        reader.release()
    again = RowFile(tmp_path, read_only=True)
    try:
        assert again.open({**RECORD, "len": 4}, layout=LAYOUT) is True
        assert again.map((4,), 8).tolist() == [[9] * 8] * 4
    finally:
        again.release()


def test_discard_deletes_the_writers_own_file_and_the_folder_it_made(tmp_path):
    writer = RowFile(tmp_path, read_only=False)
    assert writer.open(RECORD, layout=LAYOUT) is False
    writer.map((4,), 8)
    assert len(_files(tmp_path)) == 1
    writer.discard()
    assert not (tmp_path / ROWS_DIR).exists()


def test_claim_removes_own_files_of_writers_that_are_gone_and_keeps_a_live_ones(tmp_path):
    _sealed_store(tmp_path)
    stale = tmp_path / ROWS_DIR / "rows.999999.1.bin"
    stale.write_bytes(b"\0" * 32)  # a killed writer's file: nobody holds its lock
    live = RowFile(tmp_path, read_only=False)
    writer = RowFile(tmp_path, read_only=False)
    try:
        assert live.open({**RECORD, "len": 1}, layout=LAYOUT) is False  # not its record: a file of its own
        live.map((4,), 8)  # made and locked now
        assert writer.open(RECORD, layout=LAYOUT) is True
        writer.claim()
        names = _files(tmp_path)
        assert stale.name not in names and os.path.basename(live.describe()["file"]) in names
    finally:
        writer.release()
        live.discard()


# -- format -------------------------------------------------------------------------------------


def _stream_reference(batches: list[np.ndarray], next_id: int, close_after: set[int]) -> list[list[int]]:
    """Row by row: a row continues the stream's open episode or opens the next id; a done row closes it."""
    out, open_id = [], None
    for b, done in enumerate(batches):
        ids = []
        for d in done:
            if open_id is None:
                open_id, next_id = next_id, next_id + 1
            ids.append(open_id)
            if d:
                open_id = None
        out.append(ids)
        if b in close_after:
            open_id = None
    return out


@pytest.mark.parametrize("p_done", [0.02, 0.5, 1.0])
def test_episode_ids_of_a_done_split_stream_match_a_row_by_row_reference(p_done):
    rng = np.random.default_rng(0)  # the suite's seed is in torch/numpy's global state; this draw is fixed
    for trial in range(20):
        sizes = rng.integers(0, 40, size=12)
        batches = [rng.random(int(n)) < p_done for n in sizes]
        close_after = {int(b) for b in rng.integers(0, 12, size=2)}
        tagger = EpisodeTagger(next_id=7)
        got = []
        for b, done in enumerate(batches):
            got.append(tagger.assign(done, None).tolist())
            if b in close_after:
                tagger.close_stream()
        assert got == _stream_reference(batches, 7, close_after), f"trial {trial}"


def test_a_new_stream_after_trajectory_ids_continues_none_of_them():
    tagger = EpisodeTagger()
    assert tagger.assign(np.array([False, False]), np.array([3, 4])).tolist() == [0, 1]
    assert tagger.assign(np.array([False, True]), None).tolist() == [2, 2]
    assert tagger.assign(np.array([True, True]), np.array([3, 4])).tolist() == [0, 1]  # still open
    assert tagger.assign(np.array([False]), None, continue_open=False).tolist() == [3]


def test_grown_size_doubles_up_to_a_million_rows_then_adds_a_million_in_whole_chunks():
    assert grown_size(1024, 1025, 256) == 2048  # doubles
    assert grown_size(1024, 5000, 256) == 5120  # at least what is needed, rounded up to whole chunks
    assert grown_size(1000, 1001, 300) == 2100  # 2000 -> 7 chunks of 300
    assert grown_size(2**20, 2**20 + 1, 16384) == 2**21
    assert grown_size(2**22, 2**22 + 1, 16384) == 2**22 + 2**20  # a million rows at a time past a million
    for capacity, need, chunk in [(64, 65, 64), (3000, 3001, 128), (2**21, 2**23, 4096)]:
        new = grown_size(capacity, need, chunk)
        assert new >= need and new % chunk == 0


def test_dims_gives_rows_along_the_first_dimension_and_the_inner_shape():
    assert dims({"max_size": 100, "len": 10}) == (100, 10, ())
    assert dims({"max_size": 100}) == (100, 0, ())  # no rows committed yet
    assert dims({"max_size": 100, "len": 10, "ndim": 2, "inner_shape": [4]}) == (25, 3, (4,))  # rounded up
    assert dims({"max_size": 96, "len": 12, "ndim": 3, "inner_shape": [2, 3, 5]}) == (16, 2, (2, 3, 5))


# -- planner ------------------------------------------------------------------------------------


@pytest.mark.parametrize("cursor, rows", [
    (3, [3]),
    (torch.tensor(5), [5]),
    (slice(2, 5), [2, 3, 4]),
    (slice(-2, None), [8, 9]),  # a slice is resolved against max_size
    (range(1, 7, 2), [1, 3, 5]),
    (torch.tensor([[4, 1], [1, 9]]), [4, 1, 1, 9]),  # an index tensor, flattened, order and repeats kept
    ([0, 2], [0, 2]),
    ((torch.tensor([4, 1, 4]), slice(None)), [1, 4]),  # a tuple cursor: its first dim's rows, once each
    ((2, 0), [2]),
    ((), list(range(10))),
])
def test_cursor_rows_lists_the_first_dimension_rows_a_cursor_touches(cursor, rows):
    out = cursor_rows(cursor, 10)
    assert out.dtype == torch.long and out.tolist() == rows


def test_write_span_turns_contiguous_rows_into_a_slice():
    cursor, dirty = write_span(torch.arange(2, 5), None, torch.arange(2, 5))
    assert cursor == dirty == slice(2, 5)


def test_write_span_keeps_rows_that_are_not_contiguous():
    rows = torch.tensor([1, 3, 4])
    cursor, dirty = write_span(rows, None, rows)
    assert cursor is rows and dirty is rows
    wrapped = torch.tensor([9, 0])  # a ring wrapping around
    assert write_span(wrapped, None, wrapped)[1] is wrapped
    one = torch.tensor([6])
    assert write_span(one, None, one) == (one, one)  # one row: nothing to turn into a slice


def test_write_span_keeps_a_tuple_cursor_and_a_lazy_stack_but_marks_a_slice_dirty():
    rows = torch.arange(3, 6)
    tup = (rows, slice(None))
    assert write_span(tup, None, rows) == (tup, slice(3, 6))
    lazy = LazyStackedTensorDict(*[TensorDict({"x": torch.zeros(1)}, []) for _ in range(3)], stack_dim=0)
    cursor, dirty = write_span(rows, lazy, rows)
    assert cursor is rows and dirty == slice(3, 6)


# -- mirror --------------------------------------------------------------------------------------

SCHEMA = {"obs": {"dtype": "float32", "shape": [2]}, "next/done": {"dtype": "bool", "shape": [1]},
          "next/truncated": {"dtype": "bool", "shape": [1]}, "episode": {"dtype": "int64", "shape": []}}


def _mirror(max_size=8, *, chunk_rows=4, length=lambda: 0, schema=SCHEMA, ndim=1, inner_shape=()):
    m = RamMirror(max_size, ndim=ndim, length=length)
    m.chunk_rows, m.inner_shape = chunk_rows, inner_shape
    m.configure(schema)
    m.allocate()
    return m


def test_mirror_allocate_gives_one_view_per_column_over_one_packed_buffer():
    m = _mirror()
    assert m.packed.dtype == torch.uint8 and m.packed.shape == (8, m.layout.row_bytes)
    assert set(m.views.keys(True, True)) == {"obs", ("next", "done"), ("next", "truncated"), "episode"}
    assert m.views.get("obs").shape == (8, 2) and m.views.get(("next", "done")).dtype == torch.bool
    m.packed.zero_()
    m.views.get("obs")[1] = 1.5
    assert m.packed[1].any() and not m.packed[0].any()  # a view writes the packed row itself
    assert "episode" not in m.key_specs and m.key_specs["obs"] == (torch.float32, torch.Size([2]))  # tags left out


def test_mirror_write_puts_rows_at_a_slice_or_at_index_rows():
    m = _mirror()
    m.packed.zero_()  # (RAM rows are allocated uninitialised; rows past len never reach the disk)
    m.write(slice(0, 3), TensorDict({"obs": torch.ones(3, 2), "episode": torch.arange(3)}, [3]))
    m.write(torch.tensor([6, 4]), TensorDict({"obs": torch.full((2, 2), 2.0), "episode": torch.tensor([9, 8])}, [2]))
    assert m.views.get("obs")[:, 0].tolist() == [1, 1, 1, 0, 2, 0, 2, 0]
    assert m.views.get("episode").tolist() == [0, 1, 2, 0, 8, 0, 9, 0]


def test_mirror_growth_keeps_the_rows_that_hold_data():
    n = [3]
    m = _mirror(length=lambda: n[0])
    m.views.get("obs")[:] = torch.arange(8.0)[:, None]  # rows 3..7 hold no data (len 3)
    m.max_size = 16
    m.allocate(keep=True)
    assert m.views.get("obs").shape == (16, 2)
    assert m.views.get("obs")[:3, 0].tolist() == [0, 1, 2]
    n[0] = 0
    m.views.get("obs")[:] = 4.0
    m.max_size = 24
    m.allocate(keep=True)  # no row holds data: none is copied
    assert m.views.get("obs").shape == (24, 2)


def test_mirror_new_column_is_zero_for_the_rows_that_hold_data():
    m = _mirror(length=lambda: 2)
    m.views.get("obs")[:2] = 3.0
    m.configure({**SCHEMA, "reward": {"dtype": "float32", "shape": [1]}})
    m.allocate(keep=True)
    assert m.views.get("obs")[:2].eq(3.0).all() and not m.views.get("reward")[:2].any()


def test_copy_chunk_is_a_copy_that_writes_rows_past_len_as_zeros():
    n = [6]
    m = _mirror(length=lambda: n[0])
    m.views.get("obs")[:] = 1.0
    first, second = m.copy_chunk(0), m.copy_chunk(1)
    assert first[0].shape == (4, m.layout.row_bytes)
    assert m.chunk_arrays(second)["obs"][:, 0].tolist() == [1, 1, 0, 0]  # rows 6, 7 hold no data
    m.views.get("obs")[0] = 5.0  # a write after the snapshot
    arrays = m.chunk_arrays(first)
    assert arrays["obs"][:, 0].tolist() == [1, 1, 1, 1]
    assert set(arrays) == set(SCHEMA) and arrays["next/done"].dtype == bool and arrays["obs"].flags.c_contiguous


def test_copy_chunk_of_the_last_partial_chunk_has_only_its_rows():
    m = _mirror(10, chunk_rows=4, length=lambda: 10)
    assert m.copy_chunk(2)[0].shape[0] == 2


def test_mark_done_sets_done_truncated_and_nested_done_flags_of_the_rows():
    schema = {**SCHEMA, "next/agents/done": {"dtype": "bool", "shape": [3, 1]}}
    m = _mirror(schema=schema)
    m.packed.zero_()
    assert m.mark_done(torch.tensor([2, 5])).tolist() == [2, 5]
    for key in (("next", "done"), ("next", "truncated"), ("next", "agents", "done")):
        flags = m.views.get(key).reshape(8, -1).all(-1)
        assert flags.nonzero().flatten().tolist() == [2, 5], key


def test_mark_done_without_a_truncated_column_sets_done_only():
    m = _mirror(schema={k: v for k, v in SCHEMA.items() if k != "next/truncated"})
    m.packed.zero_()
    m.mark_done(torch.tensor([1]))
    assert m.views.get(("next", "done"))[:, 0].tolist() == [False, True] + [False] * 6
    assert ("next", "truncated") not in m.views.keys(True, True)


def test_mark_done_over_two_batch_dims_takes_flat_rows_and_returns_first_dim_rows():
    m = _mirror(8, ndim=2, inner_shape=(2,), schema={"next/done": {"dtype": "bool", "shape": [1]}})
    m.packed.zero_()
    assert m.max_dim0 == 4
    assert m.mark_done(torch.tensor([1, 6])).tolist() == [0, 3]  # flat row 1: (0, 1); 6: (3, 0)
    done = m.views.get(("next", "done"))[..., 0]
    assert done.nonzero().tolist() == [[0, 1], [3, 0]]


# -- _backend.links_below -------------------------------------------------------------------------


def _store_with_links(root):
    """Links in a column's chunk folder and at a chunk's name in a ``c/`` folder, at a column's description, in
    the journal, and in a node named ``c``."""
    for folder in ("obs/c/0", "_journal/obs/c", "grp/c", "next/done/c", "act"):
        os.makedirs(root / folder)
    for column in ("obs", "next/done"):  # arrays: their "c" folders hold their chunks
        (root / column / "zarr.json").write_text('{"node_type": "array"}')
    (root / "grp" / "c" / "zarr.json").write_text("{}")  # a node named "c", not a chunk folder
    os.symlink("/elsewhere/chunk", root / "obs" / "c" / "0" / "1")
    os.symlink("/elsewhere/nested", root / "next" / "done" / "c" / "0")
    os.symlink("/elsewhere/meta", root / "act" / "zarr.json")
    os.symlink("/elsewhere/journal", root / "_journal" / "obs" / "c" / "0")
    os.symlink("/elsewhere/node", root / "grp" / "c" / "0")
    os.symlink("/elsewhere/top", root / "zarr.json")


def test_links_below_with_chunks_true_reports_every_link(tmp_path):
    _store_with_links(tmp_path)
    assert links_below(tmp_path, chunks=True) == [
        ("_journal/obs/c/0", "/elsewhere/journal"), ("act/zarr.json", "/elsewhere/meta"),
        ("grp/c/0", "/elsewhere/node"), ("next/done/c/0", "/elsewhere/nested"), ("obs/c/0/1", "/elsewhere/chunk"),
        ("zarr.json", "/elsewhere/top"),
    ]


def test_links_below_with_chunks_false_skips_only_the_folders_of_the_columns_chunks(tmp_path):
    """The ``c/`` folders are listed (a link at a chunk's name in one is reported), their chunks' folders not."""
    _store_with_links(tmp_path)
    assert links_below(tmp_path, chunks=False) == [
        ("_journal/obs/c/0", "/elsewhere/journal"), ("act/zarr.json", "/elsewhere/meta"),
        ("grp/c/0", "/elsewhere/node"), ("next/done/c/0", "/elsewhere/nested"), ("zarr.json", "/elsewhere/top"),
    ]
    (tmp_path / "obs" / "zarr.json").write_text('{"node_type": "group"}')  # obs/c is no array's chunk folder
    assert ("obs/c/0/1", "/elsewhere/chunk") in links_below(tmp_path, chunks=False)


def test_links_below_with_chunks_none_reports_only_links_in_the_columns_chunk_folders(tmp_path):
    """Before the chunks are read, any folder named ``c`` counts as a chunk folder (a node named ``c`` too: found
    by a review, a ``zarr.json`` planted in a chunk folder hid its links from a tailing reader's ``refresh()``)."""
    _store_with_links(tmp_path)
    assert links_below(tmp_path, chunks=None) == [
        ("grp/c/0", "/elsewhere/node"), ("next/done/c/0", "/elsewhere/nested"), ("obs/c/0/1", "/elsewhere/chunk"),
    ]


def test_links_below_does_not_follow_a_linked_folder_and_ignores_hard_links(tmp_path):
    outside = tmp_path / "outside"
    (outside / "c").mkdir(parents=True)
    os.symlink("/elsewhere/deep", outside / "c" / "0")
    store = tmp_path / "store"
    (store / "obs" / "c").mkdir(parents=True)
    os.symlink(outside, store / "obs" / "c" / "0")  # a linked folder: reported, not walked into
    (store / "obs" / "zarr.json").write_text("{}")
    os.link(store / "obs" / "zarr.json", store / "hard.json")
    assert links_below(store) == [("obs/c/0", str(outside))]
    assert links_below(tmp_path / "missing") == []


# -- _backend.remove_partial_files, contained ------------------------------------------------------


def test_remove_partial_files_where_a_killed_writer_was_writing(tmp_path):
    """Metadata and ``_`` folders, chunks past the committed length and journalled chunks lose their partial
    files; an old chunk's folder is not listed (one listing per chunk at every open), so its partial stays."""
    attrs = {"schema": {"obs": {"dtype": "float32", "shape": [3]}, "next/done": {"dtype": "bool", "shape": [1]}},
             "max_size": 100, "chunk_rows": 10, "len": 35, "ndim": 1, "inner_shape": [],
             "journal": {"chunks": [1], "meta": {}}}
    removed = ["zarr.1.partial", "obs/zarr.2.partial", "obs/c/3/0.3.partial", "obs/c/5/0.4.partial",
               "obs/c/1/0.5.partial", "next/done/c/3/0.6.partial", "_journal/obs/c/1/0.7.partial",
               "_priority/c/0.8.partial", "act/c.0.0.11.partial"]  # act: a column of flat chunk files
    kept = ["act/c.0.0", "obs/c/0/0.9.partial", "obs/c/2/0.10.partial", "obs/c/0/0", "obs/c/3/0"]
    for rel in removed + kept:
        os.makedirs(os.path.dirname(tmp_path / rel), exist_ok=True)
        (tmp_path / rel).write_bytes(b"x")
    assert remove_partial_files(tmp_path, attrs) == len(removed)
    left = [os.path.relpath(os.path.join(d, f), tmp_path) for d, _, fs in os.walk(tmp_path) for f in fs]
    assert sorted(left) == sorted(kept)


def test_contained_store_refuses_a_write_or_delete_through_a_linked_folder(tmp_path):
    import zarr
    from zarr.core.buffer import default_buffer_prototype

    root, outside = tmp_path / "store", tmp_path / "outside"
    (root / "obs" / "c").mkdir(parents=True)
    outside.mkdir()
    (outside / "0").write_bytes(b"theirs")
    os.symlink(outside, root / "obs" / "c" / "1")
    store = ContainedStore(str(root))
    value = default_buffer_prototype().buffer.from_bytes(b"ours")
    zarr.core.sync.sync(store.set("obs/c/0", value))  # a real folder: written
    assert (root / "obs" / "c" / "0").read_bytes() == b"ours"
    for act in (lambda: store.set("obs/c/1/0", value), lambda: store.delete("obs/c/1/0"),
                lambda: store.delete_dir("obs/c/1")):
        with pytest.raises(OSError, match="'obs/c/1' is a symbolic link inside the store"):
            zarr.core.sync.sync(act())
    assert sorted(os.listdir(outside)) == ["0"] and (outside / "0").read_bytes() == b"theirs"
    check = FolderCheck(root)
    check("new/c/0")  # folders that do not exist yet are made by the write, as folders
    (root / "file").write_bytes(b"")
    with pytest.raises(NotADirectoryError, match="'file' is a file"):
        check("file/zarr.json")


def test_a_writers_open_removes_the_partial_files_of_its_columns(tmp_path):
    from torchrl_robotmem import ZarrStorage
    from torchrl_robotmem.storage.integrity import repair

    path = tmp_path / "m.zarr"
    with ZarrStorage(str(path), 64, chunk_rows=8) as st:
        st.set(slice(0, 20), TensorDict({"obs": torch.ones(20, 3)}, [20]))
    old, tail = path / "obs" / "c.0.0.old.partial", path / "obs" / "c.2.0.tail.partial"
    for f in (old, tail):
        f.write_bytes(b"left by a killed writer")
    with ZarrStorage(str(path)) as st:  # chunk 2 holds rows past the committed 20 (rows 16..23)
        assert len(st) == 20
    # chunk files (c.<c>.0) lie in their column's folder, listed whole: every partial file there goes
    # (a store of a folder a chunk keeps those of committed chunks for repair: test above, on that layout)
    assert not old.exists() and not tail.exists()
    report = repair(str(path))
    assert not [a for a in report.actions if "partial" in a], report.actions


def test_a_writers_open_refused_for_damage_leaves_the_partial_files(tmp_path):
    """The partial files go once every check of the open passed: a refused open changes no file (found by a review:
    they were deleted before the checks, and the unsealed open below found the damage while reading the rows)."""
    import shutil

    from torchrl_robotmem import ZarrStorage
    from torchrl_robotmem.storage.errors import IntegrityError

    sealed = tmp_path / "sealed.zarr"
    with ZarrStorage(str(sealed), 64, chunk_rows=8, goal_conditioned=False, env="E") as st:
        st.set(slice(0, 20), TensorDict({"obs": torch.arange(60.0).reshape(20, 3)}, [20]))
    path = tmp_path / "m.zarr"
    shutil.copytree(sealed, path)  # a copy: its row file's seal no longer matches, so the open reads the chunks
    tail = path / "obs" / "c.2.0.tail.partial"
    tail.write_bytes(b"left by a killed writer")
    chunk = path / "obs" / "c.1.0"
    chunk.write_bytes(chunk.read_bytes()[: len(chunk.read_bytes()) // 2])  # damage
    with pytest.raises(IntegrityError, match="obs"):
        ZarrStorage(str(path), goal_conditioned=False)
    assert tail.read_bytes() == b"left by a killed writer"
