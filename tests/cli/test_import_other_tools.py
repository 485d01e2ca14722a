"""``robotmem import`` of other tools' data, made by the tools themselves, and ``robotmem copy``.

* Stable-Baselines3: a ``HerReplayBuffer`` (2 envs) and a ``DictReplayBuffer``
  whose ring wrapped, saved by short real SAC runs on FetchReach-v4 with
  ``model.save_replay_buffer``;
* Minari: a dataset of FetchReach episodes recorded by Minari's own ``DataCollector``;
* a plain ``.npz`` of transitions from a gymnasium rollout (no ``__robotmem__``);
* float64 -> float32 by default, ``--keep-float64``;
* ``robotmem copy`` local -> local, local -> ``s3://`` -> local (a moto server), refusals;
* the three imported memories as ``prior=mix`` priors of one short recipe run.
"""
# ruff: noqa: F811  (the fixtures imported from _s3 are parameters of the tests)
from __future__ import annotations

import os

import numpy as np
import pytest
from _s3 import s3_server  # noqa: F401  (pytest fixture)
from training.test_her_recipe import run_recipe

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.cli import main
from torchrl_robotmem.cli.inspect import summarize

ENV = "FetchReach-v4"


def _fetch_env(max_steps: int):
    import gymnasium as gym
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    return gym.make(ENV, max_episode_steps=max_steps)


def _act(env, obs, episode: int) -> np.ndarray:
    """Odd episodes: a random action; even ones: straight for the goal (so that some rows succeed)."""
    if episode % 2:
        return env.action_space.sample()
    step = np.clip((obs["desired_goal"] - obs["achieved_goal"]) * 10.0, -1.0, 1.0)
    return np.append(step, 0.0).astype(np.float32)


def _sac_buffer(path, *, n_envs: int, her: bool, buffer_size: int, steps: int = 300):
    """Runs SAC for ``steps`` env steps on FetchReach-v4 and saves its replay buffer to ``path``; returns it."""
    import torch
    from stable_baselines3 import SAC, HerReplayBuffer
    from stable_baselines3.common.buffers import DictReplayBuffer
    from stable_baselines3.common.vec_env import DummyVecEnv

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        env = DummyVecEnv([lambda: _fetch_env(50)] * n_envs)
        model = SAC("MultiInputPolicy", env, replay_buffer_class=HerReplayBuffer if her else DictReplayBuffer,
                    learning_starts=100, buffer_size=buffer_size, batch_size=16, train_freq=(50, "step"),
                    gradient_steps=2, policy_kwargs={"net_arch": [16, 16]}, seed=0, device="cpu")
        model.learn(steps)
        model.save_replay_buffer(str(path))
    finally:
        torch.set_num_threads(threads)
    return model.replay_buffer


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    """The tools' files: SB3 buffers (HER with 2 envs; a wrapped DictReplayBuffer), a Minari dataset, a plain npz."""
    d = tmp_path_factory.mktemp("sources")
    out = {"dir": d}
    out["her"] = d / "her.pkl"
    out["her_buf"] = _sac_buffer(out["her"], n_envs=2, her=True, buffer_size=10_000)
    out["ring"] = d / "ring.pkl"
    out["ring_buf"] = _sac_buffer(out["ring"], n_envs=1, her=False, buffer_size=120)
    out["minari"] = _minari_dataset(d / "minari")
    out["npz"], out["npz_success"] = _plain_npz(d / "rollout.npz")
    return out


def _success_at_reset(env):
    """``env`` with ``is_success`` in its reset info too: ``DataCollector(record_infos=True)`` needs the same info keys
    at reset as at every step, and gymnasium-robotics' reset info is empty (Minari raises on the mismatch)."""
    import gymnasium as gym

    class SuccessAtReset(gym.Wrapper):
        def reset(self, **kwargs):
            obs, info = self.env.reset(**kwargs)
            hit = self.env.unwrapped.compute_reward(obs["achieved_goal"], obs["desired_goal"], info) == 0
            return obs, {**info, "is_success": np.float64(hit)}

    return SuccessAtReset(env)


