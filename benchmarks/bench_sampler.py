"""GoalSimilaritySampler against RandomSampler, plain and HER, over LazyTensorStorage and
ZarrStorage; and HER sampling against Stable-Baselines3's ``HerReplayBuffer.sample(256)``.

Every number is the median of ``--repeat`` calls of a full ``rb.sample()``
(batch 256). The calls of one table are interleaved round-robin (A, B, C, A,
B, C, ...) so that all of them see the same machine noise, and ratios are
taken between medians of the same run.

* Per storage (``LazyTensorStorage`` and ``ZarrStorage`` holding the same
  ``--rows`` FetchPush-shaped transitions, episodes of 50 steps): uniform
  ``RandomSampler``, ``GoalSimilaritySampler`` without a query, with one query
  (cached, or a new query before each call), 16 queries, ``uniform_ratio``,
  ``success_only``; then ``torchrl.data.HERReplayBuffer`` (future strategy,
  ``her_ratio=0.8``, rewards from ``make_reward_fn("FetchPush-v4")``) with
  ``RandomSampler`` and with ``GoalSimilaritySampler``.
* Against SB3 (``--sb3-rows`` transitions, default ``--rows``): SB3's
  ``HerReplayBuffer`` (future strategy, ``n_sampled_goal=4`` i.e. 80 %
  relabelled, rewards from the env's ``compute_reward`` through a
  ``DummyVecEnv`` of ``gymnasium.make("FetchPush-v4")``) filled through its
  ``add`` with the same transitions, and ``HERReplayBuffer`` over
  ``ZarrStorage`` / ``LazyTensorStorage``. SB3 is optional
  (``pip install 'torchrl_robotmem[sb3]'``); without it that table is skipped.

Prints markdown tables and writes ``bench_results/sampler.json``.

    python benchmarks/bench_sampler.py                               # 1M rows, batch 256
    python benchmarks/bench_sampler.py --rows 100000 --repeat 51     # quicker
"""
from __future__ import annotations

import argparse
import gc
import itertools
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time

import torch
from torchrl.data import HERReplayBuffer, LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_recall import make_goals, make_rows  # noqa: E402

from torchrl_robotmem import GoalSimilaritySampler, ZarrStorage, make_reward_fn  # noqa: E402

torch.set_num_threads(1)

ENV_ID = "FetchPush-v4"
GOAL = ("next", "achieved_goal")


