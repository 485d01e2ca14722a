"""The memory on a CUDA device: ZarrStorage's RAM mirror, sampler, recall, transform, HER, collector.

Skipped without a GPU (CI has none); run on a GPU machine with
``pytest tests/test_cuda.py``. Each test compares the CUDA path with the same
data on the CPU, so a device mix-up shows as a wrong device or a wrong value,
not only as an exception.
"""
from __future__ import annotations

import os

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import HERReplayBuffer, TensorDictReplayBuffer
from torchrl.envs.utils import RandomPolicy

from torchrl_robotmem import GoalSimilaritySampler, RecallTransform, ZarrStorage, make_env, make_reward_fn, recall
from torchrl_robotmem.goal_index import GoalIndex

# ROBOTMEM_TEST_DEVICE=cpu runs the same checks on the CPU (to check the tests themselves without a GPU)
DEVICE = os.environ.get("ROBOTMEM_TEST_DEVICE", "cuda")
pytestmark = pytest.mark.skipif(DEVICE == "cuda" and not torch.cuda.is_available(), reason="needs a CUDA device")
CUDA = torch.device(DEVICE, 0) if DEVICE == "cuda" else torch.device(DEVICE)


def _transitions(n: int, episode_len: int = 10, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    achieved = torch.rand(n, 3, generator=g)
    return TensorDict({
        "observation": torch.randn(n, 25, generator=g),
        "desired_goal": torch.rand(n, 3, generator=g),
        "achieved_goal": achieved,
        "action": torch.rand(n, 4, generator=g) * 2 - 1,
        ("next", "observation"): torch.randn(n, 25, generator=g),
        ("next", "achieved_goal"): achieved + 0.01,
        ("next", "desired_goal"): torch.rand(n, 3, generator=g),
        ("next", "reward"): -torch.ones(n, 1),
        ("next", "is_success"): (torch.rand(n, generator=g) < 0.3).float(),
        ("next", "done"): (torch.arange(n) % episode_len == episode_len - 1).unsqueeze(-1),
        ("next", "truncated"): (torch.arange(n) % episode_len == episode_len - 1).unsqueeze(-1),
        ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
        ("collector", "traj_ids"): torch.arange(n) // episode_len,
    }, batch_size=[n])


def test_cuda_mirror_round_trip_and_reopen(tmp_path):
    """device="cuda": rows written from CUDA or CPU tensors come back on CUDA, and after a reopen."""
    data = _transitions(300)
    path = tmp_path / "m.zarr"
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 1000, env="FetchPush-v4", device=DEVICE), batch_size=32)
    rb.extend(data[:200].to(CUDA))
    rb.extend(data[200:])  # a CPU batch into a CUDA mirror
    stored = rb.storage[:300]
    assert stored.device == CUDA and stored["observation"].device == CUDA
    assert torch.equal(stored["observation"].cpu(), data["observation"])
    assert torch.equal(stored["next", "is_success"].cpu(), data["next", "is_success"])
    batch = rb.sample()
    assert batch["observation"].device == CUDA and batch.batch_size == (32,)
    rb.storage.close()

    reopened = ZarrStorage(path, device=DEVICE)
    try:
        assert len(reopened) == 300
        assert torch.equal(reopened[:300]["action"].cpu(), data["action"])
        assert reopened["episode"].max().item() == 29  # 10-row episodes
    finally:
        reopened.close()
    on_cpu = ZarrStorage(path, read_only=True)  # the same store read into a CPU mirror
    try:
        assert on_cpu[:300]["action"].device.type == "cpu"
        assert torch.equal(on_cpu[:300]["action"], data["action"])
    finally:
        on_cpu.close()


def test_cuda_bad_input_leaves_the_store_unchanged(tmp_path):
    data = _transitions(50)
    storage = ZarrStorage(tmp_path / "m.zarr", 100, device=DEVICE)
    rb = TensorDictReplayBuffer(storage=storage)
    rb.extend(data.to(CUDA))
    bad = data[:10].to(CUDA)
    bad["observation"] = torch.zeros(10, 24, device=CUDA)
    with pytest.raises((ValueError, RuntimeError), match="observation"):
        rb.extend(bad)
    assert len(rb) == 50
    assert torch.equal(storage[:50]["observation"].cpu(), data["observation"])
    storage.close()


