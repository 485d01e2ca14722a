"""GoalIndex, recall and GoalSimilaritySampler over a real ZarrStorage (not LazyTensorStorage).

Exactness against brute force after appends, ring overwrites and reopening
(writer and ``read_only``), env / run filters by name across runs, the
sampler inside TensorDictReplayBuffer and HERReplayBuffer, checkpoints, and
bad input that must leave the store untouched.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import zarr
from _rows import fetch_rows  # no env / run / episode columns: the storage writes them
from torchrl.data import HERReplayBuffer, RandomSampler, TensorDictReplayBuffer

from torchrl_robotmem import GoalIndex, GoalSimilaritySampler, ZarrStorage, make_reward_fn, recall

torch.set_num_threads(1)

GOAL = ("next", "achieved_goal")
SUCCESS = ("next", "is_success")


def zarr_rb(path, max_size=None, *, sampler=None, batch_size=64, **kw):
    storage = ZarrStorage(path, max_size, chunk_rows=64, **kw, sample_tags=True)
    return TensorDictReplayBuffer(storage=storage, sampler=sampler, batch_size=batch_size)


def column(storage, key):
    return storage._storage.get(key)[: len(storage)]


def brute_force(storage, goals, k, keep=None):
    """float64 distances to every stored goal, rows outside ``keep`` excluded, nearest first."""
    g = column(storage, GOAL).double()
    q = torch.as_tensor(goals, dtype=torch.float64).reshape(-1, 3)
    d = torch.cdist(q, g)
    if keep is not None:
        d[:, ~keep] = math.inf
    d, i = torch.sort(d, dim=1, stable=True)
    if d.shape[1] < k:
        pad = k - d.shape[1]
        d = torch.cat([d, torch.full((d.shape[0], pad), math.inf, dtype=d.dtype)], 1)
        i = torch.cat([i, torch.full((i.shape[0], pad), -1)], 1)
    d, i = d[:, :k], i[:, :k]
    return d.float(), torch.where(torch.isfinite(d), i, -1)


def assert_exact(index, storage, goals, k, keep=None, **filters):
    dist, idx, mask = index.search(goals, k, **filters)
    ref_d, ref_i = brute_force(storage, goals, k, keep)
    assert torch.equal(mask, torch.isfinite(ref_d))
    assert torch.equal(idx == -1, ~mask)
    torch.testing.assert_close(dist[mask], ref_d[mask], rtol=1e-5, atol=1e-6)
    differ = (idx != ref_i) & mask
    if differ.any():  # only where two distances tie to float precision
        gaps = (ref_d[:, 1:] - ref_d[:, :-1]).abs() < 1e-6
        tie = torch.zeros_like(differ)
        tie[:, 1:] |= gaps
        tie[:, :-1] |= gaps
        assert not (differ & ~tie).any(), "indices differ from brute force"
    return dist, idx, mask


def all_filters(storage):
    """(filters, keep-mask) pairs covering no filter, success_only, env and run (as the storage tags them)."""
    success = column(storage, SUCCESS) > 0.5
    env, run = column(storage, "env"), column(storage, "run")
    out = [({}, None), ({"success_only": True}, success)]
    for code, name in enumerate(storage.env_names):
        out.append(({"env": name}, env == code))
    for r in run.unique().tolist():
        out.append(({"run": r}, run == r))
    return out


def answers(index, storage, queries, k=5):
    """Every filter's (distance, index) for the queries, checked against brute force."""
    return {
        repr(sorted(f.items())): assert_exact(index, storage, queries, k, keep, **f)[:2]
        for f, keep in all_filters(storage)
    }


def assert_same_answers(a, b):
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key][0], b[key][0]) and torch.equal(a[key][1], b[key][1]), key


