"""Compare finished runs of ``recipes/her/train.py``: one plot, one markdown table.

Each run directory (the ``hydra.run.dir`` of a run) holds ``summary.json`` with
its evaluation curve. Runs are grouped by label (``label=dir,dir,...``); the
plot draws every run (one colour a group), the table gives each run's success
at every evaluated frame count, its CPU time and the frames at which it first
reached ``--target``::

    python -m recipes.her.tools.compare --out docs/img/prior_push.png --target 0.9 \\
        "prior memory=bench_results/prior/run-push-s0,bench_results/prior/run-push-s1" \\
        "from scratch=bench_results/prior/scratch-push-s0"

A run still in progress has no ``summary.json`` yet: its curve is read from the
CSV logger's ``eval/success_rate.csv`` files instead (all of them: a run resumed
with ``collector.resume=true`` logs to one more), and its CPU time from ``time/cpu_s.csv``
at its last evaluation, marked "(partial)".

Run directories (memories, logs) are big and machine-local; their curves are
small. ``--archive DIR`` writes each run's curve, frames and CPU time to
``DIR/<run>.json``, and such a file can stand in for the run directory later
(``docs/runs/`` keeps those of docs/results.md and docs/notes/results_log.md)::

    python -m recipes.her.tools.compare --out /tmp/p.png --archive docs/runs "bc=bench_results/p60/bc-push-s0"
    python -m recipes.her.tools.compare --out docs/img/x.png "bc=docs/runs/bc-push-s0.json"
"""
from __future__ import annotations

import argparse
import csv
import glob
import json
import os

from recipes.her.run_record import EPISODES_FILE, first_reach, read_episodes


def load_run(run_dir: str) -> dict:
    """``summary.json`` of a finished run, the partial curve of a running one, or an archived ``.json``."""
    if run_dir.endswith(".json") and os.path.isfile(run_dir):
        with open(run_dir) as f:
            run = json.load(f)
        return {**run, "dir": run_dir[: -len(".json")], "running": not run.get("finished", True), "archived": True}
    path = os.path.join(run_dir, "summary.json")
    if os.path.exists(path):
        with open(path) as f:
            return {**json.load(f), "dir": run_dir, "running": False}
    points = logged_scalar(run_dir, "eval", "success_rate")
    if not points:
        raise FileNotFoundError(f"{run_dir!r}: no summary.json and no eval/success_rate.csv: not a recipes/her run.")
    curve = [[x, points[x]] for x in sorted(points)]
    cpu = logged_scalar(run_dir, "time", "cpu_s")  # training CPU-s at each evaluation
    return {"dir": run_dir, "curve": curve, "frames": curve[-1][0] if curve else 0,
            "cpu_s": cpu[max(cpu)] if cpu else None, "running": True}


def logged_scalar(run_dir: str, group: str, name: str) -> dict[int, float]:
    """``{frames: value}`` of one scalar the CSV logger wrote, over every CSV of the run (a resumed run logs to
    one more; the later file wins)."""
    files = glob.glob(os.path.join(run_dir, "her_logging", "*", "scalars", group, f"{name}.csv"))
    points: dict[int, float] = {}
    for path in sorted(files, key=os.path.getmtime):
        with open(path) as f:
            for row in csv.reader(f):
                if len(row) >= 2:
                    try:
                        points[int(float(row[0]))] = float(row[1])
                    except ValueError:
                        continue  # header
    return points


def table(groups: dict[str, list[dict]], target: float) -> str:
    frames = sorted({int(x) for runs in groups.values() for r in runs for x, _ in r["curve"]})
    head = "| run | " + " | ".join(f"{f / 1000:g}k" for f in frames) + f" | first >= {target} | CPU-s |"
    lines = [head, "|" + "---|" * (len(frames) + 3)]
    for label, runs in groups.items():
        for r in runs:
            at = {int(x): y for x, y in r["curve"]}
            cells = " | ".join(f"{at[f]:.2f}" if f in at else "" for f in frames)
            reach = first_reach(r["curve"], target)
            cpu = f"{r['cpu_s']:.0f}" if r["cpu_s"] is not None else "-"
            cpu += " (partial)" if r["running"] else ""
            lines.append(f"| {label}, {os.path.basename(r['dir'].rstrip('/'))} | {cells} | "
                         f"{reach if reach is not None else '-'} | {cpu} |")
    return "\n".join(lines)


def archive(groups: dict[str, list[dict]], directory: str) -> list[str]:
    """Each run's curve, frames, CPU time and per-episode outcomes as ``directory/<run>.json`` (what ``load_run``
    and ``recipes.her.run_record.read_episodes`` read back)."""
    os.makedirs(directory, exist_ok=True)
    paths = []
    for runs in groups.values():
        for r in runs:
            if r.get("archived"):  # read from an archive already
                continue
            path = os.path.join(directory, os.path.basename(r["dir"].rstrip("/")) + ".json")
            kept = {"curve": [[int(x), float(y)] for x, y in r["curve"]], "frames": int(r["frames"]),
                    "cpu_s": r["cpu_s"], "finished": not r["running"]}
            if os.path.isfile(os.path.join(r["dir"], EPISODES_FILE)):  # per-episode outcomes, for tools.paired
                episodes = read_episodes(r["dir"])
                kept["episodes"] = [episodes[f] for f in sorted(episodes)]
            with open(path, "w") as f:
                json.dump(kept, f)
                f.write("\n")
            paths.append(path)
    return paths


def plot(groups: dict[str, list[dict]], path: str, title: str, target: float,
         max_frames: int | None = None) -> tuple[float, float]:
    """Every run's curve, one color a group (dashed: a run not finished); returns the x axis' limits."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.8, 4.2))
    colors = ["#e6550d", "#3182bd", "#31a354", "#756bb1", "#636363", "#d62728", "#8c564b", "#e377c2"]
    for (label, runs), color in zip(groups.items(), colors * 4):
        for i, r in enumerate(runs):
            if r["curve"]:
                xs, ys = zip(*r["curve"])
                ax.plot(xs, ys, color=color, alpha=0.85, marker="o", markersize=2.5,
                        ls="--" if r["running"] else "-", label=label if i == 0 else None)
    ax.axhline(target, color="grey", lw=0.8, ls=":")
    ax.set(xlabel="new env frames", ylabel="eval success rate", ylim=(-0.02, 1.02), title=title)
    if max_frames:  # a budget shorter than some runs: the plot stops there
        ax.set_xlim(-0.02 * max_frames, 1.02 * max_frames)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, framealpha=0.9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    xlim = ax.get_xlim()
    plt.close(fig)
    return xlim


def main(argv: list[str] | None = None) -> str:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("groups", nargs="+", help="label=run_dir[,run_dir...]")
    p.add_argument("--out", required=True, help="PNG path")
    p.add_argument("--title", default="")
    p.add_argument("--target", type=float, default=0.9)
    p.add_argument("--archive", default=None, help="also write each run's curve to ARCHIVE/<run>.json")
    p.add_argument("--max-frames", type=int, default=None, help="the plot's x axis ends here")
    args = p.parse_args(argv)
    groups = {}
    for g in args.groups:
        label, _, dirs = g.partition("=")
        if not dirs:
            p.error(f"{g!r}: expected label=run_dir[,run_dir...]")
        groups[label] = [load_run(d) for d in dirs.split(",") if d]
    plot(groups, args.out, args.title, args.target, args.max_frames)
    if args.archive:
        archive(groups, args.archive)
    md = table(groups, args.target)
    print(md)
    return md


if __name__ == "__main__":
    main()
