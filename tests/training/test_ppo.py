"""On-policy learning over a persistent memory: OnPolicyBatchSampler and recipes/ppo.

Real Zarr stores, real TorchRL buffers, real FetchReach runs (subprocesses, as TorchRL's CI runs its sota scripts).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.samplers.on_policy import OnPolicyBatchSampler

ROOT = Path(__file__).resolve().parents[2]
PPO_DIR = ROOT / "recipes" / "ppo"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def rows(n: int, start: int = 0) -> TensorDict:
    i = torch.arange(start, start + n)
    return TensorDict({"obs": i.float().unsqueeze(-1), "step": i,
                       ("next", "is_success"): torch.zeros(n)}, [n])


def buffer(path: Path, batch_size: int, **kw) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(storage=ZarrStorage(path, 1000, env="FetchReach-v4"),
                                  sampler=OnPolicyBatchSampler(**kw), batch_size=batch_size)


# -- the sampler ---------------------------------------------------------------


def test_minibatches_cover_exactly_the_newest_batch_each_epoch_and_old_rows_stay(tmp_path):
    rb = buffer(tmp_path / "m.zarr", 7, epochs=3)
    rb.extend(rows(20))                    # an older batch
    newest = rows(30, start=20)
    index = rb.extend(newest)
    for _ in range(3):
        epoch = list(rb)                   # one pass: ran_out ends the iteration
        assert [len(b) for b in epoch] == [7, 7, 7, 7, 2]
        drawn = torch.cat([b["index"] for b in epoch])
        assert sorted(drawn.tolist()) == sorted(index.tolist())  # each newest row once, no older row
        for b in epoch:                    # batch_position: the row's place in the extended data
            assert torch.equal(b["obs"], newest["obs"][b["batch_position"]])
    with pytest.raises(RuntimeError, match="all 3 epochs over the newest batch \\(30 rows\\)"):
        rb.sample()
    assert len(rb) == 50
    rb.extend(rows(5, start=50))           # a new batch: drawing starts again, on it alone
    assert sorted(torch.cat([b["step"] for b in rb]).tolist()) == list(range(50, 55))
    rb.storage.close()

    with ZarrStorage(tmp_path / "m.zarr", read_only=True) as store:  # nothing was erased
        assert len(store) == 55 and store[:55]["step"].tolist() == list(range(55))


def test_a_reopened_memory_has_nothing_new_to_draw(tmp_path):
    rb = buffer(tmp_path / "m.zarr", 4)
    rb.extend(rows(10))
    rb.storage.close()
    again = buffer(tmp_path / "m.zarr", 4)
    assert len(again) == 10 and not again.can_sample()
    with pytest.raises(RuntimeError, match="no rows were written since .* holds 10 rows"):
        again.sample()
    again.extend(rows(3, start=10))
    assert again.can_sample() and sorted(again.sample()["step"].tolist()) == [10, 11, 12]
    again.storage.close()


def test_drop_last_and_a_batch_smaller_than_a_minibatch(tmp_path):
    rb = buffer(tmp_path / "m.zarr", 7, epochs=2, drop_last=True)
    rb.extend(rows(30))
    for _ in range(2):
        assert [len(b) for b in rb] == [7, 7, 7, 7]
    assert not rb.can_sample()
    rb.extend(rows(5, start=30))
    with pytest.raises(ValueError, match="5 rows, fewer than one minibatch of 7"):
        rb.sample()
    rb.storage.close()


def test_writes_replace_or_accumulate(tmp_path):
    rb = buffer(tmp_path / "a.zarr", 100)
    rb.extend(rows(4))
    rb.extend(rows(3, start=4))
    assert sorted(rb.sample()["step"].tolist()) == [4, 5, 6]       # the newest write alone
    rb.storage.close()
    rb = buffer(tmp_path / "b.zarr", 100, accumulate=True)
    rb.extend(rows(4))
    rb.extend(rows(3, start=4))
    assert sorted(rb.sample()["step"].tolist()) == list(range(7))  # writes with no draw in between: one batch
    rb.extend(rows(2, start=7))                                     # after a draw: a new batch
    assert sorted(rb.sample()["step"].tolist()) == [7, 8]
    rb.storage.close()


def test_a_batch_larger_than_a_ring_storage_draws_each_slot_once():
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(8), sampler=OnPolicyBatchSampler(), batch_size=100)
    rb.extend(rows(12))                    # slots 0-3 written twice: the later rows win
    batch = rb.sample()
    assert sorted(batch["step"].tolist()) == list(range(4, 12))
    assert sorted(batch["batch_position"].tolist()) == list(range(4, 12))


def test_state_round_trips_mid_epoch(tmp_path):
    rb = buffer(tmp_path / "m.zarr", 4, epochs=2)
    rb.extend(rows(10))
    rb.sample()
    rb.sampler.dumps(tmp_path / "sampler")
    rest = [b["index"] for b in rb]        # the rest of the first epoch
    other = OnPolicyBatchSampler(epochs=5)
    other.loads(tmp_path / "sampler")
    assert other.epochs == 2 and other.batch_rows == 10 and other.epochs_left == 1
    again = [other.sample(rb.storage, 4)[0] for _ in range(len(rest))]
    assert all(torch.equal(a, b) for a, b in zip(again, rest)) and other.ran_out
    before = other.state_dict()
    with pytest.raises(KeyError, match="'order'.*Nothing was changed"):
        other.load_state_dict({k: v for k, v in before.items() if k != "order"})
    with pytest.raises(ValueError, match="epoch 7 is outside"):
        other.load_state_dict({**before, "epoch": 7})
    assert other.state_dict() == before
    rb.empty()
    assert rb.sampler.batch_rows == 0
    rb.storage.close()


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="epochs must be >= 1"):
        OnPolicyBatchSampler(epochs=0)
    with pytest.raises(ValueError, match="a tuple of index tensors"):
        OnPolicyBatchSampler().extend((torch.arange(3), torch.arange(3)))
    with pytest.raises(ValueError, match="must be integers, got torch.float32"):
        OnPolicyBatchSampler().extend(torch.ones(3))


# -- the recipe --------------------------------------------------------------------

TINY = [
    "collector.frames_per_batch=100",
    "loss.mini_batch_size=50",
    "loss.ppo_epochs=2",
    "network.hidden_sizes=[16,16]",
    "logger.eval_iter=100",
    "logger.eval_episodes=1",
    "logger.plot=false",
]


def run_ppo(tmp_path: Path, *overrides: str, out: str = "out") -> dict:
    proc = subprocess.run(
        [sys.executable, str(PPO_DIR / "train.py"), *TINY, *overrides, f"hydra.run.dir={tmp_path / out}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((tmp_path / out / "summary.json").read_text())
    summary["stdout"] = proc.stdout
    return summary


@pytest.mark.full  # a second test of what the default tier covers (make test stays under 15 minutes)
def test_ppo_writes_a_memory_and_resumes_on_it(tmp_path):
    mem = tmp_path / "mem.zarr"
    first = run_ppo(tmp_path, f"memory.path={mem}", "collector.total_frames=200", out="run1")
    assert first["algo"] == "PPO" and first["frames"] == 200 and first["memory_rows_after"] == 200
    assert first["updates"] == 2 * 2 * 2  # 2 batches x 2 epochs x 2 minibatches
    assert [f for f, _ in first["curve"]] == [0, 100, 200]
    with ZarrStorage(mem, read_only=True) as store:
        before = store[:200]["next", "achieved_goal"].clone()
    scalars = next((tmp_path / "run1" / "ppo_logging").glob("*/scalars"))
    assert (scalars / "eval" / "success_rate.csv").read_text().splitlines()[-1].startswith("200,")

    second = run_ppo(tmp_path, "memory.path=mem.zarr", "collector.total_frames=300", "collector.resume=true",
                     out="run2")
    assert "run resumed at 200 frames" in second["stdout"] and "agent resumed" in second["stdout"]
    assert second["frames"] == 300 and second["memory_rows_before"] == 0 and second["memory_rows_after"] == 300
    assert second["updates"] == 12 and second["cpu_s"] >= first["cpu_s"]
    with ZarrStorage(mem, read_only=True) as store:
        assert len(store) == 300
        assert torch.equal(store[:200]["next", "achieved_goal"], before)  # appended after, not over
        done = store[:300]["next", "done"].squeeze(-1).nonzero().squeeze(-1)
        assert done.tolist() == list(range(49, 300, 50))                  # whole episodes
        assert "action_log_prob" not in store[:1].keys() and "advantage" not in store[:1].keys()
    assert len((tmp_path / "mem.zarr-runs.jsonl").read_text().splitlines()) == 2


def test_the_memory_is_a_her_recipe_memory(tmp_path):
    """What PPO leaves behind passes the HER recipe's prior check and is sampled by its buffer."""
    from hydra import compose, initialize_config_dir

    from recipes.her.prior_memory.layout import check_prior_layout
    from recipes.her.prior_memory.mix import TRANSITION_KEYS
    from recipes.her.utils import make_replay_buffer
    from torchrl_robotmem import make_env

    mem = tmp_path / "mem.zarr"
    run_ppo(tmp_path, f"memory.path={mem}", "collector.total_frames=100", "memory.recall.enabled=true",
            "env=reach_dense")
    with initialize_config_dir(str(ROOT / "recipes" / "her"), version_base="1.3"):
        cfg = compose("config", overrides=["optim.batch_size=16"])
    storage = ZarrStorage(mem, read_only=True)
    env = make_env("FetchReach-v4")
    try:
        assert check_prior_layout(storage, env.fake_tensordict(), TRANSITION_KEYS, log=None) == {}
        batch = make_replay_buffer(cfg, storage).sample()
        assert batch.batch_size == (16,) and "prior_goals" not in batch.keys()
    finally:
        env.close()
        storage.close()

    # and PPO recalls from it as another run's memory (memory.recall.memory=<path>, read-only)
    from recipes.ppo.utils import make_task_env

    with initialize_config_dir(str(PPO_DIR), version_base="1.3"):
        ppo_cfg = compose("config", overrides=["memory.recall.enabled=true", f"memory.recall.memory={mem}"])
    recall_env = make_task_env(ppo_cfg, 1, seed=0)
    try:
        assert recall_env.reset()["prior_goals_mask"].all()  # 5 remembered goals found
    finally:
        recall_env.close()


def test_episodes_must_be_whole_with_several_envs():
    from hydra import compose, initialize_config_dir

    from recipes.ppo.utils import check_batch

    with initialize_config_dir(str(PPO_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["env.num_envs=3", "collector.frames_per_batch=200"])
        with pytest.raises(ValueError, match="collector.frames_per_batch=150"):
            check_batch(cfg)
        cfg = compose("config", overrides=["loss.mini_batch_size=5000"])
        with pytest.raises(ValueError, match="loss.mini_batch_size=5000"):
            check_batch(cfg)
        for group, name in (("reach", "FetchReach-v4"), ("reach_dense", "FetchReachDense-v4")):
            assert compose("config", overrides=[f"env={group}"]).env.name == name
