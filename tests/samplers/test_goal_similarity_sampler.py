"""GoalSimilaritySampler inside real TorchRL replay buffers (TensorDictReplayBuffer, HERReplayBuffer)."""
from __future__ import annotations

import json
from functools import partial

import _rows
import pytest
import torch
from torchrl.data import HERReplayBuffer, LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

from torchrl_robotmem.goal_index import GoalIndex
from torchrl_robotmem.sampler import GoalSimilaritySampler

torch.set_num_threads(1)

GOAL = ("next", "achieved_goal")
ENV_NAMES = ("FetchPush-v4", "FetchSlide-v4")
# FetchPush-shaped rows with an env column (codes into ENV_NAMES)
fetch_rows = partial(_rows.fetch_rows, envs=len(ENV_NAMES))


def make_rb(sampler, n=4000, capacity=8000, batch_size=512, seed=0, **kw):
    gen = torch.Generator().manual_seed(seed)
    rb = TensorDictReplayBuffer(
        storage=LazyTensorStorage(capacity), sampler=sampler, batch_size=batch_size, **kw
    )
    if n:
        rb.extend(fetch_rows(n, gen))
    return rb, gen


def goal_dist(batch, goal):
    return (batch[GOAL] - torch.as_tensor(goal)).norm(dim=-1)


def test_no_query_is_uniform():
    rb, _ = make_rb(GoalSimilaritySampler(), n=1000)
    batch = rb.sample()
    assert "goal_distance" not in batch.keys()
    assert batch.batch_size == torch.Size([512])
    assert batch["index"].min() >= 0 and batch["index"].max() < 1000
    assert batch["index"].unique().numel() > 300  # spread over the buffer


def test_query_concentrates_near_goal_and_reports_distance():
    rb, gen = make_rb(GoalSimilaritySampler(temperature=0.02, num_candidates=128))
    goal = torch.tensor([0.3, 0.6, 0.5])
    uniform = goal_dist(rb.sample(), goal).mean()
    with rb.sampler.query(goal):
        batch = rb.sample()
    d = goal_dist(batch, goal)
    torch.testing.assert_close(batch["goal_distance"], d)
    assert batch["goal_distance"].dtype == torch.float32
    assert d.mean() < 0.25 * uniform
    # every row is among the 128 nearest
    kth = GoalIndex(rb).search(goal, 128)[0][-1]
    assert (d <= kth + 1e-6).all()
    # softmax weighting: a colder temperature pulls the batch closer
    rb.sampler.temperature = 0.002
    with rb.sampler.query(goal):
        colder = goal_dist(rb.sample(), goal)
    assert colder.mean() < d.mean()
    assert rb.sampler.current_query is None  # context manager restored "no query"


def test_batch_is_spread_over_several_queries():
    rb, _ = make_rb(GoalSimilaritySampler(temperature=0.01, num_candidates=64))
    goals = torch.tensor([[0.1, 0.1, 0.1], [0.9, 0.9, 0.9], [0.1, 0.9, 0.5]])
    rb.sampler.set_query(goals)
    batch = rb.sample()
    nearest = torch.cdist(batch[GOAL], goals).argmin(1)
    assert sorted(torch.bincount(nearest, minlength=3).tolist()) == [170, 171, 171]
    torch.testing.assert_close(batch["goal_distance"], torch.cdist(batch[GOAL], goals).amin(1))
    # shuffled: rows of the three queries are interleaved
    assert (nearest[:171] == nearest[0]).float().mean() < 0.9
    rb.sampler.clear_query()
    assert "goal_distance" not in rb.sample().keys()


def test_uniform_ratio_mixes_uniform_rows():
    rb, _ = make_rb(GoalSimilaritySampler(temperature=0.01, num_candidates=32, uniform_ratio=0.5))
    goal = torch.tensor([0.5, 0.5, 0.5])
    rb.sampler.set_query(goal)
    batch = rb.sample()
    d = goal_dist(batch, goal)
    kth = GoalIndex(rb).search(goal, 32)[0][-1]
    near = d <= kth + 1e-6
    assert 230 <= int(near.sum()) <= 330  # 256 near + the uniform rows that happen to be near
    torch.testing.assert_close(batch["goal_distance"], d)


