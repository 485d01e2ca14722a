"""The ``robotmem`` command line on real memories: subprocesses and in-process ``main([...])``.

Memories are real Zarr stores written through a TorchRL ``TensorDictReplayBuffer``
over ``ZarrStorage``; Minari datasets are real local HDF5 datasets (nothing is
downloaded).
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
import zarr
from conftest import make_transitions
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.cli import COMMANDS, main
from torchrl_robotmem.cli.inspect import summarize

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _cli(*args: str) -> subprocess.Popen:
    """``python -m torchrl_robotmem ARGS`` in a new process (started, not waited for)."""
    env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.Popen([sys.executable, "-m", "torchrl_robotmem", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def _write(path, data: TensorDict, *, env: str, max_size: int | None = None) -> None:
    storage = ZarrStorage(path, max_size, env=env)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=4)
    for start in range(0, len(data), 10):  # one extend never wraps a ring onto itself
        rb.extend(data[start:start + 10])
    storage.close()


def _episodes(n_episodes: int, start: int, *, length: int = 6, success_every: int = 3) -> TensorDict:
    """Consistent transitions: each row's ``next`` values are the next row's root values within an episode."""
    rows = []
    for e in range(start, start + n_episodes):
        t = torch.arange(length + 1, dtype=torch.float32)
        obs = torch.stack([e + 0.1 * t, -t, torch.full_like(t, float(e))], -1).repeat(1, 3)  # [T+1, 9]
        goal = torch.stack([0.07 * e + 0.01 * t, 0.03 * t, 0.02 * e + 0 * t], -1)
        desired = torch.tensor([0.1 * e, 0.2, 0.3]).expand(length + 1, 3)
        succ = torch.zeros(length, dtype=torch.float32)
        if e % success_every == 0:
            succ[-2:] = 1.0
        done = torch.zeros(length, 1, dtype=torch.bool)
        done[-1] = True
        cur = {"observation": obs[:-1], "achieved_goal": goal[:-1], "desired_goal": desired[:-1]}
        nxt = {"observation": obs[1:], "achieved_goal": goal[1:], "desired_goal": desired[1:]}
        rows.append(TensorDict({
            **cur, "action": torch.sin(torch.arange(length * 4, dtype=torch.float32) + e).reshape(length, 4),
            "done": torch.zeros(length, 1, dtype=torch.bool),
            "next": {**nxt, "reward": succ.unsqueeze(-1) - 1.0, "done": done, "truncated": done.clone(),
                     "terminated": torch.zeros(length, 1, dtype=torch.bool), "is_success": succ},
        }, [length]))
    return torch.cat(rows)


@pytest.fixture
def memory(tmp_path):
    """Two runs, two envs: 8 FetchPush episodes then 5 FetchSlide episodes of 6 steps."""
    path = str(tmp_path / "mem.zarr")
    _write(path, _episodes(8, 0), env="FetchPush-v4", max_size=500)
    _write(path, _episodes(5, 8), env="FetchSlide-v4")
    return path


def test_registry_and_help(capsys):
    assert {"inspect", "plot", "export", "import"} <= set(COMMANDS)
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in ("inspect", "plot", "export", "import"))
    assert main(["no-such-command"]) == 2


def test_a_command_that_cannot_be_imported_leaves_the_others_working(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(COMMANDS, "broken", "torchrl_robotmem.cli._no_such_module")
    assert main(["broken", "x"]) == 1
    assert "_no_such_module cannot be imported" in capsys.readouterr().err
    assert main(["inspect", str(tmp_path)]) == 2
    assert "is not a torchrl_robotmem memory" in capsys.readouterr().err


def test_subprocesses_inspect_json_while_a_writer_holds_the_store_and_refuse_a_non_memory(memory, tmp_path):
    writer = ZarrStorage(memory)  # holds the writer lock, as a training process would
    try:
        TensorDictReplayBuffer(storage=writer, batch_size=4).extend(_episodes(1, 13))
        writer.flush()
        # both at once: starting Python with torch is most of their time on a loaded machine
        procs = [_cli("inspect", "--json", memory), _cli("inspect", str(tmp_path))]
        (out, err), (_, bad_err) = (p.communicate(timeout=300) for p in procs)
    finally:
        writer.close()
    assert procs[1].returncode == 2
    assert "is not a torchrl_robotmem memory" in bad_err and "Traceback" not in bad_err, bad_err
    assert procs[0].returncode == 0, err
    s = json.loads(out)
    assert s["rows"] == 14 * 6 and s["max_size"] == 500
    assert s["episodes"] == s["finished_episodes"] == 14
    assert s["runs"] == 3
    assert s["env_names"] == ["FetchPush-v4", "FetchSlide-v4"]
    assert s["format"]["format_version"] == 1
    by_env = {e["name"]: e for e in s["envs"]}
    assert by_env["FetchPush-v4"]["rows"] == 48 and by_env["FetchPush-v4"]["episodes"] == 8
    assert by_env["FetchSlide-v4"]["rows"] == 36 and by_env["FetchSlide-v4"]["episodes"] == 6
    # episodes 0, 3, 6 succeed in FetchPush (3 / 8); 9, 12 in FetchSlide (2 / 6, run 2 continued FetchSlide)
    assert by_env["FetchPush-v4"]["episode_success_rate"] == pytest.approx(3 / 8)
    assert by_env["FetchSlide-v4"]["episode_success_rate"] == pytest.approx(2 / 6)
    assert [(r["run"], r["envs"], r["episodes"]) for r in s["per_run"]] == [
        (0, ["FetchPush-v4"], 8), (1, ["FetchSlide-v4"], 5), (2, ["FetchSlide-v4"], 1)]
    assert s["success"]["episode_success_rate"] == pytest.approx(5 / 14)
    goals = _episodes(14, 0)["next", "achieved_goal"].numpy().astype(np.float64)
    cov = s["goal_coverage"]
    assert cov["key"] == "next/achieved_goal"
    np.testing.assert_allclose(cov["min"], goals.min(0))
    np.testing.assert_allclose(cov["max"], goals.max(0))
    assert cov["cells"] == len(np.unique(np.floor(goals / 0.05).astype(np.int64), axis=0))
    assert s["bytes_on_disk"] > 0
    schema = {k["key"]: k for k in s["schema"]}
    assert schema["next/observation"]["dtype"] == "float32" and schema["next/observation"]["shape"] == [9]
    assert schema["episode"]["dtype"] == "int64" and schema["episode"]["shape"] == []


def test_not_a_memory_in_process(tmp_path, capsys):
    zarr.open_group(str(tmp_path / "foreign.zarr"), mode="w", zarr_format=3).attrs["x"] = 1
    (tmp_path / "file.txt").write_text("hi")
    for path in (tmp_path, tmp_path / "missing.zarr", tmp_path / "foreign.zarr", tmp_path / "file.txt"):
        for command in (["inspect"], ["plot"], ["export"]):
            extra = [str(tmp_path / "out.npz")] if command == ["export"] else []
            assert main([*command, str(path), *extra]) == 2
            err = capsys.readouterr().err
            assert f"{str(path)!r} is not a torchrl_robotmem memory" in err, err
    assert not (tmp_path / "out.npz").exists()


def test_inspect_text(memory, capsys):
    assert main(["inspect", memory]) == 0
    out = capsys.readouterr().out
    assert "78 of 500" in out  # 13 episodes x 6 rows
    assert "FetchPush-v4" in out and "FetchSlide-v4" in out and "37.5%" in out
    assert "next/achieved_goal" in out and "float32" in out


def test_summarize_full_ring_counts_rows_once(tmp_path):
    path = str(tmp_path / "ring.zarr")
    _write(path, make_transitions(130), env="FetchReach-v4", max_size=100)
    s = summarize(path)
    assert s["rows"] == 100 and s["full"] and s["write_count"] == 130
    assert s["envs"][0]["rows"] == 100 and s["episodes"] == 10  # rows 30..129: 10 episodes of 10


def test_plot_writes_pngs(memory, tmp_path, capsys):
    out = tmp_path / "plots"
    assert main(["plot", memory, "--out", str(out), "--window", "3"]) == 0
    for name in ("success.png", "goals.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    assert str(out / "goals.png") in capsys.readouterr().out
    # nothing is overwritten (found by a review: an existing success.png was replaced)
    (out / "success.png").write_bytes(b"someone's figure")
    assert main(["plot", memory, "--out", str(out)]) == 2
    assert "exist; refusing to overwrite them" in capsys.readouterr().err
    assert (out / "success.png").read_bytes() == b"someone's figure"


def test_npz_round_trip_is_bit_exact(tmp_path):
    src = str(tmp_path / "ring.zarr")
    _write(src, make_transitions(130), env="FetchReach-v4", max_size=100)  # a wrapped ring: write order != rows
    _write(src, make_transitions(20, 130), env="FetchPush-v4")
    a, b = str(tmp_path / "a.npz"), str(tmp_path / "b.npz")
    assert main(["export", src, a]) == 0
    assert main(["import", a, str(tmp_path / "copy.zarr")]) == 0
    assert main(["export", str(tmp_path / "copy.zarr"), b]) == 0
    za, zb = np.load(a, allow_pickle=False), np.load(b, allow_pickle=False)
    assert sorted(za.files) == sorted(zb.files)
    assert {"episode", "run", "env", "next/achieved_goal", "observation"} <= set(za.files)
    for k in za.files:
        if k != "__robotmem__":
            assert za[k].dtype == zb[k].dtype and za[k].tobytes() == zb[k].tobytes(), k
    # write order: the oldest surviving row first (rows 50..149 of what was written)
    np.testing.assert_array_equal(za["observation"], make_transitions(150)["observation"][50:].numpy())
    meta = json.loads(str(za["__robotmem__"]))
    assert meta["env_names"] == ["FetchReach-v4", "FetchPush-v4"] and meta["rows"] == 100
    copy = summarize(str(tmp_path / "copy.zarr"))
    assert copy["runs"] == 2 and copy["env_names"] == meta["env_names"] and copy["max_size"] == 100
    # the copy keeps writing: new rows get a new run and fresh episode ids
    st = ZarrStorage(str(tmp_path / "copy.zarr"))
    TensorDictReplayBuffer(storage=st, batch_size=4).extend(make_transitions(10, 150))  # rows 0..9 of the ring
    assert st["run"][:10].tolist() == [2] * 10 and int(st["episode"][:10].min()) > int(za["episode"].max())
    st.close()


def test_npz_round_trip_of_a_memory_without_a_capacity_grows_again(tmp_path):
    """Found by a review: the export recorded the growing memory's stand-in max_size (2**50 rows), so the
    import refused it ("131.0 PiB of RAM") or, empty, built a ring of 2**50 rows whose first write failed."""
    src = str(tmp_path / "grow.zarr")
    with ZarrStorage(src, chunk_rows=64, env="FetchReach-v4") as st:
        TensorDictReplayBuffer(storage=st).extend(make_transitions(1500))  # grown past its first 1,024 rows
    for name, rows in (("some", 1500), ("none", 0)):
        source = src if rows else str(tmp_path / "empty.zarr")
        if not rows:
            ZarrStorage(source).close()
        npz, copy = str(tmp_path / f"{name}.npz"), str(tmp_path / f"{name}-copy.zarr")
        assert main(["export", source, npz]) == 0
        assert json.loads(str(np.load(npz, allow_pickle=False)["__robotmem__"]))["max_size"] is None
        assert main(["import", npz, copy]) == 0
        with ZarrStorage(copy) as st:
            assert not st.bounded and len(st) == rows
            TensorDictReplayBuffer(storage=st).extend(make_transitions(1000, rows))  # it grows on
            assert len(st) == rows + 1000
            if rows:
                np.testing.assert_array_equal(st["observation"].numpy(), make_transitions(2500)["observation"].numpy())


def test_minari_round_trip_same_episodes(memory, tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "elsewhere"))
    out = str(tmp_path / "exports" / "fetch-v0")
    assert main(["export", memory, out]) == 0
    assert os.path.isfile(os.path.join(out, "data", "metadata.json"))
    assert os.environ["MINARI_DATASETS_PATH"] == str(tmp_path / "elsewhere")  # restored
    import minari

    ds = minari.MinariDataset(os.path.join(out, "data"))
    assert ds.total_episodes == 13 and ds.total_steps == 78
    assert main(["import", out, str(tmp_path / "back.zarr")]) == 0

    def per_episode(path):
        st = ZarrStorage(path, read_only=True)
        ep, env = st["episode"].numpy(), st["env"].numpy()
        keys = ["observation", "achieved_goal", "desired_goal", "action", ("next", "observation"),
                ("next", "achieved_goal"), ("next", "desired_goal"), ("next", "reward"), ("next", "is_success")]
        cols = {k: st[k].numpy() for k in keys}
        firsts = sorted(np.unique(ep, return_index=True)[1])
        out = [({k: v[ep == ep[i]] for k, v in cols.items()}, st.env_names[env[i]]) for i in firsts]
        st.close()
        return out

    before, after = per_episode(memory), per_episode(str(tmp_path / "back.zarr"))
    assert len(before) == len(after) == 13
    for (x, env_x), (y, env_y) in zip(before, after):
        assert env_x == env_y
        for k in x:
            assert x[k].dtype == y[k].dtype and np.array_equal(x[k], y[k]), k
    # --env tags every imported row with one env
    assert main(["import", out, str(tmp_path / "tagged.zarr"), "--env", "FetchReach-v4"]) == 0
    assert summarize(str(tmp_path / "tagged.zarr"))["env_names"] == ["FetchReach-v4"]


def test_existing_targets_and_bad_sources_are_refused(memory, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    npz = tmp_path / "m.npz"
    assert main(["export", memory, str(npz)]) == 0
    before = npz.read_bytes()
    assert main(["export", memory, str(npz)]) == 2
    assert "exists" in capsys.readouterr().err and npz.read_bytes() == before
    assert main(["import", str(npz), memory]) == 2  # the target memory exists
    assert "exists" in capsys.readouterr().err
    assert summarize(memory)["rows"] == 78
    (tmp_path / "ds-v0").mkdir()
    assert main(["export", memory, str(tmp_path / "ds-v0")]) == 2
    assert main(["export", memory, str(tmp_path / "no_version")]) == 2
    assert "NAME-vVERSION" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    assert main(["import", str(bad), str(tmp_path / "new.zarr")]) == 2  # a plain npz without the layout's arrays
    assert "is a plain npz (no '__robotmem__' record) without the arrays ['observation'" in capsys.readouterr().err
    assert not (tmp_path / "new.zarr").exists()
    assert main(["import", str(tmp_path / "nowhere-v0"), str(tmp_path / "new.zarr")]) == 2
    assert not (tmp_path / "new.zarr").exists()


# -- atomic commands, partial inputs -------------------------------------------------------------------


def _npz_export(path, n: int) -> dict[str, np.ndarray]:
    """An npz in the export format (``__robotmem__`` JSON + one array per key); every column a function of the row."""
    w = np.arange(n)
    arrays = {
        "observation": (w[:, None] * 5 + np.arange(5)).astype(np.float32),
        "action": np.stack([-w, w % 7], -1).astype(np.int64),
        "next/achieved_goal": np.stack([np.sin(w * 0.37), np.cos(w * 0.11), w * 1e-4], -1).astype(np.float32),
        "next/done": (w % 50 == 49)[:, None],
        "episode": w // 50, "run": np.zeros(n, np.int64), "env": np.zeros(n, np.int64),
    }
    schema = {k: {"dtype": str(a.dtype), "shape": list(a.shape[1:])} for k, a in arrays.items()}
    meta = {"format": "torchrl_robotmem.npz", "version": 1, "env_names": ["FetchPush-v4"],
            "kind": {"kind": "tensordict"}, "ndim": 1, "max_size": n, "rows": n, "schema": schema}
    np.savez(path, **arrays, __robotmem__=np.array(json.dumps(meta)))
    return arrays


def _tree(root) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def _chunks_written(directory) -> bool:
    """Whether any chunk file of ``observation`` exists under ``directory`` (a store being built)."""
    try:
        return any(name.startswith("c.") for name in os.listdir(os.path.join(directory, "observation")))
    except (FileNotFoundError, NotADirectoryError):
        return False


def test_a_killed_import_leaves_nothing_at_the_target_and_a_rerun_imports_every_row(tmp_path):
    """SIGKILL ``robotmem import`` once it has written chunks: no memory at the target (before: an empty memory
    that ``verify`` called intact, and a rerun refused); the rerun removes the leftover and imports every row."""
    import signal

    src = tmp_path / "src.npz"
    out = tmp_path / "out"
    out.mkdir()
    target = out / "m.zarr"
    n = 400_000
    for _attempt in range(4):  # bounded: an attempt whose import finished before its chunks were seen is redone
        arrays = _npz_export(src, n)
        before = _tree(tmp_path)
        proc = _cli("import", str(src), str(target))
        partial = out / f".m.zarr.partial-{proc.pid}"
        # the event: rows are on disk (chunk files), wherever the import writes them
        while proc.poll() is None and not (_chunks_written(partial) or _chunks_written(target)):
            time.sleep(0.005)
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=120)
            break
        proc.communicate(timeout=120)
        assert proc.returncode == 0
        shutil.rmtree(target)  # finished first: again, with more rows (a longer write)
        n *= 2
    else:
        pytest.fail("four imports finished before any of their chunk files was seen")
    assert proc.returncode == -signal.SIGKILL
    assert not target.exists(), "a killed import left a memory at the target"
    assert partial.is_dir() and _chunks_written(partial)  # the rows it had written, in its own build directory
    assert _tree(tmp_path) == sorted([*before, str(partial.relative_to(tmp_path)),
                                      *(str(p.relative_to(tmp_path)) for p in partial.rglob("*"))])
    # verify / inspect say what happened; the build itself is never called intact
    checks = [(["verify", str(target)], 2), (["inspect", str(target)], 2), (["verify", str(partial)], 1)]
    procs = [_cli(*args) for args, _ in checks]  # at once: starting Python with torch is most of their time
    for (args, code), p in zip(checks, procs):
        _, err = p.communicate(timeout=300)
        assert p.returncode == code, (args, err)
        assert "interrupted command" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    # the rerun: the leftover removed, every row imported bit-exact
    rerun = _cli("import", str(src), str(target))
    stdout, err = rerun.communicate(timeout=600)
    assert rerun.returncode == 0, err
    assert os.listdir(out) == ["m.zarr"], "the killed import's build directory was left"
    st = ZarrStorage(target, read_only=True)
    try:
        assert len(st) == n
        for key, value in arrays.items():
            got = st[tuple(key.split("/")) if "/" in key else key].numpy()
            assert got.dtype == value.dtype and got.tobytes() == value.tobytes(), key
    finally:
        st.close()
    assert main(["verify", str(target)]) == 0


def _minari_source(memory, tmp_path, monkeypatch) -> str:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "elsewhere"))
    src = str(tmp_path / "exports" / "fetch-v0")
    assert main(["export", memory, src]) == 0
    return src


def _h5(src, edit):
    import h5py

    with h5py.File(os.path.join(src, "data", "main_data.hdf5"), "a") as f:
        edit(f)


def _cut_off_export(src):
    """What a Minari export killed after 5 of its 13 episodes leaves: metadata.json as first written (0 episodes)."""
    _h5(src, lambda f: [f.__delitem__(f"episode_{i}") for i in range(5, 13)])
    meta_file = os.path.join(src, "data", "metadata.json")
    with open(meta_file) as fh:
        meta = json.load(fh)
    meta.update(total_episodes=0, total_steps=0)
    meta.pop("torchrl_robotmem")
    with open(meta_file, "w") as fh:
        json.dump(meta, fh)


def _truncate(path, keep=0.5):
    data = open(path, "rb").read()
    open(path, "wb").write(data[: int(len(data) * keep)])


def _short_observations(f):
    g = f["episode_2"]["observations"]
    kept = g["observation"][:-2]
    del g["observation"]
    g["observation"] = kept


def _flip_byte(path, offset):
    data = bytearray(open(path, "rb").read())
    data[offset] ^= 0xFF
    open(path, "wb").write(bytes(data))


def _npz_without(src, key):
    z = dict(np.load(src, allow_pickle=False))
    z.pop(key)
    np.savez(src, **z)


def _npz_with(src, **changes):
    z = dict(np.load(src, allow_pickle=False))
    z.update(changes)
    np.savez(src, **z)


def _reserved_key_npz(src):
    z = dict(np.load(src, allow_pickle=False))
    meta = json.loads(str(z["__robotmem__"]))
    z["_journal"] = z["observation"]
    meta["schema"]["_journal"] = meta["schema"]["observation"]
    z["__robotmem__"] = np.array(json.dumps(meta))
    np.savez(src, **z)


BAD_SOURCES = [
    # (id, format, damage(src), what the one error line names)
    ("npz-truncated", "npz", lambda s: _truncate(s), r"src\.npz' is not an npz export .*a truncated file"),
    ("npz-empty-file", "npz", lambda s: _truncate(s, 0), r"src\.npz' is not an npz export"),
    ("npz-member-damaged", "npz", lambda s: _flip_byte(s, 200),  # inside observation.npy, the first member
     r"src\.npz': array 'observation' cannot be read \(BadZipFile: Bad CRC-32"),
    ("npz-missing-key", "npz", lambda s: _npz_without(s, "observation"),
     r"src\.npz' lacks the arrays \['observation'\] its metadata lists"),
    ("npz-short-array", "npz", lambda s: _npz_with(s, observation=np.zeros((30, 5), np.float32)),
     r"src\.npz': array 'observation' holds 30 rows, but"),
    ("npz-meta-not-json", "npz", lambda s: _npz_with(s, __robotmem__=np.array("{not json")),
     r"src\.npz': its '__robotmem__' array is not JSON"),
    ("npz-reserved-key", "npz", _reserved_key_npz, r"src\.npz': Key '_journal' is reserved.*user_journal"),
    ("minari-cut-off", "minari", _cut_off_export,
     r"metadata\.json' lists 0 episodes \(0 steps\) but .*main_data\.hdf5' holds 5 episodes \(30 steps\)"),
    ("minari-episodes-missing", "minari", lambda s: _h5(s, lambda f: f.__delitem__("episode_7")),
     r"lists 13 episodes \(78 steps\) but .*main_data\.hdf5' holds 12 episodes \(72 steps; missing episode_7\)"),
    ("minari-hdf5-truncated", "minari", lambda s: _truncate(os.path.join(s, "data", "main_data.hdf5")),
     r"main_data\.hdf5' cannot be read \(OSError: .*truncated"),
    ("minari-hdf5-missing", "minari", lambda s: os.remove(os.path.join(s, "data", "main_data.hdf5")),
     r"fetch-v0/data': the Minari dataset cannot be opened"),
    ("minari-metadata-truncated", "minari", lambda s: _truncate(os.path.join(s, "data", "metadata.json")),
     r"metadata\.json' is not valid JSON"),
    ("minari-episode-key-missing", "minari", lambda s: _h5(s, lambda f: f["episode_3"].__delitem__("rewards")),
     r"fetch-v0': episode 3 cannot be read from .*main_data\.hdf5' \(KeyError: .*rewards"),
    ("minari-short-observations", "minari", lambda s: _h5(s, _short_observations),
     r"fetch-v0': episode 2 cannot be imported \(ValueError: observations 'observation' hold 5 steps"),
]


@pytest.mark.parametrize("case", BAD_SOURCES, ids=[c[0] for c in BAD_SOURCES])
def test_a_partial_or_damaged_source_is_one_error_line_and_creates_nothing(case, memory, tmp_path, monkeypatch,
                                                                            capsys):
    _, fmt, damage, match = case
    if fmt == "npz":
        src = str(tmp_path / "src.npz")
        _npz_export(src, 40)
    else:
        src = _minari_source(memory, tmp_path, monkeypatch)
    damage(src)
    capsys.readouterr()
    before = _tree(tmp_path)
    target = tmp_path / "new" / "m.zarr"
    assert main(["import", src, str(target)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("robotmem import: error: "), err
    assert re.search(match, err), err
    assert not target.exists()
    assert _tree(tmp_path) == before, "the failed import left files (or the directory made for its target)"


def test_exports_build_beside_their_target_and_remove_the_builds_of_killed_commands(memory, tmp_path, monkeypatch):
    """What a killed export leaves (``.NAME.partial-PID`` of a process that is gone) is removed by the next
    command on that target; a build whose process still runs is left alone; nothing else is touched."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "elsewhere"))
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    alive = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    out = tmp_path / "exports"
    out.mkdir()
    try:
        stale_ds = out / f".fetch-v0.partial-{dead.pid}"
        (stale_ds / "fetch-v0" / "data").mkdir(parents=True)
        (stale_ds / "fetch-v0" / "data" / "metadata.json").write_text('{"total_episodes": 0}')
        stale_npz = out / f".m.npz.partial-{dead.pid}.npz"
        stale_npz.write_bytes(b"PK\x03\x04 cut off")
        running = out / f".m.npz.partial-{alive.pid}.npz"
        running.write_bytes(b"another export, still running")
        other = out / ".unrelated.partial-1"  # not a build of these targets
        other.mkdir()
        assert main(["export", memory, str(out / "fetch-v0")]) == 0
        assert main(["export", memory, str(out / "m.npz")]) == 0
        assert sorted(os.listdir(out)) == sorted(["fetch-v0", "m.npz", running.name, other.name])
        assert running.read_bytes() == b"another export, still running"
        assert main(["import", str(out / "m.npz"), str(out / "m.zarr")]) == 0
        assert main(["import", str(out / "fetch-v0"), str(out / "back.zarr")]) == 0
        assert summarize(str(out / "m.zarr"))["rows"] == summarize(str(out / "back.zarr"))["rows"] == 78
    finally:
        alive.communicate(b"")


