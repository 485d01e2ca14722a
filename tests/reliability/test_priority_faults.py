"""Faults in the stored priorities of ``PersistentPrioritizedSampler`` (the store's ``_priority/`` group).

Real stores, real processes, no mocks:

* a priority write SIGKILLed before each of its steps, by construction: a child process (forked from a
  forkserver with torch / torchrl / zarr loaded, so it starts in milliseconds) wraps the sampler module's
  step functions (``_create_array``, ``_resize_array``, ``_write_chunk``, ``_write_record``,
  ``_delete_array``) so that the N-th call kills the process before doing its step. A dry run records the
  steps; then each N is killed in turn, for a plain write, a write after the store grew, a re-creation
  (a new dtype) and the first write over a format-1 group. The parent reopens the store and finds exactly
  the old priorities (killed before the record) or exactly the new ones (after it), without a warning, and
  a later write works;
* a chunk deleted, truncated, with a byte flipped or replaced by another slot's (well-formed) chunk: a
  warning names the chunk; its rows restart at the recorded max priority, the others keep theirs; the
  next write repairs it;
* every field of the record set to a bad value (or the record file garbled): a warning names the store and
  the field, every row restarts at 1.0, sampling works, the next write replaces the record;
* a format-1 group (one ``priority`` array) loads, a missing chunk in it is found, and the next write
  converts it.

The stores hold 2 to 3 chunks of ``CHUNK_ROWS`` (65,536) rows of one float column.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import runpy
import shutil
import signal
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import zarr
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.samplers import prioritized as pz
from torchrl_robotmem.samplers.prioritized import CHUNK_ROWS, PersistentPrioritizedSampler

pytestmark = pytest.mark.filterwarnings("ignore:ZarrStorage at")

R = CHUNK_ROWS
ROWS = 2 * R + 1000  # rows held: three chunks, the last partial
CHILD_RUN_NAME = "__robotmem_priority_fault_child__"
STEPS = ("_create_array", "_resize_array", "_write_chunk", "_write_record", "_delete_array")


def _old(n: int = ROWS) -> torch.Tensor:
    return 0.5 + torch.rand(n, generator=torch.Generator().manual_seed(1))  # in [0.5, 1.5)


def _new(n: int = ROWS) -> torch.Tensor:
    return 2.0 + torch.rand(n, generator=torch.Generator().manual_seed(2))  # in [2, 3): never an old value


def _build(path: Path, max_size: int, priority: torch.Tensor, top: float | None = None) -> None:
    """A store of ``priority.numel()`` rows whose stored priorities are ``priority`` (and max ``top``)."""
    n = priority.numel()
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path, max_size, env="FetchPush-v4"),
                                sampler=PersistentPrioritizedSampler(persist_interval=None), batch_size=8)
    rb.extend(TensorDict({"obs": torch.arange(n, dtype=torch.float32).unsqueeze(1)}, [n]))
    rb.update_priority(torch.arange(n), priority)
    if top is not None:
        rb.update_priority(torch.tensor([n - 1]), torch.tensor([top]))
    rb.sampler.flush()
    rb.storage.close()


def _load(path: Path) -> tuple[torch.Tensor, list[str]]:
    """The priorities a reader gets (and the warnings about them); sampling works."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with ZarrStorage(path, read_only=True) as storage:
            sampler = PersistentPrioritizedSampler()
            index, info = sampler.sample(storage, 32)
            assert index.shape == (32,) and bool(torch.isfinite(info["priority_weight"]).all())
            p = sampler.priority.clone()
    return p, [str(w.message) for w in caught if "priorit" in str(w.message)]


def _same(loaded: tuple[torch.Tensor, list[str]], expected: torch.Tensor) -> None:
    p, warned = loaded
    assert warned == [] and torch.equal(p, expected)


