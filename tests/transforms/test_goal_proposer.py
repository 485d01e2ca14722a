"""GoalProposer: training episodes pursue remembered achieved goals where the memory is sparsest (MEGA).

Real stores, real Fetch envs and a real recipe run: the proposed goals are goals
the memory achieved, in its sparse regions; the episode pursues its goal with
rewards and success recomputed for it; evaluation goals are untouched; a
memory reopened from disk proposes the same way; and the recipe switch runs
with HER.
"""
from __future__ import annotations

import pickle

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import step_mdp
from training.test_her_recipe import run_recipe

from torchrl_robotmem import GoalProposer, ZarrStorage, make_env, make_reward_fn

ENV = "FetchReach-v4"


def _stored(goals: torch.Tensor, stored: torch.Tensor) -> bool:
    """Whether every row of ``goals`` is, bit for bit, a row of ``stored``."""
    return bool((goals[:, None, :] == stored[None, :, :]).all(-1).any(-1).all())


def _goal_rows(goals: torch.Tensor) -> TensorDict:
    n = goals.shape[0]
    return TensorDict({"observation": torch.zeros(n, 4),
                       ("next", "achieved_goal"): goals,
                       ("next", "done"): torch.ones(n, 1, dtype=torch.bool)}, [n])


@pytest.fixture(scope="module")
def clustered(tmp_path_factory):
    """800 achieved goals in a tight cluster and 200 spread far from it (a dense region and a sparse one)."""
    g = torch.Generator().manual_seed(0)
    center = torch.tensor([1.3, 0.75, 0.5])
    dense = center + 0.002 * torch.randn(800, 3, generator=g)
    sparse = center + torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=-1) * (
        0.1 + 0.1 * torch.rand(200, 1, generator=g))
    path = str(tmp_path_factory.mktemp("clustered") / "m.zarr")
    with ZarrStorage(path, 2000, env=ENV) as s:
        s.set(slice(0, 1000), _goal_rows(torch.cat([dense, sparse])))
    return path, center


def test_proposals_are_achieved_goals_of_the_sparse_region(clustered):
    path, center = clustered
    proposer = GoalProposer(path, ENV, num_candidates=50, k=5, warmup_rows=10, seed=1)
    proposed = proposer.propose(40)
    stored = ZarrStorage(path, read_only=True)["next", "achieved_goal"][:1000]
    assert proposed.shape == (40, 3)
    assert _stored(proposed, stored)  # each one a stored achieved goal
    assert ((proposed - center).norm(dim=-1) > 0.09).all()  # every one from the sparse 20%, none from the cluster
    # the density is what decides: the same draws with k larger than the cluster still prefer the outliers
    assert ((GoalProposer(path, ENV, num_candidates=50, k=50, warmup_rows=10, seed=1).propose(40) - center)
            .norm(dim=-1) > 0.09).all()


@pytest.mark.parametrize("nan_share", [0.01, 0.5, 0.999])
def test_a_goal_that_is_nan_or_inf_is_never_a_candidate(tmp_path, nan_share):
    """Found by a review: with no filter the candidates were drawn over every row, and one whose goal is NaN
    made the index refuse the density query (``ValueError``) at a reset. They are left out, as a filter does."""
    g = torch.Generator().manual_seed(0)
    goals = torch.rand(1000, 3, generator=g)
    bad = torch.randperm(1000, generator=g)[: int(1000 * nan_share)]
    goals[bad[::2], 1] = float("nan")
    goals[bad[1::2], 0] = float("inf")
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000))
    rb.extend(_goal_rows(goals))
    proposed = GoalProposer(rb, ENV, num_candidates=100, k=3, warmup_rows=0, seed=0).propose(50)
    assert proposed.shape == (50, 3) and torch.isfinite(proposed).all()
    assert _stored(proposed, goals[torch.isfinite(goals).all(-1)])


