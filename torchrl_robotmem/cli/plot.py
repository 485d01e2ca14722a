"""Plot a memory: episode success per run and achieved goals coloured by success, one panel per env.

``robotmem plot PATH [--out DIR]`` writes two PNG files (matplotlib, Agg backend):

* ``success.png``: per env, the success of finished episodes in write order
  (a rolling mean over ``--window`` episodes) with each run's mean as a step
  line and run boundaries as vertical lines;
* ``goals.png``: per env, the achieved goals of the stored rows (the first two
  goal dimensions; at most ``--max-points`` rows, evenly spaced), successful
  rows in green over the others in grey.
"""
from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np

from . import CLIError
from ._memory import DONE_KEY, SUCCESS_KEY, flat_column, goal_key, has_key, open_memory

__all__ = ["plot_memory", "add_arguments", "run"]


def plot_memory(path: Any, out_dir: str, *, window: int = 50, max_points: int = 20_000) -> list[str]:
    """Writes ``success.png`` and ``goals.png`` for the memory at ``path`` into ``out_dir``.

    Args:
        path: the memory (opened read-only).
        out_dir (str): the directory to write into (created if missing).

    Keyword Args:
        window (int): episodes in the rolling success mean. Defaults to 50.
        max_points (int): rows drawn in the goal scatter, at most. Defaults to 20_000.

    Returns:
        the paths of the files written (a figure whose columns the memory lacks is skipped).

    Example:
        >>> import os, tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.cli.plot import plot_memory
        >>> d = tempfile.mkdtemp()
        >>> st = ZarrStorage(d + "/m.zarr", 100, env="FetchReach-v4", background=False)
        >>> st.set(slice(0, 4), TensorDict({"next": {"done": torch.ones(4, 1, dtype=torch.bool),
        ...     "is_success": torch.tensor([0.0, 1.0, 1.0, 0.0]), "achieved_goal": torch.rand(4, 3)}}, [4]))
        >>> st.close()
        >>> [os.path.basename(p) for p in plot_memory(d + "/m.zarr", d + "/plots")]
        ['success.png', 'goals.png']
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if window < 1 or max_points < 1:
        raise ValueError(f"window and max_points must be >= 1, got {window} and {max_points}.")
    c = _read_columns(path)
    os.makedirs(out_dir, exist_ok=True)
    names = c["names"]
    codes = [int(code) for code in np.unique(c["env"])]
    label = {code: names[code] if 0 <= code < len(names) else "(unknown env)" for code in codes}
    written = []
    if c["success"] is not None and c["done"] is not None and c["done"].any():
        fig = _success_figure(plt, c, codes, label, window)
        written.append(_save(fig, os.path.join(out_dir, "success.png")))
        plt.close(fig)
    if c["goals"] is not None:
        fig = _goals_figure(plt, c, codes, label, max_points)
        written.append(_save(fig, os.path.join(out_dir, "goals.png")))
        plt.close(fig)
    return written


def _read_columns(path: Any) -> dict[str, Any]:
    """The flat columns the figures draw (episode, run, env, success, done, goals) and the title, read-only."""
    storage = open_memory(path)
    try:
        if not len(storage) or not has_key(storage, "episode"):
            raise CLIError(f"{storage.path!r} holds no tagged TensorDict rows; nothing to plot")
        n = len(storage) if storage.ndim == storage.view().get("episode").ndim else None
        episode, run, env = (flat_column(storage, k)[:n] for k in ("episode", "run", "env"))
        n = len(episode)
        success = flat_column(storage, SUCCESS_KEY)[:n].reshape(n, -1)[:, 0] > 0.5 \
            if has_key(storage, SUCCESS_KEY) else None
        done = flat_column(storage, DONE_KEY)[:n].reshape(n, -1).any(-1) if has_key(storage, DONE_KEY) else None
        gkey = goal_key(storage)
        goals = flat_column(storage, gkey)[:n].reshape(n, -1) if gkey is not None else None
        return {"episode": episode, "run": run, "env": env, "success": success, "done": done, "gkey": gkey,
                "goals": goals, "names": list(storage.env_names),
                "title": os.path.basename(str(storage.path).rstrip("/"))}
    finally:
        storage.close()


def _success_figure(plt, c: dict[str, Any], codes: list[int], label: dict[int, str], window: int):
    """Per env, the rolling success of finished episodes, each run's mean and the run boundaries."""
    success, done, run, env = c["success"], c["done"], c["run"], c["env"]
    fig, axes = plt.subplots(len(codes), 1, figsize=(8, 2.8 * len(codes)), squeeze=False)
    for ax, code in zip(axes[:, 0], codes):
        ends = np.flatnonzero(done & (env == code))
        s = success[ends].astype(float)
        r = run[ends]
        x = np.arange(len(s))
        if len(s):
            k = min(window, len(s))
            rolling = np.convolve(s, np.ones(k) / k, mode="valid")
            ax.plot(x[k - 1:], rolling, color="tab:blue", label=f"rolling mean ({k} episodes)")
            for rid in np.unique(r):
                idx = np.flatnonzero(r == rid)
                ax.hlines(s[idx].mean(), idx[0], idx[-1], color="tab:orange", lw=2)
                ax.axvline(idx[0], color="grey", lw=0.5, ls=":")
                ax.text(idx[0], 1.02, f"run {rid}", fontsize=7, va="bottom")
            ax.plot([], [], color="tab:orange", lw=2, label="mean per run")
            ax.legend(loc="lower right", fontsize=7)
        ax.set_ylim(-0.02, 1.1)
        ax.set_ylabel("episode success")
        ax.set_title(f"{label[code]}: {len(s)} finished episodes", fontsize=9)
    axes[-1, 0].set_xlabel("finished episode (write order)")
    fig.suptitle(c["title"])
    fig.tight_layout()
    return fig