def _rewrite(path: Path, row: int = 0, value: float = 5.0) -> list[str]:
    """A writable reopen that sets one priority and writes; returns the warnings of its load."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with ZarrStorage(path) as storage:
            sampler = PersistentPrioritizedSampler(persist_interval=None)
            sampler.update_priority(torch.tensor([row]), torch.tensor([value]), storage=storage)
            sampler.flush()
    return [str(w.message) for w in caught if "priorit" in str(w.message)]


def _record(path: Path) -> dict:
    return json.loads((path / "_priority" / "zarr.json").read_text())["attributes"]


def _set_record(path: Path, **fields) -> None:
    """Rewrites fields of the record file itself (``NaN`` / ``Infinity`` as JSON literals)."""
    file = path / "_priority" / "zarr.json"
    meta = json.loads(file.read_text())
    meta["attributes"].update(fields)
    file.write_text(json.dumps(meta, allow_nan=True))


def _chunk_file(path: Path, chunk: int) -> Path:
    rec = _record(path)
    return path / "_priority" / rec["array"] / "c" / str(rec["chunks"][chunk])


def _write_format1(path: Path, priority: np.ndarray, top: float) -> None:
    """Replaces the store's priority group by the layout format 1 wrote (one ``priority`` array, then the attrs)."""
    root = zarr.open_group(str(path), mode="r+", zarr_format=3)
    n, cap = int(root.attrs["len"]), int(root.attrs["max_size"])
    group = root.create_group("_priority", overwrite=True)
    raw = np.zeros(cap, dtype=np.float32)
    raw[: priority.size] = priority
    array = group.create_array("priority", shape=(cap,), chunks=(R,), dtype="float32", overwrite=True,
                               config={"write_empty_chunks": True})
    for c in range(-(-cap // R)):
        array[c * R: (c + 1) * R] = raw[c * R: (c + 1) * R]
    group.attrs.update({"len": n, "cursor": n % cap, "write_count": int(root.attrs["write_count"]),
                        "max_priority": top, "alpha": 0.6, "beta": 0.4, "eps": 1e-8,
                        "format": pz.FORMAT, "format_version": 1, "dtype": "float32"})


# -- SIGKILL at every step of a priority write --------------------------------------------------


def _child(path: str, max_size: int | None, kill_at: int, dtype: str, steps_file: str) -> None:
    """Opens the store, sets every row's priority to ``_new()``, writes; SIGKILLs itself before step ``kill_at``."""
    done: list[str] = []

    def arm(name, fn):
        def step(*args, **kwargs):
            if len(done) == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)
            done.append(name)
            return fn(*args, **kwargs)
        return step

    for name in STEPS:
        setattr(pz, name, arm(name, getattr(pz, name)))
    warnings.simplefilter("ignore")
    storage = ZarrStorage(path, max_size)
    sampler = PersistentPrioritizedSampler(dtype=getattr(torch, dtype), persist_interval=None)
    n = len(storage)
    sampler.update_priority(torch.arange(n), _new(n).to(getattr(torch, dtype)), storage=storage)
    sampler.flush()
    Path(steps_file).write_text(json.dumps(done))
    storage.close()


def _run_child(ctx, **args) -> int:
    proc = ctx.Process(target=runpy.run_path, args=(__file__,),
                       kwargs={"init_globals": {"ARGS": args}, "run_name": CHILD_RUN_NAME})
    proc.start()
    proc.join(300)
    assert proc.exitcode is not None, "the child did not end"
    return proc.exitcode


@pytest.fixture(scope="module")
def ctx():
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["torch", "tensordict", "torchrl.data", "zarr", "torchrl_robotmem"])
    return ctx


@pytest.mark.parametrize("case", ["write", "grow", pytest.param("recreate", marks=pytest.mark.full),
                                  pytest.param("format1", marks=pytest.mark.full)])
def test_a_priority_write_killed_at_any_step_leaves_the_old_or_the_new_priorities(tmp_path, ctx, case):
    base = tmp_path / "base.zarr"
    _build(base, 3 * R, _old())
    if case == "format1":
        _write_format1(base, _old().numpy(), top=1.5)
    grow = 5 * R if case == "grow" else None
    dtype = "float64" if case == "recreate" else "float32"
    old, new = _old(), _new().to(getattr(torch, dtype)).float()
    _same(_load(base), old)

    dry = tmp_path / "dry.zarr"
    shutil.copytree(base, dry)
    steps_file = tmp_path / "steps.json"
    assert _run_child(ctx, path=str(dry), max_size=grow, kill_at=10**9, dtype=dtype, steps_file=str(steps_file)) == 0
    steps = json.loads(steps_file.read_text())
    commit = steps.index("_write_record")
    assert steps.count("_write_chunk") == (5 if case == "grow" else 3) and steps.count("_write_record") == 1
    if case in ("recreate", "format1"):
        assert steps[0] == "_create_array" and steps[-1] == "_delete_array"
    else:
        assert steps[0] == "_resize_array"  # the chunks go to free slots past the committed ones
    _same(_load(dry), new)

    for k in range(len(steps)):
        store = tmp_path / f"kill{k}.zarr"
        shutil.copytree(base, store)
        code = _run_child(ctx, path=str(store), max_size=grow, kill_at=k, dtype=dtype, steps_file=str(steps_file))
        assert code == -signal.SIGKILL, f"killed before step {k} ({steps[k]}): exit code {code}"
        p, warned = _load(store)
        expected = old if k <= commit else new
        assert warned == [] and torch.equal(p, expected), (
            f"killed before step {k} ({steps[k]}): {'a mix' if not torch.equal(p, old) and not torch.equal(p, new) else 'the wrong write'}")
        # the next write, over whatever the kill left, works and leaves one array named by its record
        assert _rewrite(store) == []
        p, warned = _load(store)
        assert warned == [] and p[0] == 5.0 and torch.equal(p[1:], expected[1:])
        arrays = sorted(d.name for d in (store / "_priority").iterdir() if d.is_dir())
        assert arrays == [_record(store)["array"]]


