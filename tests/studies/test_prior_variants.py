"""The prior-memory variants of recipes/her (experiments/prior_variants): their loss terms on real FetchPush
losses and a real scripted memory, and ``python -m experiments.prior_variants.train`` as a subprocess with a
budget of a few dozen frames (tests/training/test_her_recipe.py's TINY)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from training.test_her_recipe import TINY

# the prior-memory variants are experiments (experiments/prior_variants): their tests run in the full tier
pytestmark = pytest.mark.full

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))
VARIANTS_DIR = ROOT / "experiments" / "prior_variants"  # variants.yaml: recipes/her's config and the variants' keys
VARIANTS = [sys.executable, "-m", "experiments.prior_variants.train"]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}


def variants(tmp_path: Path, *overrides: str, out: str = "out") -> subprocess.CompletedProcess:
    """``python -m experiments.prior_variants.train`` with TINY and ``overrides``, launched in ``tmp_path``."""
    return subprocess.run([*VARIANTS, *TINY, *overrides, f"hydra.run.dir={tmp_path / out}"],
                          cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300)


def run_variants(tmp_path: Path, *overrides: str, out: str = "out") -> dict:
    """:func:`variants`, which must succeed; its summary, with its stdout under ``"stdout"``."""
    proc = variants(tmp_path, *overrides, out=out)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((tmp_path / out / "summary.json").read_text())
    summary["stdout"] = proc.stdout
    return summary


def test_actor_lr_option(tmp_path):
    """prior.actor_lr sets the actor's learning rate only; null leaves it at optim.lr."""
    from hydra import compose, initialize_config_dir

    from recipes.her.utils import GoalNormalizer, make_agent, make_environment, make_loss_module, make_optimizer

    for algo, actor_lr, expected in (("td3", "1e-5", 1e-5), ("sac", "null", 1e-3)):
        with initialize_config_dir(str(VARIANTS_DIR), version_base="1.3"):
            cfg = compose("variants", overrides=[f"algo={algo}", "network.hidden_sizes=[8]", f"prior.actor_lr={actor_lr}",
                                               f"memory.path={tmp_path / 'm.zarr'}"])
        train_env, eval_env = make_environment(cfg)
        try:
            model, _ = make_agent(cfg, train_env, GoalNormalizer())
            loss = make_loss_module(cfg, model)[0]
            optimizer = make_optimizer(cfg, loss, actor_lr=cfg.prior.actor_lr)
            actor_params = {id(p) for p in loss.actor_network_params.flatten_keys().values()}
            for group in optimizer.param_groups:
                is_actor = all(id(p) in actor_params for p in group["params"])
                assert group["lr"] == (expected if is_actor else 1e-3), (algo, is_actor, group["lr"])
        finally:
            train_env.close()
            eval_env.close()


def _saved_normalizer(agent: Path, overrides: list[str]):
    """The GoalNormalizer saved in a run's agent checkpoint."""
    from hydra import compose, initialize_config_dir
    from torchrl.checkpoint import Checkpoint

    from recipes.her.utils import GoalNormalizer, make_agent, make_environment, make_loss_module, make_optimizer

    with initialize_config_dir(str(VARIANTS_DIR), version_base="1.3"):
        cfg = compose("variants", overrides=overrides)
    train_env, eval_env = make_environment(cfg)
    try:
        normalizer = GoalNormalizer()
        loss = make_loss_module(cfg, make_agent(cfg, train_env, normalizer)[0])[0]
        Checkpoint(loss_module=loss, optimizer=make_optimizer(cfg, loss), normalizer=normalizer).load(str(agent))
    finally:
        train_env.close()
        eval_env.close()
    return normalizer