def interleaved_ms(fns: dict, repeat: int, warmup: int = 3) -> dict[str, float]:
    """Median wall time (ms) of each callable, called round-robin ``repeat`` times."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    times = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {name: 1e3 * statistics.median(t) for name, t in times.items()}


def make_storage(kind: str, rows: int, tmpdir: str):
    if kind == "LazyTensorStorage":
        return LazyTensorStorage(rows)
    storage = ZarrStorage(os.path.join(tmpdir, f"sampler_{rows}.zarr"), rows, env=ENV_ID)
    storage.env_code("FetchSlide-v4", create=True)  # make_rows tags rows with env codes 0 and 1
    return storage


def fill(storage, rows: int, seed: int = 0) -> float:
    """Writes ``rows`` FetchPush-shaped transitions (episodes of 50 steps); returns seconds."""
    gen = torch.Generator().manual_seed(seed)
    rb = TensorDictReplayBuffer(storage=storage)
    t0 = time.perf_counter()
    for start in range(0, rows, 100_000):
        batch = make_rows("fetch3", min(100_000, rows - start), gen, start)
        if isinstance(storage, ZarrStorage):
            # the storage draws episode and run ids itself (from the done flags: the same 50-step episodes)
            batch = batch.exclude("episode", "run")
        rb.extend(batch)
    if isinstance(storage, ZarrStorage):
        storage.flush()  # durable, and the background writer idle before anything is timed
    return time.perf_counter() - t0


def her(storage, sampler, bs, reward_fn):
    return HERReplayBuffer(reward_fn, storage=storage, sampler=sampler, batch_size=bs,
                           achieved_goal_key=GOAL, her_ratio=0.8, strategy="future")


def bench_storage(storage, queries, bs, repeat, reward_fn) -> dict:
    q1 = queries[0]
    tick = itertools.count()

    def buf(sampler):
        return TensorDictReplayBuffer(storage=storage, sampler=sampler, batch_size=bs)

    uniform = buf(RandomSampler())
    no_query = buf(GoalSimilaritySampler())
    cached = buf(GoalSimilaritySampler())
    new1 = buf(GoalSimilaritySampler())
    new16 = buf(GoalSimilaritySampler())
    mixed = buf(GoalSimilaritySampler(uniform_ratio=0.25))
    success = buf(GoalSimilaritySampler(success_only=True))

    res = {}
    t0 = time.perf_counter()
    with cached.sampler.query(q1):
        cached.sample()
    res["first_sample_with_index_build_ms"] = 1e3 * (time.perf_counter() - t0)
    cached.sampler.set_query(q1)

    def new_query(rb, Q=1):
        def call():
            i = next(tick)
            q = queries[i % 64] if Q == 1 else queries[(i % 4) * 16 : (i % 4) * 16 + 16]
            rb.sampler.set_query(q + 1e-4 * (i % 97))
            return rb.sample()
        return call

    res.update(interleaved_ms({
        "uniform_RandomSampler_ms": uniform.sample,
        "goal_sampler_no_query_ms": no_query.sample,
        "query_1_cached_ms": cached.sample,
        "query_1_new_each_call_ms": new_query(new1),
        "query_16_new_each_call_ms": new_query(new16, 16),
        "query_1_uniform_ratio_0.25_new_each_call_ms": new_query(mixed),
        "query_1_success_only_new_each_call_ms": new_query(success),
    }, repeat))
    b = cached.sample()
    u = uniform.sample()
    res["mean_goal_distance_query"] = b["goal_distance"].mean().item()
    res["mean_goal_distance_uniform"] = (u[GOAL] - q1).norm(dim=-1).mean().item()

    her_uniform = her(storage, RandomSampler(), bs, reward_fn)
    her_cached = her(storage, GoalSimilaritySampler(), bs, reward_fn)
    her_cached.sampler.set_query(q1)
    her_new = her(storage, GoalSimilaritySampler(), bs, reward_fn)
    res.update(interleaved_ms({
        "her_uniform_RandomSampler_ms": her_uniform.sample,
        "her_query_1_cached_ms": her_cached.sample,
        "her_query_1_new_each_call_ms": new_query(her_new),
    }, repeat))

    base = res["uniform_RandomSampler_ms"]
    for key in list(res):
        if key.startswith("query_") or key == "goal_sampler_no_query_ms":
            res[f"ratio {key}"] = res[key] / base
    for key in ("her_query_1_cached_ms", "her_query_1_new_each_call_ms"):
        res[f"ratio {key}"] = res[key] / res["her_uniform_RandomSampler_ms"]
    return res


def sb3_her_buffer(storage, rows):
    """SB3's HerReplayBuffer on a DummyVecEnv(FetchPush-v4), filled through ``add`` with ``storage``'s rows."""
    import gymnasium
    import gymnasium_robotics
    from stable_baselines3 import HerReplayBuffer
    from stable_baselines3.common.vec_env import DummyVecEnv

    gymnasium.register_envs(gymnasium_robotics)
    venv = DummyVecEnv([lambda: gymnasium.make(ENV_ID)])
    rb = HerReplayBuffer(rows, venv.observation_space, venv.action_space, env=venv, device="cpu",
                         n_sampled_goal=4, goal_selection_strategy="future")
    data = storage._storage
    t0 = time.perf_counter()
    for start in range(0, rows, 50_000):
        sl = slice(start, min(start + 50_000, rows))
        obs = {k: data.get(k)[sl].numpy() for k in ("observation", "achieved_goal", "desired_goal")}
        nxt = {k: data.get(("next", k))[sl].numpy() for k in ("observation", "achieved_goal", "desired_goal")}
        act = data.get("action")[sl].numpy()
        rew = data.get(("next", "reward"))[sl].numpy().reshape(-1, 1)
        done = data.get(("next", "done"))[sl].numpy().reshape(-1, 1)
        for i in range(sl.stop - sl.start):
            rb.add({k: v[i : i + 1] for k, v in obs.items()}, {k: v[i : i + 1] for k, v in nxt.items()},
                   act[i : i + 1], rew[i], done[i], [{"TimeLimit.truncated": bool(done[i, 0])}])
    return rb, time.perf_counter() - t0


def bench_sb3(storages: dict, rows: int, queries, bs, repeat, reward_fn) -> dict:
    try:
        import stable_baselines3
    except ImportError:
        print("\nStable-Baselines3 comparison: skipped (pip install 'torchrl_robotmem[sb3]')")
        return {"skipped": "stable-baselines3 not installed"}
    sb3, fill_s = sb3_her_buffer(storages["ZarrStorage"], rows)
    q1 = queries[0]
    tick = itertools.count()
    her_zarr_uniform = her(storages["ZarrStorage"], RandomSampler(), bs, reward_fn)
    her_lazy_uniform = her(storages["LazyTensorStorage"], RandomSampler(), bs, reward_fn)
    her_zarr_cached = her(storages["ZarrStorage"], GoalSimilaritySampler(), bs, reward_fn)
    her_zarr_cached.sampler.set_query(q1)
    her_zarr_new = her(storages["ZarrStorage"], GoalSimilaritySampler(), bs, reward_fn)

    def new_query():
        i = next(tick)
        her_zarr_new.sampler.set_query(queries[i % 64] + 1e-4 * (i % 97))
        return her_zarr_new.sample()

    res = {"rows": rows, "sb3_version": stable_baselines3.__version__, "sb3_fill_s": fill_s}
    res.update(interleaved_ms({
        "sb3_HerReplayBuffer_sample256_ms": lambda: sb3.sample(bs),
        "her_ZarrStorage_RandomSampler_ms": her_zarr_uniform.sample,
        "her_LazyTensorStorage_RandomSampler_ms": her_lazy_uniform.sample,
        "her_ZarrStorage_GoalSimilaritySampler_query_cached_ms": her_zarr_cached.sample,
        "her_ZarrStorage_GoalSimilaritySampler_new_query_each_call_ms": new_query,
    }, repeat))
    base = res["sb3_HerReplayBuffer_sample256_ms"]
    for key in list(res):
        if key.startswith("her_"):
            res[f"ratio {key} / sb3"] = res[key] / base
    return res


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--sb3-rows", type=int, default=None,
                        help="transitions for the SB3 comparison (default: --rows)")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--repeat", type=int, default=101)
    parser.add_argument("--zarr-dir", default=None, help="where the temporary ZarrStorage goes")
    parser.add_argument("--out", default="bench_results/sampler.json")
    args = parser.parse_args()
    bs, rep = args.batch, args.repeat
    sb3_rows = args.sb3_rows or args.rows
    queries = make_goals("fetch3", 64, torch.Generator().manual_seed(1))
    reward_fn = make_reward_fn(ENV_ID)
    tmpdir = tempfile.mkdtemp(prefix="bench_sampler_", dir=args.zarr_dir)
    out = {"rows": args.rows, "batch": bs, "repeat": rep, "torch_threads": torch.get_num_threads(),
           "machine": f"{platform.machine()}, {os.cpu_count()} cpus", "torch": torch.__version__}
    storages = {}

    def close_all():
        for st in storages.values():
            if isinstance(st, ZarrStorage):
                st.close()
        storages.clear()
        gc.collect()

    try:
        for kind in ("LazyTensorStorage", "ZarrStorage"):
            storages[kind] = make_storage(kind, args.rows, tmpdir)
            fill_s = fill(storages[kind], args.rows)
            out[kind] = {"fill_s": fill_s, **bench_storage(storages[kind], queries, bs, rep, reward_fn)}
        if sb3_rows != args.rows:
            close_all()
            for kind in ("LazyTensorStorage", "ZarrStorage"):
                storages[kind] = make_storage(kind, sb3_rows, tmpdir)
                fill(storages[kind], sb3_rows)
        out["her_vs_sb3"] = bench_sb3(storages, sb3_rows, queries, bs, rep, reward_fn)
    finally:
        close_all()
        shutil.rmtree(tmpdir, ignore_errors=True)

    print(f"\nGoalSimilaritySampler, {args.rows} rows, batch {bs}, torch threads=1, "
          f"medians of {rep} interleaved calls\n")
    kinds = ("LazyTensorStorage", "ZarrStorage")
    print("| measure | " + " | ".join(kinds) + " |\n|---|---|---|")
    for key in out["ZarrStorage"]:
        cells = [out[k].get(key) for k in kinds]
        print(f"| {key} | " + " | ".join(f"{c:.4g}" if isinstance(c, float) else str(c) for c in cells) + " |")
    sb3 = out["her_vs_sb3"]
    if "skipped" not in sb3:
        print(f"\nHER sample({bs}) against Stable-Baselines3 {sb3['sb3_version']} HerReplayBuffer, "
              f"{sb3['rows']} transitions, medians of {rep} interleaved calls\n")
        print("| measure | value |\n|---|---|")
        for key, value in sb3.items():
            print(f"| {key} | {value:.4g} |" if isinstance(value, float) else f"| {key} | {value} |")
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=2)
    print(f"\nwritten to {args.out}")


if __name__ == "__main__":
    main()