# -- damaged chunks ------------------------------------------------------------------------------


@pytest.mark.parametrize("damage", ["deleted", "truncated", "flipped", "swapped"])
def test_a_damaged_priority_chunk_restarts_its_rows_at_the_recorded_max(tmp_path, damage):
    path = tmp_path / "per.zarr"
    old = _old(R + 500)
    _build(path, 2 * R, old, top=99.0)
    old[-1] = 99.0
    file = _chunk_file(path, 0)
    key = "/".join(file.relative_to(path).parts)
    data = file.read_bytes()
    if damage == "deleted":
        file.unlink()
    elif damage == "truncated":
        file.write_bytes(data[: len(data) // 2])
    elif damage == "flipped":
        file.write_bytes(data[:100] + bytes([data[100] ^ 0xFF]) + data[101:])
    else:  # a well-formed chunk of another slot: only the record's crc32c tells
        shutil.copyfile(_chunk_file(path, 1), file)
    p, warned = _load(path)
    assert len(warned) == 1 and key in warned[0] and str(path) in warned[0] and "99" in warned[0], warned
    assert p[:R].eq(99.0).all() and torch.equal(p[R:], old[R:])
    assert _rewrite(path, row=R) == [w for w in warned]  # the writer's load warns the same
    p2, warned = _load(path)  # the write replaced the chunk
    assert warned == [] and torch.equal(p2[:R], p[:R]) and p2[R] == 5.0 and torch.equal(p2[R + 1:], old[R + 1:])


def test_a_missing_priority_array_restarts_every_row_at_the_recorded_max(tmp_path):
    path = tmp_path / "per.zarr"
    _build(path, 2 * R, _old(R + 500), top=7.0)
    shutil.rmtree(path / "_priority" / _record(path)["array"])
    p, warned = _load(path)
    assert len(warned) == 1 and "_priority/priority/zarr.json" in warned[0] and p.eq(7.0).all()
    _rewrite(path)
    p, warned = _load(path)
    assert warned == [] and p[0] == 5.0 and p[1:].eq(7.0).all()


def test_a_slot_beyond_the_array_is_a_damaged_chunk(tmp_path):
    path = tmp_path / "per.zarr"
    old = _old(R + 500)
    _build(path, 2 * R, old, top=6.0)
    rec = _record(path)
    _set_record(path, chunks=[rec["chunks"][0], 99])
    p, warned = _load(path)
    assert len(warned) == 1 and "_priority/priority/c/99" in warned[0] and "beyond" in warned[0], warned
    assert torch.equal(p[:R], old[:R]) and p[R:].eq(6.0).all()


def test_a_write_leaves_the_slots_of_the_record_before_it_for_readers_in_flight(tmp_path):
    path = tmp_path / "per.zarr"
    old = _old(R + 500)
    _build(path, 2 * R, old)
    first = _record(path)
    _rewrite(path, row=0)  # a reader that read `first` just before this write still finds its chunks
    array = zarr.open_array(str(path / "_priority" / first["array"]), mode="r")
    for c, slot in enumerate(first["chunks"]):
        assert pz._crc(np.asarray(array[slot * R: (slot + 1) * R])) == first["crc32c"][c]
    second = _record(path)
    assert second["previous"] == first["chunks"] and second["chunks"][0] not in first["chunks"]


# -- a bad record ----------------------------------------------------------------------------------


def _beyond(rec: dict) -> dict:
    """A chunk map naming more chunks than the store's rows make."""
    return {"chunks": rec["chunks"] + [90, 91], "crc32c": rec["crc32c"] + [0, 0]}


BAD_FIELDS = [
    ("max_priority", float("nan")), ("max_priority", -5), ("max_priority", float("inf")), ("max_priority", "abc"),
    ("write_count", "x"), ("write_count", None), ("write_count", -3),
    ("cursor", -7), ("cursor", 1e300), ("cursor", 3 * R),
    ("len", 3 * R), ("len", 12.0), ("dtype", "int8"), ("format_version", 9), ("array", "../rows"),
    ("chunk_rows", 0), ("chunks", _beyond), ("chunks", [0, 0]), ("crc32c", [1]), ("previous", "x"),
]


@pytest.mark.parametrize("field, value", BAD_FIELDS, ids=[f"{f}={v if not callable(v) else 'beyond'}"
                                                          for f, v in BAD_FIELDS])
def test_a_bad_record_field_is_refused_naming_the_store_and_the_field(tmp_path, field, value):
    path = tmp_path / "per.zarr"
    old = _old(R + 500)
    _build(path, 2 * R, old, top=3.0)
    _set_record(path, **(value(_record(path)) if callable(value) else {field: value}))
    p, warned = _load(path)
    assert len(warned) == 1 and str(path) in warned[0] and f"'{field}'" in warned[0], warned
    assert p.eq(1.0).all()  # every row starts over, as in a new buffer: never priorities read through a bad field
    _rewrite(path)  # the next write replaces the record
    p, warned = _load(path)
    assert warned == [] and p[0] == 5.0 and p[1:].eq(1.0).all()
    assert _record(path)["format_version"] == pz.FORMAT_VERSION


def test_a_garbled_record_file_is_refused_and_replaced(tmp_path):
    path = tmp_path / "per.zarr"
    _build(path, 2 * R, _old(R + 500))
    (path / "_priority" / "zarr.json").write_bytes(b'{"zarr_format": 3, "node_type": "gro\x00\xff')
    p, warned = _load(path)
    assert len(warned) == 1 and str(path) in warned[0] and "_priority/zarr.json" in warned[0] and p.eq(1.0).all()
    _rewrite(path)
    p, warned = _load(path)
    assert warned == [] and p[0] == 5.0 and p[1:].eq(1.0).all()


# -- format 1 --------------------------------------------------------------------------------------


def test_a_format1_priority_group_loads_and_the_next_write_converts_it(tmp_path):
    path = tmp_path / "per.zarr"
    old = _old(R + 500)
    _build(path, 2 * R, old)
    _write_format1(path, old.numpy(), top=4.0)
    assert _record(path)["format_version"] == 1
    _same(_load(path), old)
    _rewrite(path, row=3)
    rec = _record(path)
    assert rec["format_version"] == pz.FORMAT_VERSION and rec["array"] == "priority_b"
    assert not (path / "_priority" / "priority").exists()
    p, warned = _load(path)
    assert warned == [] and p[3] == 5.0 and torch.equal(p[:3], old[:3]) and torch.equal(p[4:], old[4:])


def test_a_missing_chunk_of_a_format1_group_is_found(tmp_path):
    path = tmp_path / "per.zarr"
    old = _old(R + 500)
    _build(path, 2 * R, old)
    _write_format1(path, old.numpy(), top=4.0)
    (path / "_priority" / "priority" / "c" / "1").unlink()  # would read as Zarr's fill value, 0
    p, warned = _load(path)
    assert len(warned) == 1 and "_priority/priority/c/1" in warned[0] and "missing" in warned[0]
    assert torch.equal(p[:R], old[:R]) and p[R:].eq(4.0).all()


if __name__ == CHILD_RUN_NAME:
    _child(**ARGS)  # noqa: F821 - given by runpy.run_path(init_globals=...)


@pytest.mark.parametrize("fmt", ["format2", "format1"])
def test_repair_rebuilds_a_lost_root_record_beside_a_priority_group(tmp_path, fmt):
    """The priority group is a component's state, not a column: a rebuilt record does not take it for one."""
    path = tmp_path / "m.zarr"
    _build(path, 4 * R, _old())
    if fmt == "format1":
        shutil.rmtree(path / "_priority")
        _write_format1(path, _old().numpy(), 1.5)
    os.remove(path / "zarr.json")
    from torchrl_robotmem.storage.integrity import repair

    report = repair(str(path))
    assert report.ok, report
    with ZarrStorage(path, read_only=True) as storage:
        assert len(storage) == ROWS and set(storage.schema) == {"obs", "episode", "run", "env"}