def _minari_dataset(root) -> str:
    """4 episodes of 20 FetchReach steps recorded by Minari's own ``DataCollector``; the dataset's directory.

    ``DataCollector`` (``minari[create]``, which needs jax: in the ``dev`` extra) wraps the env, records every
    step with its infos (``is_success`` among them) and ``create_dataset`` writes the dataset with the env's
    spec and spaces, as a Minari user records one.
    """
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        import minari
        from minari import DataCollector

        env = DataCollector(_success_at_reset(_fetch_env(20)), record_infos=True)
        env.action_space.seed(0)
        for ep in range(4):
            obs, _ = env.reset(seed=ep)
            while True:
                obs, _, terminated, truncated, _ = env.step(_act(env, obs, ep))
                if terminated or truncated:
                    break
        env.create_dataset("fetchreach/random-v0", algorithm_name="random", description="random FetchReach-v4 steps",
                           eval_env=ENV, author="test", author_email="test@example.com",
                           code_permalink="tests/cli/test_import_other_tools.py")
        env.close()
        assert minari.list_local_datasets()  # written where MINARI_DATASETS_PATH points
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH")
        else:
            os.environ["MINARI_DATASETS_PATH"] = old
    return str(root / "fetchreach" / "random-v0")


def _plain_npz(path):
    """3 episodes of 20 FetchReach steps saved with ``np.savez`` in the documented plain layout (float64)."""
    env = _fetch_env(20)
    env.action_space.seed(1)
    cols = {k: [] for k in ("observation", "next_observation", "achieved_goal", "next_achieved_goal", "desired_goal",
                            "action", "reward", "terminated", "truncated", "is_success")}
    for ep in range(3):
        obs, _ = env.reset(seed=10 + ep)
        while True:
            action = _act(env, obs, ep)
            nxt, reward, terminated, truncated, info = env.step(action)
            for k, v in (("observation", obs["observation"]), ("next_observation", nxt["observation"]),
                         ("achieved_goal", obs["achieved_goal"]), ("next_achieved_goal", nxt["achieved_goal"]),
                         ("desired_goal", obs["desired_goal"]), ("action", action), ("reward", reward),
                         ("terminated", terminated), ("truncated", truncated), ("is_success", info["is_success"])):
                cols[k].append(v)
            obs = nxt
            if terminated or truncated:
                break
    arrays = {k: np.asarray(v) for k, v in cols.items()}
    np.savez(path, **arrays)
    return path, arrays["is_success"]


def _import(capsys, *args) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main(["import", *map(str, args)])
    out = capsys.readouterr()
    return rc, out.out, out.err


def _episodes(path) -> list[np.ndarray]:
    st = ZarrStorage(path, read_only=True)
    ep = st["episode"].numpy()
    st.close()
    firsts = sorted(np.unique(ep, return_index=True)[1])
    return [np.flatnonzero(ep == ep[i]) for i in firsts]


def _continuous(path) -> None:
    """Within each episode a row's next observation is the next row's observation (the source's order kept)."""
    st = ZarrStorage(path, read_only=True)
    obs, nxt = st["observation"].numpy(), st["next", "observation"].numpy()
    st.close()
    for rows in _episodes(path):
        np.testing.assert_array_equal(nxt[rows[:-1]], obs[rows[1:]])


# -- Stable-Baselines3 ---------------------------------------------------------------------------------


def test_sb3_her_buffer_is_refused_without_trust_pickle_and_imported_with_it(sources, tmp_path, capsys):
    target = tmp_path / "sb3.zarr"
    rc, _, err = _import(capsys, sources["her"], target, "--format", "sb3")
    assert rc == 2 and "a pickle: loading it executes code stored in the file" in err and "--trust-pickle" in err
    assert not target.exists() and os.listdir(tmp_path) == []
    rc, _, err = _import(capsys, sources["her"], target, "--trust-pickle")  # *.pkl: sb3; no --env, no is_success
    assert rc == 2 and "pass --env ENV_ID" in err and not target.exists()

    rc, out, _ = _import(capsys, sources["her"], target, "--trust-pickle", "--env", ENV)
    assert rc == 0, out
    assert f"is_success recomputed from {ENV}'s compute_reward for 300 rows" in out
    assert "float64 stored as float32" in out and "imported 300 rows (6 episodes)" in out
    buf = sources["her_buf"]
    assert buf.n_envs == 2 and buf.pos == 150 and not buf.full
    st = ZarrStorage(target, read_only=True)
    assert len(st) == 300 and list(st.env_names) == [ENV] and st["observation"].dtype.is_floating_point
    assert str(st["observation"].dtype) == "torch.float32"
    # env 0's rows, then env 1's, oldest first: the buffer's own values
    obs = buf.observations["observation"].astype(np.float32)  # float64 in the buffer, stored as float32
    np.testing.assert_array_equal(st["observation"][:150].numpy(), obs[:150, 0])
    np.testing.assert_array_equal(st["action"][150:].numpy(), buf.actions[:150, 1])
    np.testing.assert_array_equal(st["next", "reward"][:, 0].numpy(),
                                  np.concatenate([buf.rewards[:150, 0], buf.rewards[:150, 1]]))
    # sparse reward: success exactly where the env's reward was 0
    np.testing.assert_array_equal(st["next", "is_success"].numpy(), (st["next", "reward"][:, 0] == 0).float().numpy())
    assert st["next", "truncated"].sum().item() == 6 and not st["next", "terminated"].any()
    st.close()
    assert [len(r) for r in _episodes(target)] == [50] * 6
    _continuous(target)
    s = summarize(str(target))
    assert s["episodes"] == s["finished_episodes"] == 6