def test_cuda_sampler_matches_cpu(tmp_path):
    """GoalSimilaritySampler over a CUDA mirror: the same rows' distances as over a CPU mirror."""
    data = _transitions(1000)
    query = torch.tensor([0.5, 0.5, 0.5])
    out = {}
    for i, device in enumerate(("cpu", DEVICE)):
        rb = TensorDictReplayBuffer(
            storage=ZarrStorage(tmp_path / f"{i}.zarr", 2000, device=device),
            sampler=GoalSimilaritySampler(temperature=0.02), batch_size=256)
        rb.extend(data)
        torch.manual_seed(0)
        with rb.sampler.query(query.to(device)):
            batch = rb.sample()
        assert batch["observation"].device.type == device
        goals = batch["next", "achieved_goal"].cpu()
        distance = batch["goal_distance"].cpu()
        torch.testing.assert_close(distance, (goals - query).norm(dim=-1))
        out[device] = distance
        rb.storage.close()
    # sampling near the query: far nearer than uniform rows (mean distance of a uniform row here ~0.48)
    for device, distance in out.items():
        assert distance.mean() < 0.2, device


def test_cuda_recall_matches_cpu(tmp_path):
    data = _transitions(500)
    queries = torch.rand(16, 3, generator=torch.Generator().manual_seed(1))
    results = {}
    for i, device in enumerate(("cpu", DEVICE)):
        storage = ZarrStorage(tmp_path / f"{i}.zarr", 1000, device=device)
        rb = TensorDictReplayBuffer(storage=storage)
        rb.extend(data)
        out = recall(rb, queries.to(device), k=5, success_only=True)
        distance, row, mask = GoalIndex.for_storage(storage).search(queries.to(device), k=5, one_per_episode=True)
        results[device] = (out["index"].cpu(), out["distance"].cpu(), out["action"].cpu(),
                           distance.cpu(), row.cpu(), mask.cpu())
        storage.close()
    for a, b in zip(results["cpu"], results[DEVICE]):
        torch.testing.assert_close(a, b)
    index, distance, action = results["cpu"][:3]
    assert bool((data["next", "is_success"][index.flatten()] > 0.5).all())
    torch.testing.assert_close(action.reshape(-1, 4), data["action"][index.flatten()])


def test_cuda_env_recall_transform(tmp_path):
    """RecallTransform on an env living on CUDA, over a CUDA-mirrored memory of real FetchPush rows."""
    path = tmp_path / "push.zarr"
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 5000, env="FetchPush-v4", device=DEVICE))
    collector = Collector(lambda: make_env("FetchPush-v4", seed=0), RandomPolicy(make_env("FetchPush-v4").action_spec),
                          frames_per_batch=100, total_frames=300, device=DEVICE)
    for data in collector:
        assert data.device == CUDA
        rb.extend(data)
    collector.shutdown()
    assert len(rb) == 300

    outs = {}
    for device, memory in ((DEVICE, rb), ("cpu", str(path))):
        env = make_env("FetchPush-v4", seed=1, device=device,
                       transforms=[RecallTransform(memory, k=3, context_keys={"action": "prior_actions"})])
        try:
            rb.storage.flush()
            td = env.reset()
            assert td["prior_goals"].device.type == device
            assert td["prior_goals_mask"].all()
            assert bool((td["prior_goals_dist"][:-1] <= td["prior_goals_dist"][1:]).all())
            rollout = env.rollout(5)
            assert rollout["next", "prior_actions"].shape == (5, 3, 4)
            outs[device] = td.select("prior_goals", "prior_goals_dist", "prior_actions").cpu()
        finally:
            env.close()
    torch.testing.assert_close(outs[DEVICE], outs["cpu"])
    rb.storage.close()