def test_a_missing_optional_dependency_names_its_extra(tmp_path, capsys, monkeypatch):
    """`pip install torchrl_robotmem` has no matplotlib or minari: their commands say which extra installs them."""
    path = tmp_path / "m.zarr"
    with ZarrStorage(path, 100, env="FetchPush-v4") as s:
        TensorDictReplayBuffer(storage=s, batch_size=4).extend(make_transitions(20))
    # a module set to None in sys.modules is one Python cannot import (ModuleNotFoundError), as when not installed
    for name in ("matplotlib", "matplotlib.pyplot", "minari", "minari.data_collector",
                 "minari.data_collector.episode_buffer"):
        monkeypatch.setitem(sys.modules, name, None)
    assert main(["plot", str(path), "--out", str(tmp_path / "plots")]) == 2
    assert "pip install 'torchrl_robotmem[plots]'" in capsys.readouterr().err
    assert main(["export", str(path), str(tmp_path / "ds" / "fetch-v0")]) == 1
    err = capsys.readouterr().err
    assert "needs minari" in err and "pip install 'torchrl_robotmem[minari]'" in err
    assert not (tmp_path / "ds" / "fetch-v0").exists() and not (tmp_path / "plots").exists()


def test_a_target_spelled_as_a_local_url_lands_at_its_path_and_an_empty_one_is_refused(tmp_path, monkeypatch, capsys):
    """Found by a review: copy / export / import to ``file://PATH`` built the target under ``./file:/PATH`` in the
    current directory (reporting PATH), and an empty target built a sibling of the current directory."""
    src = str(tmp_path / "m.zarr")
    with ZarrStorage(src, 100, env="E", goal_conditioned=False) as st:
        st.set(slice(0, 10), TensorDict({"obs": torch.arange(10.0)}, [10]))
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    assert main(["copy", src, f"file://{tmp_path}/c.zarr"]) == 0
    assert main(["export", src, f"local://{tmp_path}/e.npz"]) == 0
    assert main(["import", str(tmp_path / "e.npz"), f"file://{tmp_path}/i.zarr"]) == 0
    for name in ("c.zarr", "i.zarr"):
        with ZarrStorage(str(tmp_path / name), read_only=True) as st:
            assert torch.equal(st["obs"], torch.arange(10.0)), name
    assert os.path.isfile(tmp_path / "e.npz") and os.listdir(cwd) == []
    assert main(["copy", src, f"file://{tmp_path}/c.zarr"]) != 0  # exists: refused at its real path
    assert "exists; refusing to overwrite it" in capsys.readouterr().err
    before = sorted(os.listdir(tmp_path))
    for argv in (["import", str(tmp_path / "e.npz"), ""], ["export", src, " "], ["copy", src, ""]):
        assert main(argv) == 2, argv
        assert "is empty: name the file or memory to write" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == before and os.listdir(cwd) == []


