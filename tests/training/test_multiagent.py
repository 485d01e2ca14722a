"""MaMuJoCo (multi-agent MuJoCo) through TorchRL into a ZarrStorage, with the agent dimension:
real envs (HalfCheetah 2x3), a real Collector, real stores reopened in fresh processes, and a
short MADDPG run of recipes/multiagent reading the memory.

Run as a script, this file is the fresh process: ``python tests/training/test_multiagent.py collect|dump ...``."""
from __future__ import annotations

import json
import subprocess
import sys
import warnings
from functools import partial
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "multiagent" / "train.py"
STEPS = 30  # episode length: 200 frames hold 6 whole episodes and one left open
AGENT_KEYS = [("agents", "observation"), ("agents", "action"), ("next", "agents", "observation"),
              ("next", "agents", "reward"), ("next", "agents", "done"), ("next", "agents", "terminated"),
              ("next", "agents", "truncated")]

warnings.filterwarnings("ignore", message="PettingZoo in TorchRL is tested")


def collect(path: str, frames: int, seed: int):
    """One writing session: a Collector on MaMuJoCo HalfCheetah 2x3 (random actions) into ZarrStorage(path)."""
    from torchrl.collectors import Collector
    from torchrl.data import TensorDictReplayBuffer

    from torchrl_robotmem.envs_multiagent import make_mamujoco_env
    from torchrl_robotmem.storage.zarr_storage import ZarrStorage

    torch.manual_seed(int(seed))
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path, max_size=1000, env="HalfCheetah-2x3", goal_conditioned=False), batch_size=16)
    make = partial(make_mamujoco_env, "HalfCheetah", "2x3", max_episode_steps=STEPS, seed=int(seed))
    collector = Collector(make, None, frames_per_batch=100, total_frames=int(frames))
    written = [data.reshape(-1) for data in collector]
    for data in written:
        rb.extend(data)
    collector.shutdown()
    rb.storage.close()
    return torch.cat(written)


def dump(path: str, out: str) -> None:
    """Reads every stored row with its tags (a read-only open) and saves its leaves as ``{"a/b": tensor}``."""
    from torchrl_robotmem.storage.zarr_storage import ZarrStorage

    storage = ZarrStorage(path, read_only=True, sample_tags=True)
    rows = storage[:]
    leaves = {"/".join((k,) if isinstance(k, str) else k): v.clone() for k, v in rows.items(True, True)}
    torch.save({"leaves": leaves, "agents_batch": list(rows["agents"].batch_size)}, out)


def _fresh(*args: str) -> None:
    proc = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]


def _dumped(tmp_path: Path, store: Path, name: str) -> dict:
    _fresh("dump", str(store), str(tmp_path / name))
    saved = torch.load(tmp_path / name, weights_only=True)
    assert saved["agents_batch"] == [len(saved["leaves"]["episode"]), 2]  # the group's agent dim, read back
    return saved["leaves"]


def test_env_specs_and_agent_dims():
    from torchrl.envs.utils import check_env_specs

    from torchrl_robotmem.envs_multiagent import agent_names, make_mamujoco_env

    env = make_mamujoco_env("HalfCheetah", "2x3", max_episode_steps=STEPS, seed=0)
    check_env_specs(env)  # fails without FixedInfoKeys (reset and step infos differ)
    assert agent_names(env) == ["agent_0", "agent_1"]
    td = env.rollout(STEPS + 5, break_when_any_done=False)
    assert td["agents", "observation"].shape == (STEPS + 5, 2, 12)
    assert td["agents", "observation"].dtype == torch.float32
    assert td["agents", "action"].shape == (STEPS + 5, 2, 3)
    assert td["next", "agents", "reward"].shape == td["next", "agents", "done"].shape == (STEPS + 5, 2, 1)
    assert td["next", "done"].shape == (STEPS + 5, 1)
    ends = td["next", "done"].squeeze(-1).nonzero().flatten().tolist()
    assert ends == [STEPS - 1]
    assert td["next", "agents", "truncated"][STEPS - 1].all() and not td["next", "agents", "terminated"].any()
    with_info = make_mamujoco_env("HalfCheetah", "2x3", max_episode_steps=STEPS, seed=0, info_keys=["x_velocity"])
    check_env_specs(with_info)  # the kept info keys are read at every step
    assert with_info.rollout(3)["next", "agents", "info", "x_velocity"].shape == (3, 2)


