"""A memory written by one zarr release opens, verifies and takes new rows under another.

``tests/fixtures/store-zarr-<VERSION>.tar.gz`` are the same deterministic memory
(``tests/fixtures/make_version_store.py``: 160 FetchPush-shaped rows written in
two runs) written by different zarr releases: 3.1 (what CI installs) and 3.4
(the newest the index serves for Python 3.12). Every fixture is checked under
the zarr this suite runs with, so CI covers 3.4 -> 3.1 and the Python 3.12 run
(docs/install.md, "Supported versions") covers 3.1 -> 3.4.
"""
from __future__ import annotations

import json
import pathlib
import tarfile

import pytest
import torch
import zarr
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import GoalIndex, ZarrStorage
from torchrl_robotmem.storage.integrity import verify

FIXTURES = pathlib.Path(__file__).resolve().parents[1] / "fixtures"
TARBALLS = sorted(FIXTURES.glob("store-zarr-*.tar.gz"))


def _make_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_version_store", FIXTURES / "make_version_store.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


FIX = _make_module()


def _extract(tarball: pathlib.Path, into: pathlib.Path) -> tuple[pathlib.Path, dict]:
    with tarfile.open(tarball) as tar:
        tar.extractall(into, filter="data")
    return into / "memory", json.loads((into / "written_by.json").read_text())


def test_fixtures_cover_two_zarr_releases():
    versions = {p.name.removeprefix("store-zarr-").removesuffix(".tar.gz") for p in TARBALLS}
    assert {"3.1", "3.4"} <= versions, f"fixtures present: {sorted(versions)}"


@pytest.mark.parametrize("tarball", TARBALLS, ids=[p.name for p in TARBALLS])
def test_store_from_another_zarr_opens_verifies_and_reads_exactly(tarball, tmp_path):
    path, written_by = _extract(tarball, tmp_path)
    print(f"store written by zarr {written_by['zarr']}, read by zarr {zarr.__version__}")
    report = verify(path)
    assert report.ok, str(report)
    expected = FIX.expected_rows()
    st = ZarrStorage(path, read_only=True)
    assert len(st) == FIX.ROWS
    got = st.get(torch.arange(FIX.ROWS))
    for key in expected.keys(include_nested=True, leaves_only=True):
        assert torch.equal(got[key], expected[key].to(got[key].dtype)), key
    view = st.view()
    assert view["run"][: FIX.ROWS].unique().tolist() == [0, 1]  # the fixture's two runs
    assert view["episode"][FIX.ROWS - 1] > view["episode"][0]
    rb = TensorDictReplayBuffer(storage=st, batch_size=8)
    assert rb.sample()["observation"].shape == (8, 25)
    index = GoalIndex(st)
    hit = index.recall(expected["next", "achieved_goal"][42], k=1, success_only=False)
    assert torch.equal(hit["next", "achieved_goal"][0], expected["next", "achieved_goal"][42])
    st.close()


@pytest.mark.parametrize("tarball", TARBALLS, ids=[p.name for p in TARBALLS])
def test_store_from_another_zarr_takes_new_rows(tarball, tmp_path):
    path, _ = _extract(tarball, tmp_path)
    extra = FIX.expected_rows()[:20]
    st = ZarrStorage(path, env=FIX.ENV, background=False)
    st.set(torch.arange(FIX.ROWS, FIX.ROWS + 20), extra)
    st.close()
    assert verify(path).ok
    st = ZarrStorage(path, read_only=True)
    assert len(st) == FIX.ROWS + 20
    tail = st.get(torch.arange(FIX.ROWS, FIX.ROWS + 20))
    assert torch.equal(tail["observation"], extra["observation"])
    assert isinstance(tail, TensorDict)
    st.close()


def _layout(path: pathlib.Path, column: str) -> str:
    folder = path / column
    names = {p.name for p in folder.iterdir()}
    return "c/<c>/0" if "c" in names else "c.<c>.0" if any(n.startswith("c.") for n in names) else "none"


@pytest.mark.parametrize("tarball", TARBALLS, ids=[p.name for p in TARBALLS])
def test_a_column_added_to_a_store_of_a_folder_a_chunk_follows_its_layout(tarball, tmp_path):
    """Stores created before 2026-12 hold a folder a chunk (``c/<c>/0``); a store created now holds the chunk files
    in their column's folder (``c.<c>.0``: one inode a chunk, not two). A column added to an older store takes its
    layout, so one store has one layout."""
    path, _ = _extract(tarball, tmp_path)
    assert _layout(path, "observation") == "c/<c>/0"
    wider = FIX.expected_rows()[:20]
    wider["extra"] = torch.ones(20, 2)
    with ZarrStorage(path, env=FIX.ENV, background=False) as st:
        st.set(torch.arange(FIX.ROWS, FIX.ROWS + 20), wider)
    assert _layout(path, "extra") == "c/<c>/0" and verify(path).ok
    with ZarrStorage(path, read_only=True) as st:
        assert torch.equal(st["extra"][FIX.ROWS:FIX.ROWS + 20], torch.ones(20, 2))
        assert st["extra"][: FIX.ROWS].abs().sum() == 0
    fresh = tmp_path / "fresh.zarr"
    with ZarrStorage(fresh, 256, env=FIX.ENV, chunk_rows=64, background=False) as st:
        st.set(torch.arange(20), FIX.expected_rows()[:20])
        st.set(torch.arange(20, 40), wider)
    assert _layout(fresh, "observation") == _layout(fresh, "extra") == "c.<c>.0"
    assert not [p for p in fresh.rglob("*") if p.is_dir() and p.name == "c"]


@pytest.mark.parametrize("layout", ["c/<c>/0", "c.<c>.0"])
def test_repair_rebuilds_a_lost_array_description_in_either_layout(tmp_path, layout):
    """``repair`` rebuilds an array's lost ``zarr.json`` from its chunk files, whose names tell the layout."""
    from torchrl_robotmem.storage.integrity import repair

    if layout == "c/<c>/0":
        path, _ = _extract(TARBALLS[-1], tmp_path)
    else:
        path = tmp_path / "fresh.zarr"
        FIX.write(path)
    assert _layout(path, "observation") == layout
    (path / "observation" / "zarr.json").unlink()
    for stray in ("c.foo", "c.0.0.orig", "c.1.0.1234.partial"):  # no chunk's name: never decoded as one
        (path / "observation" / stray).write_bytes(b"not a chunk")
    assert not verify(path).ok
    repair(path)
    assert verify(path).ok
    with ZarrStorage(path, read_only=True) as st:
        assert len(st) == FIX.ROWS
        assert torch.equal(st["observation"][: FIX.ROWS], FIX.expected_rows()["observation"])


def test_repair_keeps_a_column_named_c_when_the_record_is_lost(tmp_path):
    """Found by a review: the listing of the arrays skipped every folder named ``c`` (a chunk folder of a store of
    a folder a chunk), a column named ``c`` too: a lost record was rebuilt without it."""
    from torchrl_robotmem.storage.integrity import repair

    path = tmp_path / "m.zarr"
    with ZarrStorage(path, 64, chunk_rows=16, goal_conditioned=False, env="E") as st:
        st.set(slice(0, 20), TensorDict({"c": torch.arange(20.0)[:, None], "obs": torch.ones(20, 2)}, [20]))
    (path / "zarr.json").unlink()  # the record lost
    repair(path)
    with ZarrStorage(path, read_only=True) as st:
        assert "c" in st.schema and torch.equal(st["c"][:20].flatten(), torch.arange(20.0))