def test_near_goal_proposes_the_sparsest_remembered_goal_on_the_way_to_the_env_goal(clustered):
    """candidates="near_goal": only the stored goals nearest the env's goal compete; the sparsest of them wins."""
    path, center = clustered
    stored = ZarrStorage(path, read_only=True)["next", "achieved_goal"][:1000]
    sparse = stored[800:]
    # env goals just past two outliers on opposite sides: each proposal must come from its own side
    targets = torch.stack([center + 1.5 * (sparse[0] - center), center + 1.5 * (sparse[1] - center)])
    proposer = GoalProposer(path, ENV, num_candidates=10, k=5, warmup_rows=10, seed=1, candidates="near_goal")
    proposed = proposer.propose(2, near=targets)
    assert _stored(proposed, stored)
    nearest = (stored[None] - targets[:, None]).norm(dim=-1).topk(10, largest=False).indices  # the candidates
    for i in range(2):
        assert any(torch.equal(proposed[i], stored[j]) for j in nearest[i])
        assert (proposed[i] - center).norm() > 0.09  # from the sparse side, not the cluster
    assert (proposed[0] - proposed[1]).norm() > 0.1  # each toward its own env goal
    with pytest.raises(ValueError, match="near of shape"):
        proposer.propose(2)
    # an env goal with no stored goal within the filter's max_distance: nothing proposed (the env keeps its goals)
    far = torch.stack([targets[0], center + 100.0])
    bounded = GoalProposer(path, ENV, num_candidates=10, k=5, warmup_rows=10, seed=1, candidates="near_goal",
                           filter={"max_distance": 1.0})
    assert bounded.propose(2, near=far) is None
    assert bounded.propose(1, near=targets[:1]) is not None
    with pytest.raises(ValueError, match="candidates must be one of"):
        GoalProposer(path, ENV, candidates="nearest")


def test_near_goal_in_an_env_proposes_near_each_reset_goal(reach_memory):
    proposer = GoalProposer(reach_memory, ENV, num_candidates=5, k=3, warmup_rows=100, seed=2, candidates="near_goal")
    env = make_env(ENV, 2, seed=11, transforms=[proposer])
    plain = make_env(ENV, 2, seed=11)
    own = plain.reset()["desired_goal"]  # the goals the env draws (the proposer replaces them)
    episode = env.rollout(3)
    stored = ZarrStorage(reach_memory, read_only=True)["next", "achieved_goal"][:400]
    goals = episode["desired_goal"][:, 0]
    nearest = (stored[None] - own[:, None]).norm(dim=-1).topk(5, largest=False).indices
    for i in range(2):
        assert any(torch.equal(goals[i], stored[j]) for j in nearest[i])
    assert proposer.proposed == 2


@pytest.fixture(scope="module")
def reached(tmp_path_factory):
    """One row an episode: 20 goals in a tight cluster, outlier A reached in one episode, outliers B in three."""
    g = torch.Generator().manual_seed(0)
    center = torch.tensor([1.3, 0.75, 0.5])
    cluster = center + 0.002 * torch.randn(20, 3, generator=g)
    a = center + torch.tensor([[0.3, 0.0, 0.0]])  # the sparsest goal: reached once
    b = center + torch.tensor([0.0, 0.2, 0.0]) + 0.003 * torch.randn(3, 3, generator=g)  # sparse, reached 3 times
    path = str(tmp_path_factory.mktemp("reached") / "m.zarr")
    with ZarrStorage(path, 100, env=ENV) as s:
        s.set(slice(0, 24), _goal_rows(torch.cat([cluster, a, b])))
    return path, cluster, a, b


def test_reached_in_proposes_only_goals_the_memory_reached_in_that_many_episodes(reached):
    """MEGA's filter, counted in the memory: the sparsest goal reached once loses to one reached in 3 episodes."""
    path, cluster, a, b = reached

    def propose(**kw):
        return GoalProposer(path, ENV, num_candidates=500, k=2, warmup_rows=1, seed=3, **kw).propose(8)

    def among(goals, group):
        return bool((goals[:, None, :] == group[None, :, :]).all(-1).any(-1).all())

    assert among(propose(), a)  # no filter: the sparsest goal, reached in one episode only
    assert among(propose(reached_in=2), b)  # reached in 3 episodes: the sparsest that qualifies
    assert among(propose(reached_in=4), cluster)  # only the cluster's goals were reached in 4 episodes
    assert among(propose(reached_in=2, reach_radius=1e-4), a)  # no two episodes that close: all tie, density decides
    assert among(propose(reached_in=50), cluster)  # none qualifies: those reached in the most episodes compete
    proposer = GoalProposer(path, ENV, reached_in=2)
    assert proposer.reach_radius == pytest.approx(0.05)  # FetchReach's success distance
    assert "reached_in=2" in repr(proposer)
    for bad in ({"reached_in": -1}, {"reached_in": 1.5}, {"reach_radius": 0.0}, {"reach_radius": "near"}):
        with pytest.raises(ValueError, match="reached_in|reach_radius"):
            GoalProposer(path, ENV, **bad)


