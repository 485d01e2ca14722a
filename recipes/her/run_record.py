"""What a run of the HER recipe keeps of itself: CPU time, progress to resume from, its summary and history.

``train.py`` imports it as ``run_record``; ``recipes.her.tools.compare`` reads
:func:`first_reach` from it. Like ``utils.py`` it imports no sibling module.
"""
from __future__ import annotations

import contextlib
import glob
import json
import os
import resource
import time

from omegaconf import DictConfig
from torchrl.checkpoint import Checkpoint

__all__ = ["EPISODES_FILE", "CpuClock", "append_history", "cost_line", "finish_run", "first_reach", "plot_success",
           "read_episodes", "read_history", "record_episodes", "recover_checkpoint", "run_progress"]

#: one line per evaluation, in the run's hydra directory: ``{"frames", "seed", "success": [0 / 1 per episode]}``
EPISODES_FILE = "eval_episodes.jsonl"


def recover_checkpoint(checkpoint_path: str) -> str | None:
    """Puts back an agent checkpoint that a kill caught mid-save; returns the backup used, if any.

    ``torchrl.checkpoint.Checkpoint.save`` publishes a new checkpoint by moving
    the old one aside (``.NAME.backup-<uuid>``) and the new one into place: a
    process killed between the two moves leaves no checkpoint at ``NAME``, only
    the backup. That backup is the last complete checkpoint; it is moved back.

    Args:
        checkpoint_path (str): the agent checkpoint directory (``memory.checkpoint``).
    """
    path = os.path.abspath(checkpoint_path)
    if os.path.exists(path):
        return None
    head, name = os.path.split(path)
    backups = sorted(glob.glob(os.path.join(glob.escape(head), f".{glob.escape(name)}.backup-*")),
                     key=os.path.getmtime)
    for backup in reversed(backups):
        if Checkpoint.is_checkpoint(backup):
            os.replace(backup, path)
            print(f"restored the agent checkpoint {path} from {backup} (a save was interrupted)")
            return backup
    return None


def run_progress(cfg: DictConfig, checkpoint_path: str, memory_rows: int) -> dict | None:
    """Where a stopped run stands, for ``collector.resume=true`` (``None``: start the run fresh).

    The progress is the metadata of the agent checkpoint that the run saves at
    every evaluation. Nothing to resume (no checkpoint, empty memory) starts a
    fresh run; a memory with rows but no progress is refused, since its rows
    would be counted as an earlier run's.
    """
    if not cfg.collector.resume:
        return None
    if not Checkpoint.is_checkpoint(checkpoint_path):
        if memory_rows:
            raise RuntimeError(
                f"collector.resume=true: the memory holds {memory_rows} transitions but there is no agent "
                f"checkpoint at {checkpoint_path} to resume from (the run was stopped before its first "
                "evaluation?). Start it again on a fresh memory.path, or drop collector.resume."
            )
        return None
    meta = Checkpoint.manifest(checkpoint_path).get("metadata") or {}
    missing = [k for k in ("frames", "curve", "cpu_s", "memory_rows", "memory_rows_before", "updates") if k not in meta]
    if missing:
        raise RuntimeError(
            f"collector.resume=true: the checkpoint at {checkpoint_path} has no run progress ({missing} missing "
            "from its metadata; written by an older recipe?). Use memory.resume_agent=true to start a new run "
            "from its networks instead."
        )
    if meta.get("env") != cfg.env.name or meta.get("seed") != cfg.seed:
        raise RuntimeError(
            f"collector.resume=true: the checkpoint at {checkpoint_path} is of env={meta.get('env')} "
            f"seed={meta.get('seed')}, this run is env={cfg.env.name} seed={cfg.seed}."
        )
    if memory_rows < meta["memory_rows"]:
        raise RuntimeError(
            f"collector.resume=true: the memory holds {memory_rows} transitions, fewer than the "
            f"{meta['memory_rows']} of the checkpoint at {checkpoint_path}: not the memory of this run."
        )
    return meta


