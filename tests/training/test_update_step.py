"""The recipe's update step and collection at hardware speed (issue 26): ``recipes/her/update.py``, parallel envs.

The CUDA-graph path runs in tests/test_cuda.py (where a GPU is); the compiled path on the CPU is checked here
with ``torch.compile(backend="aot_eager")`` (traced, not code-generated: the same graph capture and guards,
without minutes of C++ compilation on a 2-core machine).
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage

from torchrl_robotmem import ZarrStorage
from training.test_her_recipe import RECIPE_DIR, TINY, run_recipe

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

from recipes.her import utils  # noqa: E402
from recipes.her.update import LossTerms, Updater, compile_settings, draw_batches  # noqa: E402


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(RECIPE_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=["network.hidden_sizes=[16,16]", "optim.batch_size=16",
                                                        *overrides])


def _agent(cfg, env, data, seed: int = 0, compiled: bool = False):
    """The recipe's agent, loss, optimiser and update terms, built from ``seed``."""
    torch.manual_seed(seed)
    normalizer = utils.GoalNormalizer()
    normalizer.update(data)
    model, _ = utils.make_agent(cfg, env, normalizer)
    loss, target = utils.make_loss_module(cfg, model, compiled=compiled)
    optimizer = utils.make_optimizer(cfg, loss)
    return loss, LossTerms(loss, utils.loss_keys(cfg)), optimizer, target


@pytest.fixture(scope="module")
def reach_rows():
    env = utils.make_task_env(_cfg(), 1, seed=0)
    rows = env.rollout(200, break_when_any_done=False).reshape(-1)
    return env, rows


def _params(loss) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in loss.state_dict().items() if isinstance(v, torch.Tensor)}


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_updater_eager_is_the_recipe_update(reach_rows, algo):
    """Updater's eager step is the loop it replaced, written out: same losses, same parameters after 6 steps."""
    env, rows = reach_rows
    cfg = _cfg(f"algo={algo}")
    rb = utils.make_replay_buffer(cfg, LazyTensorStorage(1000))
    rb.extend(rows)
    batches = [rb.sample() for _ in range(6)]
    loss_a, terms_a, opt_a, target_a = _agent(cfg, env, rows)
    loss_b, terms_b, opt_b, target_b = _agent(cfg, env, rows)
    delay = cfg.algo.policy_update_delay if algo == "td3" else 1
    updater = Updater(terms_b, opt_b, target_b, policy_delay=delay)
    for i, batch in enumerate(batches):
        train_actor = i % delay == 0
        torch.manual_seed(100 + i)
        want = terms_a.loss(batch.clone(), train_actor)
        terms_a.total(want, train_actor).backward()
        opt_a.step()
        opt_a.zero_grad(set_to_none=True)
        if train_actor:
            target_a.step()
        torch.manual_seed(100 + i)
        got = updater(batch.clone())
        for key in utils.loss_keys(cfg):
            torch.testing.assert_close(got[key], want[key].detach())
    assert updater.num_updates == 6
    a, b = _params(loss_a), _params(loss_b)
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], msg=key)


def test_td3_delay_moves_actor_and_targets_every_other_step(reach_rows):
    env, rows = reach_rows
    cfg = _cfg("algo=td3")
    rb = utils.make_replay_buffer(cfg, LazyTensorStorage(1000))
    rb.extend(rows)
    loss, terms, optimizer, target = _agent(cfg, env, rows)
    updater = Updater(terms, optimizer, target, policy_delay=2)
    for i in range(4):
        before = _params(loss)
        updater(rb.sample())
        after = _params(loss)
        moved = {k for k in before if not torch.equal(before[k], after[k])}
        actor_moved = any(k.startswith("actor_network_params") for k in moved)
        targets_moved = any(k.startswith("target_") for k in moved)
        critic_moved = any(k.startswith("qvalue_network_params") for k in moved)
        assert critic_moved, i
        assert actor_moved == (i % 2 == 0) and targets_moved == (i % 2 == 0), (i, sorted(moved)[:4])
    # critic-only steps (pretraining after a clone) move the targets, never the actor
    before = _params(loss)
    updater(rb.sample(), critic_only=True)
    after = _params(loss)
    assert not any(not torch.equal(before[k], after[k]) for k in before if k.startswith("actor_network_params"))
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("target_"))


@pytest.mark.full  # a second path of the update the eager tests cover (torch.compile: ~45 s of CPU)
def test_compiled_update_matches_eager(reach_rows):
    """torch.compile'd steps (aot_eager: dynamo's capture, AOTAutograd) give the eager losses and parameters."""
    env, rows = reach_rows
    cfg = _cfg()
    rb = utils.make_replay_buffer(cfg, LazyTensorStorage(1000))
    rb.extend(rows)
    batches = [rb.sample() for _ in range(4)]
    eager = _agent(cfg, env, rows, compiled=True)  # vmap over the critics in both: the same arithmetic
    compiled = _agent(cfg, env, rows, compiled=True)
    run_eager = Updater(*eager[1:])
    run_compiled = Updater(*compiled[1:], compile=True, compile_backend="aot_eager", warmup=1)
    for i, batch in enumerate(batches):
        torch.manual_seed(7 + i)
        want = run_eager(batch.clone())
        torch.manual_seed(7 + i)
        got = run_compiled(batch.clone())
        for key in utils.loss_keys(cfg):
            torch.testing.assert_close(got[key], want[key], rtol=1e-4, atol=1e-5, msg=f"update {i}: {key}")
    a, b = _params(eager[0]), _params(compiled[0])
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-4, atol=1e-5, msg=key)