def test_a_copy_leaves_partial_files_out_and_refuses_a_file_gone_while_it_copies(tmp_path, monkeypatch, capsys):
    """Found by a review: a ``*.partial`` file (a write in flight, renamed away any moment, or one a killed writer
    left) was copied as a file of the store, and a file gone between the listing and its copy failed the copy
    as ``FileNotFoundError`` instead of saying that a process writes the store."""
    from torchrl_robotmem.cli import copy_memory

    src = str(tmp_path / "m.zarr")
    with ZarrStorage(src, 100, env="E", goal_conditioned=False, chunk_rows=4) as st:
        st.set(slice(0, 10), TensorDict({"obs": torch.arange(10.0)}, [10]))
    left = os.path.join(src, "obs", "c.0.1234.partial")  # as a killed writer leaves one
    with open(left, "wb") as f:
        f.write(b"half a chunk")
    assert main(["copy", src, str(tmp_path / "c.zarr")]) == 0
    assert not any(name.endswith(".partial") for _, _, files in os.walk(tmp_path / "c.zarr") for name in files)
    files = copy_memory._files

    def listed_then_gone(fs, root):  # a file the listing saw, replaced by a writer before its copy
        return ["obs/c.9.gone", *files(fs, root)]

    monkeypatch.setattr(copy_memory, "_files", listed_then_gone)
    assert main(["copy", src, str(tmp_path / "d.zarr")]) == 2  # as the record changed while copying says it
    err = capsys.readouterr().err
    assert "changed while it was copied (a process is writing it" in err, err
    assert not (tmp_path / "d.zarr").exists()

