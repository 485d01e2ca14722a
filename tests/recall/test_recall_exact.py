"""GoalIndex / recall: exactness against brute force, filters, consistency with the storage, bad input."""
from __future__ import annotations

import gc
import math
import weakref
from functools import partial

import _rows
import numpy as np
import pytest
import torch
from _rows import unit_quat
from tensordict import TensorDict
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

from torchrl_robotmem.goal_index import GoalIndex, recall
from torchrl_robotmem.goal_index.metrics import EuclideanMetric, PoseMetric, get_metric

torch.set_num_threads(1)

GOAL = ("next", "achieved_goal")
ENV_NAMES = ("FetchPush-v4", "FetchSlide-v4", "FetchPickAndPlace-v4")
# FetchPush-shaped rows tagged as a ZarrStorage would tag them: env (codes into ENV_NAMES), run, episode
fetch_rows = partial(_rows.fetch_rows, envs=len(ENV_NAMES), tags=True)


def make_rb(n, capacity=None, gen=None, goal_dim=3, storage_cls=LazyTensorStorage):
    gen = gen if gen is not None else torch.Generator().manual_seed(0)
    rb = TensorDictReplayBuffer(storage=storage_cls(capacity or n))
    if n:
        rb.extend(fetch_rows(n, gen, goal_dim=goal_dim))
    return rb, gen


def column(rb, key):
    st = rb.storage
    return st._storage.get(key)[: len(st)]


def brute_force(rb, goals, k, metric=None, keep=None, max_distance=None):
    """Reference: every distance in float64, sorted; rows outside ``keep`` excluded."""
    metric = metric or EuclideanMetric()
    g = column(rb, GOAL).double()
    q = torch.as_tensor(goals, dtype=torch.float64).reshape(-1, g.shape[1])
    d = metric.pairwise(q, g)
    if keep is not None:
        d[:, ~keep] = math.inf
    if max_distance is not None:
        d[d > max_distance] = math.inf
    d, i = torch.sort(d, dim=1, stable=True)
    if d.shape[1] < k:
        pad = k - d.shape[1]
        d = torch.cat([d, torch.full((d.shape[0], pad), math.inf, dtype=d.dtype)], 1)
        i = torch.cat([i, torch.full((i.shape[0], pad), -1)], 1)
    d, i = d[:, :k], i[:, :k]
    i = torch.where(torch.isfinite(d), i, -1)
    return d.float(), i


def assert_exact(index, rb, goals, k, metric=None, keep=None, **kw):
    dist, idx, mask = index.search(goals, k, **kw)
    ref_d, ref_i = brute_force(rb, goals, k, metric, keep, kw.get("max_distance"))
    if dist.ndim == 1:
        dist, idx, mask = dist[None], idx[None], mask[None]
    assert torch.equal(mask, torch.isfinite(ref_d))
    assert torch.equal(idx == -1, ~mask)
    torch.testing.assert_close(dist[mask], ref_d[mask], rtol=1e-5, atol=1e-6)
    # the same rows, except where two distances tie to float precision
    differ = (idx != ref_i) & mask
    if differ.any():
        gaps = (ref_d[:, 1:] - ref_d[:, :-1]).abs()
        near_tie = torch.zeros_like(differ)
        near_tie[:, 1:] |= gaps < 1e-6
        near_tie[:, :-1] |= gaps < 1e-6
        assert not (differ & ~near_tie).any(), "indices differ from brute force"
    # distances are those of the returned rows
    g = column(rb, GOAL).double()
    q = torch.as_tensor(goals, dtype=torch.float64).reshape(-1, g.shape[1])
    m = metric or EuclideanMetric()
    rows = idx.clamp_min(0)
    recomputed = m.distance(q[:, None, :], g[rows]).float()
    torch.testing.assert_close(dist[mask], recomputed[mask], rtol=1e-5, atol=1e-6)


# -- exactness ------------------------------------------------------------------
@pytest.mark.parametrize("k", [1, 5, 33])
def test_search_matches_brute_force(k):
    rb, gen = make_rb(5000)
    index = GoalIndex(rb)
    assert_exact(index, rb, torch.rand(64, 3, generator=gen), k)
    assert_exact(index, rb, torch.rand(3, generator=gen), k)  # unbatched
    assert index.backend_in_use == "kdtree"