def test_reached_in_on_an_unbounded_memory_huge_counts_allocate_nothing_and_errors_say_what_is_missing(
        tmp_path, reached):
    """An unbounded memory's capacity is 2**50 rows: a reached_in, k or near_goal count far above the rows stored
    answers as the rows do (it used to allocate the count: 745 GiB for reached_in=10**9). A filter that cannot be
    counted is refused by name: a task with no success distance at construction, a memory with no episode ids at
    the first proposal."""
    _, cluster, a, b = reached
    goals = torch.cat([cluster, a, b])
    path = str(tmp_path / "unbounded.zarr")
    with ZarrStorage(path, env=ENV) as s:  # no max_size: grows as rows arrive
        s.set(slice(0, 24), _goal_rows(goals))

    def propose(**kw):
        return GoalProposer(path, ENV, num_candidates=500, warmup_rows=1, seed=3, **kw).propose(8)

    assert _stored(propose(k=2, reached_in=10**9), cluster)  # as reached_in=50 on the bounded store
    # k beyond the rows: every candidate is as sparse as any (no k-th neighbour), so only the filter decides:
    # goals reached in 2 episodes (the cluster's, B), never A
    assert _stored(propose(k=10**9, reached_in=2), torch.cat([cluster, b]))
    near = GoalProposer(path, ENV, num_candidates=10**9, k=2, warmup_rows=1, seed=3, candidates="near_goal")
    assert _stored(near.propose(1, near=a), a)
    with pytest.raises(ValueError, match="reach_radius must be a finite"):
        GoalProposer(path, ENV, reached_in=2, reach_radius=float("inf"))
    with pytest.raises(ValueError, match="reached_in=2: HandManipulateBlockRotateZ-v1 has no success distance"):
        GoalProposer(path, "HandManipulateBlockRotateZ-v1", reached_in=2)
    GoalProposer(path, "HandManipulateBlockRotateZ-v1", reached_in=2, reach_radius=0.1)  # given: accepted
    plain = LazyTensorStorage(100)  # rows without the episode column ZarrStorage writes
    plain.set(slice(0, 24), _goal_rows(goals))
    with pytest.raises(ValueError, match="reached_in=2 counts the episodes .* no episode ids"):
        GoalProposer(plain, ENV, warmup_rows=1, seed=3, reached_in=2).propose(1)


def test_no_proposal_below_warmup_and_rate_zero_keeps_the_env_goals(clustered):
    path, _ = clustered
    assert GoalProposer(path, ENV, warmup_rows=1001).propose(3) is None
    env = make_env(ENV, seed=5, transforms=[GoalProposer(path, ENV, warmup_rows=10, rate=0.0, seed=0)])
    plain = make_env(ENV, seed=5)
    assert torch.equal(env.reset()["desired_goal"], plain.reset()["desired_goal"])


def test_kept_goals_keep_the_env_s_own_rewards_and_proposed_ones_get_the_env_s_kind(clustered):
    """An episode on the env's own goal passes through untouched (a dense-reward env keeps its dense rewards);
    one on a proposed goal is rewarded by the task's compute_reward built with the env's gym_kwargs."""
    path, _ = clustered
    torch.manual_seed(0)  # the rollouts' random actions
    plain = make_env(ENV, seed=5, reward_type="dense").rollout(5)
    torch.manual_seed(0)
    kept = make_env(ENV, seed=5, reward_type="dense",
                    transforms=[GoalProposer(path, ENV, warmup_rows=10, rate=0.0, seed=0)]).rollout(5)
    assert (plain["next", "reward"] > -1).all()  # dense: minus the distance
    for key in (("next", "reward"), ("next", "is_success"), "desired_goal"):
        assert torch.equal(kept[key], plain[key]), key
    proposer = GoalProposer(path, ENV, warmup_rows=10, seed=0, gym_kwargs={"reward_type": "dense"})
    proposed = make_env(ENV, seed=5, reward_type="dense", transforms=[proposer]).rollout(5)
    assert proposer.proposed == 1 and not torch.equal(proposed["desired_goal"], plain["desired_goal"])
    dense = make_reward_fn(ENV, reward_type="dense")(proposed)
    assert torch.equal(proposed["next", "reward"], dense.to(proposed["next", "reward"].dtype))
    assert (proposed["next", "reward"] > -1).all()
    with pytest.raises(TypeError, match="gym_kwargs must be a mapping"):
        GoalProposer(path, ENV, gym_kwargs="dense")