def test_cuda_her_over_zarr_samples_on_the_device(tmp_path):
    """HERReplayBuffer over ZarrStorage(device="cuda"): relabelled, rewarded batches on the GPU, as on the CPU.

    TorchRL 0.14.1's HER keeps episode bounds on the CPU while a CUDA
    ``LazyTensorStorage`` draws CUDA indices (a device mismatch in
    ``_sample_goal_indices``). ZarrStorage draws its indices on the CPU
    (``storage/indices.py``), so the same seed gives the same rows on either
    device; relabelled rewards on the GPU come from ``GoalRewardFn.torch_reward``
    (no host round trip) and equal the env's own.
    """
    env = make_env("FetchPush-v4", seed=0)
    try:
        data = env.rollout(200, break_when_any_done=False)
    finally:
        env.close()
    reward_fn = make_reward_fn("FetchPush-v4")
    batches = {}
    for device in (DEVICE, "cpu"):
        storage = ZarrStorage(tmp_path / f"her-{device}.zarr", 1000, env="FetchPush-v4", device=device)
        her = HERReplayBuffer(reward_fn, her_ratio=0.8, strategy="future", achieved_goal_key=("next", "achieved_goal"),
                              storage=storage, batch_size=512)
        her.extend(data)
        torch.manual_seed(0)
        batch = her.sample()
        want = torch.device("cpu") if device == "cpu" else CUDA
        assert batch["observation"].device == want and batch["next", "reward"].device == want
        batches[device] = batch.cpu()
        storage.close()
    gpu, cpu = batches[DEVICE], batches["cpu"]
    for key in ("observation", "desired_goal", ("next", "achieved_goal"), "action"):
        assert torch.equal(gpu[key], cpu[key]), key
    assert (gpu["desired_goal"] != data["desired_goal"][0]).any()  # relabelled rows are there
    distance = torch.linalg.vector_norm(cpu["next", "achieved_goal"].double() - cpu["desired_goal"].double(), dim=-1)
    clear = (distance - 0.05).abs() > 1e-9  # the env's threshold; float64 rounding aside, both must agree
    assert torch.equal(gpu["next", "reward"][clear], cpu["next", "reward"][clear])


