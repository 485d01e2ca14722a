"""What a GoalIndex holds in RAM (issue 41): one copy of the goals, int32 row ids, ``nbytes()``; still exact."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage

from torchrl_robotmem.goal_index import GoalIndex
from torchrl_robotmem.goal_index.segments import NODE_BYTES, TreeSegment

torch.set_num_threads(1)

GOAL = ("next", "achieved_goal")
ALL = (False, None, None)


def fetch_goals(n, gen, dtype=torch.float32):
    """Fetch-shaped achieved goals: a pushed object's positions on a table."""
    g = torch.tensor([1.3, 0.75, 0.42]) + torch.randn(n, 3, generator=gen) * torch.tensor([0.08, 0.08, 0.01])
    return g.to(dtype)


def memory(n, gen, capacity=None, dtype=torch.float32):
    st = LazyTensorStorage(capacity or n)
    st.set(torch.arange(n), TensorDict({
        GOAL: fetch_goals(n, gen, dtype),
        ("next", "is_success"): (torch.rand(n, generator=gen) < 0.3).float(),
    }, [n]))
    return st


def brute_top(st, queries, k, keep=None):
    """Reference top-k: float64 distances to every stored goal, sorted (stable)."""
    goals = st._storage[GOAL][: len(st)].double()
    d = torch.cdist(queries.double(), goals, compute_mode="donot_use_mm_for_euclid_dist")
    if keep is not None:
        d[:, ~keep] = float("inf")
    d, i = torch.sort(d, dim=1, stable=True)
    return d[:, :k], i[:, :k]


def assert_exact(index, st, queries, k=5, **kw):
    dist, idx, mask = index.search(queries, k, **kw)
    keep = (st._storage["next", "is_success"][: len(st)] > 0.5) if kw.get("success_only") else None
    ref_d, ref_i = brute_top(st, queries, k, keep)
    assert mask.all() and idx.dtype == torch.int64
    torch.testing.assert_close(dist.double(), ref_d, rtol=1e-6, atol=1e-7)
    same = idx == ref_i
    if not same.all():  # only where two stored goals are at the same distance
        gaps = (ref_d[:, 1:] - ref_d[:, :-1]).abs() < 1e-9
        tie = torch.zeros_like(same)
        tie[:, 1:] |= gaps
        tie[:, :-1] |= gaps
        assert (same | tie).all(), "indices differ from brute force"


def queries_near(st, gen, q=128):
    goals = st._storage[GOAL][: len(st)].float()
    rows = torch.randint(0, len(st), (q,), generator=gen)
    return goals[rows] + torch.randn(q, 3, generator=gen) * torch.tensor([0.01, 0.01, 0.002])


def test_top5_exact_on_a_seeded_memory():
    gen = torch.Generator().manual_seed(41)
    st = memory(60_000, gen)
    index = GoalIndex(st)
    q = queries_near(st, gen)
    assert_exact(index, st, q, 5)
    _, i, _ = index.search(q[0], 5)  # a single query
    ref_d, ref_i = brute_top(st, q[:1], 5)
    assert torch.equal(i, ref_i[0])
    assert_exact(index, st, q, 5, success_only=True)


def test_one_copy_of_the_goals_and_no_row_array_for_the_unfiltered_view():
    gen = torch.Generator().manual_seed(1)
    n = 20_000
    st = memory(n, gen)
    index = GoalIndex(st).refresh()
    tracker, view = index._tracker, index._views[ALL]
    snap = tracker.column(GOAL)
    assert snap.dtype == np.float64 and snap.shape == (n, 3)  # float32 goals, held once, in float64
    main = view.main
    assert isinstance(main, TreeSegment) and main.shares_data
    assert np.shares_memory(main.tree.data, snap)  # the KD-tree searches the snapshot in place
    assert main._rows_ext is None and np.array_equal(main.rows, np.arange(n))
    assert view.owner.dtype == np.int8
    tree = main.tree
    expected = snap.nbytes + view.owner.nbytes + n * np.dtype(np.intp).itemsize + tree.size * NODE_BYTES
    assert index.nbytes() == expected
    assert index.nbytes() / n < 50  # docs/recall.md states about 46 bytes a row for 3-D goals