def test_recall_returns_full_context_of_nearest_rows():
    rb, gen = make_rb(2000)
    goals = torch.rand(4, 3, generator=gen)
    out = GoalIndex(rb).recall(goals, k=6)
    assert out.batch_size == torch.Size([4, 6])
    stored = rb.storage._storage
    expected_keys = set(stored.keys(True, True)) | {"distance", "mask", "index"}
    assert set(out.keys(True, True)) == expected_keys
    assert out["distance"].dtype == torch.float32
    assert out["mask"].dtype == torch.bool and out["mask"].all()
    assert out["index"].dtype == torch.int64
    rows = stored[out["index"]]
    for key in stored.keys(True, True):
        if key == "index":
            continue
        assert torch.equal(out[key], rows[key]), key
    d = (out["next", "achieved_goal"] - goals[:, None]).norm(dim=-1)
    torch.testing.assert_close(out["distance"], d)
    assert (out["distance"][:, 1:] >= out["distance"][:, :-1]).all()
    # unbatched goal -> batch [k]; list and numpy goals accepted
    assert GoalIndex(rb).recall([0.5, 0.5, 0.5], k=3).batch_size == torch.Size([3])
    assert GoalIndex(rb).recall(np.array([0.5, 0.5, 0.5]), k=3).batch_size == torch.Size([3])


def test_exact_after_appends_ring_overwrites_and_inplace_writes():
    rb, gen = make_rb(3000, capacity=4000)
    index = GoalIndex(rb, tail_size=512, rebuild_fraction=0.4)
    queries = torch.rand(32, 3, generator=gen)
    assert_exact(index, rb, queries, 5)
    seen_levels = set()
    for step in range(14):  # fills up, then overwrites the ring round-robin
        rb.extend(fetch_rows(300, gen, start=3000 + 300 * step))
        assert_exact(index, rb, queries, 5)
        view = index._views[(False, None, None)]
        seen_levels.update(
            name for name in ("mid", "live") if getattr(view, name) is not None
        )
        seen_levels.update({"stale"} if view.main.n_stale else set())
    assert len(rb.storage) == rb.storage.max_size
    assert seen_levels == {"mid", "live", "stale"}  # every incremental path ran
    # in-place writes (not through the writer's cursor)
    rows = torch.tensor([5, 17, 2500])
    new = fetch_rows(3, gen)
    new["next", "achieved_goal"] = queries[:3] + 1e-4
    rb.storage[rows] = new
    dist, idx, _ = index.search(queries[:3], 1)
    assert torch.equal(idx[:, 0], rows)
    assert_exact(index, rb, queries, 5)


@pytest.mark.parametrize("backend", ["kdtree", "brute"])
@pytest.mark.parametrize("flt", ["success_only", "env", "run"])
def test_filtered_views_exact_after_ring_overwrites(flt, backend):
    """Filtered views through a ring overwriting 200 rows at a time, incrementally.

    An overwritten row leaves the segment that held it, whether or not its new
    contents pass the filter: a row that stops passing must not be served with
    its old goal (the unfiltered view cannot show this: every changed row
    re-enters it).
    """
    rb, gen = make_rb(3000, capacity=4000)
    index = GoalIndex(rb, env_names=ENV_NAMES, backend=backend, tail_size=128, rebuild_fraction=0.4)
    queries = torch.rand(32, 3, generator=gen)
    kw = {"success_only": {"success_only": True}, "env": {"env": "FetchSlide-v4"}, "run": {"run": 1}}[flt]

    def keep():
        return {"success_only": column(rb, ("next", "is_success")) > 0.5, "env": column(rb, "env") == 1,
                "run": column(rb, "run") == 1}[flt]

    assert_exact(index, rb, queries, 5, keep=keep(), **kw)
    (key,) = [k for k in index._views if k != (False, None, None)]
    seen_levels, builds = set(), []
    for step in range(21):  # fills up, then overwrites the ring round-robin
        rb.extend(fetch_rows(200, gen, start=3000 + 200 * step))
        assert_exact(index, rb, queries, 5, keep=keep(), **kw)
        view = index._views[key]
        seen_levels.update(name for name in ("mid", "live") if getattr(view, name) is not None)
        seen_levels.update({"stale"} if view.main.n_stale else set())
        builds.append(view.builds)
    assert len(rb.storage) == rb.storage.max_size
    assert seen_levels == {"mid", "live", "stale"}, seen_levels  # every incremental path ran
    assert builds[-1] < len(builds), builds  # most steps were incremental, not rebuilds