# -- exactness: appends, ring overwrites, reopening ----------------------------------
def test_exact_after_extends_and_ring_overwrites(tmp_path):
    gen = torch.Generator().manual_seed(0)
    rb = zarr_rb(tmp_path / "m.zarr", 600, env="FetchPush-v4")
    st = rb.storage
    # a small tail and a large rebuild fraction: every incremental path runs
    index = GoalIndex(rb, tail_size=64, rebuild_fraction=0.5)
    queries = torch.rand(24, 3, generator=gen)
    paths = set()
    for step in range(40):  # 40 * 50 rows through a 600-row ring: it wraps 3.3 times
        rb.extend(fetch_rows(50, gen, start=50 * step))
        answers(index, st, queries)
        view = index._views[(False, None, None)]
        paths.update(name for name in ("mid", "live") if getattr(view, name) is not None)
        paths.update({"stale"} if view.main.n_stale else set())
    assert len(st) == st.max_size and st.write_count == 40 * 50 >= 3 * st.max_size
    assert paths == {"mid", "live", "stale"}
    # in-place writes through the storage (not the writer's cursor) are seen too
    rows = torch.tensor([3, 311, 599])
    new = fetch_rows(3, gen)
    new[GOAL] = queries[:3] + 1e-4
    st.set(rows, new, set_cursor=False)
    assert torch.equal(index.search(queries[:3], 1)[1][:, 0], rows)
    answers(index, st, queries)
    # recall() returns the stored rows (tags included) of the exact neighbours
    out = recall(rb, queries, 4, success_only=True)
    ref_d, ref_i = brute_force(st, queries, 4, keep=column(st, SUCCESS) > 0.5)
    assert torch.equal(out["index"], ref_i)
    stored = st._storage[out["index"]]
    for key in stored.keys(True, True):
        assert torch.equal(out[key], stored[key]), key
    assert {"episode", "run", "env"} <= set(out.keys())
    st.close()


def test_same_answers_after_close_and_reopen(tmp_path):
    gen = torch.Generator().manual_seed(1)
    path = tmp_path / "m.zarr"
    rb = zarr_rb(path, 500, env="FetchPush-v4")
    for step in range(3):
        rb.extend(fetch_rows(250, gen, start=250 * step))  # wraps once, whole episodes
    st = rb.storage
    queries = torch.rand(16, 3, generator=gen)
    before = answers(GoalIndex(rb), st, queries)
    before_recall = recall(st, queries, 5).clone()
    rows_before = st._storage[: len(st)].clone()
    st.close()

    for read_only in (False, True):
        reopened = ZarrStorage(path, read_only=read_only, sample_tags=True)
        assert len(reopened) == 500 and reopened.state_dict()["zarr"]["cursor"] == 250
        assert (reopened._storage[: len(reopened)] == rows_before).all()
        assert_same_answers(answers(GoalIndex(reopened), reopened, queries), before)
        again = recall(reopened, queries, 5)  # module-level: a fresh index for the new storage object
        assert (again == before_recall).all()
        reopened.close()

    # the writer keeps wrapping after reopening and the index keeps up
    rb = zarr_rb(path, env="FetchSlide-v4")
    index = GoalIndex(rb, tail_size=32, rebuild_fraction=0.1)
    now = answers(index, rb.storage, queries)  # one more filter: env="FetchSlide-v4" (no rows yet)
    assert_same_answers({key: now[key] for key in before}, before)
    for step in range(4):
        rb.extend(fetch_rows(150, gen, start=750 + 150 * step))
        answers(index, rb.storage, queries)
    after = answers(index, rb.storage, queries)
    rb.storage.close()
    reader = ZarrStorage(path, read_only=True, sample_tags=True)
    assert_same_answers(answers(GoalIndex(reader), reader, queries), after)
    reader.close()


def test_read_only_reader_follows_a_live_writer(tmp_path):
    gen = torch.Generator().manual_seed(2)
    path = tmp_path / "m.zarr"
    rb = zarr_rb(path, 400, env="FetchPush-v4")
    rb.extend(fetch_rows(300, gen))
    rb.storage.flush()
    reader = ZarrStorage(path, read_only=True, sample_tags=True)
    index = GoalIndex(reader)
    queries = torch.rand(16, 3, generator=gen)
    answers(index, reader, queries)
    for step in range(3):  # grows, then overwrites rows the reader had indexed
        rb.extend(fetch_rows(150, gen, start=300 + 150 * step))
        rb.storage.flush()
        assert reader.refresh() == len(rb.storage)
        assert_same_answers(answers(index, reader, queries), answers(GoalIndex(rb), rb.storage, queries))
    reader.close()
    rb.storage.close()


