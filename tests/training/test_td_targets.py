"""recipes/her/targets.py: optim.target_clip clamps the TD targets of the recipe's real SAC / TD3 / DDPG losses."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from torchrl.data import LazyTensorStorage

ROOT = Path(__file__).resolve().parents[2]
RECIPE_DIR = ROOT / "recipes" / "her"
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

from recipes.her import utils  # noqa: E402
from recipes.her.targets import ClippedTD0Estimator, clip_targets, target_range  # noqa: E402

torch.set_num_threads(1)


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(RECIPE_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=["network.hidden_sizes=[16,16]", "optim.batch_size=32",
                                                        *overrides])


@pytest.fixture(scope="module")
def reach_batch():
    cfg = _cfg()
    env = utils.make_task_env(cfg, 1, seed=0)
    rows = env.rollout(100, break_when_any_done=False).reshape(-1)
    rb = utils.make_replay_buffer(cfg, LazyTensorStorage(1000))
    rb.extend(rows)
    torch.manual_seed(0)
    return env, rows, rb.sample()


def _target_values(algo: str, target_clip, reach_batch) -> torch.Tensor:
    """The critic targets of one batch, with the target critic's output pushed to about +1000."""
    env, rows, batch = reach_batch
    cfg = _cfg(f"algo={algo}")
    torch.manual_seed(0)
    normalizer = utils.GoalNormalizer()
    normalizer.update(rows)
    model, _ = utils.make_agent(cfg, env, normalizer)
    loss, _ = utils.make_loss_module(cfg, model)
    assert clip_targets(loss, target_clip, cfg.optim.gamma) == target_range(target_clip, cfg.optim.gamma)
    target = loss.target_value_network_params if algo == "ddpg" else loss.target_qvalue_network_params
    last_bias = [k for k in target.keys(True, True) if k[-1] == "bias"][-1]
    target.get(last_bias).data.add_(1000.0)  # a critic that has diverged upwards, as SAC's did on FetchSlide
    batch = batch.clone()
    if algo == "sac":  # SAC reports |Q - target| per row, not the target
        _, meta = loss.qvalue_v2_loss(batch)
        return meta["td_error"]
    _, meta = (loss.value_loss if algo == "td3" else loss.loss_value)(batch)
    return meta["target_value"]


@pytest.mark.parametrize("algo", ["sac", "td3", "ddpg"])
def test_targets_stay_in_the_range_of_a_sparse_return(algo, reach_batch):
    low = -1.0 / (1.0 - 0.95)  # optim.gamma of env=reach
    clamped = _target_values(algo, "auto", reach_batch)
    if algo == "sac":  # |Q - target| with fresh critics (|Q| of a few units) and a target in [low, 0]
        assert clamped.max() < -low + 10.0
    else:
        assert clamped.max() <= 0.0 and clamped.min() >= low - 1e-4
    free = _target_values(algo, None, reach_batch)
    assert free.abs().max() > 500.0  # without the clamp the diverged critic passes straight into the targets


def test_target_range_values_and_refusals():
    assert target_range("auto", 0.98) == (-50.0, 0.0)
    assert target_range([-2, 3], 0.98) == (-2.0, 3.0)
    assert target_range(None, 0.98) is None
    with pytest.raises(ValueError, match="optim.target_clip must be auto, null or"):
        target_range("on", 0.98)
    cfg = _cfg("algo=td3")
    env = utils.make_task_env(cfg, 1, seed=0)
    try:
        model, _ = utils.make_agent(cfg, env, utils.GoalNormalizer())
        loss, _ = utils.make_loss_module(cfg, model)
        with pytest.raises(ValueError, match="low < high"):
            clip_targets(loss, [0, -1], 0.98)
        assert type(loss.value_estimator).__name__ == "TD0Estimator"  # a refused range changes nothing
        clip_targets(loss, "auto", 0.98)
        assert isinstance(loss.value_estimator, ClippedTD0Estimator)
        with pytest.raises(TypeError, match="set optim.target_clip=null"):
            clip_targets(loss, "auto", 0.98)  # only a plain TD(0) estimator is turned, and only once
    finally:
        env.close()