@pytest.mark.parametrize("backend", ["kdtree", "brute"])
def test_filters_match_brute_force(backend):
    rb, gen = make_rb(3000, capacity=3500)
    index = GoalIndex(rb, env_names=ENV_NAMES, backend=backend, tail_size=200)
    queries = torch.rand(16, 3, generator=gen)
    for step in range(3):
        if step:
            rb.extend(fetch_rows(400, gen))  # the last one wraps around the ring
        success = column(rb, ("next", "is_success")) > 0.5
        env = column(rb, "env")
        run = column(rb, "run")
        assert_exact(index, rb, queries, 7, keep=success, success_only=True)
        assert_exact(index, rb, queries, 5, keep=env == 1, env="FetchSlide-v4")
        assert_exact(index, rb, queries, 5, keep=(env == 0) | (env == 2),
                     env=["FetchPush-v4", "FetchPickAndPlace-v4"])
        assert_exact(index, rb, queries, 5, keep=env == 2, env=2)  # raw code
        assert_exact(index, rb, queries, 5, keep=run == 1, run=1)
        assert_exact(index, rb, queries, 5, keep=success & (env == 1) & (run == 0),
                     success_only=True, env="FetchSlide-v4", run=[0])


def test_env_names_from_storage_attribute():
    rb, gen = make_rb(500)
    rb.storage.env_names = ENV_NAMES  # as ZarrStorage provides
    out = GoalIndex(rb).recall(torch.rand(3, generator=gen), 4, env="FetchPickAndPlace-v4")
    assert (out["env"] == 2).all()


@pytest.mark.parametrize("max_distance", [0.0, 0.05, 0.1])
def test_max_distance(max_distance):
    rb, gen = make_rb(3000)
    index = GoalIndex(rb)
    queries = torch.rand(16, 3, generator=gen)
    queries[0] = column(rb, GOAL)[7]  # exact hit at distance 0
    assert_exact(index, rb, queries, 20, max_distance=max_distance)
    dist, idx, mask = index.search(queries, 20, max_distance=max_distance)
    assert mask[0, 0] and (dist[mask] <= max_distance).all()


def test_fewer_matches_than_k_are_masked_zeros():
    rb, gen = make_rb(3)
    out = GoalIndex(rb).recall(torch.rand(2, 3, generator=gen), k=5)
    assert out["mask"].sum(1).tolist() == [3, 3]
    missing = ~out["mask"]
    assert torch.isinf(out["distance"][missing]).all()
    assert (out["index"][missing] == -1).all()
    for key in ("observation", "action", ("next", "achieved_goal"), ("next", "reward"), "env"):
        assert (out[key][missing] == 0).all(), key
    # filters leaving fewer than k
    rb, gen = make_rb(400)
    n_success = int((column(rb, ("next", "is_success")) > 0.5).sum())
    out = GoalIndex(rb).recall(torch.rand(3, generator=gen), k=n_success + 10, success_only=True)
    assert int(out["mask"].sum()) == n_success
    assert (out["next", "is_success"][out["mask"]] == 1).all()


def test_empty_storage_gives_masked_result():
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
    out = GoalIndex(rb).recall(torch.zeros(3), k=4)
    assert out.batch_size == torch.Size([4]) and not out["mask"].any()
    assert (out["index"] == -1).all() and torch.isinf(out["distance"]).all()
    rb, gen = make_rb(50)
    index = GoalIndex(rb)
    assert index.search(torch.rand(3), 2)[2].all()
    rb.empty()
    dist, idx, mask = index.search(torch.rand(2, 3), 2)
    assert not mask.any() and (idx == -1).all()
    rb.extend(fetch_rows(10, gen))
    assert_exact(index, rb, torch.rand(4, 3, generator=gen), 3)