# -- filters by env name and run -----------------------------------------------------
def test_env_and_run_filters_across_two_runs(tmp_path):
    gen = torch.Generator().manual_seed(3)
    path = tmp_path / "m.zarr"
    with ZarrStorage(path, 2000, env="FetchPush-v4", chunk_rows=64, sample_tags=True) as st:
        TensorDictReplayBuffer(storage=st).extend(fetch_rows(500, gen))
    st = ZarrStorage(path, env="FetchSlide-v4", chunk_rows=64, sample_tags=True)
    rb = TensorDictReplayBuffer(storage=st, batch_size=256)
    rb.extend(fetch_rows(500, gen))
    assert st.env_names == ("FetchPush-v4", "FetchSlide-v4")
    env, run = column(st, "env"), column(st, "run")
    assert torch.equal(env, run) and env[:500].eq(0).all() and env[500:].eq(1).all()
    success = column(st, SUCCESS) > 0.5
    index = GoalIndex(rb)
    queries = torch.rand(16, 3, generator=gen)
    assert_exact(index, st, queries, 6, env == 0, env="FetchPush-v4")
    assert_exact(index, st, queries, 6, env == 1, env="FetchSlide-v4")
    assert_exact(index, st, queries, 6, None, env=["FetchPush-v4", "FetchSlide-v4"])
    assert_exact(index, st, queries, 6, env == 1, env=1)  # the raw code
    assert_exact(index, st, queries, 6, run == 0, run=0)
    assert_exact(index, st, queries, 6, (run == 1) & success, run=[1], success_only=True)
    assert_exact(index, st, queries, 6, (env == 0) & success, env="FetchPush-v4", success_only=True)
    out = recall(rb, queries[0], 8, env="FetchSlide-v4")
    assert out["mask"].all() and (out["env"] == 1).all() and (out["run"] == 1).all()
    # a registered env without rows matches nothing (masked, no error)
    st.env = "FetchReach-v4"
    dist, idx, mask = index.search(queries, 3, env="FetchReach-v4")
    assert not mask.any() and (idx == -1).all() and torch.isinf(dist).all()
    # the sampler filters by name through the storage's env_names
    sampler = GoalSimilaritySampler(env="FetchSlide-v4", uniform_ratio=0.25, num_candidates=64)
    srb = TensorDictReplayBuffer(storage=st, sampler=sampler, batch_size=256)
    with sampler.query(queries[:4]):
        batch = srb.sample()
    assert (batch["env"] == 1).all() and batch["index"].min() >= 500
    st.close()
    # and so does a reader of the closed store
    reader = ZarrStorage(path, read_only=True, sample_tags=True)
    assert reader.env_names == ("FetchPush-v4", "FetchSlide-v4", "FetchReach-v4")
    assert_exact(GoalIndex(reader), reader, queries, 6, env == 0, env="FetchPush-v4")
    reader.close()


# -- the sampler inside TorchRL buffers over ZarrStorage -----------------------------
def goal_dist(batch, goal):
    return (batch[GOAL] - torch.as_tensor(goal)).norm(dim=-1)


def test_sampler_in_tensordict_replay_buffer(tmp_path):
    gen = torch.Generator().manual_seed(4)
    sampler = GoalSimilaritySampler(temperature=0.02, num_candidates=128)
    rb = zarr_rb(tmp_path / "m.zarr", 3000, sampler=sampler, batch_size=512, env="FetchPush-v4")
    rb.extend(fetch_rows(3000, gen))
    goal = torch.tensor([0.3, 0.6, 0.5])
    uniform = rb.sample()
    assert "goal_distance" not in uniform.keys()
    with sampler.query(goal):
        batch = rb.sample()
    d = goal_dist(batch, goal)
    torch.testing.assert_close(batch["goal_distance"], d)
    assert d.mean() < 0.25 * goal_dist(uniform, goal).mean()
    kth = GoalIndex(rb).search(goal, 128)[0][-1]
    assert (d <= kth + 1e-6).all()
    # a full ring: new rows near the query replace old ones and are drawn at once
    far = torch.tensor([2.0, 2.0, 2.0])
    sampler.set_query(far)
    assert (rb.sample()["goal_distance"] > 1.0).all()
    new = fetch_rows(10, gen)
    new[GOAL] = far + 1e-3 * torch.rand(10, 3, generator=gen)
    rb.extend(new)  # overwrites rows 0..9
    after = rb.sample()
    assert set(after["index"][after["goal_distance"] < 0.01].tolist()) <= set(range(10))
    assert (after["goal_distance"] < 0.01).float().mean() > 0.5
    torch.testing.assert_close(after["goal_distance"], goal_dist(after, far))
    rb.storage.close()