@pytest.mark.parametrize("nan_share", [0.5, 0.999])
def test_uniform_rows_of_a_query_never_have_a_non_finite_goal(nan_share):
    """Found by a review: with no filter, the uniform part of a queried batch drew rows whose goal is NaN (their
    goal_distance NaN), while a filter every row passes drew none. Rows with a non-finite goal are never drawn."""
    rb, _ = make_rb(GoalSimilaritySampler(num_candidates=16, uniform_ratio=1.0), n=2000, batch_size=1000)
    bad = torch.arange(int(2000 * nan_share))
    rb.storage._storage[GOAL][bad, 0] = float("nan")
    rb.storage._storage[GOAL][bad[::7], 1] = float("inf")
    rb.sampler.set_query(torch.tensor([0.5, 0.5, 0.5]))
    for _ in range(3):
        batch = rb.sample()
        assert torch.isfinite(batch[GOAL]).all() and torch.isfinite(batch["goal_distance"]).all()
        assert not torch.isin(batch["index"], bad).any()


def test_a_query_with_nothing_within_max_distance_leaves_the_batch_to_the_others():
    """Found by a review: one query out of reach made sample() refuse although rows matched the other."""
    rb, _ = make_rb(GoalSimilaritySampler(num_candidates=16, max_distance=0.2), n=2000, batch_size=64)
    near, far = torch.tensor([0.5, 0.5, 0.5]), torch.tensor([5.0, 5.0, 5.0])
    rb.sampler.set_query(torch.stack([near, far]))
    batch = rb.sample()
    assert len(batch) == 64 and (goal_dist(batch, near) <= 0.2 + 1e-6).all()
    rb.sampler.set_query(far.unsqueeze(0))
    with pytest.raises(RuntimeError, match="no stored row matches"):
        rb.sample()


def test_success_only_and_env_filters_are_respected():
    sampler = GoalSimilaritySampler(success_only=True, env="FetchSlide-v4", env_names=ENV_NAMES,
                                    uniform_ratio=0.3, num_candidates=64)
    rb, _ = make_rb(sampler)
    rb.sampler.set_query(torch.rand(4, 3))
    for _ in range(3):
        batch = rb.sample()
        assert (batch["next", "is_success"] == 1).all()
        assert (batch["env"] == 1).all()
    storage = rb.storage
    ok = (storage._storage.get(("next", "is_success"))[: len(storage)] == 1) & (
        storage._storage.get("env")[: len(storage)] == 1
    )
    assert batch["index"].unique().numel() > 50 and ok[batch["index"]].all()


def test_new_rows_are_seen_without_hooks_and_ring_overwrites():
    rb, gen = make_rb(GoalSimilaritySampler(num_candidates=16, temperature=0.01), n=3000, capacity=3000)
    goal = torch.tensor([2.0, 2.0, 2.0])  # far from every stored goal
    rb.sampler.set_query(goal)
    before = rb.sample()
    assert (before["goal_distance"] > 1.0).all()
    new = fetch_rows(10, gen)
    new[GOAL] = goal + 0.001 * torch.rand(10, 3, generator=gen)
    rb.extend(new)  # full buffer: overwrites rows 0..9
    after = rb.sample()
    assert (after["goal_distance"] < 0.01).float().mean() > 0.5
    assert set(after["index"][after["goal_distance"] < 0.01].tolist()) <= set(range(10))
    torch.testing.assert_close(after["goal_distance"], goal_dist(after, goal))


def test_generator_makes_sampling_reproducible():
    def draw(seed):
        rb, _ = make_rb(GoalSimilaritySampler(uniform_ratio=0.25), generator=torch.Generator().manual_seed(seed))
        rb.sampler.set_query(torch.tensor([[0.2, 0.2, 0.2], [0.7, 0.3, 0.5]]))
        return rb.sample()["index"]

    assert torch.equal(draw(1), draw(1))
    assert not torch.equal(draw(1), draw(2))