# -- metrics ----------------------------------------------------------------------
def test_metric_registry_and_pose_definition():
    assert isinstance(get_metric("euclidean"), EuclideanMetric)
    assert isinstance(get_metric("hand"), PoseMetric)
    assert get_metric("pose", rotation_weight=0.5).rotation_weight == 0.5
    with pytest.raises(ValueError, match="known metrics"):
        get_metric("cosine")
    with pytest.raises(ValueError, match="rotation_weight"):
        PoseMetric(rotation_weight=-1)
    gen = torch.Generator().manual_seed(0)
    a = torch.cat([torch.rand(5, 3, generator=gen), unit_quat(5, gen)], 1).double()
    b = torch.cat([torch.rand(6, 3, generator=gen), unit_quat(6, gen)], 1).double()
    m = PoseMetric(rotation_weight=0.3)
    pw = m.pairwise(a, b)
    torch.testing.assert_close(pw, m.distance(a[:, None], b[None]))
    dot = (a[:, None, 3:] * b[None, :, 3:]).sum(-1).abs().clamp(max=1)
    expected = (a[:, None, :3] - b[None, :, :3]).norm(dim=-1) + 0.3 * 2 * torch.arccos(dot)
    torch.testing.assert_close(pw, expected)
    flipped = b.clone()
    flipped[:, 3:] *= -1
    torch.testing.assert_close(m.pairwise(a, flipped), pw)  # q and -q: one rotation
    # 180 degrees about z: angle pi
    ident = torch.tensor([[0.0, 0, 0, 1, 0, 0, 0]], dtype=torch.float64)
    half_turn = torch.tensor([[0.0, 0, 0, 0, 0, 0, 1]], dtype=torch.float64)
    torch.testing.assert_close(m.pairwise(ident, half_turn), torch.tensor([[0.3 * math.pi]], dtype=torch.float64))


@pytest.mark.parametrize("backend", ["kdtree", "brute"])
def test_pose_metric_exact_and_sign_invariant(backend):
    rb, gen = make_rb(3000, capacity=3600, goal_dim=7)
    index = GoalIndex(rb, metric="pose", backend=backend, tail_size=200)
    metric = index.metric
    queries = torch.cat([torch.rand(24, 3, generator=gen) * 0.05, unit_quat(24, gen)], 1)
    assert_exact(index, rb, queries, 5, metric=metric)
    stored = column(rb, GOAL)[[3, 99, 2048]].clone()
    stored[:, 3:] *= -1  # same rotations, other sign
    dist, idx, _ = index.search(stored, 1)
    assert idx[:, 0].tolist() == [3, 99, 2048]
    assert (dist[:, 0] < 1e-6).all()
    for _ in range(3):
        rb.extend(fetch_rows(300, gen, goal_dim=7))
        assert_exact(index, rb, queries, 5, metric=metric)
    success = column(rb, ("next", "is_success")) > 0.5
    assert_exact(index, rb, queries, 4, metric=metric, keep=success, success_only=True)
    assert_exact(index, rb, queries, 30, metric=metric, max_distance=0.1)
    with pytest.raises(ValueError, match="dimension 7"):
        GoalIndex(make_rb(10)[0], metric="pose").search(torch.zeros(3), 1)


