"""Milliseconds per update and frames per second of the HER recipe, against TorchRL's own sota SAC update.

For each recipe config (``reach``: SAC 2x64, batch 256; ``push``: SAC 3x256, batch 512) and device, in one run:

* **TorchRL sota** - the ``update`` function of ``sota-implementations/sac/sac.py`` (pytorch/rl at ae9719f),
  verbatim, on the recipe's own networks and ``SACLoss``; its batch from a ``TensorDictReplayBuffer`` over a
  ``LazyTensorStorage`` (uniform, no HER), one ``sample()`` per update as the sota loop does;
* **recipe** - ``recipes/her/update.py``'s ``Updater`` on batches drawn from ``HERReplayBuffer`` over a
  ``ZarrStorage`` (relabelled, rewarded): one draw per update (``optim.batches_per_draw=1``) and the 100
  batches of a collection step drawn together (the default);
* with ``--compile`` (and ``--cudagraphs`` on CUDA) the same, compiled as each side's switches do.

"update" is the step alone on a fixed batch; "sample+update" includes drawing the batch (and, on CUDA, its
copy). Times are medians over ``--repeat`` rounds of ``--updates`` steps, after warm-up. With
``--recipe-frames N`` the recipe itself also runs ``N`` frames (``collector.init_random_frames=500``, no
evaluation until the end) and its ``frames_per_s`` (collection, memory and updates) is reported.

    python benchmarks/bench_update.py                                  # reach and push, CPU
    python benchmarks/bench_update.py --configs push --recipe-frames 1500
    python benchmarks/bench_update.py --device cuda --compile --cudagraphs --recipe-frames 3000
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "her"
sys.path.insert(0, str(ROOT))

from hydra import compose, initialize_config_dir  # noqa: E402
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer  # noqa: E402

from recipes.her import utils  # noqa: E402
from recipes.her.update import LossTerms, Updater, draw_batches  # noqa: E402
from torchrl_robotmem import ZarrStorage  # noqa: E402

CONFIGS = {"reach": ["env=reach"], "push": ["env=push"]}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _median_ms(fn, device, updates: int, repeat: int) -> float:
    rounds = []
    for _ in range(repeat):
        _sync(device)
        t = time.perf_counter()
        for _ in range(updates):
            fn()
        _sync(device)
        rounds.append((time.perf_counter() - t) / updates * 1e3)
    return statistics.median(rounds)


def sota_update_fn(loss_module, optimizer, target_net_updater):
    """``update`` of TorchRL's sota-implementations/sac/sac.py (ae9719f), verbatim."""
    def update(sampled_tensordict):
        # Compute loss
        loss_td = loss_module(sampled_tensordict)

        actor_loss = loss_td["loss_actor"]
        q_loss = loss_td["loss_qvalue"]
        alpha_loss = loss_td["loss_alpha"]

        (actor_loss + q_loss + alpha_loss).sum().backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

        # Update qnet_target params
        target_net_updater.step()
        return loss_td.detach()
    return update


def _agent(cfg, env, rows, device, compiled: bool, cudagraphs: bool):
    torch.manual_seed(0)
    normalizer = utils.GoalNormalizer(device=device)
    normalizer.update(rows)
    model, _ = utils.make_agent(cfg, env, normalizer)
    loss, target = utils.make_loss_module(cfg, model, compiled=compiled)
    optimizer = utils.make_optimizer(cfg, loss, capturable=cudagraphs)
    return loss, optimizer, target