def test_compile_settings_and_refusals():
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert compile_settings(_cfg(), cpu)["compile"] is False and compile_settings(_cfg(), cpu)["cudagraphs"] is False
    on_gpu = compile_settings(_cfg(), cuda)
    assert on_gpu["compile"] and on_gpu["cudagraphs"] and on_gpu["mode"] == "default"
    assert compile_settings(_cfg("compile.compile=true"), cpu)["mode"] == "default"
    with pytest.raises(ValueError, match="compile.cudagraphs=true needs a CUDA device"):
        compile_settings(_cfg("compile.cudagraphs=true"), cpu)
    with pytest.raises(ValueError, match="compile.compile must be true, false or auto"):
        compile_settings(_cfg("compile.compile=sometimes"), cpu)
    opt = torch.optim.Adam([torch.nn.Parameter(torch.zeros(2))])
    with pytest.raises(ValueError, match="capturable=True"):
        Updater(None, opt, None, cudagraphs=True)
    with pytest.raises(ValueError, match="policy_delay must be >= 1"):
        Updater(None, opt, None, policy_delay=0)


def test_draw_batches_mixes_relabelled_rows_into_every_batch(tmp_path):
    """One draw of n*B rows, shuffled: HER's 80% relabelled share is exact over the draw and in every batch's range."""
    from conftest import make_transitions

    cfg = _cfg("env=push")
    storage = ZarrStorage(tmp_path / "m.zarr", 2000, env="FetchPush-v4")
    rb = utils.make_replay_buffer(cfg, storage, batch_size=None)
    rb.extend(make_transitions(1000))  # desired goals are all zero; achieved goals never are
    torch.manual_seed(0)
    batches = draw_batches(lambda k: rb.sample(k), n=10, batch_size=32)
    assert len(batches) == 10 and all(b.shape == torch.Size([32]) for b in batches)
    relabelled = [int((b["desired_goal"] != 0).any(-1).sum()) for b in batches]
    assert sum(relabelled) == int(320 * cfg.replay_buffer.her_ratio)
    # unshuffled, the first 8 batches would be all relabelled and the last two none; shuffled, a batch is
    # mixed unless its 32 rows all fall on one side (p < 1e-3 a batch, so all ten pure: p < 1e-30)
    assert any(0 < r < 32 for r in relabelled), relabelled
    # each row keeps the reward HER gave it for its (new) goal: relabelled before the shuffle, rows kept whole
    reward_fn = utils.make_reward_fn(cfg.env.name)
    for b in batches:
        assert torch.equal(b["next", "reward"], reward_fn(b))
    with pytest.raises(ValueError, match="n and batch_size must be >= 1"):
        draw_batches(lambda k: rb.sample(k), n=0, batch_size=32)
    storage.close()


def test_normalizer_updates_in_place():
    """A compiled or CUDA-graphed update reads the normaliser's tensors by address: updates keep them."""
    norm = utils.GoalNormalizer()
    td = TensorDict({"observation": torch.randn(10, 4), "desired_goal": torch.randn(10, 3),
                     ("next", "achieved_goal"): torch.randn(10, 3)}, [10])
    norm.update(td)
    held = [t.data_ptr() for t in norm._observation]
    norm.update(td * 3)
    assert [t.data_ptr() for t in norm._observation] == held
    want = torch.cat([td["observation"], td["observation"] * 3]).double()
    torch.testing.assert_close(norm._observation[0], want.mean(0).float())


@pytest.mark.full
def test_recipe_parallel_envs_store_whole_episodes(tmp_path):
    """env.num_envs=2 env.parallel=true: two worker processes; each env's episodes lie contiguous in the memory."""
    mem = tmp_path / "m.zarr"
    s = run_recipe(tmp_path, "env.num_envs=2", "env.parallel=true", "collector.frames_per_batch=100",
                   "collector.total_frames=100", "collector.init_random_frames=50", "logger.eval_iter=100",
                   f"memory.path={mem}")
    assert s["frames"] == 100 and s["memory_rows_after"] == 100 and s["updates"] > 0
    with ZarrStorage(mem, read_only=True) as storage:
        rows = storage[0:100]
    steps = rows["step_count"].reshape(2, 50)
    assert torch.equal(steps, torch.arange(50).expand(2, 50)), "an episode was cut apart in the memory"
    assert rows["next", "done"].reshape(2, 50)[:, -1].all() and not rows["next", "done"].reshape(2, 50)[:, :-1].any()


def test_recipe_refuses_a_batch_that_cuts_episodes(tmp_path):
    import subprocess

    proc = subprocess.run(
        [sys.executable, str(RECIPE_DIR / "train.py"), *TINY, "env.num_envs=2", "collector.frames_per_batch=50",
         f"memory.path={tmp_path / 'm.zarr'}", f"hydra.run.dir={tmp_path / 'out'}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode != 0
    assert "frames_per_batch must be a multiple of 100" in proc.stderr and "collector.frames_per_batch=100" in proc.stderr
    assert not (tmp_path / "m.zarr").exists()