@pytest.mark.parametrize("backend", ["kdtree", "brute"])
def test_pose_search_rescores_beyond_embedding_order(backend):
    # 300 rows at 0.05 m + 0.5 rad (pose distance 0.1) come first in the tree's embedding
    # (~0.07) but lose to one row at 0.08 m and no rotation (distance 0.08 in both)
    gen = torch.Generator().manual_seed(4)
    rows = fetch_rows(2000, gen, goal_dim=7)
    goals = rows["next", "achieved_goal"]
    goals[:, :3] += 1.0  # the rest: far away
    direction = torch.randn(300, 3, generator=gen)
    axis = torch.randn(300, 3, generator=gen)
    goals[:300, :3] = 0.05 * direction / direction.norm(dim=1, keepdim=True)
    goals[:300, 3] = math.cos(0.25)
    goals[:300, 4:] = math.sin(0.25) * axis / axis.norm(dim=1, keepdim=True)
    goals[1234] = torch.tensor([0.08, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(2000))
    rb.extend(rows)
    index = GoalIndex(rb, metric="pose", backend=backend)
    origin = torch.tensor([0.0, 0, 0, 1, 0, 0, 0])
    dist, idx, _ = index.search(origin, 3)
    assert idx[0] == 1234
    torch.testing.assert_close(dist, torch.tensor([0.08, 0.1, 0.1]))
    assert_exact(index, rb, origin[None], 20, metric=index.metric)


@pytest.mark.parametrize("backend", ["auto", "kdtree", "brute"])
def test_15d_hand_reach_goals(backend):
    rb, gen = make_rb(3000, capacity=3500, goal_dim=15)
    index = GoalIndex(rb, backend=backend, tail_size=200)
    queries = torch.rand(16, 15, generator=gen)
    assert_exact(index, rb, queries, 5)
    rb.extend(fetch_rows(700, gen, goal_dim=15))
    assert_exact(index, rb, queries, 5)
    assert index.backend_in_use == ("kdtree" if backend == "auto" else backend)


def test_brute_backend_rounding_margin():
    # a tight cluster inside widely spread goals: float32 products cannot rank the cluster
    # (their rounding error dwarfs its distances), so the search must widen and re-score
    gen = torch.Generator().manual_seed(3)
    rows = fetch_rows(4000, gen, goal_dim=15)
    goals = 1000 * torch.rand(4000, 15, generator=gen)
    goals[:500] = 500 + 1e-3 * torch.rand(500, 15, generator=gen)
    rows["next", "achieved_goal"] = goals
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(4000))
    rb.extend(rows)
    queries = goals[:8] + 1e-5
    assert_exact(GoalIndex(rb, backend="brute"), rb, queries, 5)


def test_custom_metric_callable():
    def manhattan(a, b):
        return (a[:, None, :] - b[None, :, :]).abs().sum(-1)

    rb, gen = make_rb(1500, capacity=1800)
    index = GoalIndex(rb, metric=manhattan, tail_size=100)
    queries = torch.rand(8, 3, generator=gen)
    metric = get_metric(manhattan)
    assert_exact(index, rb, queries, 5, metric=metric)
    rb.extend(fetch_rows(500, gen))
    assert_exact(index, rb, queries, 5, metric=metric)
    with pytest.raises(ValueError, match="no tree embedding"):
        GoalIndex(rb, metric=manhattan, backend="kdtree")


# -- storages, caching, reopening -------------------------------------------------
def test_memmap_storage_and_reopen(tmp_path):
    gen = torch.Generator().manual_seed(5)
    rb = TensorDictReplayBuffer(storage=LazyMemmapStorage(2000, scratch_dir=tmp_path / "mm"))
    rb.extend(fetch_rows(1500, gen))
    queries = torch.rand(8, 3, generator=gen)
    index = GoalIndex(rb.storage)
    assert_exact(index, rb, queries, 5)
    rb.dumps(tmp_path / "ckpt")
    reopened = TensorDictReplayBuffer(storage=LazyMemmapStorage(2000))
    reopened.loads(tmp_path / "ckpt")
    assert_exact(GoalIndex(reopened), reopened, queries, 5)
    assert torch.equal(recall(reopened, queries, 5)["index"], index.search(queries, 5)[1])
    # loading other contents into a buffer that is already indexed
    other, _ = make_rb(1200, capacity=2000, gen=torch.Generator().manual_seed(9))
    other.dumps(tmp_path / "other")
    rb.loads(tmp_path / "other")
    assert_exact(index, rb, queries, 5)


