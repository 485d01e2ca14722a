"""Many collectors and Ray over one ZarrStorage: one writer process, many producers.

* ``MultiSyncCollector`` / ``MultiAsyncCollector`` workers (spawned processes,
  real ``FetchReach-v4`` envs) feed a buffer whose ``ZarrStorage`` lives in the
  main process, the single writer: every frame a worker produced is stored once,
  bit-exact, with one episode tag per collector trajectory.
* ``replay_buffer=`` given to a multi-process collector: TorchRL pickles the
  buffer into each worker, where a ``ZarrStorage`` arrives as a read-only handle.
  The worker's first write fails with an error that says what to do, and the
  store is unchanged.
* ``RayReplayBuffer`` with ``storage=partial(ZarrStorage, path, max_size)``: the
  storage lives in the Ray actor, the single writer; the driver and Ray tasks
  extend and sample through it, a second writer is refused, and the store
  reopens with every row after the actor is gone.

Ray starts a local instance (``num_cpus=2``, no dashboard); the test is skipped,
with the reason, only if Ray cannot start here. Every spawned worker imports
torch, TorchRL and MuJoCo (5-15 s each on a busy 2-core box), so the default
suite runs one multi-process collector (``MultiAsyncCollector``, two workers);
``DISTRIBUTED_FULL=1`` adds ``MultiSyncCollector`` and the real
``replay_buffer=`` collector run (the error path is also checked without
spawning, by pickling the storage as TorchRL does).
"""
from __future__ import annotations

import os
import tempfile
from functools import partial
from pathlib import Path

import pytest
import torch
from conftest import make_transitions
from tensordict import TensorDict
from torchrl.collectors import MultiAsyncCollector, MultiSyncCollector
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage, make_env

ENV = "FetchReach-v4"
TRAJ = ("collector", "traj_ids")
FULL = pytest.mark.skipif(not os.environ.get("DISTRIBUTED_FULL"), reason="slow (spawns workers): DISTRIBUTED_FULL=1")


@pytest.mark.parametrize("collector_cls", [pytest.param(MultiSyncCollector, marks=FULL), MultiAsyncCollector])
def test_multi_process_collectors_feed_one_writer(tmp_path, collector_cls):
    storage = ZarrStorage(tmp_path / "m.zarr", 10_000, env=ENV)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=32)
    make = partial(make_env, ENV)
    collector = collector_cls([make, make], None, frames_per_batch=100, total_frames=400)
    yielded = []
    try:
        for data in collector:  # the workers step the envs; this process is the one writer
            flat = data.reshape(-1)
            yielded.append(flat.exclude("index").clone())
            rb.extend(flat)
    finally:
        collector.shutdown()
    written = torch.cat(yielded)
    n = written.numel()
    assert n >= 400 and len(rb) == n and rb.sample().batch_size == torch.Size([32])
    storage.close()

    reader = ZarrStorage(tmp_path / "m.zarr", read_only=True, sample_tags=True)
    rows = reader.get(torch.arange(n))
    for key in ("observation", ("next", "observation"), "action", ("next", "reward"), TRAJ):
        assert torch.equal(rows.get(key), written.get(key)), key
    # one episode tag per (collector) trajectory, across the two workers
    traj, episode = rows.get(TRAJ).reshape(-1), rows.get("episode")
    assert traj.unique().numel() == episode.unique().numel() >= 2
    for e in episode.unique():
        assert rows.get(TRAJ)[episode == e].unique().numel() == 1
    assert reader["run"].unique().tolist() == [0] and reader.env_names == (ENV,)


@FULL
def test_replay_buffer_in_multi_collector_fails_with_advice(tmp_path, capfd):
    storage = ZarrStorage(tmp_path / "m.zarr", 10_000, env=ENV)
    rb = TensorDictReplayBuffer(storage=storage)
    before = make_env(ENV).rollout(10).reshape(-1)
    rb.extend(before)
    make = partial(make_env, ENV)
    collector = MultiAsyncCollector([make, make], None, frames_per_batch=50, total_frames=200, replay_buffer=rb)
    try:
        with pytest.raises(RuntimeError, match="process failed"):
            for _ in collector:
                pass
    finally:
        collector.shutdown()
    err = capfd.readouterr().err  # the workers' tracebacks (they share this process's stderr)
    assert "the copy another process receives" in err and "call rb.extend(data)" in err
    assert len(rb) == 10
    storage.close()
    reader = ZarrStorage(tmp_path / "m.zarr", read_only=True)
    assert len(reader) == 10
    assert torch.equal(reader.get(torch.arange(10))["observation"], before["observation"])


def test_pickled_storage_refuses_writes_with_advice(tmp_path):
    import pickle

    storage = ZarrStorage(tmp_path / "m.zarr", 100)
    TensorDictReplayBuffer(storage=storage).extend(make_transitions(5))
    copy = pickle.loads(pickle.dumps(storage))  # what a worker or a Ray task receives
    assert copy.read_only and len(copy) == 5
    with pytest.raises(RuntimeError, match="Do not pass replay_buffer= to MultiSyncCollector"):
        TensorDictReplayBuffer(storage=copy).extend(make_transitions(5, 5))
    assert len(ZarrStorage(tmp_path / "m.zarr", read_only=True)) == 5


# -- Ray ----------------------------------------------------------------------------


@pytest.mark.full
def test_ray_replay_buffer_with_zarr_storage(tmp_path):
    ray = pytest.importorskip("ray", reason="ray is not installed")
    from torchrl.data.replay_buffers.ray_buffer import RayReplayBuffer

    path = str(tmp_path / "m.zarr")
    try:
        rb = RayReplayBuffer(
            storage=partial(ZarrStorage, path, 1000, env="FetchPush-v4"),
            replay_buffer_cls=TensorDictReplayBuffer,
            batch_size=8,
            ray_init_config={"address": None, "num_cpus": 2, "include_dashboard": False, "log_to_driver": False},
            remote_config={"num_cpus": 0},
        )
    except Exception as err:  # noqa: BLE001 - the skip reason names it
        pytest.skip(f"ray cannot start here: {type(err).__name__}: {err}")

    @ray.remote(num_cpus=0)
    def produce(client, data: TensorDict) -> int:  # a Ray task extending through the actor
        client.extend(data)
        return len(client)

    try:
        rb.extend(make_transitions(100))
        assert ray.get(produce.remote(rb.client(), make_transitions(50, 100))) == 150
        assert len(rb) == 150 and rb.sample().batch_size == torch.Size([8])
        # the actor holds the store's writer lock: no second writer, readers welcome
        with pytest.raises(RuntimeError, match="writing to"):
            ZarrStorage(path)
        rb.dumps(tempfile.mkdtemp(dir=tmp_path))  # makes everything durable (a checkpoint)
        reader = ZarrStorage(path, read_only=True)
        assert len(reader) == 150
        assert torch.equal(reader.get(torch.arange(150))["observation"], make_transitions(150)["observation"])
    finally:
        rb.shutdown()
        ray.shutdown()
    # the actor is gone (killed): the store reopens for writing and resumes
    storage = ZarrStorage(path)
    local = TensorDictReplayBuffer(storage=storage)
    assert len(local) == 150 and local.writer._cursor == 150
    local.extend(make_transitions(10, 150))
    assert Path(path, "zarr.json").exists() and len(storage) == 160
    storage.close()
