"""RecallTransform on real MuJoCo envs, real Zarr stores and real TorchRL collectors."""
from __future__ import annotations

import functools
import pickle

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector, MultiAsyncCollector, MultiSyncCollector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import check_env_specs, step_mdp

from torchrl_robotmem import ZarrStorage, make_env
from torchrl_robotmem.goal_index import GoalIndex
from torchrl_robotmem.transform import RecallTransform

K = 4
EP_LEN = 10  # short episodes keep MuJoCo time low; resets are what is tested

# env id -> (goal dim, metric)
ENVS = {
    "FetchPush-v4": (3, "euclidean"),
    "HandManipulateBlock-v1": (7, "pose"),
}


def _collect(env_fn, storage, frames: int, frames_per_batch: int = 2 * EP_LEN):
    """Runs a single-process collector and extends a buffer on ``storage`` from the main process."""
    rb = TensorDictReplayBuffer(storage=storage, batch_size=8)
    collector = Collector(env_fn, None, frames_per_batch=frames_per_batch, total_frames=frames)
    for data in collector:
        rb.extend(data.reshape(-1))
    collector.shutdown()
    return rb


@pytest.fixture(scope="module")
def memories(tmp_path_factory):
    """A closed ZarrStorage memory per env id (4 random-policy episodes), by path."""
    paths = {}
    for env_id in ENVS:
        path = str(tmp_path_factory.mktemp("mem") / f"{env_id}.zarr")
        rb = _collect(
            functools.partial(make_env, env_id, seed=0, max_episode_steps=EP_LEN),
            ZarrStorage(path, 1000, env=env_id, sample_tags=True),
            frames=4 * EP_LEN,
        )
        rb.storage.close()
        paths[env_id] = path
    return paths


def _episode_starts(storage) -> torch.Tensor:
    n = len(storage)
    episode = storage["episode"][:n]
    first = torch.ones(n, dtype=torch.bool)
    first[1:] = episode[1:] != episode[:-1]
    return first.nonzero().squeeze(-1)


def _assert_matches_search(goals, priors, dist, mask, memory, metric, goal_key=("next", "achieved_goal"), **filters):
    """The transform's output equals a direct GoalIndex search on ``memory`` for ``goals``."""
    d, index, m = GoalIndex(memory, metric=metric).search(goals, K, **filters)
    assert torch.equal(mask, m)
    torch.testing.assert_close(dist, torch.where(m, d, torch.zeros(())), rtol=0, atol=1e-6)
    expected = memory[index.clamp_min(0)].get(goal_key).float() * m.unsqueeze(-1)
    assert torch.equal(priors, expected)


# -- recall from a memory, through a collector ----------------------------------