def test_a_partial_reset_keeps_the_rewards_of_an_env_on_its_own_goal(clustered):
    """Two envs, the first on a proposed goal, the second (after its own reset, with rate 0) on the env's goal:
    only the first's rewards are recomputed (sparse, the proposer's default), the second keeps the env's (dense)."""
    path, _ = clustered
    proposer = GoalProposer(path, ENV, warmup_rows=10, seed=0)
    env = make_env(ENV, 2, seed=1, reward_type="dense", transforms=[proposer])
    td = env.reset()
    proposer.rate = 0.0  # the next reset keeps the env's own goal
    td = step_mdp(env.rand_step(td))
    td["_reset"] = torch.tensor([[False], [True]])
    td = env.reset(td)
    own_goal = td["desired_goal"][1].clone()
    step = env.rand_step(td)
    assert torch.equal(step["next", "desired_goal"][1], own_goal)
    sparse, dense = make_reward_fn(ENV)(step), make_reward_fn(ENV, reward_type="dense")(step)
    reward = step["next", "reward"]
    assert float(reward[0]) == float(sparse[0])  # recomputed for the proposed goal
    assert abs(float(reward[1]) - float(dense[1])) < 1e-5  # the env's own (in float64 from its own goal)
    assert float(dense[1]) != float(sparse[1])


@pytest.mark.parametrize("dim", [15, 1])
def test_a_memory_of_another_goal_size_is_refused_naming_both_sizes(tmp_path, dim):
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000))
    rb.extend(TensorDict({("next", "achieved_goal"): torch.rand(200, dim)}, [200]))
    env = make_env(ENV, seed=0, transforms=[GoalProposer(rb, ENV, warmup_rows=10, seed=0)])
    with pytest.raises(ValueError, match=rf"'desired_goal' has 3 dimensions but the memory's goals .* have {dim}"):
        env.observation_spec  # noqa: B018 - the spec a collector reads first
    empty = TensorDictReplayBuffer(storage=LazyTensorStorage(1000))  # no rows at the spec: at the first proposal
    env = make_env(ENV, seed=0, transforms=[GoalProposer(empty, ENV, warmup_rows=10, seed=0)])
    empty.extend(TensorDict({("next", "achieved_goal"): torch.rand(200, dim)}, [200]))
    with pytest.raises(ValueError, match=rf"'desired_goal' has 3 dimensions but the memory's goals .* have {dim}"):
        env.reset()


@pytest.fixture(scope="module")
def reach_memory(tmp_path_factory):
    """A real FetchReach memory: 400 random-policy frames (8 episodes)."""
    path = str(tmp_path_factory.mktemp("reach") / "reach.zarr")
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 5000, env=ENV))
    collector = Collector(lambda: make_env(ENV, seed=0), None, frames_per_batch=200, total_frames=400)
    for data in collector:
        rb.extend(data.reshape(-1))
    collector.shutdown()
    rb.storage.close()
    return path


def test_an_episode_pursues_its_proposed_goal_with_consistent_rewards(reach_memory):
    proposer = GoalProposer(reach_memory, ENV, num_candidates=20, k=3, warmup_rows=100, seed=2)
    env = make_env(ENV, 3, seed=7, transforms=[proposer])
    episode = env.rollout(20)  # [3 envs, 20 steps]
    stored = ZarrStorage(reach_memory, read_only=True)["next", "achieved_goal"][:400]
    goals = episode["desired_goal"][:, 0]
    assert _stored(goals, stored)  # proposed: achieved by the memory
    assert (episode["desired_goal"] == goals.unsqueeze(1)).all() and (episode["next", "desired_goal"] == goals.unsqueeze(1)).all()
    reward_fn = make_reward_fn(ENV)
    expected = reward_fn(episode)  # the task's own compute_reward of the achieved goal and the goal pursued
    assert torch.equal(episode["next", "reward"], expected.to(episode["next", "reward"].dtype))
    success = reward_fn.success(episode)
    assert torch.equal(episode["next", "is_success"].reshape(success.shape).float(), success)
    assert proposer.proposed == 3 and proposer.kept == 0


def test_a_partial_reset_proposes_for_the_reset_env_only(reach_memory):
    proposer = GoalProposer(reach_memory, ENV, num_candidates=20, k=3, warmup_rows=100, seed=3)
    env = make_env(ENV, 2, seed=1, transforms=[proposer])
    td = env.reset()
    first = td["desired_goal"].clone()
    td = step_mdp(env.rand_step(td))  # what a collector holds between steps
    td["_reset"] = torch.tensor([[False], [True]])
    after = env.reset(td)
    assert torch.equal(after["desired_goal"][0], first[0])  # the running env keeps the goal it pursues
    assert not torch.equal(after["desired_goal"][1], first[1])
    assert proposer.proposed == 3