def _goals_figure(plt, c: dict[str, Any], codes: list[int], label: dict[int, str], max_points: int):
    """Per env, the first two achieved-goal dimensions, successful rows in green over the others in grey."""
    goals, success, env, gkey = c["goals"], c["success"], c["env"], c["gkey"]
    fig, axes = plt.subplots(1, len(codes), figsize=(4.2 * len(codes), 4), squeeze=False)
    for ax, code in zip(axes[0], codes):
        rows = np.flatnonzero(env == code)
        if len(rows) > max_points:
            rows = rows[np.linspace(0, len(rows) - 1, max_points).astype(np.int64)]
        g = goals[rows]
        y = g[:, 1] if g.shape[1] > 1 else np.zeros(len(g))
        ok = success[rows] if success is not None else np.zeros(len(rows), bool)
        ax.scatter(g[~ok, 0], y[~ok], s=3, c="lightgrey", label="not successful", rasterized=True)
        ax.scatter(g[ok, 0], y[ok], s=3, c="tab:green", label="successful", rasterized=True)
        ax.set_xlabel(f"{'/'.join(gkey) if isinstance(gkey, tuple) else gkey}[0]")
        ax.set_ylabel("[1]" if g.shape[1] > 1 else "")
        ax.set_title(f"{label[code]}: {len(rows)} rows", fontsize=9)
        ax.legend(loc="best", fontsize=7, markerscale=3)
    fig.suptitle(c["title"])
    fig.tight_layout()
    return fig


def _save(fig, path: str) -> str:
    fig.savefig(path, dpi=110)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="the memory (opened read-only)")
    parser.add_argument("--out", default=".", help="directory for the PNG files (default: the current directory)")
    parser.add_argument("--window", type=int, default=50, help="episodes in the rolling success mean (default 50)")
    parser.add_argument("--max-points", type=int, default=20_000, help="rows in the goal scatter, at most")


def run(args: argparse.Namespace) -> int:
    if args.window < 1 or args.max_points < 1:
        raise CLIError(f"--window and --max-points must be >= 1, got {args.window} and {args.max_points}")
    for path in plot_memory(args.path, args.out, window=args.window, max_points=args.max_points):
        print(path)
    return 0