@pytest.mark.parametrize("env_id", list(ENVS))
def test_collector_priors_match_search_and_survive_reopen(env_id, memories, tmp_path):
    goal_dim, metric = ENVS[env_id]
    path = memories[env_id]
    env_fn = functools.partial(
        make_env, env_id, seed=1, max_episode_steps=EP_LEN,
        transforms=[RecallTransform(path, K, metric=metric, context_keys={"action": "prior_actions"})],
    )
    out_path = tmp_path / "played.zarr"
    rb = _collect(env_fn, ZarrStorage(out_path, 1000, env=env_id, sample_tags=True), frames=4 * EP_LEN)
    n = len(rb)
    played = rb.storage[:n]
    act_dim = played["action"].shape[-1]
    assert played["prior_goals"].shape == (n, K, goal_dim)
    assert played["prior_goals_dist"].shape == (n, K) and played["prior_goals_dist"].dtype == torch.float32
    assert played["prior_goals_mask"].shape == (n, K) and played["prior_goals_mask"].dtype == torch.bool
    assert played["prior_actions"].shape == (n, K, act_dim)
    assert played["prior_goals_mask"].all()  # the memory holds 40 rows > K
    sample = rb.sample()
    assert sample["prior_goals"].shape == (8, K, goal_dim)
    assert sample["next", "prior_goals_mask"].shape == (8, K)

    # constant within an episode, root and "next" alike
    episode = played["episode"]
    starts = _episode_starts(rb.storage)
    assert len(starts) == 4
    first = played[starts]
    for key in ("prior_goals", "prior_goals_dist", "prior_goals_mask", "prior_actions"):
        per_row = first[key][torch.searchsorted(episode[starts], episode)]
        assert torch.equal(played[key], per_row), key
        assert torch.equal(played["next", key], per_row), key

    # equal to a direct search at reset time (the memory is read-only: unchanged since)
    memory = ZarrStorage(path, read_only=True, sample_tags=True)
    goals = first["desired_goal"]
    _assert_matches_search(goals, first["prior_goals"], first["prior_goals_dist"],
                           first["prior_goals_mask"], memory, metric)
    # the recalled context belongs to the recalled goal (ties share the goal, not the action)
    got = torch.cat([first["prior_goals"], first["prior_actions"]], -1)
    stored = torch.cat([memory[: len(memory)]["next", "achieved_goal"], memory[: len(memory)]["action"]], -1)
    assert (got.reshape(-1, 1, got.shape[-1]) == stored).all(-1).any(-1).all()

    # reopen: the played buffer kept its priors, and a fresh transform on a reopened
    # memory recalls the same ones for the same goals
    rb.storage.close()
    reopened = ZarrStorage(out_path, read_only=True, sample_tags=True)
    assert torch.equal(reopened[:n]["prior_goals"], played["prior_goals"])
    fresh = RecallTransform(path, K, metric=metric).forward(TensorDict({"desired_goal": goals}, [len(goals)]))
    assert torch.equal(fresh["prior_goals"], first["prior_goals"])
    assert torch.equal(fresh["prior_goals_dist"], first["prior_goals_dist"])


# -- same-buffer mode -------------------------------------------------------------


def test_same_buffer_memory_grows_between_episodes(tmp_path):
    rb = TensorDictReplayBuffer(storage=ZarrStorage(tmp_path / "m.zarr", 1000, env="FetchPush-v4", sample_tags=True))
    env = make_env("FetchPush-v4", seed=3, max_episode_steps=EP_LEN, transforms=[RecallTransform(rb, K)])
    for ep in range(3):
        before = len(rb)
        rollout = env.rollout(EP_LEN)
        start = rollout[0]
        if ep == 0:  # nothing remembered yet: zeros, no error
            assert not rollout["prior_goals_mask"].any()
            assert not rollout["prior_goals"].any() and not rollout["prior_goals_dist"].any()
        else:
            assert start["prior_goals_mask"].all()
            _assert_matches_search(start["desired_goal"], start["prior_goals"], start["prior_goals_dist"],
                                   start["prior_goals_mask"], rb.storage, "euclidean")
            # the recalled goals are achieved goals of the earlier episodes
            earlier = rb.storage[:before]["next", "achieved_goal"]
            assert (start["prior_goals"][:, None] == earlier).all(-1).any(-1).all()
        rb.extend(rollout)
    rb.storage.close()


def test_same_buffer_through_collector(tmp_path):
    """The collector's own buffer: an episode recalls what was written before its reset."""
    storage = ZarrStorage(tmp_path / "m.zarr", 1000, env="FetchPush-v4", sample_tags=True)
    rb = TensorDictReplayBuffer(storage=storage)
    fpb = 2 * EP_LEN
    collector = Collector(
        lambda: make_env("FetchPush-v4", seed=4, max_episode_steps=EP_LEN, transforms=[RecallTransform(rb, K)]),
        None, frames_per_batch=fpb, total_frames=4 * fpb, replay_buffer=rb,
    )
    for _ in collector:
        pass
    collector.shutdown()
    assert len(rb) == 4 * fpb
    for row in _episode_starts(storage).tolist():
        # The collector extends the buffer after each batch; the reset that starts a
        # batch's first episode ran during the previous batch's last step.
        batch, offset = divmod(row, fpb)
        seen = fpb * (batch if offset else max(batch - 1, 0))
        start = storage[row]
        if seen == 0:
            assert not start["prior_goals_mask"].any()
            continue
        assert start["prior_goals_mask"].all()
        prefix = LazyTensorStorage(seen)
        prefix.set(torch.arange(seen), storage[:seen])
        _assert_matches_search(start["desired_goal"], start["prior_goals"], start["prior_goals_dist"],
                               start["prior_goals_mask"], prefix, "euclidean")
    storage.close()