def test_evaluation_goals_are_untouched_and_a_reopened_memory_proposes_alike(reach_memory, tmp_path):
    """The recipe's eval env has no proposer; a pickled proposer, reopening the store, proposes the same goals."""
    from omegaconf import OmegaConf

    from recipes.her.utils import make_environment

    cfg = OmegaConf.create({
        "seed": 0, "env": {"name": ENV, "max_episode_steps": 50, "num_envs": 1, "parallel": False},
        "logger": {"eval_episodes": 3},
        "memory": {"recall": {"enabled": False},
                   "propose": {"enabled": True, "_target_": "torchrl_robotmem.GoalProposer", "num_candidates": 10,
                               "k": 3, "rate": 1.0, "warmup_rows": 100}},
    })
    storage = ZarrStorage(reach_memory, read_only=True)
    train, evaluation = make_environment(cfg, memory=storage)
    assert any(isinstance(t, GoalProposer) for t in train.transform)
    assert not any(isinstance(t, GoalProposer) for t in evaluation.transform)
    plain = make_env(ENV, 3, seed=cfg.seed + 10_000)
    evaluation.set_seed(cfg.seed + 10_000)
    plain.set_seed(cfg.seed + 10_000)
    assert torch.equal(evaluation.reset()["desired_goal"], plain.reset()["desired_goal"])
    # reopened: a proposer on the path, sent through pickle, proposes what one on the live storage does
    a = GoalProposer(reach_memory, ENV, num_candidates=30, k=3, warmup_rows=100, seed=4)
    b = pickle.loads(pickle.dumps(GoalProposer(reach_memory, ENV, num_candidates=30, k=3, warmup_rows=100, seed=4)))
    assert torch.equal(a.propose(5), b.propose(5))


def test_bad_arguments_are_refused_naming_them(reach_memory):
    for kwargs, named in (({"k": 0}, "k must be"), ({"num_candidates": -1}, "num_candidates must be"),
                          ({"rate": 1.5}, "rate must be"), ({"warmup_rows": 2.5}, "warmup_rows must be")):
        with pytest.raises(ValueError, match=named):
            GoalProposer(reach_memory, ENV, **kwargs)
    with pytest.raises(TypeError, match="env must be the task's id"):
        GoalProposer(reach_memory, "")


def test_the_recipe_switch_runs_with_her_and_reports_the_proposals(tmp_path):
    mem = tmp_path / "mem.zarr"
    s = run_recipe(tmp_path, f"memory.path={mem}", "memory.propose.enabled=true", "memory.propose.warmup_rows=25",
                   "memory.propose.num_candidates=10", "memory.propose.k=3", "collector.total_frames=150",
                   "collector.frames_per_batch=50")
    assert s["frames"] == 150 and s["memory_rows_after"] == 150 and s["updates"] > 0
    # episodes of 50 frames, one a batch; an episode's reset comes before the batch that ends it is stored: the
    # first two start on an empty memory (kept), the third on the first episode's 50 rows (proposed)
    assert s["proposer"]["kept"] >= 2 and s["proposer"]["proposed"] >= 1
    stored = ZarrStorage(mem, read_only=True)
    goals, achieved = stored["desired_goal"][:150], stored["next", "achieved_goal"][:50]
    assert _stored(goals[100:101], achieved)  # the third episode pursues a goal the first achieved
    assert (goals[100:] == goals[100]).all()
    reward = make_reward_fn(ENV)(stored[:150])
    assert torch.equal(stored["next", "reward"][:150], reward.to(stored["next", "reward"].dtype))


def test_the_env_spec_is_read_before_the_run_creates_its_memory(tmp_path):
    """Found by a review: the goal-size check at the spec opened a path memory the run had not created yet."""
    path = str(tmp_path / "m.zarr")
    env = make_env(ENV, seed=0, transforms=[GoalProposer(path, ENV, warmup_rows=10, seed=0)])
    assert env.observation_spec["observation"].shape == (10,)  # sizing a policy, before the memory exists
    storage = ZarrStorage(path, 1000, env=ENV)
    assert env.rollout(3)["next", "reward"].shape == (3, 1)
    storage.close()