def bench_config(name: str, args, device: torch.device) -> list[dict]:
    overrides = [*CONFIGS[name], f"device={device.type}"]
    with initialize_config_dir(config_dir=str(RECIPE), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    batch_size = cfg.optim.batch_size
    env = utils.make_task_env(cfg, 1, seed=0)
    rows = env.rollout(args.rows, break_when_any_done=False).reshape(-1)  # real transitions, random actions
    tmp = tempfile.mkdtemp()
    her = utils.make_replay_buffer(cfg, ZarrStorage(Path(tmp) / "m.zarr", 100_000, env=cfg.env.name,
                                                    device=str(device)), batch_size=None)
    her.extend(rows)
    plain = TensorDictReplayBuffer(storage=LazyTensorStorage(100_000, device=device), batch_size=batch_size)
    plain.extend(rows)
    fixed = utils.to_device(her.sample(batch_size), device)
    modes = [(False, False)] + ([(True, False)] if args.compile else [])
    if args.cudagraphs and device.type == "cuda":
        modes.append((True, True))
    if args.modes:  # a subset, e.g. only "graphs" where the time is short
        names = {(False, False): "eager", (True, False): "compiled", (True, True): "graphs"}
        modes = [m for m in modes if names[m] in args.modes]
    out = []
    for compiled, graphs in modes:
        out += bench_mode(name, cfg, env, rows, her, plain, fixed, device, compiled, graphs, args)
        print(json.dumps(out[-5:]), flush=True)
    if args.recipe_frames:
        out.extend(recipe_fps(name, args, device))
    return out


def bench_mode(name, cfg, env, rows, her, plain, fixed, device, compiled: bool, graphs: bool, args) -> list[dict]:
    """The five timings of one mode (eager / compiled / compiled + CUDA graphs) of one config."""
    batch_size = cfg.optim.batch_size
    label = "eager" if not compiled else ("compiled + CUDA graphs" if graphs else "compiled")
    # TorchRL sota: its update on the recipe's networks, wrapped as its switches wrap it
    loss, optimizer, target = _agent(cfg, env, rows, device, compiled, graphs)
    update = sota_update_fn(loss, optimizer, target)
    if compiled:
        update = torch.compile(update, mode="default" if graphs else args.compile_mode)
    if graphs:
        from tensordict.nn import CudaGraphModule
        update = CudaGraphModule(update, in_keys=[], out_keys=[], warmup=5)

    def sota_step(batch=None):
        if graphs:
            torch.compiler.cudagraph_mark_step_begin()
        # a fixed batch is passed as a shallow copy: SACLoss writes its outputs (with grad) into the batch it is
        # given, and CudaGraphModule refuses an input that requires grad (the sota loop samples a fresh one)
        return update(plain.sample() if batch is None else batch.copy())

    fixed_plain = plain.sample()  # the sota loop's own batches (no HER, no tag columns): what it is compiled for
    for _ in range(args.warmup):
        sota_step(fixed_plain)
        sota_step()
    sota_update = _median_ms(lambda: sota_step(fixed_plain), device, args.updates, args.repeat)
    sota_full = _median_ms(sota_step, device, args.updates, args.repeat)
    # the recipe's Updater, HER over ZarrStorage
    loss, optimizer, target = _agent(cfg, env, rows, device, compiled, graphs)
    updater = Updater(LossTerms(loss, utils.loss_keys(cfg)), optimizer, target, compile=compiled,
                      compile_mode="default" if graphs else args.compile_mode, cudagraphs=graphs, warmup=5)
    for _ in range(args.warmup + 5):
        updater(fixed)
    recipe_update = _median_ms(lambda: updater(fixed), device, args.updates, args.repeat)
    recipe_one = _median_ms(lambda: updater(utils.to_device(her.sample(batch_size), device)), device,
                            args.updates, args.repeat)
    queue: list = []

    def drawn():
        if not queue:
            queue.extend(draw_batches(lambda k: utils.to_device(her.sample(k), device), 100, batch_size))
        return updater(queue.pop())

    recipe_drawn = _median_ms(drawn, device, 100, args.repeat)
    out = []
    for variant, ms in [("TorchRL sota SAC: update", sota_update), ("TorchRL sota SAC: sample+update", sota_full),
                        ("recipe: update", recipe_update), ("recipe: HER sample+update, one draw each", recipe_one),
                        ("recipe: HER sample+update, 100 drawn together", recipe_drawn)]:
        out.append({"config": name, "device": str(device), "mode": label, "variant": variant, "ms": ms,
                    "x_sota": (sota_update if variant.endswith(": update") else sota_full) / ms})
    return out


def recipe_fps(name: str, args, device: torch.device) -> list[dict]:
    """frames/s of the recipe itself over ``--recipe-frames`` frames (its summary's ``frames_per_s``)."""
    results = []
    modes = [("eager", ["compile.compile=false", "compile.cudagraphs=false"])]
    if args.compile:
        modes.append(("compiled", ["compile.compile=true", "compile.cudagraphs=false"]))
    if args.cudagraphs and device.type == "cuda":
        modes.append(("compiled + CUDA graphs", ["compile.compile=true", "compile.cudagraphs=true"]))
    for label, switches in modes:
        tmp = Path(tempfile.mkdtemp())
        cmd = [sys.executable, str(RECIPE / "train.py"), *CONFIGS[name], f"device={device.type}", *switches,
               f"collector.total_frames={args.recipe_frames}", "collector.init_random_frames=500",
               f"logger.eval_iter={args.recipe_frames}", "logger.eval_episodes=10", "logger.plot=false",
               "logger.backend=", f"num_threads={args.threads}", f"memory.path={tmp / 'm.zarr'}",
               f"hydra.run.dir={tmp / 'out'}", *args.recipe_args]
        proc = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": "disable"})
        if proc.returncode:
            print(proc.stderr[-3000:], file=sys.stderr)
            continue
        summary = json.loads((tmp / "out" / "summary.json").read_text())
        results.append({"config": name, "device": str(device), "mode": label, "variant": "recipe: frames/s",
                        "fps": summary["frames_per_s"], "frames": summary["frames"],
                        "success": summary["curve"][-1][1]})
        print(json.dumps(results[-1]), flush=True)
    return results


def table(results: list[dict]) -> str:
    lines = ["| config | device | mode | what | ms / update | speed vs TorchRL sota |", "|---|---|---|---|---|---|"]
    for r in results:
        if "ms" in r:
            lines.append(f"| {r['config']} | {r['device']} | {r['mode']} | {r['variant']} | {r['ms']:.2f} | "
                         f"{r['x_sota']:.2f}x |")
    fps = [r for r in results if "fps" in r]
    if fps:
        lines += ["", "| config | device | mode | recipe frames/s | frames | success at the end |", "|---|---|---|---|---|---|"]
        lines += [f"| {r['config']} | {r['device']} | {r['mode']} | {r['fps']:.1f} | {r['frames']} | {r['success']:.2f} |"
                  for r in fps]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", default=["reach", "push"], choices=sorted(CONFIGS))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--compile", action="store_true", help="also the torch.compile'd updates")
    parser.add_argument("--compile-mode", default=None, help="torch.compile mode without CUDA graphs")
    parser.add_argument("--cudagraphs", action="store_true", help="also compiled + CUDA graphs (CUDA only)")
    parser.add_argument("--modes", nargs="*", default=None, choices=["eager", "compiled", "graphs"],
                        help="only these of the modes the switches select (default: all of them)")
    parser.add_argument("--updates", type=int, default=30)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--rows", type=int, default=2_000, help="transitions in the memory (random-action episodes)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--recipe-frames", type=int, default=0, help="also run the recipe this many frames")
    parser.add_argument("--recipe-args", nargs="*", default=[], help="more recipe overrides for --recipe-frames")
    parser.add_argument("--json", default=None, help="write the results here too")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore")
    device = torch.device(args.device)
    results = []
    for name in args.configs:
        results += bench_config(name, args, device)
    print(table(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