def test_filtered_view_holds_int32_row_ids_and_its_own_tree_data():
    gen = torch.Generator().manual_seed(2)
    n = 20_000
    st = memory(n, gen)
    index = GoalIndex(st)
    q = queries_near(st, gen, 64)
    assert_exact(index, st, q, 5, success_only=True)
    view = index._views[(True, None, None)]
    main = view.main
    members = int((st._storage["next", "is_success"] > 0.5).sum())
    assert main.rows.dtype == np.int32 and main.size == members
    assert not main.shares_data
    before = index.nbytes()
    index.member_rows(success_only=True)  # the cached member rows are counted too
    assert index.nbytes() == before + members * 8


def test_exact_while_rows_under_a_shared_tree_are_overwritten():
    """Overwritten rows change in the snapshot the tree searches; they are stale there, and skipped."""
    gen = torch.Generator().manual_seed(3)
    n = 30_000
    st = memory(n, gen)
    index = GoalIndex(st, tail_size=256, rebuild_fraction=0.05)
    q = queries_near(st, gen, 64)
    assert_exact(index, st, q, 5)
    view = index._views[ALL]
    builds = view.builds
    # 600 rows (2% of the main segment: below the rebuild budget), moved onto the queries and far away
    rows = torch.randperm(n, generator=gen)[:600]
    new = fetch_goals(600, gen)
    new[:64] = q + 1e-5
    new[64:300] = 100.0
    st.set(rows, TensorDict({GOAL: new, ("next", "is_success"): torch.ones(600)}, [600]), set_cursor=False)
    assert_exact(index, st, q, 5)
    assert view.builds == builds and view.main.n_stale == 600 and view.main.shares_data
    assert np.shares_memory(view.main.tree.data, index._tracker.column(GOAL))
    # the goals moved in place were seen: the nearest of each query is its moved row
    _, idx, _ = index.search(q, 1)
    assert torch.equal(idx[:, 0], rows[:64])
    # and moving them back is seen too (a one-ulp change of one coordinate included)
    back = st._storage[GOAL][rows[:1]].clone()
    back[0, 0] = torch.nextafter(back[0, 0], torch.tensor(2.0))
    st.set(rows[:1], TensorDict({GOAL: back, ("next", "is_success"): torch.ones(1)}, [1]), set_cursor=False)
    assert_exact(index, st, q, 5)


def test_float64_goals_are_held_once_too():
    gen = torch.Generator().manual_seed(4)
    st = memory(10_000, gen, dtype=torch.float64)
    index = GoalIndex(st)
    assert_exact(index, st, queries_near(st, gen, 32).double(), 5)
    main = index._views[ALL].main
    assert main.shares_data and np.shares_memory(main.tree.data, index._tracker.column(GOAL))
    assert not np.shares_memory(index._tracker.column(GOAL), st._storage[GOAL].numpy())  # a snapshot, not the storage


def test_snapshot_grows_up_to_the_storage_capacity_only():
    gen = torch.Generator().manual_seed(5)
    st = LazyTensorStorage(1000)
    st.set(torch.arange(600), TensorDict({GOAL: fetch_goals(600, gen)}, [600]))
    index = GoalIndex(st)
    index.search(torch.zeros(3), 5)
    st.set(torch.arange(600, 900), TensorDict({GOAL: fetch_goals(300, gen)}, [300]))
    index.search(torch.zeros(3), 5)
    assert index._tracker.column(GOAL).shape[0] == 1000  # doubling would allocate 1200 rows
    assert index._views[ALL].owner.size <= 1000
    assert_exact(index, st, queries_near(st, gen, 16), 5)


@pytest.mark.parametrize("backend", ["kdtree", "brute"])
def test_pose_goals_keep_their_dtype_and_the_tree_its_own_embedding(backend):
    gen = torch.Generator().manual_seed(6)
    n = 5000
    q = torch.randn(n, 4, generator=gen)
    goals = torch.cat([torch.rand(n, 3, generator=gen), q / q.norm(dim=1, keepdim=True)], 1)
    st = LazyTensorStorage(n)
    st.set(torch.arange(n), TensorDict({GOAL: goals}, [n]))
    index = GoalIndex(st, metric="pose", backend=backend).refresh()
    assert index._tracker.column(GOAL).dtype == np.float32
    main = index._views[ALL].main
    assert not getattr(main, "shares_data", False)
    assert index.nbytes() > index._tracker.nbytes() + n  # the embedding is the segment's own