@pytest.mark.parametrize("kind", ["tensor", "pytree"])
def test_an_import_of_a_tensor_or_pytree_memory_s_export_succeeds(tmp_path, capsys, kind):
    """Found by a review: the import wrote the memory, then its report read an ``episode`` column such a memory
    does not have: a traceback and exit 1, and a rerun was refused (the target existed)."""
    from torchrl.data import ReplayBuffer

    src = str(tmp_path / "t.zarr")
    data = torch.arange(30.0).reshape(10, 3)
    st = ZarrStorage(src, max_size=50, goal_conditioned=False)
    ReplayBuffer(storage=st, batch_size=4).extend(data if kind == "tensor" else {"a": data, "b": (data[:, 0], data)})
    st.close()
    assert main(["export", src, str(tmp_path / "t.npz")]) == 0
    capsys.readouterr()
    assert main(["import", str(tmp_path / "t.npz"), str(tmp_path / "u.zarr")]) == 0
    assert capsys.readouterr().out.strip() == f"imported 10 rows into {tmp_path / 'u.zarr'}"
    with ZarrStorage(str(tmp_path / "u.zarr"), read_only=True) as back, ZarrStorage(src, read_only=True) as before:
        assert len(back) == 10
        got, want = back[:10], before[:10]
        assert torch.equal(got, want) if kind == "tensor" else all(
            torch.equal(a, b) for a, b in zip(torch.utils._pytree.tree_leaves(got), torch.utils._pytree.tree_leaves(want)))


