"""HER over a memory that fills and wraps (``PersistentHERReplayBuffer``), against TorchRL 0.14.1's faults there.

Found by a review: once a ring is full, TorchRL's ``HERReplayBuffer`` raised at the first sample after an
extend (its cache key compares the tensor of the rows last written), and relabelled the rows of the episode
that wraps, before the wrap, with goals of another episode. Every row here carries its episode and step, and
its achieved goal is unique, so each relabelled goal names the row it came from.
"""
from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import HERReplayBuffer, LazyTensorStorage

from torchrl_robotmem import PersistentHERReplayBuffer, ZarrStorage, make_reward_fn

ENV = "FetchReach-v4"


def _episode(ep: int, steps: int) -> TensorDict:
    t = torch.arange(steps)
    goal = torch.stack([torch.full((steps,), float(ep)), t.float(), torch.zeros(steps)], -1)  # unique: (episode, t)
    done = (t == steps - 1).unsqueeze(-1)
    return TensorDict({"observation": torch.zeros(steps, 2), "desired_goal": torch.full((steps, 3), -1.0),
                       "ep": torch.full((steps,), ep), "t": t,
                       ("next", "achieved_goal"): goal, ("next", "desired_goal"): torch.full((steps, 3), -1.0),
                       ("next", "reward"): -torch.ones(steps, 1), ("next", "done"): done,
                       ("next", "terminated"): torch.zeros(steps, 1, dtype=torch.bool)}, [steps])


def _buffer(storage, strategy: str, cls=PersistentHERReplayBuffer):
    return cls(make_reward_fn(ENV), her_ratio=1.0, strategy=strategy, achieved_goal_key=("next", "achieved_goal"),
               storage=storage, batch_size=400)


def _check(rb) -> None:
    """Every relabelled goal is an achieved goal of the row's own episode (for "future": at or after its step)."""
    batch = rb.sample()
    goal = batch["desired_goal"]
    src_ep, src_t = goal[:, 0].long(), goal[:, 1].long()
    assert (src_ep == batch["ep"]).all(), "a goal from another episode"
    assert (goal == batch["next", "desired_goal"]).all()
    if rb.strategy.value == "future":
        assert (src_t >= batch["t"]).all(), "a goal from the past"
    stored = {(int(e), int(t)) for e, t in zip(rb.storage[:]["ep"], rb.storage[:]["t"])}
    assert all((int(e), int(t)) in stored for e, t in zip(src_ep, src_t)), "a goal no stored row achieved"


def _storages(tmp_path, size):
    return {"lazy": lambda: LazyTensorStorage(size),
            "zarr": lambda: ZarrStorage(str(tmp_path / "m.zarr"), size, env=ENV, goal_conditioned=False)}


@pytest.mark.parametrize("kind", ["lazy", "zarr"])
@pytest.mark.parametrize("strategy", ["future", "final", "episode"])
def test_a_full_ring_samples_after_every_extend_and_never_crosses_an_episode(tmp_path, kind, strategy):
    rb = _buffer(_storages(tmp_path, 130)[kind](), strategy)
    for ep in range(9):  # 50-step episodes into 130 rows: full from the 3rd, an episode spans each wrap
        rb.extend(_episode(ep, 50))
        _check(rb)
    assert len(rb) == 130


def test_torchrl_s_own_buffer_fails_there():
    """The faults the class mends, shown on TorchRL's own buffer (when this fails, TorchRL has fixed them)."""
    rb = _buffer(LazyTensorStorage(130), "final", cls=HERReplayBuffer)
    for ep in range(3):
        rb.extend(_episode(ep, 50))
    rb.sample()
    rb.extend(_episode(3, 50))
    with pytest.raises(RuntimeError, match="ambiguous"):
        rb.sample()
    rb = _buffer(LazyTensorStorage(130), "final", cls=HERReplayBuffer)  # a fresh buffer samples once
    for ep in range(5):  # rows 120-129 are episode 2 before the wrap; TorchRL gives them episode 4's range
        rb.extend(_episode(ep, 50))
    with pytest.raises(AssertionError, match="another episode"):
        _check(rb)


