"""experiments.her.hand_memory (issue 27): coverage by exact recall and hindsight clones, on a real HandReach memory.

Real parts: two random HandReach-v3 episodes from the library's TorchRL env, written to a
real ZarrStorage (episodes delimited by its done flags only), the tool run on it.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from experiments.her import hand_memory  # noqa: E402

# experiments/ is reproduced in the full tier (make test-full, every landing): make test covers the product
pytestmark = pytest.mark.full


@pytest.fixture(scope="module")
def hand_memory_path(tmp_path_factory):
    from torchrl_robotmem import ZarrStorage
    from torchrl_robotmem.envs import make_env

    torch.manual_seed(0)
    env = make_env("HandReach-v3", seed=0)
    try:
        rows = env.rollout(100, break_when_any_done=False)
    finally:
        env.close()
    path = tmp_path_factory.mktemp("hand") / "hand.zarr"
    with ZarrStorage(path, max_size=200, env="HandReach-v3") as store:
        store.set(range(100), rows)
    return path


def test_read_rows_numbers_the_episodes_from_the_done_flags(hand_memory_path):
    data = hand_memory.read_rows([str(hand_memory_path), str(hand_memory_path)])
    assert data["obs"].shape == (200, 63) and data["act"].shape == (200, 20) and data["ag"].shape == (200, 15)
    assert data["ep"].tolist() == [0] * 50 + [1] * 50 + [2] * 50 + [3] * 50  # the second memory's episodes follow


def test_cover_clone_and_plot(hand_memory_path, tmp_path, capsys):
    out = tmp_path / "results.jsonl"
    hand_memory.main(["cover", str(hand_memory_path), "--episodes", "5", "--out", str(out)])
    hand_memory.main(["clone", str(hand_memory_path), "--horizon", "1", "2", "--steps", "5", "--episodes", "2",
                      "--out", str(out)])
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["what"] for r in rows] == ["cover", "clone", "clone"]
    cover = rows[0]
    assert 0 < cover["pinch_goals"] <= 10  # 10 goals drawn (seeded), 10% of them rest poses on average
    assert 0 <= cover["within_0.01"] <= cover["within_0.02"] <= 1 and cover["nearest_median"] > 0
    assert [r["horizon"] for r in rows[1:]] == [1, 2]
    assert all(r["memory_rows"] == 100 and r["new_frames"] == 0 and 0 <= r["success"] <= 1 for r in rows[1:])
    assert capsys.readouterr().out.count("{") == 3  # one JSON line a result on stdout too
    run = tmp_path / "run.json"  # a run's curve as `compare --archive` keeps it
    run.write_text(json.dumps({"curve": [[0, 0.0], [50, 0.1], [100, 0.1]], "frames": 100}))
    assert hand_memory.load_run(str(run))["curve"] == [[0, 0.0], [50, 0.1], [100, 0.1]]  # what plot draws
    png = tmp_path / "hand.png"
    hand_memory.main(["plot", str(out), "--runs", f"SAC={run}", "--png", str(png)])
    assert png.stat().st_size > 0
    with pytest.raises(SystemExit):  # every other command needs a memory
        hand_memory.main(["cover"])