class CpuClock:
    """CPU seconds of a run: training, evaluation, and the whole process.

    * :meth:`seconds`: training, the process's CPU since the clock started with
      the ``paused()`` sections (evaluation, saves) left out: what
      ``collector.cpu_budget_s`` and ``time/cpu_s`` count;
    * :meth:`evaluation`: the ``evaluating()`` sections (they are paused too);
    * :meth:`process`: everything the process used since it started (imports, envs,
      saves included) and its finished child processes (the store's commit worker
      once closed): what a user pays for.

    The offsets carry a resumed run's seconds from its earlier launches.

    Args:
        offset (float): training CPU-seconds before a resume.
        eval_offset (float): evaluation CPU-seconds before a resume.
        process_offset (float): process CPU-seconds of the earlier launches.

    Example:
        >>> clock = CpuClock()
        >>> with clock.evaluating():
        ...     _ = sum(range(10_000))
        >>> clock.evaluation() >= 0 and clock.process() >= clock.seconds() + clock.evaluation() - 1e-6
        True
    """

    def __init__(self, offset: float = 0.0, eval_offset: float = 0.0, process_offset: float = 0.0):
        self._start = time.process_time() - offset  # offset: CPU-seconds of the run before a resume
        self._excluded = 0.0
        self._eval = float(eval_offset)
        self._process_offset = float(process_offset)

    @classmethod
    def resumed(cls, progress: dict | None) -> CpuClock:
        """A clock that carries on the seconds of :func:`run_progress`'s ``progress`` (``None``: from zero)."""
        if not progress:
            return cls()
        return cls(progress["cpu_s"], progress.get("eval_cpu_s", 0.0), progress.get("process_cpu_s", 0.0))

    @contextlib.contextmanager
    def paused(self):
        t0 = time.process_time()
        try:
            yield
        finally:
            self._excluded += time.process_time() - t0

    @contextlib.contextmanager
    def evaluating(self):
        """A paused section counted as evaluation."""
        t0 = time.process_time()
        with self.paused():
            yield
        self._eval += time.process_time() - t0

    def seconds(self) -> float:
        return time.process_time() - self._start - self._excluded

    def evaluation(self) -> float:
        return self._eval

    def process(self) -> float:
        own = resource.getrusage(resource.RUSAGE_SELF)
        children = resource.getrusage(resource.RUSAGE_CHILDREN)
        return self._process_offset + own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def first_reach(curve: list, target: float | None) -> int | None:
    """Frames of the first evaluation at or above ``target`` (``None``: never, or no target)."""
    if target is None:
        return None
    return next((int(x) for x, y in curve if y >= target), None)


def finish_run(cfg: DictConfig, history: list[dict], history_path: str, summary: dict,
               clock: CpuClock | None = None) -> None:
    """The end of a run: the plot, ``summary.json``, one more line of the memory's history, the report.

    With ``clock``, the summary gets the run's evaluation and whole-process CPU-seconds
    (``eval_cpu_s``, ``process_cpu_s``), read after the plot so that they count it.
    """
    if cfg.logger.plot:  # this run, and the earlier runs on the same memory
        curves = {
            f"run {i + 1}: {run['algo']}, memory of {run['memory_rows_before']} transitions": run["curve"]
            for i, run in enumerate([*history, summary])
        }
        if plot_success(curves, "success_rate.png", title=f"{cfg.env.name}, eval success"):
            print(f"plot: {os.path.abspath('success_rate.png')}")
    if clock is not None:
        summary["eval_cpu_s"] = round(clock.evaluation(), 2)
        summary["process_cpu_s"] = round(clock.process(), 2)
    with open("summary.json", "w") as f:
        json.dump(summary, f)
    append_history(history_path, summary)
    target, reached_at = cfg.logger.target_success, summary["frames_to_target"]
    print(
        f"evaluated success {summary['curve'][-1][1]:.2f} after {summary['frames']} new env frames "
        f"({summary['cpu_s']:.1f} CPU-s, {summary['updates']} updates); memory now {summary['memory_rows_after']} "
        "transitions" + (f"; reached {target} at {reached_at} frames" if reached_at is not None else "")
    )
    if clock is not None:
        print(cost_line(summary, target))
    if summary.get("frames_per_s"):
        print(f"training loop: {summary['frames_per_s']:.1f} frames/s over {summary['loop_wall_s']:.1f} s "
              "(collection, memory and updates; evaluation excluded)")
    earlier = [run for run in history if run.get("frames_to_target") is not None]
    if reached_at is not None and earlier:
        first = earlier[0]["frames_to_target"]
        print(
            f"the first run on this memory needed {first} frames to reach {target}; "
            f"this one {reached_at}: {first - reached_at} fewer"
        )
        first_cpu, cpu = earlier[0].get("process_cpu_s"), summary.get("process_cpu_s")
        if first_cpu is not None and cpu is not None:
            print(f"CPU-s (whole process): first run {first_cpu:.1f}, this one {cpu:.1f}")


