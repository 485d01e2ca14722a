"""``ZarrStorage(..., goal_conditioned=False)``: rows of an env without a success flag get no success advice.

The warning of a handle's first write (``storage/context.py``: no ``("next", "is_success")``
column, no env name) is right for a goal env and noise for MaMuJoCo or any env that has no
success flag. The flag turns the success half off, is recorded in the store (an optional
attribute: stores written before it, such as ``tests/fixtures``, open as goal-conditioned) so
that a reopen remembers it, and leaves the env-name half on.
"""
from __future__ import annotations

import pathlib
import tarfile
import warnings

import pytest
import torch
import zarr
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage.integrity import verify

FIXTURES = pathlib.Path(__file__).resolve().parents[1] / "fixtures"
ADVICE = "the rows written have"


def cheetah_rows(n: int = 20) -> TensorDict:
    """MaMuJoCo-shaped transitions (2 agents, HalfCheetah 2x3): no goals and no success flag."""
    done = (torch.arange(n) % 10 == 9).unsqueeze(-1)
    return TensorDict({
        "agents": TensorDict({"observation": torch.randn(n, 2, 12), "action": torch.rand(n, 2, 3)}, [n, 2]),
        "next": {"agents": TensorDict({"observation": torch.randn(n, 2, 12), "reward": torch.randn(n, 2, 1)}, [n, 2]),
                 "done": done, "terminated": torch.zeros(n, 1, dtype=torch.bool), "truncated": done},
    }, [n])


def write(path, rows=None, **kwargs) -> list[str]:
    """Opens ``path`` with ``kwargs``, extends a buffer with ``rows`` and closes; returns the advice warnings."""
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        storage = ZarrStorage(str(path), **kwargs)
        TensorDictReplayBuffer(storage=storage).extend(cheetah_rows() if rows is None else rows)
        storage.close()
    return [str(w.message) for w in record if issubclass(w.category, UserWarning) and ADVICE in str(w.message)]


def goal_conditioned(path, **kwargs) -> bool:
    """What a handle on ``path`` (read-only unless ``kwargs`` say otherwise) holds the rows to be."""
    storage = ZarrStorage(str(path), **{"read_only": True, **kwargs})
    try:
        return storage.goal_conditioned
    finally:
        storage.close()


def recorded(path) -> dict:
    return zarr.open_group(str(path), mode="r").attrs.asdict()


def test_without_the_flag_the_success_advice_is_given(tmp_path):
    path = tmp_path / "cheetah.zarr"
    [advice] = write(path, max_size=100, env="HalfCheetah-2x3")
    assert "no ('next', 'is_success') column" in advice and "goal_conditioned=False" in advice
    assert "no env name" not in advice
    assert "goal_conditioned" not in recorded(path), "a store never told records nothing"
    assert goal_conditioned(path) is True


def test_goal_conditioned_false_is_quiet_and_remembered(tmp_path):
    path = tmp_path / "cheetah.zarr"
    assert write(path, max_size=100, env="HalfCheetah-2x3", goal_conditioned=False) == []
    assert recorded(path)["goal_conditioned"] is False
    # the next run opens the path alone: the store says so, no advice
    assert write(path, env="HalfCheetah-2x3") == []
    assert goal_conditioned(path) is False and recorded(path)["len"] == 40
    assert verify(str(path)).ok


def test_goal_conditioned_false_keeps_the_env_name_advice(tmp_path):
    path = tmp_path / "cheetah.zarr"
    [advice] = write(path, max_size=100, goal_conditioned=False)  # no env= either
    assert "no env name" in advice and "env='FetchReach-v4'" in advice
    assert "is_success" not in advice and "make_env" not in advice


def test_goal_rows_still_warned_and_true_overrides_the_record(tmp_path):
    path = tmp_path / "reach.zarr"
    assert write(path, max_size=100, env="HalfCheetah-2x3", goal_conditioned=False) == []
    # told otherwise: the advice is back, and the store records the change
    [advice] = write(path, env="HalfCheetah-2x3", goal_conditioned=True)
    assert "no ('next', 'is_success') column" in advice
    assert recorded(path)["goal_conditioned"] is True
    assert len(write(path, env="HalfCheetah-2x3")) == 1


def test_rows_with_a_success_flag_never_warn(tmp_path):
    rows = cheetah_rows().set(("next", "is_success"), torch.zeros(20))
    assert write(tmp_path / "a.zarr", rows, max_size=100, env="FetchReach-v4") == []
    assert write(tmp_path / "b.zarr", rows, max_size=100, env="FetchReach-v4", goal_conditioned=False) == []


def test_a_reader_given_the_flag_writes_nothing(tmp_path):
    path = tmp_path / "cheetah.zarr"
    write(path, max_size=100, env="HalfCheetah-2x3")
    before = (path / "zarr.json").read_bytes()
    reader = ZarrStorage(str(path), read_only=True, goal_conditioned=False)
    assert reader.goal_conditioned is False
    reader.close()
    assert (path / "zarr.json").read_bytes() == before


@pytest.mark.parametrize("tarball", sorted(FIXTURES.glob("store-zarr-*.tar.gz")), ids=lambda p: p.name)
def test_stores_older_than_the_flag_open_as_goal_conditioned(tarball, tmp_path):
    with tarfile.open(tarball) as tar:
        tar.extractall(tmp_path, filter="data")
    path = tmp_path / "memory"
    assert "goal_conditioned" not in recorded(path)
    storage = ZarrStorage(str(path), env="FetchPush-v4")  # writable, nothing said: nothing recorded
    assert storage.goal_conditioned is True
    storage.close()
    assert "goal_conditioned" not in recorded(path)
    storage = ZarrStorage(str(path), goal_conditioned=False)
    storage.close()
    assert goal_conditioned(path) is False
    assert verify(str(path)).ok


def test_built_by_hydra_from_plain_values(tmp_path):
    from hydra.utils import instantiate

    cfg = {"_target_": "torchrl_robotmem.ZarrStorage", "path": str(tmp_path / "m.zarr"), "max_size": 100,
           "env": "HalfCheetah-2x3", "goal_conditioned": False}
    storage = instantiate(cfg)
    assert storage.goal_conditioned is False
    storage.close()
    assert recorded(tmp_path / "m.zarr")["goal_conditioned"] is False


def test_refuses_what_is_not_a_bool(tmp_path):
    with pytest.raises(TypeError, match="goal_conditioned must be True, False or None"):
        ZarrStorage(str(tmp_path / "m.zarr"), 10, goal_conditioned="no")