def test_sb3_wrapped_ring_is_read_oldest_first(sources, tmp_path, capsys):
    buf = sources["ring_buf"]
    assert buf.full and buf.pos == 300 % 120
    target = tmp_path / "ring.zarr"
    rc, out, _ = _import(capsys, sources["ring"], target, "--trust-pickle", "--env", ENV, "--format", "sb3")
    assert rc == 0 and "imported 120 rows (3 episodes)" in out, out
    # steps 180..299 survive: the end of an episode cut by the ring (20 rows), then two whole episodes
    assert [len(r) for r in _episodes(target)] == [20, 50, 50]
    st = ZarrStorage(target, read_only=True)
    np.testing.assert_array_equal(st["observation"][0].numpy(),
                                  buf.observations["observation"][buf.pos, 0].astype(np.float32))
    success, reward = st["next", "is_success"].numpy(), st["next", "reward"][:, 0].numpy()
    assert success.sum() > 0 and np.array_equal(success, (reward == 0).astype(np.float32))
    st.close()
    _continuous(target)


# -- Minari, plain npz, float64 ------------------------------------------------------------------------


def test_minari_dataset_of_fetch_episodes(sources, tmp_path, capsys):
    target = tmp_path / "minari.zarr"
    rc, out, _ = _import(capsys, sources["minari"], target, "--env", ENV)
    assert rc == 0 and "imported 80 rows (4 episodes)" in out, out
    assert "float64 stored as float32" in out and "observation" in out
    st = ZarrStorage(target, read_only=True)
    assert {str(st[k].dtype) for k in ("observation", "desired_goal", ("next", "achieved_goal"))} == {"torch.float32"}
    success, reward = st["next", "is_success"].numpy(), st["next", "reward"][:, 0].numpy()
    assert success.sum() > 0 and np.array_equal(success, (reward == 0).astype(np.float32))
    st.close()
    assert [len(r) for r in _episodes(target)] == [20] * 4
    _continuous(target)