def test_module_recall_uses_the_shared_index_of_the_storage():
    rb, gen = make_rb(800)
    st = rb.storage
    index = GoalIndex.for_storage(st)
    out = recall(rb, torch.rand(3, generator=gen), 3)
    assert out.batch_size == torch.Size([3])
    assert index.stats()["view_builds"] == 1  # recall() searched the shared index
    recall(st, torch.rand(2, 3, generator=gen), 3, success_only=True)  # storage or buffer
    assert GoalIndex.for_storage(rb) is index and index.stats()["views"] == 2
    # metrics are compared by what they compute
    assert GoalIndex.for_storage(st, metric="l2") is index
    assert GoalIndex.for_storage(st, metric=EuclideanMetric()) is index
    assert GoalIndex.for_storage(st, metric="pose") is not index
    assert GoalIndex.for_storage(st, metric="pose", metric_kwargs={"rotation_weight": 0.5}) is not \
        GoalIndex.for_storage(st, metric="pose")
    other = GoalIndex.for_storage(st, goal_key="achieved_goal")
    assert other is not index and other.goal_key == "achieved_goal"
    assert GoalIndex(st) is not index  # the constructor makes a private index
    ref = weakref.ref(st)
    del rb, st
    gc.collect()
    assert ref() is None  # the shared index does not keep its storage alive
    with pytest.raises(RuntimeError, match="garbage-collected"):
        index.search(torch.zeros(3), 1)


# -- bad input --------------------------------------------------------------------
def _snapshot(rb):
    st = rb.storage
    return st._storage[: len(st)].clone(), len(st), st._mutation_revision


@pytest.mark.parametrize(
    "goal, k, kwargs, error, match",
    [
        (torch.zeros(4), 5, {}, ValueError, "dimension 4"),
        (torch.zeros(2, 2), 5, {}, ValueError, "dimension 2"),
        (torch.zeros(2, 2, 3), 5, {}, ValueError, r"\[B, goal_dim\]"),
        (torch.tensor([0.1, float("nan"), 0.2]), 5, {}, ValueError, "NaN or infinite"),
        ([0.1, float("inf"), 0.2], 5, {}, ValueError, "NaN or infinite"),
        ("abc", 5, {}, ValueError, "numeric"),
        (torch.zeros(3), 0, {}, ValueError, "k must be a positive integer"),
        (torch.zeros(3), -2, {}, ValueError, "k must be a positive integer"),
        (torch.zeros(3), 2.5, {}, ValueError, "k must be a positive integer"),
        (torch.zeros(3), 5, {"env": "HandReach-v3"}, ValueError, "known envs: .*FetchPush-v4"),
        (torch.zeros(3), 5, {"run": "first"}, ValueError, "run must be"),
        (torch.zeros(3), 5, {"max_distance": -1.0}, ValueError, "max_distance"),
        (torch.zeros(3), 5, {"success_only": "yes"}, ValueError, "success_only"),
    ],
)
def test_bad_input_raises_and_leaves_storage_unchanged(goal, k, kwargs, error, match):
    rb, _ = make_rb(300)
    before = _snapshot(rb)
    index = GoalIndex(rb, env_names=ENV_NAMES)
    with pytest.raises(error, match=match):
        index.recall(goal, k, **kwargs)
    after = _snapshot(rb)
    assert (before[0] == after[0]).all()
    assert before[1:] == after[1:]


def test_missing_columns_and_names():
    rb, _ = make_rb(100)
    with pytest.raises(KeyError, match=r"no column 'goal'.*available keys: .*'observation'"):
        GoalIndex(rb, goal_key="goal").search(torch.zeros(3), 1)
    with pytest.raises(ValueError, match="no env names are known"):
        GoalIndex(rb).search(torch.zeros(3), 1, env="FetchPush-v4")
    bare = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    bare.extend(TensorDict({GOAL: torch.rand(5, 3)}, [5]))
    with pytest.raises(KeyError, match="env filter needs the column 'env'"):
        GoalIndex(bare).search(torch.zeros(3), 1, env=0)
    with pytest.raises(KeyError, match="success_only needs the column"):
        GoalIndex(bare).search(torch.zeros(3), 1, success_only=True)
    with pytest.raises(TypeError, match="Storage or ReplayBuffer"):
        GoalIndex(torch.zeros(3))
    with pytest.raises(ValueError, match="backend"):
        GoalIndex(bare, backend="faiss")