def cost_line(summary: dict, target: float | None = None) -> str:
    """What the run cost: env frames (new, and in the memory) beside CPU-seconds (process, training, evaluation).

    Example:
        >>> cost_line({"frames": 0, "frames_to_target": 0, "memory_rows_before": 2750, "memory_rows_after": 2750,
        ...            "process_cpu_s": 9.5, "cpu_s": 3.0, "eval_cpu_s": 1.1}, 0.95)
        'frames to target 0.95: 0 new (2,750 total), CPU-s: 9.5 (training 3.0, evaluation 1.1, the rest 5.4)'
    """
    reached = summary.get("frames_to_target")
    if reached is not None:
        frames = f"frames to target {target}: {reached:,} new ({summary['memory_rows_before'] + reached:,} total)"
    else:
        missed = f", target {target} not reached" if target is not None else ""
        frames = f"frames: {summary['frames']:,} new{missed} ({summary['memory_rows_after']:,} in the memory)"
    total, train, evaluation = summary["process_cpu_s"], summary["cpu_s"], summary["eval_cpu_s"]
    return (f"{frames}, CPU-s: {total:.1f} (training {train:.1f}, evaluation {evaluation:.1f}, "
            f"the rest {max(0.0, total - train - evaluation):.1f})")


def record_episodes(frames: int, seed: int, outcomes: list[int], path: str = EPISODES_FILE) -> None:
    """Appends one evaluation's per-episode successes to ``path`` (a resumed run goes on appending)."""
    with open(path, "a") as f:
        f.write(json.dumps({"frames": int(frames), "seed": int(seed), "success": [int(x) for x in outcomes]}) + "\n")


def read_episodes(run_dir: str) -> dict[int, dict]:
    """``{frames: {"frames", "seed", "success"}}`` from ``run_dir/eval_episodes.jsonl`` (a later line for the same
    frames, a resumed run evaluating again, replaces an earlier one), or from the ``episodes`` of a run's
    archive (``recipes.her.tools.compare --archive``, a ``.json`` path)."""
    if run_dir.endswith(".json") and os.path.isfile(run_dir):
        with open(run_dir) as f:
            records = json.load(f).get("episodes")
        if records is None:
            raise KeyError(f"{run_dir} holds no per-episode outcomes (archived before runs wrote {EPISODES_FILE}).")
    else:
        with open(os.path.join(run_dir, EPISODES_FILE)) as f:
            records = [json.loads(line) for line in f if line.strip()]
    return {int(rec["frames"]): rec for rec in records}


def read_history(path: str) -> list[dict]:
    """Summaries of the earlier runs on a memory (one JSON object a line)."""
    try:
        with open(path) as f:
            return [json.loads(line) for line in f if line.strip()]
    except FileNotFoundError:
        return []


def append_history(path: str, summary: dict) -> None:
    with open(path, "a") as f:
        f.write(json.dumps(summary) + "\n")


def plot_success(curves: dict[str, list[tuple[int, float]]], path: str, title: str = "") -> bool:
    """Writes success rate vs env frames (one line per curve) to ``path``; False without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, points in curves.items():
        if points:
            frames, success = zip(*points)
            ax.plot(frames, success, marker="o", markersize=3, label=label)
    ax.axhline(0.95, color="grey", lw=0.8, ls="--")
    ax.set(xlabel="env frames collected in this run", ylabel="eval success rate", ylim=(-0.02, 1.02), title=title)
    ax.grid(alpha=0.3)
    if len(curves) > 1:
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True