@pytest.mark.full
def test_prior_memory_is_sampled_beside_the_runs_own(tmp_path):
    """prior.paths: a scripted FetchPush memory, read-only, half of every batch (issue 9)."""
    from experiments.scripted.collect import main as collect
    from torchrl_robotmem import ZarrStorage

    prior = tmp_path / "scripted-push.zarr"
    collect([f"path={prior}", "env=push", "episodes=2", "backend=gym", "seed=0"])
    n_prior = len(ZarrStorage(prior, read_only=True))
    assert n_prior == 100
    s = run_variants(tmp_path, "env=pick_and_place", f"memory.path={tmp_path / 'own.zarr'}",
                   "prior=bc", f"prior.paths=[{prior}]", "prior.ratio=0.5",
                   "prior.ratio_final=0.1", "prior.anneal_frames=50", "prior.bc=0.4",
                   "prior.clone_steps=5", "prior.bc_original_goals=true",
                   "prior.actor_freeze_frames=25", "prior.freeze_normalizer=true")
    assert s["memory_rows_after"] == 50 and s["updates"] > 0
    # prior.freeze_normalizer: the statistics are the prior's alone (the 50 own rows would make 150)
    normalizer = _saved_normalizer(tmp_path / "own.zarr-agent", ["env=pick_and_place", "network.hidden_sizes=[16,16]"])
    assert normalizer.stats["observation"][0].item() == n_prior
    assert normalizer.stats["goal"][0].item() == 2 * n_prior
    assert "cloned the prior's actions into the actor: 5 steps" in s["stdout"]  # prior.clone_steps
    for name in ("loss_bc", "bc_kept"):  # prior.bc: the Q-filtered cloning term is trained and logged
        logged = next((tmp_path / "out" / "her_logging").glob(f"*/scalars/train/{name}.csv")).read_text()
        rows = [line.split(",") for line in logged.splitlines() if line[:1].isdigit()]
        # prior.actor_freeze_frames=25: the first 25 frames train the critics only, so the term is
        # logged for the second batch alone (its mean is over actor updates, not diluted by zeros)
        assert [int(float(r[0])) for r in rows] == [50] and all(float(r[1]) >= 0 for r in rows)
    logged = next((tmp_path / "out" / "her_logging").glob("*/scalars/train/prior_ratio.csv")).read_text()
    ratios = [round(float(line.split(",")[1]), 6) for line in logged.splitlines() if line[:1].isdigit()]
    assert ratios == [0.3, 0.1]  # annealed from 0.5: after 25 and 50 of 50 frames
    # experiments.her.failures replays the run's evaluation from its saved agent and sorts the failures
    from experiments.her.failures import failures

    f = failures(str(tmp_path / "own.zarr-agent"),
                 ["env=pick_and_place", "network.hidden_sizes=[16,16]", "logger.eval_episodes=3"])
    assert f["episodes"] == 3 and f["untouched"] + f["near_miss"] + f["far"] == round(3 * (1 - f["success"]))
    assert f["goals_on_table"] + f["goals_in_air"] == 3  # the split by goal height covers every episode
    # the prior memory is only read
    assert len(ZarrStorage(prior, read_only=True)) == n_prior
    # a prior written for another observation layout is refused with the reason
    reach = tmp_path / "reach.zarr"
    run_variants(tmp_path, f"memory.path={reach}", out="reach")
    proc = subprocess.run(
        [*VARIANTS, *TINY, "env=push", f"memory.path={tmp_path / 'p.zarr'}",
         "prior=mix", f"prior.paths=[{reach}]", f"hydra.run.dir={tmp_path / 'bad'}"],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode != 0 and "observation layout" in proc.stderr
    # cloning prior actions without a prior memory is refused
    proc = subprocess.run(
        [*VARIANTS, *TINY, "env=push", f"memory.path={tmp_path / 'q.zarr'}",
         "prior.bc=0.4", f"hydra.run.dir={tmp_path / 'bad2'}"],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode != 0 and "set prior.paths=" in proc.stderr
    proc = subprocess.run(
        [*VARIANTS, *TINY, "env=push", f"memory.path={tmp_path / 'r.zarr'}",
         "prior.clone_steps=10", f"hydra.run.dir={tmp_path / 'bad3'}"],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode != 0 and "clone_steps" in proc.stderr and "set prior.paths=" in proc.stderr
    # recipes.her.tools.compare: the two finished runs in one plot and one table
    from recipes.her.tools import compare

    png = tmp_path / "cmp.png"
    md = compare.main(["--out", str(png), "--target", "0.5", "--archive", str(tmp_path / "runs"),
                       f"prior={tmp_path / 'out'}", f"reach={tmp_path / 'reach'}"])
    rows = md.splitlines()
    assert rows[0] == "| run | 0k | 0.05k | first >= 0.5 | CPU-s |"
    assert rows[2].startswith("| prior, out | ") and rows[3].startswith("| reach, reach | ") and len(rows) == 4
    assert f"| {s['cpu_s']:.0f} |" in rows[2] and png.stat().st_size > 0
    # --archive keeps each run's curve as a small json that stands in for the (big, local) run directory
    again = compare.main(["--out", str(png), "--target", "0.5", f"prior={tmp_path / 'runs' / 'out.json'}",
                          f"reach={tmp_path / 'runs' / 'reach.json'}"])
    assert again == md
    with pytest.raises(FileNotFoundError, match="not a recipes/her run"):
        compare.load_run(str(tmp_path / "bad" / "nothing"))


def test_clone_anchor_weight_schedule():
    """prior.clone_anchor_final: geometric from clone_anchor, so the trust region widens by a constant factor."""
    from omegaconf import OmegaConf

    from experiments.prior_variants import clone_anchor_weight

    cfg = OmegaConf.create({"prior": {"clone_anchor": 100.0}})
    assert clone_anchor_weight(cfg, 0) == clone_anchor_weight(cfg, 10**6) == 100.0
    cfg.prior.clone_anchor_final, cfg.prior.clone_anchor_anneal_frames = 1.0, 1000
    assert [round(clone_anchor_weight(cfg, f), 6) for f in (0, 500, 1000, 5000)] == [100.0, 10.0, 1.0, 1.0]
    cfg.prior.clone_anchor_final = 0.0
    with pytest.raises(ValueError, match="clone_anchor_final must be > 0"):
        clone_anchor_weight(cfg, 0)


def _push_loss_and_scripted_batch(tmp_path: Path, algo: str):
    """A fresh FetchPush loss module of ``algo`` (32x32 networks) and 64 rows of a 2-episode scripted memory."""
    from hydra import compose, initialize_config_dir

    from experiments.scripted.collect import main as collect
    from recipes.her import utils
    from torchrl_robotmem import ZarrStorage

    torch.manual_seed(0)
    prior = tmp_path / "scripted-push.zarr"
    collect([f"path={prior}", "env=push", "episodes=2", "backend=gym", "seed=0"])
    with initialize_config_dir(config_dir=str(VARIANTS_DIR), version_base="1.3"):
        cfg = compose("variants", overrides=["env=push", f"algo={algo}", "network.hidden_sizes=[32,32]"])
    train_env, eval_env = utils.make_environment(cfg)
    model, _ = utils.make_agent(cfg, train_env, utils.GoalNormalizer())
    loss = utils.make_loss_module(cfg, model)[0]
    train_env.close()
    eval_env.close()
    return loss, ZarrStorage(prior, read_only=True)[:64]


@pytest.mark.parametrize("algo", ["sac", "td3", "ddpg"])
def test_prior_bc_clones_the_prior_actions_where_the_critics_prefer_them(tmp_path, algo):
    """prior.bc (experiments/prior_variants/bc.py): the Q-filtered behaviour-cloning term, on a real scripted memory and real losses."""
    from experiments.prior_variants import PriorBC
    from recipes.her.prior_memory import PRIOR_KEY

    loss, batch = _push_loss_and_scripted_batch(tmp_path, algo)
    batch.set(PRIOR_KEY, torch.ones(64, dtype=torch.bool))
    demo = batch["action"]

    with pytest.raises(ValueError, match="prior.bc must be >= 0"):
        PriorBC(loss, weight=-1.0)
    # no prior rows in the batch: nothing to imitate
    own = batch.clone()
    own.set(PRIOR_KEY, torch.zeros(64, dtype=torch.bool))
    assert PriorBC(loss, weight=1.0)(own)["loss_bc"].item() == 0.0
    # the Q filter keeps a subset of the rows, and only those count
    full, filtered = PriorBC(loss, weight=1.0, q_filter=False)(batch), PriorBC(loss, weight=1.0)(batch)
    assert full["bc_kept"].item() == 1.0 and 0.0 <= filtered["bc_kept"].item() <= 1.0
    assert filtered["loss_bc"].item() <= full["loss_bc"].item() + 1e-6
    # minimising the unfiltered term moves the deterministic actor onto the stored actions
    actor = loss.actor_network
    params = list(loss.actor_network_params.flatten_keys().values())
    opt = torch.optim.Adam(params, lr=3e-3)
    bc = PriorBC(loss, weight=1.0, q_filter=False)

    def actor_error() -> float:
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC), \
                loss.actor_network_params.to_module(actor):
            return (actor(batch.select(*actor.in_keys).clone())["action"] - demo).pow(2).mean().item()

    before = actor_error()
    for _ in range(300):
        opt.zero_grad()
        bc(batch)["loss_bc"].backward()
        opt.step()
    assert actor_error() < 0.5 * before


@pytest.mark.parametrize("algo", ["sac", pytest.param("td3", marks=pytest.mark.full)])
def test_crr_actor_loss_regresses_onto_the_better_stored_actions(tmp_path, algo):
    """prior.actor_update=crr (experiments.prior_variants.CRRActorLoss): the actor's loss has no critic gradient, only filtered regression."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from experiments.prior_variants import CRRActorLoss

    loss, batch = _push_loss_and_scripted_batch(tmp_path, algo)
    crr = CRRActorLoss(loss)
    out = crr(batch)
    assert 0.0 < out["crr_kept"].item() < 1.0 and out["loss_actor"].item() > 0
    # the actor's own actions are never "better than the actor's": nothing is kept, the loss is 0
    actor = loss.actor_network
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC), loss.actor_network_params.to_module(actor):
        own = batch.clone().set("action", actor(batch.select(*actor.in_keys).clone())["action"])
    nothing = crr(own)
    assert nothing["crr_kept"].item() == 0.0 and nothing["loss_actor"].item() == 0.0
    # the gradient reaches the actor only: the critics' action gradient plays no part
    out["loss_actor"].backward()
    critic = loss.qvalue_network_params
    assert all(p.grad is None for p in critic.values(True, True))
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.actor_network_params.values(True, True))
    # in the train entry: runs, logs the kept share; an unknown value is refused with the choices
    s = run_variants(tmp_path, f"algo={algo}", "prior.actor_update=crr", f"memory.path={tmp_path / 'mem.zarr'}")
    assert s["updates"] > 0
    kept = next((tmp_path / "out" / "her_logging").glob("*/scalars/train/crr_kept.csv")).read_text().splitlines()
    values = [float(line.split(",")[1]) for line in kept if line[:1].isdigit()]
    assert len(values) == 2 and all(0.0 <= v <= 1.0 for v in values)  # after 25 and 50 frames
    proc = subprocess.run(
        [*VARIANTS, *TINY, "prior.actor_update=dpg",
         f"memory.path={tmp_path / 'bad.zarr'}", f"hydra.run.dir={tmp_path / 'bad'}"],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode != 0 and "prior.actor_update must be q_gradient or crr" in proc.stderr


@pytest.mark.full
def test_clone_anchor_keeps_the_actor_near_the_clone(tmp_path):
    """prior.clone_anchor (experiments.prior_variants.CloneAnchor): a trust region around the cloned actor's own outputs."""
    from experiments.prior_variants import CloneAnchor

    loss, batch = _push_loss_and_scripted_batch(tmp_path, "td3")
    with pytest.raises(ValueError, match="clone_anchor must be > 0"):
        CloneAnchor(loss, weight=0.0)
    params = list(loss.actor_network_params.values(True, True))
    clone = [p.detach().clone() for p in params]
    anchor = CloneAnchor(loss, weight=100.0)
    anchor.reset()
    out = anchor(batch)
    assert out["loss_anchor"].item() == 0.0 and out["anchor_shift"].item() == 0.0  # at the clone itself
    assert not [n for n, _ in anchor.named_parameters()]  # the frozen copy is not trained by anyone

    def shift_after_actor_updates(with_anchor: bool) -> float:
        """100 Adam steps of TD3's own actor loss (the critics' action gradient), from the clone."""
        with torch.no_grad():
            for p, c in zip(params, clone):
                p.copy_(c)
        opt = torch.optim.Adam(params, lr=1e-3)
        for _ in range(100):
            opt.zero_grad()
            total = loss(batch)["loss_actor"]
            if with_anchor:
                total = total + anchor(batch)["loss_anchor"]
            total.backward()
            opt.step()
        return anchor(batch)["anchor_shift"].item()

    free, anchored = shift_after_actor_updates(False), shift_after_actor_updates(True)
    assert free > 0.05 and anchored < free / 3, (free, anchored)
    # in the train entry: needs the clone, logs the shift, and the copy is saved with the agent
    prior = tmp_path / "scripted-push.zarr"
    s = run_variants(tmp_path, "env=push", "algo=td3", f"memory.path={tmp_path / 'mem.zarr'}", "prior=mix", f"prior.paths=[{prior}]",
                   "prior.clone_steps=5", "prior.clone_anchor=10", "prior.freeze_normalizer=true",
                   "prior.clone_anchor_final=0.1", "prior.clone_anchor_anneal_frames=50")
    assert s["updates"] > 0
    logged = next((tmp_path / "out" / "her_logging").glob("*/scalars/train/anchor_shift.csv")).read_text()
    shifts = [float(line.split(",")[1]) for line in logged.splitlines() if line[:1].isdigit()]
    assert len(shifts) == 2 and all(v >= 0 for v in shifts)
    logged = next((tmp_path / "out" / "her_logging").glob("*/scalars/train/anchor_weight.csv")).read_text()
    weights = [round(float(line.split(",")[1]), 6) for line in logged.splitlines() if line[:1].isdigit()]
    assert weights == [1.0, 0.1]  # prior.clone_anchor_final: 10 -> 0.1 geometric, after 25 and 50 of 50 frames
    assert any(p.name.endswith("clone_anchor") for p in (tmp_path / "mem.zarr-agent" / "components").iterdir())
    proc = subprocess.run(
        [*VARIANTS, *TINY, "prior.clone_anchor=10",
         f"memory.path={tmp_path / 'bad.zarr'}", f"hydra.run.dir={tmp_path / 'bad'}"],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode != 0 and "set prior.clone_steps=N" in proc.stderr


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_pretrain_actor_clones_the_successful_prior_episodes(tmp_path, algo):
    """prior.clone_steps (experiments.prior_variants.pretrain_actor): the actor imitates the scripted memory before any RL update."""
    from hydra import compose, initialize_config_dir
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from experiments.prior_variants import pretrain_actor
    from experiments.scripted.collect import main as collect
    from recipes.her import utils
    from torchrl_robotmem import ZarrStorage

    torch.manual_seed(0)
    prior = tmp_path / "scripted-push.zarr"
    collect([f"path={prior}", "env=push", "episodes=2", "backend=gym", "seed=0", "noise=0"])
    storage = ZarrStorage(prior, read_only=True)
    rows = storage[: len(storage)]
    assert rows["episode_success"].max() == 1.0  # the default-parameter controller succeeds
    with initialize_config_dir(config_dir=str(VARIANTS_DIR), version_base="1.3"):
        cfg = compose("variants", overrides=["env=push", f"algo={algo}", "network.hidden_sizes=[32,32]"])
    train_env, eval_env = utils.make_environment(cfg)
    normalizer = utils.GoalNormalizer()
    normalizer.update(rows)
    model, _ = utils.make_agent(cfg, train_env, normalizer)
    loss = utils.make_loss_module(cfg, model)[0]
    train_env.close()
    eval_env.close()
    ok = rows[rows["episode_success"] > 0.5]
    actor = loss.actor_network

    def actor_error() -> float:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            return (model[0](ok.select(*actor.in_keys).clone())["action"] - ok["action"].clamp(-1, 1)).pow(2).mean().item()

    before = actor_error()
    mse = pretrain_actor(loss, [storage], steps=300, batch_size=64, lr=3e-3)
    # the policy the collector runs (model[0]) is the one that moved: its parameters are the loss module's
    assert actor_error() < 0.3 * before and mse < 0.3 * before
    # no gradient is left behind for the run's own optimiser to step on
    assert all(p.grad is None for p in loss.actor_network_params.values(True, True))
    # the prior's episodes must hold what the actor reads
    bare = ZarrStorage(tmp_path / "bare.zarr", max_size=10)
    bare.set(range(4), rows[:4].exclude("desired_goal"))
    with pytest.raises(KeyError, match="desired_goal"):  # also what prior.bc_original_goals reads
        pretrain_actor(loss, [bare], steps=1)




def test_the_rows_cloned_from_a_float64_prior_are_cast_too(tmp_path):
    """prior.clone_steps on a raw-gym (float64) memory: the rows cloned into the actor (load_demos) are cast as
    the batches' are, and pretraining after the clone is critic-only."""
    from training.test_her_priors_and_pretraining import raw_gym_rows, write_memory

    prior = write_memory(tmp_path / "raw-gym.zarr", raw_gym_rows())
    s = run_variants(tmp_path, f"memory.path={tmp_path / 'own.zarr'}", "prior=mix", f"prior.paths=[{prior}]",
                     "prior.clone_steps=3")
    assert s["frames"] == 50 and s["updates"] > 0
    assert "cloned the prior's actions into the actor: 3 steps" in s["stdout"]
    assert any("cast to torch.float32" in line for line in s["stdout"].splitlines())


def test_without_a_variant_it_is_the_recipes_run(tmp_path):
    """The same overrides, no variant: experiments.prior_variants.train and recipes/her/train.py make the same run
    (same evaluations, updates and logged losses), so a prior=mix or no-prior run of prior_runs is the recipe's."""
    from training.test_her_recipe import run_recipe

    args = ["algo=td3", "seed=3", "logger.eval_iter=25"]
    ours = run_variants(tmp_path, *args, f"memory.path={tmp_path / 'v.zarr'}", out="v")
    recipe = run_recipe(tmp_path, *args, f"memory.path={tmp_path / 'r.zarr'}", out="r")
    assert ours["curve"] == recipe["curve"] and ours["updates"] == recipe["updates"] > 0

    def logged(out: str, name: str) -> list[str]:
        text = next((tmp_path / out / "her_logging").glob(f"*/scalars/train/{name}.csv")).read_text()
        return [line for line in text.splitlines() if line[:1].isdigit()]

    for name in ("loss_actor", "loss_qvalue"):
        assert logged("v", name) == logged("r", name) != []