# -- batched envs -------------------------------------------------------------------


def test_partial_reset_only_recomputes_reset_rows(transitions):
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000))
    far = transitions(50)
    far["next", "achieved_goal"] += 10.0
    rb.extend(far)
    t = RecallTransform(rb, K)
    env = make_env("FetchPush-v4", num_envs=2, seed=5, max_episode_steps=EP_LEN, transforms=[t])
    td = env.reset()
    old = td.select("prior_goals", "prior_goals_dist", "prior_goals_mask").clone()
    assert old["prior_goals_dist"].min() > 5  # only far goals so far

    # Remember both envs' current goals exactly: any row that is recomputed now
    # recalls a goal at distance 0.
    near = transitions(2, start=50)
    near["next", "achieved_goal"] = td["desired_goal"].clone()
    rb.extend(near)

    td = step_mdp(env.rand_step(td))
    td["_reset"] = torch.tensor([[False], [True]])
    td = env.reset(td)
    assert torch.equal(td["prior_goals"][0], old["prior_goals"][0])
    assert torch.equal(td["prior_goals_dist"][0], old["prior_goals_dist"][0])
    _assert_matches_search(td["desired_goal"][1], td["prior_goals"][1], td["prior_goals_dist"][1],
                           td["prior_goals_mask"][1], rb.storage, "euclidean")
    assert not torch.equal(td["prior_goals"][1], old["prior_goals"][1])

    # and the next steps repeat the per-env cache
    out = env.rand_step(td)
    assert torch.equal(out["next", "prior_goals"], td["prior_goals"])
    # a full reset recomputes everything: env 0's goal is now remembered exactly
    td = env.reset()
    assert td["prior_goals_dist"][:, 0].max() < old["prior_goals_dist"].min()
    env.close()


# -- empty memory and filters ---------------------------------------------------------


def test_empty_memory_gives_zeros_and_false_mask(tmp_path, transitions):
    # a storage with no rows yet: shapes from the env's specs (action from the input spec)
    t = RecallTransform(LazyTensorStorage(100), K, context_keys={"action": "prior_actions"})
    env = make_env("FetchPush-v4", seed=0, max_episode_steps=EP_LEN, transforms=[t])
    check_env_specs(env)
    rollout = env.rollout(3)
    assert rollout["prior_goals"].shape == (3, K, 3) and rollout["prior_actions"].shape == (3, K, 4)
    assert not rollout["prior_goals_mask"].any()
    assert not rollout["prior_goals"].any() and not rollout["prior_actions"].any()

    # a created-but-never-written store, opened by path
    path = str(tmp_path / "empty.zarr")
    ZarrStorage(path, 100).close()
    env = make_env("HandManipulateBlock-v1", seed=0, max_episode_steps=EP_LEN,
                   transforms=[RecallTransform(path, K, metric="pose")])
    check_env_specs(env)
    td = env.reset()
    assert td["prior_goals"].shape == (K, 7) and not td["prior_goals_mask"].any()

    # a memory with rows but none passing the filter
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
    none_succeeded = transitions(20)
    none_succeeded["next", "is_success"].zero_()
    rb.extend(none_succeeded)
    t = RecallTransform(rb, K, success_only=True, context_keys={"action": "prior_actions"})
    out = t.forward(TensorDict({"desired_goal": torch.zeros(2, 3)}, [2]))
    assert not out["prior_goals_mask"].any() and not out["prior_goals_dist"].any()

    # fewer than k matches: the first slots are filled, the rest are zeros with mask False
    two = transitions(2, start=20)
    two["next", "is_success"].fill_(1.0)
    rb.extend(two)
    out = t.forward(TensorDict({"desired_goal": torch.zeros(2, 3)}, [2]))
    assert torch.equal(out["prior_goals_mask"], torch.tensor([[True, True, False, False]] * 2))
    assert (out["prior_goals_dist"][:, :2] > 0).all() and not out["prior_goals_dist"][:, 2:].any()
    assert not out["prior_goals"][:, 2:].any() and not out["prior_actions"][:, 2:].any()
    assert out["prior_actions"][:, :2].ne(0).any(-1).all()