@pytest.mark.parametrize("how", ["external storage", "external link"])
def test_a_minari_dataset_whose_data_lies_in_another_file_is_refused(sources, tmp_path, capsys, how):
    """HDF5 lets a dataset keep its bytes in any file (external raw storage, external links): an import would copy
    a private file into the memory. The import refuses, naming the dataset, and creates nothing."""
    import shutil

    import h5py

    ds = tmp_path / "evil-v0"
    shutil.copytree(sources["minari"], ds)
    secret = tmp_path / "private" / "id_rsa"
    secret.parent.mkdir()
    with h5py.File(ds / "data" / "main_data.hdf5", "a") as f:
        actions = f["episode_0/actions"]
        shape, dtype = actions.shape, actions.dtype
        secret.write_bytes(b"private key bytes " * (int(np.prod(shape)) * dtype.itemsize // 18 + 1))
        del f["episode_0/actions"]
        if how == "external storage":
            f.create_dataset("episode_0/actions", shape=shape, dtype=dtype,
                             external=[(str(secret), 0, int(np.prod(shape)) * dtype.itemsize)])
        else:
            other = tmp_path / "private" / "other.hdf5"
            with h5py.File(other, "w") as g:
                g.create_dataset("actions", data=np.zeros(shape, dtype))
            f["episode_0/actions"] = h5py.ExternalLink(str(other), "/actions")
    target = tmp_path / "imported.zarr"
    rc, _, err = _import(capsys, ds, target, "--env", ENV)
    assert rc != 0 and "episode_0/actions" in err and "outside it" in err, err
    assert not target.exists()


def test_plain_npz_and_float64(sources, tmp_path, capsys):
    target = tmp_path / "plain.zarr"
    rc, out, _ = _import(capsys, sources["npz"], target)
    assert rc == 0 and "imported 60 rows (3 episodes)" in out, out
    assert "float64 stored as float32 (--keep-float64 keeps it): achieved_goal, desired_goal, " in out
    st = ZarrStorage(target, read_only=True)
    np.testing.assert_array_equal(st["next", "is_success"].numpy(), sources["npz_success"].astype(np.float32))
    assert sources["npz_success"].sum() > 0
    assert str(st["observation"].dtype) == "torch.float32" and st["next", "truncated"].sum().item() == 3
    st.close()
    _continuous(target)
    # --keep-float64 keeps them
    rc, out, _ = _import(capsys, sources["npz"], tmp_path / "f64.zarr", "--keep-float64")
    assert rc == 0 and "float64 stored" not in out
    st = ZarrStorage(tmp_path / "f64.zarr", read_only=True)
    assert str(st["observation"].dtype) == str(st["next", "achieved_goal"].dtype) == "torch.float64"
    st.close()
    # without is_success: recomputed from --env's compute_reward, the same as the env's own
    z = dict(np.load(sources["npz"]))
    z.pop("is_success")
    np.savez(tmp_path / "nosucc.npz", **z, extra=np.zeros(60))
    rc, out, _ = _import(capsys, tmp_path / "nosucc.npz", tmp_path / "re.zarr", "--env", ENV)
    assert rc == 0 and f"is_success recomputed from {ENV}'s compute_reward for 60 rows" in out
    assert "ignored arrays not in the plain-npz layout: extra" in out
    np.testing.assert_array_equal(ZarrStorage(tmp_path / "re.zarr", read_only=True)["next", "is_success"].numpy(),
                                  sources["npz_success"].astype(np.float32))


@pytest.mark.parametrize("change, message", [
    (lambda z: z.pop("next_observation"), r"without the arrays \['next_observation'\]"),
    (lambda z: z.update(reward=np.zeros((60, 2))), r"array 'reward' has shape \[60, 2\]"),
    (lambda z: z.update(action=np.zeros((59, 4))), r"array 'action' has shape \[59, 4\]; every array holds one row"),
    (lambda z: z.update(next_achieved_goal=np.zeros((60, 2))), r"'next_achieved_goal' has shape \[60, 2\], "),
    (lambda z: [z.pop(k) for k in ("terminated", "truncated")], r"one of terminated/truncated/done/episode"),
])
def test_a_bad_plain_npz_names_the_array(change, message, sources, tmp_path, capsys):
    import re

    z = dict(np.load(sources["npz"]))
    change(z)
    np.savez(tmp_path / "bad.npz", **z)
    rc, _, err = _import(capsys, tmp_path / "bad.npz", tmp_path / "m.zarr")
    assert rc == 2 and re.search(message, err), err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "m.zarr").exists()


# -- robotmem copy -------------------------------------------------------------------------------------


@pytest.fixture
def small_memory(sources, tmp_path):
    path = tmp_path / "src.zarr"
    assert main(["import", str(sources["npz"]), str(path), "--env", ENV]) == 0
    return path


@pytest.mark.filterwarnings("ignore:Duplicate name")  # a zip store rewrites its zarr.json
def test_copy_local_and_refusals(small_memory, tmp_path, capsys):
    dst = tmp_path / "sub" / "copy.zarr"
    capsys.readouterr()
    assert main(["copy", str(small_memory), str(dst)]) == 0
    out = capsys.readouterr().out
    assert "copied 60 rows" in out and "verified: intact (60 rows" in out
    a, b = ZarrStorage(small_memory, read_only=True), ZarrStorage(dst, read_only=True)
    assert a[:].exclude("run").to_dict().keys() == b[:].exclude("run").to_dict().keys()
    assert (a[:] == b[:]).all() and a.env_names == b.env_names
    a.close(), b.close()
    assert sorted(os.listdir(dst.parent)) == ["copy.zarr"]  # the hidden build was renamed into place
    before = sorted(p.name for p in dst.rglob("*"))
    assert main(["copy", str(small_memory), str(dst)]) == 2
    assert "exists; refusing to overwrite it" in capsys.readouterr().err
    assert sorted(p.name for p in dst.rglob("*")) == before
    assert main(["copy", str(tmp_path / "nothing.zarr"), str(tmp_path / "x.zarr")]) == 2
    assert main(["copy", str(small_memory), str(small_memory / "inside.zarr")]) == 2
    assert "inside it" in capsys.readouterr().err
    # a single-file (*.zip) memory: copied byte for byte
    rows = ZarrStorage(small_memory, read_only=True)[:]
    with ZarrStorage(tmp_path / "z.zip", 100, env=ENV) as z:
        z.set(slice(0, 60), rows.exclude("episode", "run", "env"))
    assert main(["copy", str(tmp_path / "z.zip"), str(tmp_path / "z2.zip")]) == 0
    assert "the same bytes as the source" in capsys.readouterr().out
    assert (tmp_path / "z.zip").read_bytes() == (tmp_path / "z2.zip").read_bytes()
    assert not (tmp_path / "x.zarr").exists()
    # between the layouts (a review found both failing with misleading errors, one saying to run it again)
    capsys.readouterr()
    assert main(["copy", str(tmp_path / "z.zip"), str(tmp_path / "d.zarr")]) == 2
    assert "copy to a path ending in .zip" in capsys.readouterr().err
    assert main(["copy", str(small_memory), str(tmp_path / "d.zip")]) == 2
    assert "copy to a path not ending in .zip" in capsys.readouterr().err
    assert not (tmp_path / "d.zarr").exists() and not (tmp_path / "d.zip").exists()
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".d.")]  # no build left beside them either
    # import of a memory says to copy it
    assert main(["import", str(small_memory), str(tmp_path / "new.zarr")]) == 2
    err = capsys.readouterr().err
    assert "is a torchrl_robotmem memory; to copy it use: robotmem copy" in err and "Minari" not in err
    assert not (tmp_path / "new.zarr").exists()


