"""Smoke tests of recipes/her, as TorchRL's CI runs its sota scripts: real envs, real
stores, each run a subprocess with a budget of a few dozen frames."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
RECIPE_DIR = ROOT / "recipes" / "her"
ENV_GROUPS = {
    "reach": "FetchReach-v4",
    "push": "FetchPush-v4",
    "slide": "FetchSlide-v4",
    "pick_and_place": "FetchPickAndPlace-v4",
    "hand_reach": "HandReach-v3",
    "block": "HandManipulateBlock-v1",
    "egg": "HandManipulateEgg-v1",
    "pen": "HandManipulatePen-v1",
}
TINY = [
    "collector.total_frames=50",
    "collector.init_random_frames=25",
    "collector.frames_per_batch=25",
    "optim.batch_size=8",
    "network.hidden_sizes=[16,16]",
    "memory.pretrain_updates=3",
    "logger.eval_iter=50",
    "logger.eval_episodes=1",
    "logger.plot=false",
]


def run_recipe(tmp_path: Path, *overrides: str, out: str = "out") -> dict:
    proc = subprocess.run(
        [sys.executable, str(RECIPE_DIR / "train.py"), *TINY, *overrides, f"hydra.run.dir={tmp_path / out}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((tmp_path / out / "summary.json").read_text())
    summary["stdout"] = proc.stdout
    return summary


@pytest.mark.parametrize("algo", ["sac", pytest.param("td3", marks=pytest.mark.full),
                                  pytest.param("ddpg", marks=pytest.mark.full)])
def test_fetch_reach_runs(tmp_path, algo):
    s = run_recipe(tmp_path, f"algo={algo}", f"memory.path={tmp_path / 'mem.zarr'}")
    assert s["algo"] == algo.upper() and s["frames"] == 50 and s["memory_rows_after"] == 50
    assert s["updates"] > 0
    assert [f for f, _ in s["curve"]] == [0, 50]
    assert (tmp_path / "mem.zarr-agent").is_dir()  # torchrl.checkpoint of the agent
    scalars = next((tmp_path / "out" / "her_logging").glob("*/scalars"))
    assert (scalars / "eval" / "success_rate.csv").read_text().splitlines()[-1].startswith("50,")
    # every evaluation's per-episode successes, for goal-by-goal comparisons (recipes.her.tools.paired)
    from recipes.her.run_record import read_episodes

    episodes = read_episodes(str(tmp_path / "out"))
    assert sorted(episodes) == [0, 50] and all(e["seed"] == 0 and len(e["success"]) == 1 for e in episodes.values())
    assert [(f, float(sum(episodes[f]["success"]))) for f, _ in s["curve"]] == [(f, r) for f, r in s["curve"]]
    from recipes.her.tools import compare  # the archive of the run keeps them (run directories are machine-local)

    compare.main(["--out", str(tmp_path / "c.png"), "--archive", str(tmp_path / "runs"), f"a={tmp_path / 'out'}"])
    assert read_episodes(str(tmp_path / "runs" / "out.json")) == episodes


@pytest.mark.skipif(torch.cuda.is_available(), reason="the refusal on a machine without CUDA (tests/test_cuda.py runs it)")
def test_device_cuda_without_a_gpu_is_refused_before_anything_is_written(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(RECIPE_DIR / "train.py"), *TINY, "device=cuda", f"memory.path={tmp_path / 'm.zarr'}",
         f"hydra.run.dir={tmp_path / 'out'}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode != 0 and "torch sees no CUDA device" in proc.stderr and "device=cpu" in proc.stderr
    assert not (tmp_path / "m.zarr").exists()


def test_shadow_hand_runs(tmp_path):
    s = run_recipe(tmp_path, "env=hand_reach", f"memory.path={tmp_path / 'hand.zarr'}")
    assert s["env"] == "HandReach-v3" and s["memory_rows_after"] == 50


@pytest.mark.full  # a second test of what the default tier covers (make test stays under 15 minutes)
def test_resume_appends_to_the_memory(tmp_path):
    from torchrl_robotmem import ZarrStorage

    mem = tmp_path / "mem.zarr"
    first = run_recipe(tmp_path, f"memory.path={mem}", out="run1")
    with ZarrStorage(mem, read_only=True) as store:
        before = store[:50]["next", "achieved_goal"].clone()
    # second run: relative path (hydra changes directory), fresh networks, and the
    # memory switches on: the goal sampler and the recall transform over the reopened store
    second = run_recipe(
        tmp_path, "memory.path=mem.zarr", "collector.total_frames=25",
        "replay_buffer.sampler.enabled=true", "memory.recall.enabled=true", out="run2",
    )
    assert first["memory_rows_before"] == 0
    assert second["memory_rows_before"] == 50 and second["memory_rows_after"] == 75
    assert "memory " in second["stdout"] and ": 50 transitions" in second["stdout"]
    assert second["updates"] >= 3  # pretraining on the remembered rows, no random frames left to do
    with ZarrStorage(mem, read_only=True) as store:
        assert len(store) == 75
        assert torch.equal(store[:50]["next", "achieved_goal"], before)  # appended after, not over
        runs = store["run"][:75]
        assert runs[:50].unique().numel() == 1 and (runs[50:] > runs[0]).all()
        assert "prior_goals" not in store[:1].keys()  # recalled at sampling time, never stored
    third = run_recipe(tmp_path, "memory.path=mem.zarr", "memory.resume_agent=true",
                       "collector.total_frames=25", "memory.recall.enabled=true", out="run3")
    assert "agent resumed from checkpoint" in third["stdout"]
    assert third["memory_rows_before"] == 75


def test_a_memory_that_fills_and_wraps_trains_on(tmp_path):
    """Found by a review: once the memory was full, the first HER sample after an extend raised (TorchRL
    0.14.1's HERReplayBuffer; the recipe now builds PersistentHERReplayBuffer, docs/her.md)."""
    s = run_recipe(tmp_path, "collector.total_frames=100", "logger.eval_iter=100", "replay_buffer.size=60",
                   f"memory.path={tmp_path / 'mem.zarr'}")
    assert s["frames"] == 100 and s["memory_rows_after"] == 60 and s["updates"] > 0


def test_lazy_tensor_storage_through_the_config(tmp_path):
    s = run_recipe(
        tmp_path, "replay_buffer.storage._target_=torchrl.data.LazyTensorStorage",
        f"memory.path={tmp_path / 'never.zarr'}",
    )
    assert s["memory_rows_after"] == 50
    assert not (tmp_path / "never.zarr").exists()


@pytest.mark.parametrize("group", sorted(ENV_GROUPS))
def test_every_env_group_composes(group):
    from hydra import compose, initialize_config_dir

    from torchrl_robotmem.envs import env_family

    with initialize_config_dir(str(RECIPE_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[f"env={group}"])
    assert cfg.env.name == ENV_GROUPS[group]
    env_family(cfg.env.name)  # a supported id
    assert cfg.collector.frames_per_batch % cfg.env.max_episode_steps == 0
    assert cfg.replay_buffer.storage._target_ == "torchrl_robotmem.ZarrStorage"


def test_compare_plot_stops_at_max_frames(tmp_path):
    """--max-frames: the plot of runs longer than a budget ends at the budget."""
    from recipes.her.tools import compare

    runs = {"long": [{"curve": [[0, 0.0], [100, 0.5], [200, 0.9]], "running": False}]}
    assert compare.plot(runs, str(tmp_path / "a.png"), "", 0.5)[1] > 200
    assert compare.plot(runs, str(tmp_path / "b.png"), "", 0.5, max_frames=100)[1] == pytest.approx(102)
    assert (tmp_path / "b.png").stat().st_size > 0


def test_compare_reads_a_run_in_progress_from_its_logs(tmp_path):
    """A stopped or running run (no summary.json): its curve and CPU-s come from every CSV its resumes logged."""
    import os
    import time

    from recipes.her.tools import compare

    run = tmp_path / "slide-s0"
    for i, (evals, cpus) in enumerate(((["0,0.0", "5000,0.1"], ["0,1.5", "5000,400.0"]),
                                      (["5000,0.2", "10000,0.3"], ["5000,410.0", "10000,800.5"]))):
        scalars = run / "her_logging" / f"launch{i}" / "scalars"
        for group, name, lines in (("eval", "success_rate", evals), ("time", "cpu_s", cpus)):
            (scalars / group).mkdir(parents=True, exist_ok=True)
            path = scalars / group / f"{name}.csv"
            path.write_text("\n".join(lines) + "\n")
            os.utime(path, (time.time() + i, time.time() + i))  # the resumed launch's files are the later ones
    loaded = compare.load_run(str(run))
    assert loaded["curve"] == [[0, 0.0], [5000, 0.2], [10000, 0.3]] and loaded["running"]
    assert loaded["cpu_s"] == 800.5
    row = compare.table({"prior": [loaded]}, 0.25).splitlines()[2]
    assert row.endswith("| 10000 | 800 (partial) |")


def test_paired_compares_two_arms_goal_by_goal(tmp_path):
    from scipy.stats import binomtest

    from recipes.her.run_record import record_episodes
    from recipes.her.tools import paired

    runs = {}
    for arm, outcomes in (("a", {0: [1] * 8 + [0] * 2, 1: [1] * 6 + [0] * 4}), ("b", {0: [0] * 10, 1: [1] * 5 + [0] * 5})):
        for seed, success in outcomes.items():
            run_dir = tmp_path / f"{arm}{seed}"
            run_dir.mkdir()
            record_episodes(0, seed, [0] * 10, path=str(run_dir / "eval_episodes.jsonl"))
            record_episodes(500, seed, [1] * 10, path=str(run_dir / "eval_episodes.jsonl"))
            record_episodes(500, seed, success, path=str(run_dir / "eval_episodes.jsonl"))  # resumed: the later line
            runs[arm, seed] = str(run_dir)
    out = tmp_path / "paired.json"
    result = paired.main(["--frames", "500", "--out", str(out),
                          f"memory={runs['a', 0]},{runs['a', 1]}",
                          f"control={runs['b', 0]},{runs['b', 1]}"])
    assert result["pooled"]["a"] == 0.7 and result["pooled"]["b"] == 0.25 and result["pooled"]["n"] == 20
    assert (result["test"]["a_only"], result["test"]["b_only"]) == (9, 0)  # 8 on seed 0, 1 on seed 1
    assert result["test"]["p"] == pytest.approx(binomtest(9, 9, 0.5).pvalue)
    assert json.loads(out.read_text())["outcomes"]["memory"]["1"] == [1] * 6 + [0] * 4
    with pytest.raises(KeyError, match="no evaluation at 250 frames"):
        paired.main(["--frames", "250", f"a={runs['a', 0]}", f"b={runs['b', 0]}"])
    with pytest.raises(ValueError, match="no seed in both arms"):
        paired.main(["--frames", "500", f"a={runs['a', 0]}", f"b={runs['b', 1]}"])
    # an arm read at another evaluation: the same runs at 500 frames against their own first evaluation
    itself = paired.main(["--frames", "500", f"later={runs['a', 0]},{runs['a', 1]}",
                          f"first@0={runs['a', 0]},{runs['a', 1]}"])
    assert itself["pooled"]["b"] == 0.0 and (itself["test"]["a_only"], itself["test"]["b_only"]) == (14, 0)
    with pytest.raises(SystemExit):
        paired.main(["--frames", "500", f"a@x={runs['a', 0]}", f"b={runs['b', 0]}"])


def test_recall_from_another_memory_read_only(tmp_path):
    """memory.recall.memory=<path>: the envs recall the prior memory's successful goals, not the run's own."""
    from hydra import compose, initialize_config_dir

    from experiments.scripted.collect import collect
    from recipes.her.utils import make_task_env
    from torchrl_robotmem import ZarrStorage, recall

    prior = tmp_path / "scripted.zarr"
    collect("push", 4, str(prior), backend="gym")  # default parameters: successful episodes
    own = ZarrStorage(tmp_path / "own.zarr", 1000)  # empty: recall from it would find nothing
    with initialize_config_dir(str(RECIPE_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["env=push", "memory.recall.enabled=true", f"memory.recall.memory={prior}",
                                           "+memory.recall.success_only=true"])
    env = make_task_env(cfg, 1, seed=0, memory=own)
    try:
        td = env.reset()
        with ZarrStorage(prior, read_only=True) as store:
            want = recall(store, td["desired_goal"].reshape(3), k=5, success_only=True)
            assert want["distance"].numel() == 5 and (store[want["index"]]["next", "is_success"] > 0.5).all()
        assert td["prior_goals_mask"].all()
        assert torch.allclose(td["prior_goals"].reshape(5, 3), want["next", "achieved_goal"])
        assert torch.allclose(td["prior_goals_dist"].reshape(5), want["distance"])
    finally:
        env.close()
        own.close()
    assert len(ZarrStorage(prior, read_only=True)) == 200  # read, never written


def test_critic_layer_norm_option(tmp_path):
    """network.critic_layer_norm=true puts a LayerNorm after each hidden layer of the critic only."""
    from hydra import compose, initialize_config_dir

    from recipes.her.utils import GoalNormalizer, make_agent, make_environment

    with initialize_config_dir(str(RECIPE_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["network.hidden_sizes=[16,8]", "network.critic_layer_norm=true",
                                           f"memory.path={tmp_path / 'm.zarr'}"])
    train_env, eval_env = make_environment(cfg)
    try:
        (actor, critic), _ = make_agent(cfg, train_env, GoalNormalizer())
        norms = [m.normalized_shape for m in critic.modules() if isinstance(m, torch.nn.LayerNorm)]
        assert norms == [(16,), (8,)]
        assert not any(isinstance(m, torch.nn.LayerNorm) for m in actor.modules())
        td = train_env.reset()
        assert critic(actor(td))["state_action_value"].shape[-1] == 1
    finally:
        train_env.close()
        eval_env.close()


def test_a_killed_run_resumes_from_its_last_evaluation(tmp_path):
    """collector.resume=true: SIGKILL mid-run, launch again, the run ends where an unbroken one would."""
    import signal
    import time

    from torchrl.checkpoint import Checkpoint

    from torchrl_robotmem import ZarrStorage

    mem, agent = tmp_path / "mem.zarr", tmp_path / "mem.zarr-agent"
    args = [sys.executable, str(RECIPE_DIR / "train.py"), *TINY, f"memory.path={mem}", "collector.total_frames=150",
            "collector.resume=true", f"hydra.run.dir={tmp_path / 'out'}"]
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    meta = {}
    while time.monotonic() < deadline and proc.poll() is None:
        if Checkpoint.is_checkpoint(agent):
            try:
                meta = Checkpoint.manifest(agent)["metadata"]
            except FileNotFoundError:  # caught between the two moves of a save: read it at the next poll
                continue
            if meta["frames"] >= 50:
                break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed: make it longer"
    assert not meta["finished"] and meta["frames"] >= 50 and [f for f, _ in meta["curve"]][:2] == [0, 50]
    with ZarrStorage(mem, read_only=True) as store:
        rows = len(store)
    assert rows >= meta["memory_rows"]

    done = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"run resumed at {rows} frames" in done.stdout
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    # the frames of the killed process count, the curve goes on, nothing is evaluated twice
    assert s["frames"] == 150 and s["memory_rows_after"] == 150 and s["memory_rows_before"] == 0
    frames = [f for f, _ in s["curve"]]
    assert frames[: len(meta["curve"])] == [f for f, _ in meta["curve"]] and frames[-1] == 150
    assert frames == sorted(set(frames)) and s["cpu_s"] > meta["cpu_s"] and s["updates"] > meta["updates"]
    assert Checkpoint.manifest(agent)["metadata"]["finished"]
    # launched again: nothing left to do, nothing added
    again = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "after 150 new env frames" in again.stdout
    with ZarrStorage(mem, read_only=True) as store:
        assert len(store) == 150
    # a memory with rows but no checkpoint is refused, not counted as this run's frames
    other = tmp_path / "other.zarr"
    run_recipe(tmp_path, f"memory.path={other}", out="other")
    import shutil

    shutil.rmtree(tmp_path / "other.zarr-agent")
    refused = subprocess.run([sys.executable, str(RECIPE_DIR / "train.py"), *TINY, f"memory.path={other}",
                              "collector.resume=true", f"hydra.run.dir={tmp_path / 'bad'}"],
                             cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert refused.returncode != 0 and "no agent checkpoint" in refused.stderr


def test_prior_ratio_schedule():
    from omegaconf import OmegaConf

    from recipes.her.prior_memory import prior_ratio

    cfg = OmegaConf.create({"prior": {"ratio": 0.5, "ratio_final": None, "anneal_frames": 0}})
    assert prior_ratio(cfg, 0) == prior_ratio(cfg, 10**6) == 0.5
    cfg.prior.ratio_final, cfg.prior.anneal_frames = 0.1, 1000
    assert [round(prior_ratio(cfg, f), 6) for f in (0, 500, 1000, 5000)] == [0.5, 0.3, 0.1, 0.1]


def test_prior_runs_queue_lists_resumable_commands(tmp_path, capsys):
    from experiments.her import prior_runs

    assert {"prior-push-s2", "scratch-push-s2", "pushprior-pnp-s0", "ownprior-pnp-s2", "scratch-pnp-s1"} <= set(prior_runs.RUNS)
    cmd = prior_runs.command("anneal-push-s1", str(tmp_path))
    assert "collector.resume=true" in cmd and "seed=1" in cmd and "prior.ratio_final=0.1" in cmd
    assert f"memory.path={tmp_path / 'anneal-push-s1.zarr'}" in cmd
    (tmp_path / "prior-push-s0").mkdir()
    (tmp_path / "prior-push-s0" / "summary.json").write_text(json.dumps({"frames": 60000, "curve": [[0, 0.1], [60000, 0.8]], "cpu_s": 10}))
    prior_runs.main(["--root", str(tmp_path), "--list", "--only", "prior-push-s0,scratch-pnp-s0"])
    out = capsys.readouterr().out
    assert "finished: 60000 frames, final 0.80" in out and "scratch-pnp-s0         not started" in out
    with pytest.raises(SystemExit):
        prior_runs.main(["--root", str(tmp_path), "--only", "nope"])


def test_clone_sensitivity_reports_success_against_weight_noise(tmp_path):
    """experiments.her.clone_sensitivity: clones a scripted memory, perturbs the weights, evaluates, plots."""
    from experiments.her.clone_sensitivity import main, sensitivity
    from experiments.scripted.collect import main as collect

    prior = tmp_path / "scripted-push.zarr"
    collect([f"path={prior}", "env=push", "episodes=2", "backend=gym", "seed=0", "noise=0"])
    rows = sensitivity(str(prior), [0.0, 0.5], steps=20, episodes=2)
    assert [r["sigma"] for r in rows] == [0.0, 0.5]
    assert rows[0]["mean_abs_action_change"] == 0.0 < rows[1]["mean_abs_action_change"]
    assert all(0.0 <= r["success"] <= 1.0 for r in rows)
    jsonl = tmp_path / "rows.jsonl"
    jsonl.write_text("\n".join(json.dumps(r) for r in rows))
    main(["unused", "--replot", str(jsonl), "--plot", str(tmp_path / "s.png")])
    assert (tmp_path / "s.png").stat().st_size > 0


_KILL_MID_SAVE = """
import os, signal, sys
import torch
from torchrl.checkpoint import Checkpoint

path = sys.argv[1]
net = torch.nn.Linear(3, 2)
torch.nn.init.constant_(net.weight, 1.0)
Checkpoint(net=net).save(path, metadata={"version": 1})
torch.nn.init.constant_(net.weight, 2.0)
real_replace = os.replace

def replace_then_die(src, dst):
    real_replace(src, dst)
    os.kill(os.getpid(), signal.SIGKILL)  # after the old checkpoint moved aside, before the new one moved in

os.replace = replace_then_die
Checkpoint(net=net).save(path, metadata={"version": 2})
"""


def test_an_agent_checkpoint_a_kill_caught_mid_save_is_put_back(tmp_path):
    """A process SIGKILLed between the two moves of ``Checkpoint.save`` leaves only the backup: it is restored."""
    from torchrl.checkpoint import Checkpoint

    from recipes.her.run_record import recover_checkpoint

    agent = tmp_path / "mem.zarr-agent"
    proc = subprocess.run([sys.executable, "-c", _KILL_MID_SAVE, str(agent)], capture_output=True, text=True)
    assert proc.returncode == -9, proc.stderr[-2000:]
    assert not agent.exists(), "the kill was meant to land between the two moves of the save"
    backup = recover_checkpoint(str(agent))
    assert backup is not None and Path(backup).name.startswith(".mem.zarr-agent.backup-")
    assert Checkpoint.manifest(agent)["metadata"] == {"version": 1}
    net = torch.nn.Linear(3, 2)
    Checkpoint(net=net).load(agent)
    assert bool((net.weight == 1.0).all())
    assert recover_checkpoint(str(agent)) is None  # a checkpoint in place is left alone


@pytest.mark.full  # a second test of what the default tier covers (make test stays under 15 minutes)
def test_the_same_seed_gives_the_same_run(tmp_path):
    """Two runs of one command (a prior memory, pretraining, HER, evaluation) end bit-identical: every
    tensor of the agent checkpoint, every logged loss, every evaluation episode."""
    from experiments.scripted.collect import main as collect
    from recipes.her.run_record import read_episodes

    prior = tmp_path / "prior.zarr"
    collect([f"path={prior}", "env=push", "episodes=2", "backend=gym", "seed=0"])
    args = ["env=push", "seed=3", "prior=mix", f"prior.paths=[{prior}]", "logger.eval_episodes=2"]
    runs = [run_recipe(tmp_path, *args, f"memory.path={tmp_path / f'{n}.zarr'}", out=n) for n in ("a", "b")]
    assert runs[0]["curve"] == runs[1]["curve"] and runs[0]["updates"] == runs[1]["updates"] > 0

    def tensors(name):
        root = tmp_path / f"{name}.zarr-agent"
        return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*.memmap"))}

    a, b = tensors("a"), tensors("b")
    assert a and a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []

    def losses(name):
        scalars = next((tmp_path / name / "her_logging").glob("*/scalars/train"))
        return {p.name: p.read_text() for p in sorted(scalars.glob("loss_*.csv"))}

    assert losses("a") and losses("a") == losses("b")
    assert read_episodes(str(tmp_path / "a")) == read_episodes(str(tmp_path / "b"))