@pytest.mark.full
def test_memory_round_trip_with_agent_dims_and_resume(tmp_path):
    store = tmp_path / "ma.zarr"
    first = collect(str(store), 200, seed=0)  # this process: the first writing session
    one = _dumped(tmp_path, store, "one.pt")  # a fresh process reads it back
    # bit-exact: every collected leaf, with its agent dimension
    for key in first.keys(True, True):
        name = "/".join((key,) if isinstance(key, str) else key)
        assert torch.equal(one[name], first.get(key)), name
    for key in AGENT_KEYS:
        assert one["/".join(key)].shape[:2] == (200, 2), key
    # episode tags from the global done flags, over collector batches (episodes span batch borders)
    assert one["episode"].tolist() == [i // STEPS for i in range(200)]
    assert one["run"].tolist() == [0] * 200

    # a second session in a fresh process appends, then reads the store back (read-only) after closing it
    _fresh("collect", str(store), "100", "1", str(tmp_path / "two.pt"))
    saved = torch.load(tmp_path / "two.pt", weights_only=True)
    two = saved["leaves"]
    assert saved["agents_batch"] == [300, 2]
    assert two["run"].tolist() == [0] * 200 + [1] * 100
    for name, value in one.items():  # the old rows are untouched except the open episode's end
        if name in ("next/done", "next/truncated", "next/agents/done", "next/agents/truncated"):
            continue
        assert torch.equal(two[name][:200], value), name
    # the episode the first session left open (rows 180-199) was closed at its last row, for every done key
    for name in ("next/done", "next/truncated"):
        assert two[name][199].all() and torch.equal(two[name][:199], one[name][:199])
    for name in ("next/agents/done", "next/agents/truncated"):
        assert two[name][199].all(), f"{name}: the agents' flags of the closed episode"
    assert not two["next/terminated"][199].any() and not two["next/agents/terminated"][199].any()
    # new episodes get new ids: 7 came before (0-6), the new session's start at 7
    assert two["episode"][200:].tolist() == [7 + i // STEPS for i in range(100)]
    assert two["agents/observation"][200:].shape == (100, 2, 12)


def test_sampled_groups_keep_their_agent_dim(tmp_path):
    """As with LazyTensorStorage, a sampled batch's ("agents") TensorDict has batch [B, n_agents]."""
    from torchrl.data import TensorDictReplayBuffer

    from torchrl_robotmem.storage.zarr_storage import ZarrStorage

    data = collect(str(tmp_path / "ma.zarr"), 100, seed=0)
    rb = TensorDictReplayBuffer(storage=ZarrStorage(tmp_path / "ma.zarr", read_only=True), batch_size=8)
    batch = rb.sample()
    assert batch["agents"].batch_size == batch["next", "agents"].batch_size == (8, 2)
    assert batch["collector"].batch_size == (8,)
    assert rb.storage[5]["agents"].batch_size == (2,)
    assert torch.equal(batch["agents", "observation"], data["agents", "observation"][batch["index"]])
    assert torch.equal(batch["agents"][:, 1]["action"], data["agents", "action"][batch["index"], 1])


def _run_recipe(tmp_path: Path, out: str, *overrides: str, memory: str = "mem.zarr") -> dict:
    tiny = ["collector.total_frames=200", "collector.frames_per_batch=100", "collector.init_random_frames=150",
            "env.max_episode_steps=50", "train.minibatch_size=32", "train.updates_per_batch=5",
            "model.num_cells=16", "eval.episodes=1", "exploration.annealing_frames=400"]
    proc = subprocess.run(
        [sys.executable, str(RECIPE), *tiny, f"memory.path={tmp_path / memory}", *overrides,
         f"hydra.run.dir={tmp_path / out}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads((tmp_path / out / "summary.json").read_text())


def test_maddpg_recipe_trains_on_the_memory_and_resumes(tmp_path):
    first = _run_recipe(tmp_path, "one")
    assert first["algo"] == "HetMADDPG" and first["frames"] == 200
    assert first["memory_rows_before"] == 0 and first["memory_rows_after"] == 200
    assert first["updates"] == 5  # the first batch is random warm-up: updates start at 150 rows
    assert first["memory_runs"] == [0] and first["memory_episodes"] == 4
    assert (tmp_path / "mem.zarr-agent.pt").is_file()
    second = _run_recipe(tmp_path, "two", "memory.resume_agent=true", "memory.pretrain_updates=3")
    assert second["memory_rows_before"] == 200 and second["memory_rows_after"] == 400
    assert second["agent_frames_before"] == 200
    assert second["updates"] == 3 + 2 * 5  # stored rows: updates before the first frame and after each batch
    assert second["memory_runs"] == [0, 1] and second["memory_episodes"] == 8
    scalars = next((tmp_path / "two" / "multiagent_logging").glob("*/scalars"))
    assert (scalars / "loss_value.csv").read_text().splitlines()[-1].startswith("200,")


@pytest.mark.full
def test_maddpg_on_zarr_storage_trains_as_on_lazy_tensor_storage(tmp_path):
    """The memory is a drop-in replay storage: same seed, same batches, same networks, same returns."""
    zarr = _run_recipe(tmp_path, "zarr")
    lazy = _run_recipe(tmp_path, "lazy", "replay_buffer.storage._target_=torchrl.data.LazyTensorStorage",
                       memory="lazy.zarr")
    assert lazy["updates"] == zarr["updates"] == 5
    assert lazy["return_after"] == zarr["return_after"]
    assert lazy["train_episode_returns"] == zarr["train_episode_returns"]
    assert "memory_runs" not in lazy and not (tmp_path / "lazy.zarr").exists()  # nothing persisted


if __name__ == "__main__":
    command, *rest = sys.argv[1:]
    if command == "collect":
        collect(*rest[:3])
        if len(rest) > 3:
            dump(rest[0], rest[3])
    else:
        dump(*rest)