def test_state_dict_and_dumps_round_trip(tmp_path):
    sampler = GoalSimilaritySampler(metric="pose", metric_kwargs={"rotation_weight": 0.5}, temperature=0.1,
                                    num_candidates=17, success_only=True, env=["FetchPush-v4"],
                                    env_names=ENV_NAMES, uniform_ratio=0.2)
    sampler.set_query([[0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]])
    sd = sampler.state_dict()
    json.dumps(sd)  # plain JSON values
    fresh = GoalSimilaritySampler()
    fresh.load_state_dict(sd)
    assert fresh.state_dict() == sd
    assert fresh.goal_key == ("next", "achieved_goal")
    sampler.dumps(tmp_path / "s")
    assert [p.name for p in (tmp_path / "s").iterdir()] == ["sampler_metadata.json"]
    other = GoalSimilaritySampler()
    other.loads(tmp_path / "s")
    assert other.state_dict() == sd
    torch.testing.assert_close(other.current_query, sampler.current_query)
    # through the buffer's own dumps/loads
    rb, _ = make_rb(GoalSimilaritySampler(temperature=0.3, uniform_ratio=0.1), n=500)
    rb.sampler.set_query([0.5, 0.5, 0.5])
    rb.dumps(tmp_path / "rb")
    rb2 = TensorDictReplayBuffer(storage=LazyTensorStorage(8000), sampler=GoalSimilaritySampler(), batch_size=512)
    rb2.loads(tmp_path / "rb")
    assert rb2.sampler.state_dict() == rb.sampler.state_dict()
    assert rb2.sample()["goal_distance"].shape == (512,)


def reward_fn(td):
    d = (td["next", "achieved_goal"] - td["desired_goal"]).norm(dim=-1, keepdim=True)
    return -(d > 0.05).float()


def test_her_replay_buffer_with_goal_sampler():
    gen = torch.Generator().manual_seed(0)
    her = HERReplayBuffer(
        reward_fn, her_ratio=0.5, storage=LazyTensorStorage(5000),
        sampler=GoalSimilaritySampler(temperature=0.01, num_candidates=64), batch_size=256,
        achieved_goal_key=("next", "achieved_goal"),
    )
    her.extend(fetch_rows(4000, gen))
    goal = torch.tensor([0.4, 0.4, 0.4])
    with her.sampler.query(goal):
        batch = her.sample()
    torch.testing.assert_close(batch["goal_distance"], goal_dist(batch, goal))
    kth = GoalIndex(her).search(goal, 64)[0][-1]
    assert (batch["goal_distance"] <= kth + 1e-6).all()
    # HER relabelled the first half: goals taken from the same episode, rewards recomputed
    relabelled = batch[:128]
    torch.testing.assert_close(relabelled["next", "reward"], reward_fn(relabelled))
    goals = her.storage._storage.get(("next", "achieved_goal"))[:4000]
    episode = batch["index"][:128] // 50
    match = (relabelled["desired_goal"][:, None] == goals.view(80, 50, 3)[episode]).all(-1).any(-1)
    assert match.all()
    # plain HER (RandomSampler) draws far from the goal by comparison
    plain = HERReplayBuffer(reward_fn, storage=her.storage, sampler=RandomSampler(), batch_size=256,
                            achieved_goal_key=("next", "achieved_goal"))
    assert goal_dist(plain.sample(), goal).mean() > 4 * batch["goal_distance"].mean()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"temperature": 0.0}, "temperature"),
        ({"temperature": float("nan")}, "temperature"),
        ({"num_candidates": 0}, "num_candidates"),
        ({"uniform_ratio": 1.5}, "uniform_ratio"),
        ({"success_only": "yes"}, "success_only"),
    ],
)
def test_bad_configuration(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GoalSimilaritySampler(**kwargs)


def test_bad_queries_and_impossible_filters():
    sampler = GoalSimilaritySampler()
    with pytest.raises(ValueError, match="NaN or infinite"):
        sampler.set_query([0.1, float("nan"), 0.3])
    with pytest.raises(ValueError, match=r"\[Q, goal_dim\]"):
        sampler.set_query(torch.zeros(2, 2, 3))
    rb, _ = make_rb(sampler, n=200)
    n_before, rev = len(rb), rb.storage._mutation_revision
    sampler.set_query(torch.zeros(4))
    with pytest.raises(ValueError, match="dimension 4"):
        rb.sample()
    nobody = GoalSimilaritySampler(success_only=True)
    rb2, gen = make_rb(nobody, n=0)
    rb2.extend(fetch_rows(100, gen, success_rate=0.0))
    nobody.set_query(torch.zeros(3))
    with pytest.raises(RuntimeError, match="no stored row matches"):
        rb2.sample()
    empty = TensorDictReplayBuffer(storage=LazyTensorStorage(10), sampler=GoalSimilaritySampler(), batch_size=4)
    with pytest.raises(RuntimeError, match="empty"):
        empty.sample()
    assert (len(rb), rb.storage._mutation_revision) == (n_before, rev)