def _recipe(tmp_path, *overrides: str, out: str = "out", variants: bool = False) -> dict:
    """recipes/her/train.py with ``device=DEVICE``, a few dozen frames (tests/training/test_her_recipe.py's TINY).

    ``variants``: ``python -m experiments.prior_variants.train`` (the recipe with the prior-memory variants).
    """
    import json
    import subprocess
    import sys

    from training.test_her_recipe import RECIPE_DIR, ROOT, TINY

    train = ["-m", "experiments.prior_variants.train"] if variants else [str(RECIPE_DIR / "train.py")]
    proc = subprocess.run(
        [sys.executable, *train, *TINY, f"device={DEVICE}", *overrides, f"hydra.run.dir={tmp_path / out}"],
        cwd=ROOT if variants else tmp_path, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads((tmp_path / out / "summary.json").read_text())


EAGER = ("compile.compile=false", "compile.cudagraphs=false")  # the recipe tests below that are not about compiling


@pytest.mark.parametrize("algo", ["sac", "td3", "ddpg"])
def test_cuda_recipe_trains_and_resumes(tmp_path, algo):
    """device=cuda: networks and updates on the GPU (the memory too, but not with recall); a second run resumes."""
    memory = f"memory.path={tmp_path / 'mem.zarr'}"
    first = _recipe(tmp_path, f"algo={algo}", memory, "memory.recall.enabled=true", *EAGER)
    assert first["frames"] == 50 and first["memory_rows_after"] == 50 and first["updates"] > 0
    again = _recipe(tmp_path, f"algo={algo}", memory, "memory.recall.enabled=true", "memory.resume_agent=true",
                    *EAGER, out="again")
    assert again["memory_rows_before"] == 50 and again["memory_rows_after"] == 100


def test_cuda_recipe_with_a_prior_memory_clone_and_anchor(tmp_path):
    """prior.paths + clone_steps + bc + clone_anchor (experiments/prior_variants) with the actor on the GPU."""
    from experiments.scripted.collect import main as collect

    prior = tmp_path / "scripted-push.zarr"
    collect([f"path={prior}", "env=push", "episodes=2", "backend=gym", "seed=0"])
    s = _recipe(tmp_path, "env=push", "algo=td3", f"memory.path={tmp_path / 'td3.zarr'}", "prior=bc", f"prior.paths=[{prior}]",
                *EAGER,
                "prior.clone_steps=5", "prior.bc=0.4", "prior.bc_original_goals=true",
                "prior.clone_anchor=10", "prior.freeze_normalizer=true", out="td3", variants=True)
    assert s["updates"] > 0
    s = _recipe(tmp_path, "env=push", f"memory.path={tmp_path / 'crr.zarr'}", "prior=mix", f"prior.paths=[{prior}]", "algo=td3",
                "prior.clone_steps=5", "prior.actor_update=crr", "replay_buffer.sampler.enabled=true",
                *EAGER, out="crr", variants=True)
    assert s["updates"] > 0


# -- the fast path (issue 26): compiled, CUDA-graphed updates ------------------------------------------


def _update_parts(algo: str, rows, env, compiled: bool, graphs: bool):
    from training.test_update_step import _cfg

    from recipes.her import utils
    from recipes.her.update import LossTerms, Updater

    cfg = _cfg(f"algo={algo}", f"device={DEVICE}")
    torch.manual_seed(0)
    normalizer = utils.GoalNormalizer(device=CUDA)
    normalizer.update(rows)
    model, _ = utils.make_agent(cfg, env, normalizer)
    loss, target = utils.make_loss_module(cfg, model, compiled=True)
    optimizer = utils.make_optimizer(cfg, loss, capturable=graphs)
    updater = Updater(LossTerms(loss, utils.loss_keys(cfg)), optimizer, target, compile=compiled,
                      compile_mode="default", cudagraphs=graphs, warmup=2,
                      policy_delay=cfg.algo.policy_update_delay if algo == "td3" else 1)
    return cfg, loss, updater, normalizer


@pytest.mark.skipif(DEVICE != "cuda", reason="CUDA graphs")
def test_cuda_graphed_update_matches_eager(tmp_path):
    """DDPG (no random draws in its loss): compiled + CUDA-graphed steps give the eager losses and parameters,
    also after the normaliser's statistics change (updated in place, read by the captured graph)."""

    env = make_env("FetchReach-v4", seed=0)
    rows = env.rollout(200, break_when_any_done=False)
    out = {}
    for name, compiled, graphs in (("eager", False, False), ("graphed", True, True)):
        cfg, loss, updater, normalizer = _update_parts("ddpg", rows, env, compiled, graphs)
        rb = HERReplayBuffer(make_reward_fn("FetchReach-v4"), achieved_goal_key=("next", "achieved_goal"),
                             storage=ZarrStorage(tmp_path / f"{name}.zarr", 1000, env="FetchReach-v4", device=DEVICE),
                             batch_size=cfg.optim.batch_size)
        rb.extend(rows)
        torch.manual_seed(1)
        batches = [rb.sample() for _ in range(12)]
        losses = []
        for i, batch in enumerate(batches):
            if i == 6:
                normalizer.update(rows[:50] * 1.5)
            losses.append(updater(batch)["loss_value"])
        out[name] = (torch.stack(losses).cpu(), {k: v.detach().cpu() for k, v in loss.state_dict().items()})
    torch.testing.assert_close(out["graphed"][0], out["eager"][0], rtol=1e-3, atol=1e-5)
    for key, value in out["eager"][1].items():
        torch.testing.assert_close(out["graphed"][1][key], value, rtol=1e-3, atol=1e-5, msg=key)
    env.close()


@pytest.mark.skipif(DEVICE != "cuda", reason="CUDA graphs")
def test_cuda_recipe_compiled_and_graphed_by_default(tmp_path):
    """device=cuda's defaults (compile, CUDA graphs, memory on the GPU): SAC trains, resumes, reports frames/s."""
    memory = f"memory.path={tmp_path / 'mem.zarr'}"
    first = _recipe(tmp_path, memory, "collector.total_frames=100", "logger.eval_iter=100")
    assert first["frames"] == 100 and first["updates"] > 0 and first["frames_per_s"] > 0
    again = _recipe(tmp_path, memory, "collector.total_frames=100", "logger.eval_iter=100",
                    "memory.resume_agent=true", out="again")
    assert again["memory_rows_before"] == 100 and again["memory_rows_after"] == 200
