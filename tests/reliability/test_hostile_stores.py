"""Hostile stores: metadata someone else wrote is checked before it is used, and ``repair`` stays in its store.

A memory may come from elsewhere (a colleague's copy, a download). Every case
here edits the records of a real store on disk the way a bad copy or a hostile
author could, and checks that the library refuses it, naming the record at
fault, and that nothing changes anywhere on disk (every file of the store and
of a sibling store next to it is hashed before and after):

* a schema key with ``..`` (``repair`` used to rewrite ``<key>/zarr.json``
  through the store's parent, damaging the sibling);
* a symbolic link inside the store (``repair`` would write through it);
* an array whose own ``zarr.json`` disagrees with the schema (``repair`` used to
  rewrite the array's metadata to fit the schema: float32 rows read as int32,
  or every chunk moved to the backup);
* a pending journal whose own record claims more rows than exist, another
  dtype, or another structure (readers used to serve 900 zero rows, or cast);
* sizes no machine can hold (``max_size`` 10**15, a row shape [10**9]), or a
  ``len`` far past the chunk files (opening used to try to allocate petabytes
  or loop for hours). These run in a child process under an address-space
  limit, so a regression fails instead of swapping.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import textwrap

import pytest
import torch
import zarr
from tensordict import TensorDict

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage.integrity import IntegrityError, repair, verify

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX paths, symlinks and rlimits")

ROWS, CHUNK, MAX = 300, 64, 1000


def _rows(n: int, start: int = 0) -> TensorDict:
    i = torch.arange(start, start + n)
    return TensorDict(
        {
            # fractional values: a cast to an integer dtype would show
            "observation": (i.unsqueeze(-1) + torch.arange(6)).float() + 0.25,
            "action": -i.float().unsqueeze(-1).expand(n, 4).clone(),
            "next": {"observation": (i.unsqueeze(-1) + torch.arange(6) + 1).float(),
                     "done": ((i + 1) % 10 == 0).unsqueeze(-1)},
        },
        [n],
    )


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("pristine") / "m.zarr")
    with ZarrStorage(path, MAX, chunk_rows=CHUNK, env="FetchPush-v4") as s:
        s.set(slice(0, ROWS), _rows(ROWS))
    return path


@pytest.fixture
def stores(pristine, tmp_path):
    """Two copies of one intact store side by side (``a`` is damaged by the test, ``b`` is its sibling)."""
    root = tmp_path / "memories"
    root.mkdir()
    for name in ("a.zarr", "b.zarr"):
        shutil.copytree(pristine, root / name)
    (root / "notes.txt").write_text("a file beside the stores\n")
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


def _edit_json(path, rel, fn):
    full = os.path.join(path, rel)
    with open(full) as f:
        meta = json.load(f)
    fn(meta)
    with open(full, "w") as f:
        json.dump(meta, f)


def _edit_attrs(path, fn):
    _edit_json(path, "zarr.json", lambda meta: fn(meta["attributes"]))


# -- repair stays inside the store ------------------------------------------------------


def test_schema_key_leaving_the_store_is_refused_and_nothing_anywhere_changes(stores):
    a, b = str(stores / "a.zarr"), str(stores / "b.zarr")
    # the sibling holds float64 observations: a rewrite of its metadata from a's schema would show
    shutil.rmtree(b)
    with ZarrStorage(b, MAX, chunk_rows=CHUNK) as s:
        rows = _rows(ROWS)
        rows["observation"] = rows["observation"].double()
        s.set(slice(0, ROWS), rows)

    def escape(attrs):
        attrs["schema"]["../b.zarr/observation"] = attrs["schema"].pop("observation")

    _edit_attrs(a, escape)
    before = _hash_tree(stores)

    with pytest.raises(IntegrityError, match=r"schema' key '\.\./b\.zarr/observation' is not a path inside the store"):
        ZarrStorage(a, read_only=True)
    report = verify(a)
    assert not report.ok and any("../b.zarr/observation" in str(p) for p in report.errors)
    with pytest.raises(IntegrityError, match=r"(?s)schema key '\.\./b\.zarr/observation' is not a path inside.*"
                                             r"repair refuses this store.*nothing was changed"):
        repair(a)
    assert _hash_tree(stores) == before  # the damaged store, its sibling and the file beside them
    with ZarrStorage(b, read_only=True) as s:
        assert s["observation"].dtype == torch.float64


def test_symlink_inside_the_store_is_never_written_through(stores, tmp_path):
    a = stores / "a.zarr"
    outside = tmp_path / "elsewhere" / "action"
    outside.parent.mkdir()
    shutil.move(str(a / "action"), str(outside))
    os.symlink(outside, a / "action")
    os.remove(outside / "zarr.json")  # damage that repair would mend by writing action/zarr.json
    before, elsewhere = _hash_tree(stores), _hash_tree(tmp_path / "elsewhere")

    assert not verify(str(a)).ok
    with pytest.raises(IntegrityError, match=r"(?s)action: a symbolic link .*writes only inside the store's folder"):
        repair(str(a))
    assert _hash_tree(stores) == before and _hash_tree(tmp_path / "elsewhere") == elsewhere


# -- repair never rewrites one record to fit another -------------------------------------


@pytest.mark.parametrize("field,value,named", [
    ("dtype", "int32", r"float32 \[1000, 6\].*records int32"),
    ("dtype", "float16", r"float32 \[1000, 6\].*records float16"),
    ("shape", [7], r"float32 \[1000, 6\].*records float32 \[1000, 7\]"),
])
def test_repair_refuses_when_the_schema_and_an_array_disagree(stores, field, value, named):
    a = str(stores / "a.zarr")
    _edit_attrs(a, lambda attrs: attrs["schema"]["observation"].update({field: value}))
    before = _hash_tree(stores)

    with pytest.raises(IntegrityError, match=rf"(?s)array 'observation' .*{named}"):
        ZarrStorage(a, read_only=True)
    with pytest.raises(IntegrityError, match=rf"(?s)array 'observation' .*\(observation/zarr\.json\).*{named}.*"
                                             rf"repair does not choose between them"):
        repair(a)
    assert _hash_tree(stores) == before  # no metadata rewritten, no truncation, no chunk moved


def test_repair_does_not_rebuild_array_metadata_its_chunks_contradict(stores):
    """A lost ``zarr.json`` is rebuilt from the schema only if the chunk files decode that way."""
    a = str(stores / "a.zarr")
    os.remove(os.path.join(a, "observation", "zarr.json"))
    _edit_attrs(a, lambda attrs: attrs["schema"]["observation"].update(dtype="float16"))
    before = _hash_tree(stores)
    with pytest.raises(IntegrityError, match=r"(?s)array 'observation'.*none of its chunk files decodes as the "
                                             r"schema records it \(float16 \[6\]"):
        repair(a)
    assert _hash_tree(stores) == before


# -- a pending journal's own record ------------------------------------------------------


def _pending_journal(path, meta: dict, chunks=(4,), dtypes: dict | None = None):
    """A journal record as the commit engine writes it (contents first, then the record), edited to ``meta``."""
    g = zarr.open_group(path, mode="r+")
    for p in g.attrs["schema"]:
        arr = g[p]
        dtype = (dtypes or {}).get(p, arr.dtype)
        j = g.create_array(f"_journal/{p}", shape=arr.shape, chunks=arr.chunks, dtype=dtype, fill_value=0, overwrite=True)
        for c in chunks:
            j[c * CHUNK:(c + 1) * CHUNK] = arr[c * CHUNK:(c + 1) * CHUNK]
    g.update_attributes({"journal": {"chunks": list(chunks), "meta": meta}})


JOURNALS = {
    # a record claiming 900 rows when 300 exist: readers served 600 zero rows
    "longer_len": (dict(len=900, cursor=900, last_cursor=899, write_count=900), None,
                   r"pending journal's 'len' \(900\) claims rows that neither the journal \(chunks \[4\]\) nor the "
                   r"arrays hold"),
    "len_past_max_size": (dict(len=5000, cursor=0, last_cursor=-1, write_count=5000), None,
                          r"pending journal records attribute 'len' must be an integer in \[0, 1000\], got 5000"),
    # its arrays in another dtype: readers cast the journalled rows silently
    "other_dtype": (dict(len=ROWS, cursor=ROWS, last_cursor=ROWS - 1, write_count=ROWS), {"observation": "int32"},
                    r"array '_journal/observation' .*journal array is int32 \[1000, 6\].*schema records float32"),
    # a record that rewrites the structure: its schema replaced the store's
    "rewrites_schema": (dict(len=ROWS, schema={"observation": {"dtype": "int32", "shape": [6]}}), None,
                        r"pending journal rewrites \['schema'\]"),
}


@pytest.mark.parametrize("case", sorted(JOURNALS))
def test_pending_journal_record_is_checked_before_it_is_replayed(stores, case):
    a = str(stores / "a.zarr")
    meta, dtypes, named = JOURNALS[case]
    _pending_journal(a, meta, dtypes=dtypes)
    before = _hash_tree(stores)
    for read_only in (True, False):
        with pytest.raises(IntegrityError, match=rf"(?s){named}"):
            ZarrStorage(a, read_only=read_only)
    assert _hash_tree(stores) == before  # the writable open replayed nothing
    report = verify(a)
    assert any(p.kind == "journal" for p in report.errors), str(report)
    result = repair(a)  # the journal cannot be trusted: dropped, and the chunk it may have torn (4) cut off
    assert result.ok and any("dropped the pending journal" in x for x in result.actions), str(result)
    with ZarrStorage(a, read_only=True) as s:
        assert len(s) == 4 * CHUNK
        assert torch.equal(s["observation"][:], _rows(4 * CHUNK)["observation"])


# -- sizes checked against what the store holds -------------------------------------------


_CHILD = textwrap.dedent("""
    import json, resource, sys, traceback
    resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30))  # a regression fails (MemoryError) instead of swapping
    from torchrl_robotmem import ZarrStorage
    from torchrl_robotmem.storage.integrity import repair, verify
    path, what = sys.argv[1], sys.argv[2]
    try:
        if what == "open":
            ZarrStorage(path, read_only=True)
            out = {"result": "opened"}
        elif what == "verify":
            report = verify(path)
            out = {"result": "report", "ok": report.ok, "problems": [str(p) for p in report.errors], "rows": report.rows}
        else:
            out = {"result": "repair", "report": str(repair(path, dry_run=True))}
    except Exception as err:
        out = {"result": "error", "type": type(err).__name__, "message": str(err),
               "value_error": isinstance(err, ValueError), "trace": traceback.format_exc()[-2000:]}
    print(json.dumps(out))