def test_copy_to_s3_and_back(small_memory, tmp_path, capsys, s3_server, monkeypatch):
    from _s3 import new_bucket

    for k, v in s3_server.child_env().items():
        if k.startswith("AWS_"):
            monkeypatch.setenv(k, v)
    url = f"s3://{new_bucket(s3_server)}/copy.zarr"
    capsys.readouterr()
    assert main(["copy", str(small_memory), url]) == 0
    assert "copied 60 rows" in capsys.readouterr().out
    remote = ZarrStorage(url, read_only=True, storage_options=s3_server.storage_options)
    assert len(remote) == 60 and list(remote.env_names) == [ENV]
    remote.close()
    assert main(["copy", str(small_memory), url]) == 2  # exists
    assert "exists; refusing to overwrite it" in capsys.readouterr().err
    back = tmp_path / "back.zarr"
    assert main(["copy", url, str(back)]) == 0
    a, b = ZarrStorage(small_memory, read_only=True), ZarrStorage(back, read_only=True)
    assert (a[:] == b[:]).all()
    a.close(), b.close()


# -- the imported memories as priors of a recipe run ---------------------------------------------------


def test_imported_memories_are_priors_of_a_recipe_run(sources, tmp_path):
    paths = [tmp_path / "sb3.zarr", tmp_path / "minari.zarr", tmp_path / "plain.zarr"]
    assert main(["import", str(sources["her"]), str(paths[0]), "--trust-pickle", "--env", ENV]) == 0
    assert main(["import", sources["minari"], str(paths[1]), "--env", ENV]) == 0
    assert main(["import", str(sources["npz"]), str(paths[2]), "--env", ENV]) == 0
    s = run_recipe(tmp_path, "env=reach", f"memory.path={tmp_path / 'own.zarr'}", "prior=mix",
                   f"prior.paths=[{','.join(map(str, paths))}]")
    assert s["frames"] == 50 and s["memory_rows_after"] == 50 and s["updates"] > 0
    # each prior opened as it was imported: rows, episodes and a success column
    assert [(p["rows"], p["episodes"], p["success_column"]) for p in s["priors"]] == [(300, 6, True), (80, 4, True),
                                                                                      (60, 3, True)]
    assert [len(ZarrStorage(p, read_only=True)) for p in paths] == [300, 80, 60]  # only read