def test_success_and_env_filters(tmp_path, transitions):
    storage = ZarrStorage(tmp_path / "m.zarr", 1000, env="FetchPush-v4", sample_tags=True)
    rb = TensorDictReplayBuffer(storage=storage)
    rb.extend(transitions(70))
    storage.env = "FetchSlide-v4"
    rb.extend(transitions(70, start=70))
    n = len(storage)
    goals = storage[:n]["next", "achieved_goal"]
    success = storage[:n]["next", "is_success"] > 0.5
    slide = storage[:n]["env"] == storage.env_code("FetchSlide-v4")
    queries = TensorDict({"desired_goal": goals[[3, 50, 100, 133]] + 0.003}, [4])

    def brute(keep):
        d = torch.cdist(queries["desired_goal"].double(), goals.double()).masked_fill(~keep, float("inf"))
        return d.topk(K, largest=False).indices

    for kwargs, keep in (
        ({"success_only": True}, success),
        ({"env": "FetchSlide-v4"}, slide),
        ({"env": ["FetchSlide-v4"], "success_only": True}, slide & success),
        ({}, torch.ones(n, dtype=torch.bool)),
    ):
        out = RecallTransform(rb, K, **kwargs).forward(queries.clone())
        assert out["prior_goals_mask"].all()
        assert torch.equal(out["prior_goals"], goals[brute(keep)]), kwargs

    # an env filter through a real env, on a memory of two envs, opened by path
    storage.close()
    env = make_env("FetchPush-v4", seed=0, max_episode_steps=EP_LEN,
                   transforms=[RecallTransform(str(tmp_path / "m.zarr"), K, env="FetchPush-v4")])
    td = env.reset()
    from_push = goals[~slide]
    assert (td["prior_goals"][:, None] == from_push).all(-1).any(-1).all()


# -- specs, collectors, processes -------------------------------------------------------


def _checked_recall_env(memory, num_envs: int = 1, parallel: bool = False) -> object:
    """Env factory run by collectors, in their workers for the multi-process ones."""
    env = make_env("FetchPush-v4", num_envs, seed=0, max_episode_steps=EP_LEN, parallel=parallel,
                   transforms=[RecallTransform(memory, K, context_keys={"action": "prior_actions"})])
    check_env_specs(env)
    return env


@pytest.mark.timeout(600)  # a hang guard, not a speed limit: spawned workers import torch (10+ s on a loaded box)
@pytest.mark.parametrize("num_envs,parallel", [(1, False), (2, False), (2, True)], ids=["single", "serial2", "parallel2"])
def test_check_env_specs_single_and_batched(memories, num_envs, parallel):
    # Outside the batched env the transform stays in this process: a storage object is fine,
    # even with ParallelEnv's spawned workers.
    memory = ZarrStorage(memories["FetchPush-v4"], read_only=True, sample_tags=True)
    env = _checked_recall_env(memory, num_envs, parallel)
    batch = (num_envs,) if num_envs > 1 else ()
    spec = env.observation_spec
    assert spec["prior_goals"].shape == (*batch, K, 3) and spec["prior_goals"].dtype == torch.float32
    assert spec["prior_goals_dist"].shape == (*batch, K)
    assert spec["prior_goals_mask"].shape == (*batch, K) and spec["prior_goals_mask"].dtype == torch.bool
    assert spec["prior_actions"].shape == (*batch, K, 4)
    rollout = env.rollout(3)
    assert spec.is_in(rollout[..., 0].select(*spec.keys(True, True)))
    assert rollout["prior_goals_mask"].all()
    env.close()