""")


def _in_child(path, what: str) -> dict:
    """Runs ``what`` on ``path`` in a child under a 6 GB address-space limit; a hang is a failure, not a wait."""
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(path), what], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _claim_rows(path, n: int):
    """Makes the commit record and every array's ``zarr.json`` claim ``n`` rows of capacity (a consistent lie)."""
    _edit_attrs(path, lambda attrs: attrs.update(max_size=n))
    for dirpath, _, files in os.walk(path):
        if "zarr.json" in files and dirpath != str(path):
            def grow(meta):
                if meta.get("node_type") == "array":
                    meta["shape"][0] = n
            _edit_json(dirpath, "zarr.json", grow)


@pytest.mark.parametrize("case", ["max_size", "row_shape"])
def test_sizes_no_machine_can_hold_are_refused_naming_the_field(stores, case):
    a = stores / "a.zarr"
    if case == "max_size":
        _claim_rows(a, 10**15)
        named = r"attribute 'max_size' \(1000000000000000\)"
    else:
        _edit_attrs(a, lambda attrs: attrs["schema"]["observation"].update(shape=[10**9]))
        _edit_json(a, "observation/zarr.json", lambda meta: meta.update(
            shape=[MAX, 10**9], chunk_grid={"name": "regular", "configuration": {"chunk_shape": [CHUNK, 10**9]}}))
        named = r"attribute 'schema' entry 'observation' \(shape \[1000000000\]\)"
    before = _hash_tree(stores)
    out = _in_child(a, "open")
    assert out["result"] == "error" and out["value_error"], out
    assert str(a) in out["message"] and __import__("re").search(named, out["message"]), out["message"]
    assert "more than this machine can allocate" in out["message"]
    assert _hash_tree(stores) == before