def test_copy_of_a_damaged_memory_names_the_source_and_what_mends_it(tmp_path, capsys):
    """Found by a review: the open of a sealed source reads no chunk, so the damage surfaced in the copy's own
    check: the error blamed the removed build, told to verify / repair it and to run the copy again."""
    src = str(tmp_path / "a.zarr")
    with ZarrStorage(src, 100, env="E", goal_conditioned=False) as st:
        st.set(slice(0, 10), TensorDict({"obs": torch.arange(10.0)}, [10]))
    with open(os.path.join(src, "obs", "c.0"), "wb") as f:
        f.write(b"bit rot")  # after the clean close: the row file still serves every row
    capsys.readouterr()
    assert main(["copy", src, str(tmp_path / "b.zarr")]) == 1
    err = capsys.readouterr().err
    assert f"{src!r} is damaged" in err and "obs/c.0" in err and f"robotmem repair {src}" in err, err
    assert "partial" not in err and "run it again" not in err
    assert not os.path.exists(tmp_path / "b.zarr") and sorted(os.listdir(tmp_path)) == ["a.zarr"]


@pytest.mark.parametrize("cell, said", [("nan", "--cell must be a finite size > 0, got nan"),
                                        ("inf", "--cell must be a finite size > 0, got inf"),
                                        ("1e-300", "is too small for goals of magnitude up to")])
def test_inspect_refuses_a_coverage_cell_it_cannot_count_in(memory, capsys, cell, said):
    """Found by a review: --cell nan and --cell 1e-300 reported 1 occupied cell (the floor overflowed int64)."""
    capsys.readouterr()
    assert main(["inspect", memory, "--cell", cell]) == 2
    assert said in capsys.readouterr().err


def test_inspect_of_a_group_as_the_goal_key_names_the_stored_columns(memory, capsys):
    """Found by a review: --goal-key next (a group of columns, not a column) was a traceback."""
    capsys.readouterr()
    assert main(["inspect", memory, "--goal-key", "next"]) == 2
    err = capsys.readouterr().err
    assert "the memory has no column 'next'; stored keys:" in err and "next/achieved_goal" in err
