"""SLM Lab's off-policy memory kinds over a persistent storage: combined experience replay and
prioritized replay whose priorities persist in the store (torchrl_robotmem.samplers).

Real Zarr stores and TorchRL buffers; the reopen checks run in a fresh process. Draws are seeded and
the priority checks are safe by construction (a favoured row carries ~1e16 times another's mass).
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from _rows import fetch_rows
from _s3 import s3_server, s3_url  # noqa: F401  (pytest fixtures)
from torchrl.data import HERReplayBuffer, LazyTensorStorage, PrioritizedSampler, TensorDictReplayBuffer

from torchrl_robotmem import GoalSimilaritySampler, ZarrStorage
from torchrl_robotmem.cli import main as robotmem
from torchrl_robotmem.samplers.combined import CombinedExperienceSampler
from torchrl_robotmem.samplers.prioritized import PersistentPrioritizedSampler

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.filterwarnings("ignore:ZarrStorage at")


def _rows(n, seed=0, start=0):
    return fetch_rows(n, torch.Generator().manual_seed(seed), start)


def _per(path, **kw):
    storage = ZarrStorage(path, max_size=kw.pop("max_size", None), env="FetchPush-v4")
    return TensorDictReplayBuffer(storage=storage, sampler=PersistentPrioritizedSampler(alpha=0.7, beta=0.5, **kw),
                                  batch_size=64, priority_key="td_error")


def _in_fresh_process(code: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120,
                          cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


# -- combined experience replay ------------------------------------------------------------------


@pytest.mark.parametrize("make_storage", [lambda p: LazyTensorStorage(300), lambda p: ZarrStorage(p, 300)],
                         ids=["lazy", "zarr"])
def test_every_combined_batch_holds_the_rows_of_the_latest_write(tmp_path, make_storage):
    rb = TensorDictReplayBuffer(storage=make_storage(tmp_path / "cer.zarr"), sampler=CombinedExperienceSampler(),
                                batch_size=32)
    rb.extend(_rows(280))
    for k, start in ((5, 280), (30, 285)):  # the second write wraps the ring: rows 285..299 and 0..14
        rb.extend(_rows(k, seed=k, start=start))
        newest = set(((torch.arange(k) + start) % 300).tolist())
        for _ in range(5):
            batch = rb.sample()
            assert newest <= set(batch["index"].tolist())
            assert torch.equal(batch["observation"], rb.storage[batch["index"]]["observation"])
    if isinstance(rb.storage, ZarrStorage):
        rb.storage.close()


def test_combined_batches_hold_the_stores_newest_rows_after_a_reopen(tmp_path):
    path = tmp_path / "cer.zarr"
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 100), batch_size=16)
    rb.extend(_rows(90))
    rb.extend(_rows(20, seed=1, start=90))  # the ring wrapped: the newest rows are 7, 8, 9
    rb.storage.close()
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path), sampler=CombinedExperienceSampler(newest=3), batch_size=16)
    torch.manual_seed(0)
    for _ in range(5):
        assert {7, 8, 9} <= set(rb.sample()["index"].tolist())
    assert rb.sampler.newest_index(rb.storage).tolist() == [7, 8, 9]
    assert CombinedExperienceSampler().newest_index(rb.storage).tolist() == [9]  # no write yet: the newest row
    rb.storage.close()


def test_combined_over_the_goal_sampler_under_her(tmp_path):
    def reward_fn(td):
        return torch.zeros(td.shape[0], 1)

    base = GoalSimilaritySampler(uniform_ratio=0.5)
    rb = HERReplayBuffer(reward_fn, achieved_goal_key=("next", "achieved_goal"), storage=ZarrStorage(tmp_path / "m.zarr", 500),
                         sampler=CombinedExperienceSampler(base, newest=4), batch_size=32)
    rb.extend(_rows(200))
    with rb.sampler.query(torch.tensor([0.5, 0.5, 0.5])):  # the base's query, through the wrapper
        batch = rb.sample()
    assert {196, 197, 198, 199} <= set(batch["index"].tolist())
    unknown = batch["goal_distance"].isnan()  # the newest rows' distance: not the base's to say
    assert sorted(batch["index"][unknown].tolist()) == [196, 197, 198, 199]
    rb.storage.close()


def test_combined_over_prioritized_weighs_the_newest_rows_too():
    per = PersistentPrioritizedSampler(alpha=1.0, beta=1.0)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), sampler=CombinedExperienceSampler(per, newest=2),
                                batch_size=16)
    rb.extend(_rows(50))
    rb.update_priority(torch.arange(50), torch.arange(1, 51).float())
    batch = rb.sample()
    assert {48, 49} <= set(batch["index"].tolist())
    assert torch.allclose(batch["priority_weight"], per.importance_weight(batch["index"]))


def test_combined_refuses_bad_arguments():
    with pytest.raises(ValueError, match="newest"):
        CombinedExperienceSampler(newest=0)
    with pytest.raises(TypeError, match="Sampler"):
        CombinedExperienceSampler(base="uniform")


# -- prioritized replay ------------------------------------------------------------------------------


def test_prioritized_samples_by_priority_with_torchrls_weights(tmp_path):
    rb = _per(tmp_path / "per.zarr", max_size=512)
    rb.extend(_rows(300))
    assert isinstance(rb.sampler, PrioritizedSampler)  # TorchRL's buffers route update_tensordict_priority to it
    favoured = torch.tensor([3, 77, 150, 222, 299])
    priority = torch.full((300,), 1e-8)
    priority[favoured] = 1e8  # (1e16) ** 0.7: another row is drawn with a chance ~1e-9 in the 640 draws
    rb.update_priority(torch.arange(300), priority)
    torch.manual_seed(0)
    drawn = torch.cat([rb.sample()["index"] for _ in range(10)])
    assert set(drawn.tolist()) <= set(favoured.tolist())
    # importance weights as TorchRL's PrioritizedSampler: ((p + eps) ** alpha / min) ** -beta
    batch = rb.sample()
    w = (priority.double() + 1e-8) ** 0.7
    assert torch.allclose(batch["priority_weight"].double(), (w[batch["index"]] / w.min()) ** -0.5, rtol=1e-5)
    # the TensorDictReplayBuffer flow: the priority key of a sampled batch
    rb.update_tensordict_priority(batch.set("td_error", torch.full((64,), 2.0)))
    assert torch.equal(rb.sampler.priority[batch["index"]], torch.full((64,), 2.0))
    rb.sampler.flush()
    rb.storage.close()


def test_prioritized_replay_on_a_memory_without_a_capacity_is_refused_saying_what_to_do(tmp_path):
    """Found by a review: the table was sized by the memory's max_size (2**50 rows without a capacity), and the
    first extend failed allocating 9e15 bytes."""
    storage = ZarrStorage(tmp_path / "grow.zarr", goal_conditioned=False)
    rb = TensorDictReplayBuffer(storage=storage, sampler=PersistentPrioritizedSampler(), batch_size=8)
    with pytest.raises(ValueError, match="grows without bound.*ZarrStorage\\(path, max_size\\)"):
        rb.extend(_rows(10))
    assert len(storage) == 10  # TorchRL's writer stores the rows before the sampler sees them: sound rows, kept
    with pytest.raises(ValueError, match="grows without bound"):
        rb.sample()
    storage.close()


def test_new_rows_get_the_max_priority_and_draws_follow_it():
    sampler = PersistentPrioritizedSampler(alpha=1.0, beta=0.4)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), sampler=sampler, batch_size=256)
    rb.extend(_rows(100))
    rb.update_priority(torch.arange(100), torch.full((100,), 1e-6))
    rb.update_priority(torch.tensor([5]), torch.tensor([7.0]))
    rb.extend(_rows(10, seed=1, start=100))
    assert sampler.priority[100:].eq(7.0).all() and sampler.default_priority == 7.0
    torch.manual_seed(0)
    drawn = rb.sample()["index"]
    assert set(drawn.tolist()) <= {5, *range(100, 110)}  # the rest carry 1e-6 / 77 of the mass


def test_priorities_persist_bit_equal_across_a_fresh_process(tmp_path):
    path = tmp_path / "per.zarr"
    rb = _per(path, max_size=300_000)
    rb.extend(_rows(2000))
    gen = torch.Generator().manual_seed(3)
    rb.update_priority(torch.arange(2000), torch.rand(2000, generator=gen) * 10)
    rb.update_priority(torch.tensor([11]), torch.tensor([42.0]))
    expected = rb.sampler.priority.clone()
    rb.sampler.flush()  # (exit and SIGTERM write them too: the fresh process below relies on neither)
    rb.storage.close()
    out = _in_fresh_process(f"""
        import json, warnings, torch
        warnings.simplefilter("ignore")
        from tensordict import TensorDict
        from torchrl.data import TensorDictReplayBuffer
        from torchrl_robotmem import ZarrStorage
        from torchrl_robotmem.samplers.prioritized import PersistentPrioritizedSampler
        rb = TensorDictReplayBuffer(storage=ZarrStorage({str(path)!r}),
                                    sampler=PersistentPrioritizedSampler(alpha=0.7, beta=0.5), batch_size=8)
        p = rb.sampler.priority.clone()
        # rows written after the last priority write get the max priority
        _ = rb.extend(TensorDict({{k: v[:5] for k, v in rb.storage[:5].items()}}, [5]))
        rb.update_priority(torch.tensor([0]), torch.tensor([7.0]))  # no flush: written by the exit hook
        print(json.dumps({{"p": p.tolist(), "new": rb.sampler.priority[2000:].tolist(), "n": len(rb)}}))
    """)
    assert out["n"] == 2005
    assert torch.equal(torch.tensor(out["p"], dtype=torch.float32), expected)
    assert out["new"] == [42.0] * 5
    with ZarrStorage(path, read_only=True) as storage:
        sampler = PersistentPrioritizedSampler(alpha=0.7, beta=0.5)
        sampler.sample(storage, 4)
        assert sampler.priority[0] == 7.0 and torch.equal(sampler.priority[1:2000], expected[1:])


def test_closing_the_storage_writes_the_priorities(tmp_path):
    path = tmp_path / "per.zarr"
    rb = _per(path, max_size=1000)
    rb.extend(_rows(100))
    rb.update_priority(torch.arange(100), torch.linspace(0.1, 9.0, 100))
    expected = rb.sampler.priority.clone()
    rb.storage.close()  # no sampler.flush(): the storage's close writes them first
    with ZarrStorage(path, read_only=True) as storage:
        sampler = PersistentPrioritizedSampler(alpha=0.7, beta=0.5)
        sampler.sample(storage, 4)
        assert torch.equal(sampler.priority[:100], expected[:100])


def test_rows_committed_after_the_last_priority_write_get_the_max_priority(tmp_path):
    path = tmp_path / "per.zarr"
    rb = _per(path, max_size=1000)
    rb.extend(_rows(100))
    rb.update_priority(torch.arange(100), torch.full((100,), 0.5))
    rb.update_priority(torch.tensor([0]), torch.tensor([3.0]))
    rb.sampler.flush()
    rb.storage.close()
    # a run without the sampler appends 20 rows: the stored priorities do not know them
    with ZarrStorage(path) as storage:
        TensorDictReplayBuffer(storage=storage, batch_size=8).extend(_rows(20, seed=1, start=100))
    reader = TensorDictReplayBuffer(storage=ZarrStorage(path, read_only=True),
                                    sampler=PersistentPrioritizedSampler(alpha=0.7, beta=0.5), batch_size=8)
    reader.sample()
    p = reader.sampler.priority
    assert p[0] == 3.0 and p[1:100].eq(0.5).all() and p[100:120].eq(3.0).all() and len(p) == 120
    reader.storage.close()


@pytest.mark.parametrize("index, priority, error", [
    (torch.arange(10), torch.ones(9), "9 priorities"),
    (torch.arange(10), torch.full((10,), float("nan")), "finite"),
    (torch.arange(10), -torch.ones(10), ">= 0"),
    (torch.arange(10), torch.ones(10, dtype=torch.bool), "real numbers"),
    (torch.arange(10).float(), torch.ones(10), "integers"),
    (torch.tensor([0, 500]), torch.ones(2), "not held"),
])
def test_bad_priorities_raise_and_change_nothing(tmp_path, index, priority, error):
    path = tmp_path / "per.zarr"
    rb = _per(path, max_size=1000)
    rb.extend(_rows(100))
    rb.update_priority(torch.arange(100), torch.linspace(0.1, 2.0, 100))
    rb.sampler.flush()
    before = rb.sampler.priority.clone()
    with pytest.raises((ValueError, TypeError, IndexError), match=error):
        rb.update_priority(index, priority)
    assert torch.equal(rb.sampler.priority, before)
    rb.sampler.flush()
    rb.storage.close()
    with ZarrStorage(path, read_only=True) as storage:
        sampler = PersistentPrioritizedSampler(alpha=0.7, beta=0.5)
        sampler.sample(storage, 4)
        assert torch.equal(sampler.priority, before)


def test_verify_inspect_repair_copy_and_reopen_tolerate_the_stored_priorities(tmp_path, capsys):
    path = tmp_path / "per.zarr"
    rb = _per(path, max_size=1000)
    rb.extend(_rows(100))
    rb.update_priority(torch.arange(100), torch.linspace(0.1, 2.0, 100))
    rb.sampler.flush()
    rb.storage.close()
    assert (path / "_priority" / "priority" / "zarr.json").is_file()
    assert robotmem(["verify", str(path)]) == 0
    assert robotmem(["inspect", str(path)]) == 0
    assert robotmem(["repair", str(path)]) == 0 and "nothing to repair" in capsys.readouterr().out
    assert robotmem(["copy", str(path), str(tmp_path / "copy.zarr")]) == 0
    assert "intact" in capsys.readouterr().out
    with ZarrStorage(tmp_path / "copy.zarr", read_only=True) as storage:  # the copy keeps the priorities
        sampler = PersistentPrioritizedSampler(alpha=0.7, beta=0.5)
        sampler.sample(storage, 4)
        assert torch.allclose(sampler.priority, torch.linspace(0.1, 2.0, 100))
        assert len(storage) == 100 and "_priority" not in storage[:2].keys()


def test_priorities_persist_in_an_object_store(s3_url, s3_server):  # noqa: F811
    opts = s3_server.storage_options
    rb = TensorDictReplayBuffer(storage=ZarrStorage(s3_url, 200, storage_options=opts),
                                sampler=PersistentPrioritizedSampler(), batch_size=8)
    rb.extend(_rows(50))
    rb.update_priority(torch.arange(50), torch.linspace(0.5, 5.0, 50))
    rb.sampler.flush()
    rb.storage.close()
    with ZarrStorage(s3_url, read_only=True, storage_options=opts) as storage:
        sampler = PersistentPrioritizedSampler()
        sampler.sample(storage, 4)
        assert torch.equal(sampler.priority, torch.linspace(0.5, 5.0, 50))


def test_state_dict_and_dumps_round_trip(tmp_path):
    src = PersistentPrioritizedSampler(alpha=0.6, beta=0.4)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(64), sampler=src, batch_size=8)
    rb.extend(_rows(40))
    rb.update_priority(torch.arange(40), torch.rand(40) + 0.1)
    rb.dumps(tmp_path / "ckpt")
    dst = PersistentPrioritizedSampler(alpha=0.6, beta=0.4)
    rb2 = TensorDictReplayBuffer(storage=LazyTensorStorage(64), sampler=dst, batch_size=8)
    rb2.loads(tmp_path / "ckpt")
    rb2.sample()
    assert torch.equal(dst.priority, src.priority) and dst.default_priority == src.default_priority
    dst.load_state_dict(src.state_dict())
    assert torch.equal(dst.priority, src.priority)
    # a resumed buffer checkpointed again at a new path (pytorch/rl #4388), and a new prioritized buffer on
    # the loaded storage (#3120): every row at the default priority, as TorchRL's fill gives it
    rb2.dumps(tmp_path / "ckpt2")
    third = PersistentPrioritizedSampler(alpha=0.6, beta=0.4)
    rb3 = TensorDictReplayBuffer(storage=LazyTensorStorage(64), sampler=third, batch_size=8)
    rb3.loads(tmp_path / "ckpt2")
    rb3.sample()
    assert torch.equal(third.priority, src.priority)
    reuse = TensorDictReplayBuffer(storage=rb2.storage, sampler=PersistentPrioritizedSampler(), batch_size=8)
    assert reuse.sample()["priority_weight"].eq(1.0).all() and reuse.sampler.priority.eq(1.0).all()


def test_her_recipe_with_combined_replay_over_the_goal_sampler(tmp_path):
    from training.test_her_recipe import run_recipe

    s = run_recipe(tmp_path, "replay_buffer.combined=true", "replay_buffer.sampler.enabled=true",
                   f"memory.path={tmp_path / 'mem.zarr'}")
    assert s["memory_rows_after"] == 50 and s["updates"] > 0
