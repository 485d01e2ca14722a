"""experiments/cross_env: statistics, and the experiment command end to end on 2 episodes per arm."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch
from scipy.stats import binomtest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

from experiments.cross_env import run  # noqa: E402
from recipes.her.tools.stats import mcnemar, wilson  # noqa: E402

# experiments/ is reproduced in the full tier (make test-full, every landing): make test covers the product
pytestmark = pytest.mark.full

torch.set_num_threads(1)


def test_wilson_known_values():
    assert wilson(10, 100) == pytest.approx((0.0552, 0.1744), abs=1e-4)
    assert wilson(0, 20)[0] == 0.0 and wilson(20, 20)[1] == 1.0
    assert wilson(0, 0) == (0.0, 1.0)


def test_mcnemar_uses_discordant_pairs_only():
    a = [1] * 30 + [1] * 12 + [0] * 3 + [0] * 55
    b = [1] * 30 + [0] * 12 + [1] * 3 + [0] * 55
    t = mcnemar(a, b)
    assert (t["a_only"], t["b_only"]) == (12, 3)
    assert t["p"] == pytest.approx(binomtest(12, 15, 0.5).pvalue)
    assert t["diff"] == pytest.approx(0.09)
    assert mcnemar([1, 0], [1, 0])["p"] == 1.0
    with pytest.raises(ValueError):
        mcnemar([1], [1, 0])


def test_a_killed_memory_build_never_leaves_a_memory_behind(tmp_path):
    """SIGKILL during the pooled memory's build: ``seed0.zarr`` does not exist (learned_only rebuilds it)."""
    import signal
    import subprocess
    import time

    from experiments.scripted.controllers import StrikeParams
    from torchrl_robotmem import ZarrStorage

    path = tmp_path / "seed0.zarr"
    building = Path(str(path) + ".building")
    code = ("import sys; sys.path.insert(0, sys.argv[1]); from experiments.cross_env.run import build_memory;"
            "from experiments.scripted.controllers import StrikeParams;"
            "build_memory(sys.argv[2], 0, 10**6, 1, StrikeParams())")  # never finishes: killed mid-build
    proc = subprocess.Popen([sys.executable, "-c", code, str(ROOT), str(path)])
    try:
        while proc.poll() is None:  # wait until it has written rows
            time.sleep(0.2)
            # the commit record, once the writer has put it there (Zarr writes zarr.json atomically: the
            # group's empty one first, then the one with the format marker)
            written = [p for p in (building, path)
                       if (p / "zarr.json").is_file() and "torchrl_robotmem" in (p / "zarr.json").read_text()]
            if written:
                with ZarrStorage(str(written[0]), read_only=True) as store:
                    if len(store) >= 50:
                        break
        assert proc.poll() is None, "the build process died before it was killed"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert building.is_dir() and not path.exists()  # the half-written build is under its own name
    out = run.build_memory(str(path), 0, 1, 1, StrikeParams())  # a later build replaces it
    assert not building.exists() and out["push"]["path"] == str(path)
    with ZarrStorage(str(path), read_only=True) as store:
        assert len(store) == 100  # 1 + 1 episodes of 50 steps


@pytest.mark.full
def test_cross_env_command_end_to_end(tmp_path):
    out = tmp_path / "out"
    res = run.main([
        "seeds=1", "episodes=2", "push_episodes=2", "slide_episodes=2", "tune_episodes=2",
        "speeds=0.8", f"out={out}", f"workdir={tmp_path / 'mem'}",
        # the learned arm: FetchSlide SAC+HER with the pooled memory as prior vs scratch, a few frames
        "learned_frames=100", "learned_seeds=1", "learned_eval_episodes=1", "learned_eval_iter=100",
        "learned_overrides=collector.init_random_frames=50;memory.pretrain_updates=5;optim.batch_size=16;"
        "network.hidden_sizes=[16,16];replay_buffer.size=1000;logger.backend=",
    ])
    assert set(res["summary"]["arms"]) == set(run.ARMS)
    for arm in run.ARMS:
        assert res["summary"]["arms"][arm]["n"] == 2
    learned = res["learned"]
    assert learned["status"] == "run"
    for arm in ("prior", "scratch"):
        (run_,) = learned["runs"][arm]
        assert run_["env"] == "FetchSlide-v4" and run_["frames"] == 100
        assert run_["memory_rows_after"] == 100  # its own memory: the prior is read-only
    assert (out / "learned.png").stat().st_size > 0
    saved = json.loads((out / "results.json").read_text())
    assert saved["preregistered"]["primary"] == ["pooled_memory", "pooled_control"]
    assert (out / "cross_env.png").stat().st_size > 0
    report = (out / "report.md").read_text()
    assert "Primary contrast" in report and "| learned arm, seed |" in report
    # learned_only: the learned arm alone, next to the saved scripted arms; runs are resumed and extended,
    # and the pooled memory is rebuilt when the workdir lost it
    import shutil

    shutil.rmtree(tmp_path / "mem" / "seed0.zarr")
    again = run.main([
        f"out={out}", f"workdir={tmp_path / 'mem'}", "learned_only=true", "learned_jobs=2",  # both arms at once
        "learned_frames=200", "learned_seeds=1", "learned_eval_episodes=1", "learned_eval_iter=100",
        "learned_overrides=collector.init_random_frames=50;memory.pretrain_updates=5;optim.batch_size=16;"
        "network.hidden_sizes=[16,16];replay_buffer.size=1000;logger.backend=",
    ])
    assert again["summary"] == saved["summary"]  # scripted arms untouched
    for arm in ("prior", "scratch"):
        (run_,) = again["learned"]["runs"][arm]
        assert run_["frames"] == 200 and run_["memory_rows_after"] == 200
        assert [f for f, _ in run_["curve"]] == [0, 100, 200]  # continued, not restarted
    assert json.loads((out / "results.json").read_text())["config"]["learned_frames"] == 200
    # learned_arms=clone: the actor cloned from the pooled memory's successful episodes, added beside the
    # prior and scratch runs kept from before
    cloned = run.main([
        f"out={out}", f"workdir={tmp_path / 'mem'}", "learned_only=true", "learned_arms=clone",
        "learned_frames=100", "learned_seeds=1", "learned_eval_episodes=1", "learned_eval_iter=100",
        "learned_overrides=prior.clone_steps=5;memory.pretrain_updates=5;optim.batch_size=16;"
        "network.hidden_sizes=[16,16];replay_buffer.size=1000;logger.backend=",
    ])
    assert set(cloned["learned"]["runs"]) == {"prior", "scratch", "clone"}
    (run_,) = cloned["learned"]["runs"]["clone"]
    assert run_["env"] == "FetchSlide-v4" and run_["algo"] == "TD3" and run_["frames"] == 100
    assert cloned["learned"]["runs"]["prior"][0]["frames"] == 200  # kept, not rerun
    assert "cloned from the memory" in (out / "report.md").read_text()
    with pytest.raises(ValueError, match="learned_arms must name some of prior, scratch, clone"):
        run.main([f"out={out}", f"workdir={tmp_path / 'mem'}", "learned_only=true", "learned_arms=bc",
                  "learned_frames=100"])