def test_a_reopened_full_memory_samples_extends_and_samples_again(tmp_path):
    path = str(tmp_path / "m.zarr")
    rb = _buffer(ZarrStorage(path, 130, env=ENV, goal_conditioned=False), "final")
    for ep in range(5):
        rb.extend(_episode(ep, 50))
    rb.storage.close()
    again = _buffer(ZarrStorage(path, env=ENV, goal_conditioned=False), "final")
    _check(again)
    for ep in range(5, 8):
        again.extend(_episode(ep, 50))
        _check(again)
    again.storage.close()


def test_a_write_of_exactly_max_size_rows_between_two_samples_rebuilds_the_episode_bounds():
    """len, the last row and fullness are the same before and after: the storage's mutation counter tells."""
    rb = _buffer(LazyTensorStorage(60), "final")
    rb.extend(_episode(0, 30))
    rb.extend(_episode(1, 30))
    _check(rb)
    rb.extend(torch.cat([_episode(2, 20), _episode(3, 40)]))  # 60 rows: the same cursor, new episode bounds
    _check(rb)


@pytest.mark.parametrize("kind", ["lazy", "zarr"])
@pytest.mark.parametrize("restore", ["load_state_dict", "loads"])
def test_a_restored_full_ring_whose_newest_episode_is_open_never_crosses_it(tmp_path, kind, restore):
    """Found by a review: TorchRL's load_state_dict / loads restore no storage's last cursor, so the open
    episode at the write cursor lost its end and relabelled with the older episode's goals behind it. The row
    before the writer's cursor (which TorchRL restores) ends it."""
    def ring(tag):
        return LazyTensorStorage(130) if kind == "lazy" else ZarrStorage(
            str(tmp_path / f"{tag}.zarr"), 130, env=ENV, goal_conditioned=False, chunk_rows=16)

    source = _buffer(ring("source"), "final")
    for ep in range(3):
        source.extend(_episode(ep, 50))
    source.extend(_episode(3, 50)[:20])  # 170 rows into 130: episode 3 open at row 39, episode 0's tail after it
    restored = _buffer(ring("restored"), "final")
    if restore == "load_state_dict":
        restored.load_state_dict(source.state_dict())
    else:
        source.dumps(tmp_path / "ckpt")
        restored.loads(tmp_path / "ckpt")
    for strategy in ("final", "episode", "future"):
        restored.strategy = type(restored.strategy)(strategy)
        _check(restored)
    for rb in (source, restored):
        if hasattr(rb.storage, "close"):
            rb.storage.close()


@pytest.mark.parametrize("kind", ["lazy", "zarr"])
@pytest.mark.parametrize("restore", ["load_state_dict", "loads"])
def test_a_checkpoint_restored_into_a_buffer_that_wrote_since_never_crosses_the_open_episode(tmp_path, kind, restore):
    """Found by a review: a rollback (or a resume into a buffer that has written) kept the storage's last cursor
    of before the restore (TorchRL's storages do not reset it), so the checkpoint's open episode lost its end."""
    rb = _buffer(LazyTensorStorage(130) if kind == "lazy" else ZarrStorage(
        str(tmp_path / "m.zarr"), 130, env=ENV, goal_conditioned=False, chunk_rows=16), "final")
    for ep in range(3):
        rb.extend(_episode(ep, 50))
    rb.extend(_episode(3, 50)[:20])  # episode 3 open at row 39
    state = copy.deepcopy(rb.state_dict())  # (TorchRL's state holds the storage's own tensors)
    if restore == "loads":
        rb.dumps(tmp_path / "ckpt")
    rb.extend(_episode(3, 50)[20:])  # training goes on: the last written row moves on
    rb.extend(_episode(4, 50)[:17])
    _check(rb)
    if restore == "load_state_dict":
        rb.load_state_dict(state)
    else:
        rb.loads(tmp_path / "ckpt")
    for strategy in ("final", "episode", "future"):
        rb.strategy = type(rb.strategy)(strategy)
        _check(rb)
    if hasattr(rb.storage, "close"):
        rb.storage.close()