@pytest.mark.timeout(600)  # a hang guard, not a speed limit
@pytest.mark.parametrize("kind", ["sync", "multi_sync", pytest.param("multi_async", marks=pytest.mark.full)])
def test_inside_collectors(memories, kind):
    """Multi-process collectors build the env in spawned workers: the memory goes as a path."""
    path = memories["FetchPush-v4"]
    make = functools.partial(_checked_recall_env, path)
    if kind == "sync":
        collector = Collector(make, None, frames_per_batch=EP_LEN, total_frames=2 * EP_LEN)
    elif kind == "multi_sync":
        collector = MultiSyncCollector([make, make], None, frames_per_batch=2 * EP_LEN, total_frames=4 * EP_LEN)
    else:
        collector = MultiAsyncCollector([make, make], None, frames_per_batch=EP_LEN, total_frames=2 * EP_LEN)
    try:
        batches = [data.reshape(-1) for data in collector]
    finally:
        collector.shutdown()
    data = torch.cat(batches)
    assert data["prior_goals"].shape == (len(data), K, 3)
    assert data["next", "prior_actions"].shape == (len(data), K, 4)
    assert data["prior_goals_mask"].all()  # each worker opened the store and found rows
    # what the workers recalled is what a search of the same memory here returns
    memory = ZarrStorage(path, read_only=True, sample_tags=True)
    _assert_matches_search(data["desired_goal"], data["prior_goals"], data["prior_goals_dist"],
                           data["prior_goals_mask"], memory, "euclidean")
    _, index, _ = GoalIndex(memory).search(data["desired_goal"], K)
    recalled = memory[index.reshape(-1)]["action"].reshape(len(data), K, 4)
    stored = memory[: len(memory)]
    # the recalled actions belong to the recalled goals (ties share the goal, not the action)
    got = torch.cat([data["next", "prior_goals"], data["next", "prior_actions"]], -1)
    pairs = torch.cat([stored["next", "achieved_goal"], stored["action"]], -1)
    assert (got.reshape(-1, 1, 7) == pairs).all(-1).any(-1).all()
    assert recalled.shape == data["next", "prior_actions"].shape


def test_pickling_needs_a_path(memories, tmp_path):
    path = memories["FetchPush-v4"]
    t = RecallTransform(path, K)
    t.forward(TensorDict({"desired_goal": torch.zeros(3)}, []))  # opens the store
    clone = pickle.loads(pickle.dumps(t))
    assert clone._source._storage is None  # reopened lazily by the receiving process
    goal = TensorDict({"desired_goal": torch.tensor([1.3, 0.7, 0.42])}, [])
    assert torch.equal(clone.forward(goal.clone())["prior_goals"], t.forward(goal.clone())["prior_goals"])

    storage = ZarrStorage(tmp_path / "w.zarr", 10)
    with pytest.raises(RuntimeError, match="Pass the store's path"):
        pickle.dumps(RecallTransform(TensorDictReplayBuffer(storage=storage), K))
    storage.close()


def test_argument_validation():
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    with pytest.raises(ValueError, match="k must be"):
        RecallTransform(rb, 0)
    with pytest.raises(ValueError, match="out_keys must name 3"):
        RecallTransform(rb, out_keys=("a", "b"))
    with pytest.raises(ValueError, match="unknown metric"):
        RecallTransform(rb, metric="manhattan")
    with pytest.raises(TypeError, match="memory must be"):
        RecallTransform(42)
    with pytest.raises(ValueError, match="distinct"):
        RecallTransform(rb, context_keys={"action": "prior_goals"})


def test_goal_size_mismatch_is_caught_at_spec_time(memories):
    hand_memory = memories["HandManipulateBlock-v1"]  # 7-D goals
    env = make_env("FetchPush-v4", seed=0, transforms=[RecallTransform(hand_memory, K)])
    with pytest.raises(ValueError, match="Goal sizes disagree"):
        env.observation_spec
    env = make_env("FetchPush-v4", seed=0, transforms=[RecallTransform(LazyTensorStorage(10), K, metric="pose")])
    with pytest.raises(ValueError, match="needs goals of dimension 7"):
        env.observation_spec