def test_index_pickles_and_rebuilds_lazily():
    import pickle

    rb, gen = make_rb(600)
    index = GoalIndex(rb, metric="euclidean", tail_size=64)
    queries = torch.rand(4, 3, generator=gen)
    expected = index.search(queries, 3)
    clone = pickle.loads(pickle.dumps(index))
    assert clone.stats()["views"] == 0 and clone.tail_size == 64
    for a, b in zip(clone.search(queries, 3), expected):
        assert torch.equal(a, b)


def test_a_huge_k_on_a_memory_without_a_capacity_is_refused(tmp_path):
    """Found by a review: a memory without a capacity has max_size 2**50, so nothing clamped k: k = 10**9
    raised MemoryError (or the process was killed). Its k columns stay k (a policy sizes on them); a k past
    its rows asking for more than 2**26 results is refused, naming k and the rows."""
    from torchrl_robotmem import ZarrStorage

    storage = ZarrStorage(str(tmp_path / "grow.zarr"), goal_conditioned=False)
    rb = TensorDictReplayBuffer(storage=storage)
    rb.extend(_rows.fetch_rows(60, torch.Generator().manual_seed(0)))  # untagged rows (no env codes)
    index = GoalIndex(rb)
    queries = torch.rand(4, 3, generator=torch.Generator().manual_seed(1))
    dist, idx, mask = index.search(queries, 100)  # past the 60 rows: 100 columns, 60 of them matches
    assert dist.shape == (4, 100) and mask.sum(1).tolist() == [60] * 4
    assert_exact(index, rb, queries, 60)
    with pytest.raises(ValueError, match=r"k=1000000000 .* 60 rows"):
        index.search(queries, 10**9)
    storage.close()


# -- k above the rows stored ------------------------------------------------------
@pytest.mark.parametrize("backend", ["kdtree", "brute"])
def test_k_far_above_the_rows_is_clamped_to_the_capacity(backend):
    """``k`` = 10**12 over 60 rows of a 100-row storage: 100 columns (no query can match more), the 60 rows first.

    The width depends on ``k`` and the capacity only, never on how many rows are
    stored (a policy sized on ``top_k`` keeps its shapes from the first, empty
    step); the search works on the rows that pass the filter. Before the clamp
    the index allocated ``[B, k]`` arrays (numpy raised MemoryError for 10**12;
    10**8 was the probe's gigabytes).
    """
    import tracemalloc

    rb, gen = make_rb(60, capacity=100)
    index = GoalIndex(rb, backend=backend)
    queries = torch.rand(4, 3, generator=gen)
    huge = 10**12
    tracemalloc.start()
    try:
        dist, idx, mask = index.search(queries, huge)
        out = index.recall(queries[0], huge, success_only=True)
        per_episode = index.search(queries, huge, one_per_episode=True)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20, f"{peak} bytes traced for a search over 60 rows"
    assert dist.shape == idx.shape == mask.shape == (4, 100) and mask.sum(1).tolist() == [60] * 4
    assert_exact(index, rb, queries, 100)  # the same answer as brute force with k = the capacity
    assert torch.equal(idx, index.search(queries, 100)[1])
    # the filter: as many unmasked as rows pass it, the rest -1 / inf / zeros
    success = column(rb, ("next", "is_success")) > 0.5
    assert out.batch_size == (100,) and int(out["mask"].sum()) == int(success.sum()) > 0
    assert set(out["index"][out["mask"]].tolist()) == set(success.nonzero().squeeze(-1).tolist())
    assert (out["index"][~out["mask"]] == -1).all() and torch.isinf(out["distance"][~out["mask"]]).all()
    assert not out["observation"][~out["mask"]].any()
    # one_per_episode: one unmasked column per episode (rows 0..59: 2)
    d_ep, i_ep, m_ep = per_episode
    assert m_ep.shape == (4, 100) and m_ep.sum(1).tolist() == [2] * 4
    assert (column(rb, "episode")[i_ep[m_ep].reshape(4, 2)].sort(1).values == torch.tensor([0, 1])).all()
    # the module function, k around the capacity, and an empty storage: the shape follows k and max_size only
    assert recall(rb, queries, 101)["index"].shape == (4, 100)
    assert recall(rb, queries, 99)["index"].shape == (4, 99)
    empty = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
    assert GoalIndex(empty).search(queries, huge)[2].shape == (4, 100)