def test_len_far_past_the_chunk_files_costs_what_the_store_holds(stores):
    """A ``len`` of 10**12 rows over arrays that claim 10**13: verify and repair list the chunk files, not the claim."""
    a = stores / "a.zarr"
    _claim_rows(a, 10**13)
    _edit_attrs(a, lambda attrs: attrs.update(len=10**12))
    before = _hash_tree(stores)
    out = _in_child(a, "verify")
    assert out["result"] == "report" and not out["ok"] and out["rows"] == 10**12, out
    assert "array 'observation' chunk 5 (observation/c.5.0, rows 320-383): chunk file missing" in out["problems"]
    assert any("more chunk files missing: the committed length (1000000000000 rows) spans 15625000000 chunks, 5 exist"
               in p for p in out["problems"]), out["problems"]
    out = _in_child(a, "repair")
    assert out["result"] == "error" and "attribute 'max_size' (10000000000000)" in out["message"], out
    assert _hash_tree(stores) == before


@pytest.mark.parametrize("value", ["x", -4, None, 1.5])
def test_hostile_overwrites_count_is_refused_naming_it_and_repaired(stores, value):
    """The record's count of journalled commits (a reader compares it across its load): a bad one is refused for
    writing, named, changes nothing; ``repair`` mends it and the rows are all there."""
    a = str(stores / "a.zarr")
    _edit_attrs(a, lambda attrs: attrs.update(overwrites=value))
    before = _hash_tree(stores)
    with pytest.raises(IntegrityError, match=r"attribute 'overwrites' must be an integer >= 0"):
        ZarrStorage(a)
    assert _hash_tree(stores) == before
    repair(a)
    with ZarrStorage(a) as s:
        assert len(s) == ROWS and torch.equal(s[:ROWS]["observation"], _rows(ROWS)["observation"])
        s.set(slice(0, 2), _rows(2), set_cursor=False)  # a journalled commit counts from the mended value
    with open(os.path.join(a, "zarr.json")) as f:
        assert json.load(f)["attributes"]["overwrites"] == 1


@pytest.mark.parametrize("version", [[1], "1", None, True])
def test_malformed_format_marker_is_refused_naming_it(stores, version):
    a = str(stores / "a.zarr")
    _edit_attrs(a, lambda attrs: attrs["torchrl_robotmem"].update(format_version=version))
    before = _hash_tree(stores)
    for read_only in (True, False):
        with pytest.raises(ValueError, match=r"malformed 'torchrl_robotmem' attribute \(format_version"):
            ZarrStorage(a, read_only=read_only)
    assert _hash_tree(stores) == before