def test_sampler_in_her_replay_buffer(tmp_path):
    gen = torch.Generator().manual_seed(5)
    reward_fn = make_reward_fn("FetchPush-v4")
    storage = ZarrStorage(tmp_path / "m.zarr", 4000, env="FetchPush-v4", chunk_rows=64, sample_tags=True)
    her = HERReplayBuffer(
        reward_fn, her_ratio=0.5, storage=storage, batch_size=256,
        sampler=GoalSimilaritySampler(temperature=0.01, num_candidates=64),
        achieved_goal_key=GOAL,
    )
    her.extend(fetch_rows(4000, gen))
    goal = torch.tensor([0.4, 0.4, 0.4])
    with her.sampler.query(goal):
        batch = her.sample()
    torch.testing.assert_close(batch["goal_distance"], goal_dist(batch, goal))
    kth = GoalIndex(her).search(goal, 64)[0][-1]
    assert (batch["goal_distance"] <= kth + 1e-6).all()
    # the first half was relabelled with an achieved goal of the same stored episode
    relabelled = batch[:128]
    torch.testing.assert_close(relabelled["next", "reward"], reward_fn(relabelled))
    episodes = column(storage, "episode")
    goals = column(storage, GOAL)
    same_episode = episodes[None, :] == relabelled["episode"][:, None]
    hit = (goals[None, :, :] == relabelled["desired_goal"][:, None, :]).all(-1) & same_episode
    assert hit.any(1).all()
    # plain HER (RandomSampler) over the same store draws far from the goal by comparison
    plain = HERReplayBuffer(reward_fn, storage=storage, sampler=RandomSampler(), batch_size=256,
                            achieved_goal_key=GOAL)
    assert goal_dist(plain.sample(), goal).mean() > 4 * batch["goal_distance"].mean()
    storage.close()


def test_sampler_dumps_loads_next_to_rb_dumps(tmp_path):
    gen = torch.Generator().manual_seed(6)
    path = tmp_path / "m.zarr"
    sampler = GoalSimilaritySampler(temperature=0.03, num_candidates=40, uniform_ratio=0.25,
                                    env="FetchPush-v4")
    rb = TensorDictReplayBuffer(storage=ZarrStorage(path, 2000, env="FetchPush-v4", chunk_rows=64, sample_tags=True),
                                sampler=sampler, batch_size=128, generator=torch.Generator().manual_seed(3))
    rb.extend(fetch_rows(1500, gen))
    sampler.set_query([[0.2, 0.3, 0.4], [0.8, 0.1, 0.5]])
    rb.dumps(tmp_path / "ckpt")
    assert (tmp_path / "ckpt" / "sampler" / "sampler_metadata.json").exists()
    assert (tmp_path / "ckpt" / "storage" / "zarr_storage.json").exists()
    expected = rb.sample()  # the first draw after the checkpoint
    rb.storage.close()

    rb2 = TensorDictReplayBuffer(storage=ZarrStorage(path), sampler=GoalSimilaritySampler(), batch_size=1)
    rb2.loads(tmp_path / "ckpt")
    assert rb2.sampler.state_dict() == sampler.state_dict()
    torch.testing.assert_close(rb2.sampler.current_query, sampler.current_query)
    got = rb2.sample()  # same rows, same rng state, same query: the same batch
    assert torch.equal(got["index"], expected["index"])
    torch.testing.assert_close(got["goal_distance"], expected["goal_distance"])
    # a sampler checkpoint alone, loaded into a sampler of a read-only buffer
    sampler.dumps(tmp_path / "s")
    reader = ZarrStorage(path, read_only=True, sample_tags=True)
    other = GoalSimilaritySampler()
    other.loads(tmp_path / "s")
    rb3 = TensorDictReplayBuffer(storage=reader, sampler=other, batch_size=64)
    batch = rb3.sample()
    assert batch["goal_distance"].shape == (64,) and (batch["env"] == 0).all()
    reader.close()
    rb2.storage.close()


# -- bad input leaves the store unchanged --------------------------------------------
def _state(rb):
    st = rb.storage
    st.flush()
    disk = zarr.open_group(str(st.path), mode="r")
    return {
        "len": len(st),
        "cursor": (st.state_dict()["zarr"]["cursor"], rb.writer._cursor, st.write_count),
        "revision": int(st._mutation_revision),
        "env_names": st.env_names,
        "rows": st._storage[: len(st)].clone(),
        "disk_goals": np.asarray(disk["next/achieved_goal"][:]),
        "disk_attrs": {k: disk.attrs[k] for k in ("len", "cursor", "write_count", "env_names", "runs")},
    }


def _assert_same_state(a, b):
    assert (a["len"], a["cursor"], a["revision"], a["env_names"]) == (b["len"], b["cursor"], b["revision"], b["env_names"])
    assert (a["rows"] == b["rows"]).all()
    np.testing.assert_array_equal(a["disk_goals"], b["disk_goals"])
    assert a["disk_attrs"] == b["disk_attrs"]


