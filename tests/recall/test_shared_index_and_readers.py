"""The recall package's seams: one shared index per storage, one match per episode, refreshing readers.

* :meth:`GoalIndex.for_storage` is THE index of a storage: a sampler, a
  RecallTransform and a RobotMemory over the same storage search one object,
  built once.
* ``one_per_episode=True`` returns the nearest row of each of the k nearest
  episodes, checked against a brute-force reference on real Zarr stores
  (appends, ring overwrites, filters) and a LazyTensorStorage.
* ``RecallTransform(path, refresh_every=N)`` sees the rows a writer committed
  after N steps of a real env (FetchReach-v4).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _rows import fetch_rows
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_robotmem import GoalIndex, GoalSimilaritySampler, RecallTransform, RobotMemory, ZarrStorage, make_env
from torchrl_robotmem.goal_index import RowFilter, recall
from torchrl_robotmem.goal_index.metrics import EuclideanMetric, PoseMetric

torch.set_num_threads(1)

GOAL = ("next", "achieved_goal")
SUCCESS = ("next", "is_success")


def column(storage, key):
    return storage[key][: len(storage)] if isinstance(storage, ZarrStorage) else storage._storage.get(key)[: len(storage)]


def clustered_rows(n, gen, start=0, spread=0.02):
    """FetchPush-shaped rows whose goals cluster per 50-step episode: the k nearest rows share episodes."""
    rows = fetch_rows(n, gen, start=start)
    episode = torch.arange(start, start + n) // 50
    centers = torch.rand(int(episode.max()) + 1, 3, generator=torch.Generator().manual_seed(7))
    rows[GOAL] = centers[episode] + spread * torch.randn(n, 3, generator=gen)
    return rows


def brute_force_episodes(storage, goals, k, keep=None, metric=None, max_distance=None):
    """Reference: per query, the k episodes with the smallest min distance, with that distance."""
    metric = metric or EuclideanMetric()
    g = column(storage, GOAL).double()
    ep = column(storage, "episode").reshape(-1)
    d = metric.pairwise(torch.as_tensor(goals, dtype=torch.float64).reshape(-1, g.shape[1]), g)
    if keep is not None:
        d[:, ~keep] = math.inf
    if max_distance is not None:
        d[d > max_distance] = math.inf
    out_d = torch.full((d.shape[0], k), math.inf, dtype=torch.float64)
    out_e = torch.full((d.shape[0], k), -1, dtype=torch.int64)
    for i, row in enumerate(d):
        best = {}
        for e, dist in zip(ep.tolist(), row.tolist()):
            if dist < best.get(e, math.inf):
                best[e] = dist
        ranked = sorted(best.items(), key=lambda item: item[1])[:k]
        for j, (e, dist) in enumerate(ranked):
            out_d[i, j], out_e[i, j] = dist, e
    return out_d, out_e


def assert_one_per_episode(index, storage, goals, k, keep=None, metric=None, **kw):
    dist, rows, mask = index.search(goals, k, one_per_episode=True, **kw)
    if dist.ndim == 1:  # one goal
        dist, rows, mask = dist[None], rows[None], mask[None]
    ref_d, ref_e = brute_force_episodes(storage, goals, k, keep, metric, kw.get("max_distance"))
    assert torch.equal(mask, torch.isfinite(ref_d))
    torch.testing.assert_close(dist[mask].double(), ref_d[mask], rtol=1e-5, atol=1e-6)
    ep = column(storage, "episode").reshape(-1)
    got_e = torch.where(mask, ep[rows.clamp_min(0)], -1)
    assert torch.equal(got_e, ref_e), "episodes differ from brute force"
    for r in got_e:  # k different episodes
        r = r[r >= 0]
        assert r.unique().numel() == r.numel()
    # each row is its episode's nearest, at the distance returned
    g = column(storage, GOAL).double()
    m = metric or EuclideanMetric()
    q = torch.as_tensor(goals, dtype=torch.float64).reshape(-1, g.shape[1])
    recomputed = m.distance(q[:, None, :], g[rows.clamp_min(0)])
    torch.testing.assert_close(recomputed[mask], ref_d[mask], rtol=1e-5, atol=1e-6)


# -- one shared index ------------------------------------------------------------------
def test_sampler_transform_and_robotmemory_share_one_index(tmp_path):
    gen = torch.Generator().manual_seed(0)
    mem = RobotMemory(tmp_path / "m.zarr", max_size=5000, env="FetchPush-v4")
    mem.buffer.extend(fetch_rows(2000, gen))
    sampler = GoalSimilaritySampler(num_candidates=64)
    rb = TensorDictReplayBuffer(storage=mem.storage, sampler=sampler, batch_size=32)
    transform = RecallTransform(rb, k=3)
    goals = torch.rand(4, 3, generator=gen)

    with sampler.query(goals[0]):
        assert rb.sample()["goal_distance"].shape == (32,)
    priors = transform.forward(TensorDict({"desired_goal": goals}, [4]))
    recalled = mem.recall(goals, top_k=3, one_per_episode=False)  # rows, as the transform's priors

    index = mem.index
    assert sampler.index_for(mem.storage) is index
    assert transform.index is index
    assert GoalIndex.for_storage(rb) is index
    assert index.stats()["view_builds"] == 1  # built once, for all three
    assert torch.equal(priors["prior_goals"], recalled[GOAL])
    # new rows reach all three through the one index, without a rebuild
    rb.extend(fetch_rows(100, gen, start=2000))
    fresh = mem.recall(goals, top_k=3, one_per_episode=False)
    assert torch.equal(transform.forward(TensorDict({"desired_goal": goals}, [4]))["prior_goals"], fresh[GOAL])
    with sampler.query(goals):
        rb.sample()
    assert index.stats() == {"rows": 2100, "revision": index.revision, "views": 1, "view_builds": 1}
    mem.close()


def test_row_filter_is_checked_once_and_shared():
    assert RowFilter(env="FetchPush-v4").env == ("FetchPush-v4",)
    assert RowFilter(run=[2, 1]).resolve(None).runs == (1, 2)
    assert RowFilter(success_only=True) == RowFilter(success_only=True, env=None)
    for bad, match in [({"success_only": 1}, "success_only"), ({"env": []}, "env must be"),
                       ({"env": [1.5]}, "env must be"), ({"run": "first"}, "run must be"),
                       ({"run": [True]}, "run must be")]:
        with pytest.raises(ValueError, match=match):
            RowFilter(**bad)
    with pytest.raises(ValueError, match="known envs"):
        RowFilter(env="HandReach-v3").resolve(("FetchPush-v4",))
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(500))
    rb.extend(fetch_rows(400, torch.Generator().manual_seed(1), envs=2, tags=True))
    index = GoalIndex(rb)
    flt = RowFilter(success_only=True, env=1)
    queries = torch.rand(3, 3, generator=torch.Generator().manual_seed(2))
    a = index.search(queries, 4, filter=flt)
    b = index.search(queries, 4, success_only=True, env=1)
    assert index.stats()["views"] == 1
    for x, y in zip(a, b, strict=True):  # the same answer: distances, rows and mask
        assert torch.equal(x, y)
    assert a[2].any()  # (rows pass the filter: the answer is not all padding)
    assert torch.equal(index.member_rows(flt), index.member_rows(success_only=True, env=[1]))
    with pytest.raises(ValueError, match="not both"):
        index.search(torch.rand(3), 4, filter=flt, success_only=True)


# -- one match per episode ------------------------------------------------------------
def test_one_per_episode_matches_brute_force_through_ring_overwrites(tmp_path):
    gen = torch.Generator().manual_seed(3)
    storage = ZarrStorage(tmp_path / "ep.zarr", 1200, env="FetchPush-v4", chunk_rows=64)
    rb = TensorDictReplayBuffer(storage=storage)
    index = GoalIndex(rb, tail_size=64, rebuild_fraction=0.3)
    queries = torch.rand(12, 3, generator=gen)
    for step in range(9):  # 9 * 300 rows through a 1200-row ring: episodes are cut by the wrap
        rb.extend(clustered_rows(300, gen, start=300 * step))
        assert_one_per_episode(index, storage, queries, 5)
    assert len(storage) == storage.max_size
    success = column(storage, SUCCESS) > 0.5
    assert_one_per_episode(index, storage, queries, 4, keep=success, success_only=True)
    assert_one_per_episode(index, storage, queries, 6, max_distance=0.2)
    assert_one_per_episode(index, storage, queries[0], 3)  # one goal
    # more episodes asked for than stored: every episode once, the rest masked
    n_episodes = column(storage, "episode").unique().numel()
    dist, rows, mask = index.search(queries[:2], n_episodes + 3, one_per_episode=True)
    assert mask.sum(1).tolist() == [n_episodes, n_episodes] and (rows[~mask] == -1).all()
    # recall(), the module function, and a reopened reader agree
    out = recall(rb, queries, 5, one_per_episode=True)
    assert torch.equal(out["index"], index.search(queries, 5, one_per_episode=True)[1])
    assert (out["episode"].sort(1).values.diff(dim=1) > 0).all()
    storage.flush()
    reader = ZarrStorage(tmp_path / "ep.zarr", read_only=True)
    assert torch.equal(GoalIndex(reader).search(queries, 5, one_per_episode=True)[1], out["index"])
    storage.close()


def test_one_per_episode_pose_metric_and_missing_column():
    gen = torch.Generator().manual_seed(4)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(3000))
    rows = fetch_rows(3000, gen, goal_dim=7, tags=True)
    rows[GOAL][:, :3] = rows[GOAL][:, :3].view(60, 50, 3)[:, :1].expand(60, 50, 3).reshape(3000, 3)
    rb.extend(rows)  # every episode holds one position: its rows differ by orientation only
    queries = fetch_rows(8, gen, goal_dim=7)[GOAL]
    for backend in ("kdtree", "brute"):
        index = GoalIndex(rb, metric="pose", backend=backend)
        assert_one_per_episode(index, rb.storage, queries, 5, metric=PoseMetric())
    bare = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    bare.extend(TensorDict({GOAL: torch.rand(5, 3)}, [5]))
    with pytest.raises(KeyError, match="one_per_episode needs the column 'episode'"):
        GoalIndex(bare).search(torch.zeros(3), 2, one_per_episode=True)
    with pytest.raises(ValueError, match="one_per_episode must be a bool"):
        GoalIndex(bare).search(torch.zeros(3), 2, one_per_episode="yes")


def test_transform_one_per_episode(tmp_path):
    gen = torch.Generator().manual_seed(5)
    rb = TensorDictReplayBuffer(storage=ZarrStorage(tmp_path / "t.zarr", 2000, env="FetchReach-v4"))
    rb.extend(clustered_rows(1000, gen))
    goals = torch.rand(6, 3, generator=gen)
    td = TensorDict({"desired_goal": goals}, [6])
    plain = RecallTransform(rb, k=4).forward(td.clone())
    per_ep = RecallTransform(rb, k=4, one_per_episode=True).forward(td.clone())
    dist, rows, _ = GoalIndex.for_storage(rb).search(goals, 4, one_per_episode=True)
    assert torch.equal(per_ep["prior_goals"], rb.storage[GOAL][rows])
    torch.testing.assert_close(per_ep["prior_goals_dist"], dist)
    episodes = rb.storage["episode"][rows]
    assert all(e.unique().numel() == 4 for e in episodes)
    assert (plain["prior_goals_dist"] <= per_ep["prior_goals_dist"]).all()  # the plain k nearest are nearer
    rb.storage.close()


# -- refreshing a read-only memory ------------------------------------------------------
def test_transform_refresh_every_sees_rows_a_writer_committed(tmp_path):
    path = str(tmp_path / "live.zarr")
    gen = torch.Generator().manual_seed(6)
    writer = TensorDictReplayBuffer(storage=ZarrStorage(path, 5000, env="FetchReach-v4"))
    far = fetch_rows(100, gen)
    far[GOAL] = 5.0 + torch.rand(100, 3, generator=gen)  # far from every FetchReach goal
    writer.extend(far)
    writer.storage.flush()

    transform = RecallTransform(path, k=3, refresh_every=4)
    env = make_env("FetchReach-v4", seed=0, transforms=[transform])
    td = env.reset()
    assert td["prior_goals_mask"].all() and (td["prior_goals"] >= 5.0).all()

    near = fetch_rows(1000, gen, start=100)  # rows all over the FetchReach goal space
    near[GOAL] = torch.tensor([1.05, 0.4, 0.3]) + torch.rand(1000, 3, generator=gen) * torch.tensor([0.6, 0.7, 0.6])
    writer.extend(near)
    writer.storage.flush()  # committed: a reader may see them now

    for _ in range(3):
        env.rand_step(td)
    td = env.reset()  # 3 steps < refresh_every: the memory was not re-read
    assert (td["prior_goals"] >= 5.0).all()
    for _ in range(4):
        td = env.rand_step(td)
        assert (td["next", "prior_goals"] >= 5.0).all()  # priors never change within an episode
    td = env.reset()  # after 4 steps: re-read at this reset
    assert len(transform.storage) == 1100
    assert (td["prior_goals"] < 5.0).all()
    reader = ZarrStorage(path, read_only=True)
    dist, rows, _ = GoalIndex(reader).search(td["desired_goal"], 3)
    assert torch.equal(td["prior_goals"], reader[GOAL][rows])
    torch.testing.assert_close(td["prior_goals_dist"], dist)
    writer.storage.close()


def test_refresh_every_bad_values(tmp_path):
    storage = ZarrStorage(tmp_path / "w.zarr", 100, env="FetchReach-v4")
    with pytest.raises(ValueError, match="refresh_every applies to a read-only memory"):
        RecallTransform(storage, refresh_every=10)
    with pytest.raises(ValueError, match="refresh_every applies"):
        RecallTransform(LazyTensorStorage(10), refresh_every=10)
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="refresh_every must be"):
            RecallTransform(str(tmp_path / "w.zarr"), refresh_every=bad)
    with pytest.raises(ValueError, match="one_per_episode must be"):
        RecallTransform(storage, one_per_episode=1)
    storage.close()
    assert RecallTransform(ZarrStorage(tmp_path / "w.zarr", read_only=True), refresh_every=1).refresh_every == 1


def test_member_rows_and_revision_are_public():
    gen = torch.Generator().manual_seed(8)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(400))
    rb.extend(fetch_rows(300, gen, tags=True))
    index = GoalIndex.for_storage(rb)
    rev = index.revision
    success = (column(rb.storage, SUCCESS) > 0.5).numpy()
    assert index.member_rows(success_only=True).tolist() == np.flatnonzero(success).tolist()
    assert index.revision == rev  # no change, no new revision
    rb.extend(fetch_rows(50, gen, start=300, tags=True))
    assert index.revision > rev
    assert index.member_rows().numel() == 350


# -- one filter argument ----------------------------------------------------------------
def test_the_subpackage_and_the_function_have_different_names():
    import importlib

    import torchrl_robotmem

    assert torchrl_robotmem.recall is recall and callable(recall)
    assert importlib.import_module("torchrl_robotmem.goal_index").GoalIndex is GoalIndex
    with pytest.raises(ModuleNotFoundError):  # the old subpackage path is gone, not shimmed
        importlib.import_module("torchrl_robotmem.recall")


def two_env_store(path):
    """A real ZarrStorage of two runs: 1500 FetchPush-v4 rows (run 0), then 1000 FetchSlide-v4 rows (run 1)."""
    gen = torch.Generator().manual_seed(11)
    storage = ZarrStorage(path, 4000, env="FetchPush-v4", chunk_rows=64)
    TensorDictReplayBuffer(storage=storage).extend(clustered_rows(1500, gen))
    storage.close()
    storage = ZarrStorage(path, env="FetchSlide-v4")
    TensorDictReplayBuffer(storage=storage).extend(clustered_rows(1000, gen, start=1500))
    storage.flush()
    return storage


FILTER_FORMS = [
    {"success_only": True},
    {"env": "FetchSlide-v4"},
    {"run": [0]},
    {"success_only": True, "env": ["FetchPush-v4"], "max_distance": 0.3},
    {"env": 1, "one_per_episode": True},
]


def test_filter_keywords_and_row_filter_give_the_same_rows(tmp_path):
    storage = two_env_store(tmp_path / "f.zarr")
    rb = TensorDictReplayBuffer(storage=storage)
    mem = RobotMemory(tmp_path / "f.zarr", read_only=True)
    index = GoalIndex.for_storage(storage)
    queries = torch.rand(6, 3, generator=torch.Generator().manual_seed(3))
    goals = TensorDict({"desired_goal": queries}, [6])
    for kw in FILTER_FORMS:
        flt = RowFilter(**kw)
        assert RowFilter.coerce(**kw) == RowFilter.coerce(flt) == RowFilter.coerce(dict(kw)) == flt
        dist, rows, mask = index.search(queries, 5, **kw)
        assert mask.any(), kw  # (rows pass the filter: the answer is not all padding)
        for form in (flt, dict(kw)):
            for x, y in zip(index.search(queries, 5, filter=form), (dist, rows, mask), strict=True):
                assert torch.equal(x, y), kw
            assert torch.equal(recall(rb, queries, 5, filter=form)["index"], rows)
            assert torch.equal(index.member_rows(form), index.member_rows(**kw))
        assert torch.equal(recall(rb, queries, 5, **kw)["index"], rows)
        assert torch.equal(index.recall(queries, 5, **kw)["index"], rows)
        # the memory's own reader (another ZarrStorage object on the same store): the same rows
        # (RobotMemory recalls episodes by default: one_per_episode=False asks for rows, as the others)
        assert torch.equal(mem.recall(queries, top_k=5, **{"one_per_episode": False, **kw})["index"], rows)
        assert torch.equal(mem.recall(queries, top_k=5, filter=flt, one_per_episode=False)["index"], rows)
        by_keywords = RecallTransform(rb, 5, **kw)
        by_filter = RecallTransform(rb, 5, filter=flt)
        assert by_keywords.filter == by_filter.filter == flt
        priors = by_keywords.forward(goals.clone())
        assert torch.equal(priors["prior_goals_mask"], mask)
        assert torch.equal(priors["prior_goals"], by_filter.forward(goals.clone())["prior_goals"])
        sampler = GoalSimilaritySampler(num_candidates=16, **kw)
        assert sampler.filter == GoalSimilaritySampler(filter=flt).filter == flt
        fresh = GoalSimilaritySampler()
        fresh.load_state_dict(sampler.state_dict())
        assert fresh.filter == flt
        if bool(mask[:, 0].all()):
            srb = TensorDictReplayBuffer(storage=storage, sampler=sampler, batch_size=64)
            with sampler.query(queries):
                drawn = srb.sample()["index"]
            assert np.isin(drawn.numpy(), index.member_rows(flt).numpy()).all(), kw
    mem.close()
    storage.close()


def test_each_bad_filter_keyword_is_named(tmp_path):
    storage = two_env_store(tmp_path / "b.zarr")
    rb = TensorDictReplayBuffer(storage=storage)
    mem = RobotMemory(tmp_path / "b.zarr", read_only=True)
    index = GoalIndex.for_storage(storage)
    q = torch.zeros(3)
    readers = {
        "GoalIndex.search": lambda **kw: index.search(q, 3, **kw),
        "GoalIndex.recall": lambda **kw: index.recall(q, 3, **kw),
        "GoalIndex.member_rows": lambda **kw: index.member_rows(**kw),
        "recall": lambda **kw: recall(rb, q, 3, **kw),
        "GoalSimilaritySampler": lambda **kw: GoalSimilaritySampler(**kw),
        "RecallTransform": lambda **kw: RecallTransform(rb, 3, **kw),
        "RobotMemory.recall": lambda **kw: mem.recall(q, 3, **kw),
        "RowFilter.coerce": lambda **kw: RowFilter.coerce(**kw),
    }
    bad = [
        ({"sucess_only": True}, TypeError, "unknown filter keyword 'sucess_only'"),
        ({"radius": 0.1}, TypeError, "'radius'"),
        ({"success_only": "yes"}, ValueError, "success_only must be a bool"),
        ({"env": []}, ValueError, "env must be"),
        ({"env": 1.5}, ValueError, "env must be"),
        ({"run": "first"}, ValueError, "run must be"),
        ({"max_distance": -1.0}, ValueError, "max_distance must be >= 0"),
        ({"max_distance": "far"}, ValueError, "max_distance must be a number"),
        ({"one_per_episode": "yes"}, ValueError, "one_per_episode must be a bool"),
        ({"filter": RowFilter(success_only=True), "env": "FetchPush-v4"}, ValueError, "filter= or env=, not both"),
        ({"filter": {"success_only": True}, "run": 0}, ValueError, "filter= or run=, not both"),
        ({"filter": {"succes": True}}, TypeError, "'succes'"),
        ({"filter": 3}, TypeError, "filter must be a RowFilter"),
        ({"filter": "success_only"}, TypeError, "filter must be a RowFilter"),
    ]
    for name, call in readers.items():
        for kw, error, match in bad:
            with pytest.raises(error, match=match):
                call(**kw)
                pytest.fail(f"{name}({kw}) did not raise")
    # a name the storage does not know is caught where it is resolved, naming the known ones
    with pytest.raises(ValueError, match="known envs"):
        index.search(q, 3, env="HandReach-v3")
    mem.close()
    storage.close()


def test_row_filter_from_a_hydra_config():
    instantiate = pytest.importorskip("hydra.utils").instantiate
    from omegaconf import OmegaConf

    cfg = OmegaConf.create({"_target_": "torchrl_robotmem.goal_index.RowFilter", "success_only": True,
                            "env": ["FetchPush-v4", "FetchSlide-v4"], "run": 1, "max_distance": 0.5})
    flt = instantiate(cfg)
    assert flt == RowFilter(success_only=True, env=("FetchPush-v4", "FetchSlide-v4"), run=(1,), max_distance=0.5)
    sampler = instantiate({"_target_": "torchrl_robotmem.GoalSimilaritySampler", "num_candidates": 8, "filter": cfg})
    assert sampler.filter == flt
    # a plain mapping without _target_ (a DictConfig group) is coerced too
    assert GoalSimilaritySampler(filter=OmegaConf.create({"env": ["FetchPush-v4"]})).filter == RowFilter(env="FetchPush-v4")
    assert RowFilter(**flt.to_dict()) == flt