BAD_CALLS = {
    "wrong goal dim": (lambda rb: recall(rb, torch.zeros(4), 3), ValueError, "dimension 4"),
    "wrong goal dim, batched": (lambda rb: GoalIndex(rb).search(torch.zeros(2, 2), 3), ValueError, "dimension 2"),
    "NaN goal": (lambda rb: recall(rb, [0.1, float("nan"), 0.2], 3), ValueError, "NaN or infinite"),
    "k=0": (lambda rb: recall(rb, torch.zeros(3), 0), ValueError, "k must be a positive integer"),
    "k<0": (lambda rb: GoalIndex(rb).recall(torch.zeros(3), -1), ValueError, "k must be a positive integer"),
    "unknown env": (lambda rb: recall(rb, torch.zeros(3), 3, env="HandReach-v3"), ValueError,
                    "unknown env 'HandReach-v3'.*FetchPush-v4"),
    "sampler, wrong query dim": (
        lambda rb: _sample(rb, GoalSimilaritySampler(), torch.zeros(4)), ValueError, "dimension 4"),
    "sampler, NaN query": (
        lambda rb: _sample(rb, GoalSimilaritySampler(), torch.tensor([0.0, math.nan, 0.0])), ValueError,
        "NaN or infinite"),
    "sampler, unknown env": (
        lambda rb: _sample(rb, GoalSimilaritySampler(env="HandReach-v3"), torch.zeros(3)), ValueError,
        "unknown env"),
    "sampler, k=0": (
        lambda rb: _sample(rb, GoalSimilaritySampler(num_candidates=0), torch.zeros(3)), ValueError,
        "num_candidates"),
}


def _sample(rb, sampler, query):
    her = HERReplayBuffer(make_reward_fn("FetchPush-v4"), storage=rb.storage, sampler=sampler,
                          batch_size=32, achieved_goal_key=GOAL)
    sampler.set_query(query)
    return her.sample()


@pytest.fixture(scope="module")
def bad_input_store(tmp_path_factory):
    path = tmp_path_factory.mktemp("bad") / "m.zarr"
    rb = zarr_rb(path, 300, env="FetchPush-v4")
    rb.extend(fetch_rows(400, torch.Generator().manual_seed(7)))  # wrapped
    yield rb
    rb.storage.close()


@pytest.mark.parametrize("case", list(BAD_CALLS))
def test_bad_input_leaves_store_unchanged(bad_input_store, case):
    rb = bad_input_store
    call, error, match = BAD_CALLS[case]
    before = _state(rb)
    with pytest.raises(error, match=match):
        call(rb)
    _assert_same_state(before, _state(rb))
    assert_exact(GoalIndex(rb), rb.storage, torch.rand(4, 3), 5)  # still answers correctly


def test_store_without_goal_key_is_refused_and_unchanged(tmp_path):
    gen = torch.Generator().manual_seed(8)
    rows = fetch_rows(120, gen)
    del rows[GOAL]
    del rows[SUCCESS]
    rb = zarr_rb(tmp_path / "m.zarr", 200, env="FetchPush-v4")
    rb.extend(rows)
    rb.storage.flush()
    disk = zarr.open_group(str(rb.storage.path), mode="r")
    before = (len(rb), rb.writer._cursor, rb.storage._storage[:120].clone(), dict(disk.attrs))
    with pytest.raises(KeyError, match=r"no column \('next', 'achieved_goal'\)"):
        recall(rb, torch.zeros(3), 3)
    with pytest.raises(KeyError, match="success_only needs the column"):
        GoalIndex(rb, goal_key="achieved_goal").search(torch.zeros(3), 3, success_only=True)
    sampler = GoalSimilaritySampler()
    srb = TensorDictReplayBuffer(storage=rb.storage, sampler=sampler, batch_size=8)
    sampler.set_query(torch.zeros(3))
    with pytest.raises(KeyError, match="no column"):
        srb.sample()
    rb.storage.flush()
    disk = zarr.open_group(str(rb.storage.path), mode="r")
    after = (len(rb), rb.writer._cursor, rb.storage._storage[:120].clone(), dict(disk.attrs))
    assert before[:2] == after[:2] and (before[2] == after[2]).all() and before[3] == after[3]
    # another goal column of the same store works
    out = recall(rb, torch.zeros(3), 3, goal_key="achieved_goal")
    assert out["mask"].all()
    rb.storage.close()
