"""Plot a memory: episode success per run and achieved goals coloured by success, one panel per env.

``robotmem plot PATH [--out DIR]`` writes two PNG files (matplotlib, Agg backend):

* ``success.png``: per env, the success of finished episodes in write order
  (a trailing rolling mean over ``--window`` episodes, one point per episode;
  by default the window follows the memory: ``min(50, max(1, episodes // 10))``,
  stated in the legend and the axis label) with each run's mean as a step
  line and run boundaries as vertical lines;
* ``goals.png``: per env, the achieved goals of the stored rows (the first two
  goal dimensions; at most ``--max-points`` rows, evenly spaced), successful
  rows in green over the others in grey.

Every axis is labelled in words (and metres for the goals of Fetch and Shadow Hand envs).
"""
from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np

from ._memory import DONE_KEY, SUCCESS_KEY, flat_column, goal_key, has_key, open_settled, partial_path
from .errors import CLIError

__all__ = ["plot_memory", "memory_figures", "add_arguments", "rolling_success", "success_window", "run"]

#: The largest default window of the rolling success mean, in episodes.
MAX_WINDOW = 50
#: Envs whose goals are positions in metres (Fetch, Shadow Hand).
_METRE_ENVS = ("Fetch", "HandReach", "HandManipulate")


def success_window(episodes: int, window: int | None = None) -> int:
    """The rolling-mean window for a panel of ``episodes`` finished episodes.

    ``window`` if given (at most ``episodes``), else ``min(50, max(1, episodes // 10))``: a
    20-episode memory gets a 2-episode window, 500 episodes or more get 50.

    Example:
        >>> success_window(20), success_window(500), success_window(3), success_window(20, 50)
        (2, 50, 1, 20)
    """
    if window is None:
        return min(MAX_WINDOW, max(1, episodes // 10))
    return max(1, min(int(window), episodes))


def rolling_success(success: np.ndarray, window: int) -> np.ndarray:
    """The trailing mean of ``success`` over the last ``window`` episodes, one value per episode.

    The first ``window - 1`` values average the episodes so far, so no episode is hidden.

    Example:
        >>> rolling_success(np.array([0.0, 1.0, 1.0, 0.0]), 2).tolist()
        [0.0, 0.5, 1.0, 0.5]
    """
    s = np.asarray(success, dtype=float)
    total = np.concatenate([[0.0], np.cumsum(s)])
    i = np.arange(1, len(s) + 1)
    start = np.maximum(i - window, 0)
    return (total[i] - total[start]) / (i - start)


#: the files :func:`plot_memory` writes
FIGURES = ("success.png", "goals.png")


def plot_memory(path: Any, out_dir: str, *, window: int | None = None, max_points: int = 20_000) -> list[str]:
    """Writes ``success.png`` and ``goals.png`` for the memory at ``path`` into ``out_dir``.

    Args:
        path: the memory (opened read-only).
        out_dir (str): the directory to write into (created if missing).

    Keyword Args:
        window (int, optional): episodes in the rolling success mean. Defaults to
            ``min(50, max(1, episodes // 10))`` per env (:func:`success_window`).
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
    import matplotlib.pyplot as plt

    existing = [os.path.join(out_dir, n) for n in FIGURES if os.path.lexists(os.path.join(out_dir, n))]
    if existing:  # nothing is overwritten (as an export's OUT)
        raise CLIError(f"{', '.join(repr(p) for p in existing)} exist{'s' if len(existing) == 1 else ''}; refusing to "
                       f"overwrite {'it' if len(existing) == 1 else 'them'}. Remove {'it' if len(existing) == 1 else 'them'} "
                       f"or choose another --out.")
    figures = memory_figures(path, window=window, max_points=max_points)
    os.makedirs(out_dir, exist_ok=True)
    written = []
    for name, fig in figures.items():
        written.append(_save(fig, os.path.join(out_dir, name)))
        plt.close(fig)
    return written


def memory_figures(path: Any, *, window: int | None = None, max_points: int = 20_000) -> dict[str, Any]:
    """The figures :func:`plot_memory` writes, as matplotlib figures (Agg backend), by file name; close them after use.

    Args:
        path: the memory (opened read-only).

    Keyword Args:
        window, max_points: as for :func:`plot_memory`.

    Returns:
        ``{"success.png": Figure, "goals.png": Figure}``, without a figure whose columns the memory lacks.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if (window is not None and window < 1) or max_points < 1:
        raise ValueError(f"window and max_points must be >= 1, got {window} and {max_points}.")
    c = _read_columns(path)
    names = c["names"]
    codes = [int(code) for code in np.unique(c["env"])]
    label = {code: names[code] if 0 <= code < len(names) else "(unknown env)" for code in codes}
    figures = {}
    if c["success"] is not None and c["done"] is not None and c["done"].any():
        figures["success.png"] = _success_figure(plt, c, codes, label, window)
    if c["goals"] is not None:
        figures["goals.png"] = _goals_figure(plt, c, codes, label, max_points)
    return figures


def _read_columns(path: Any) -> dict[str, Any]:
    """The flat columns the figures draw (episode, run, env, success, done, goals) and the title, read-only."""
    storage = open_settled(path)
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


def _success_figure(plt, c: dict[str, Any], codes: list[int], label: dict[int, str], window: int | None):
    """Per env, the rolling success of finished episodes, each run's mean and the run boundaries."""
    success, done, run, env = c["success"], c["done"], c["run"], c["env"]
    fig, axes = plt.subplots(len(codes), 1, figsize=(8, 2.8 * len(codes)), squeeze=False)
    for ax, code in zip(axes[:, 0], codes):
        ends = np.flatnonzero(done & (env == code))
        s = success[ends].astype(float)
        r = run[ends]
        k = success_window(len(s), window)
        if len(s):
            ax.plot(np.arange(len(s)), rolling_success(s, k), color="tab:blue", marker="." if len(s) < 100 else None,
                    label=f"rolling mean over {k} episode{'s' if k > 1 else ''}")
            for rid in np.unique(r):
                idx = np.flatnonzero(r == rid)
                ax.hlines(s[idx].mean(), idx[0], idx[-1], color="tab:orange", lw=2)
                ax.axvline(idx[0], color="grey", lw=0.5, ls=":")
                ax.text(idx[0], 1.02, f"run {rid}", fontsize=7, va="bottom")
            ax.plot([], [], color="tab:orange", lw=2, label="mean per run")
            ax.legend(loc="lower right", fontsize=7)
        ax.set_ylim(-0.02, 1.1)
        ax.set_ylabel(f"success rate\n(rolling mean over {k} episode{'s' if k > 1 else ''})", fontsize=8)
        ax.set_xlabel("finished episode (write order)", fontsize=8)
        ax.set_title(f"{label[code]}: {len(s)} finished episodes, success rolling mean over {k}", fontsize=9)
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
        xlabel, ylabel = _goal_axes(gkey, g.shape[1], label[code])
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.set_title(f"{label[code]}: {len(rows)} rows", fontsize=9)
        ax.legend(loc="best", fontsize=7, markerscale=3)
    fig.suptitle(c["title"])
    fig.tight_layout()
    return fig


def _goal_axes(gkey: Any, goal_dim: int, env_name: str) -> tuple[str, str]:
    """The words on the goal scatter's axes: which goal, which dimension, and metres for Fetch / Hand goals."""
    name = "achieved goal" if "achieved_goal" in (gkey if isinstance(gkey, tuple) else (gkey,)) else "goal"
    column = "/".join(gkey) if isinstance(gkey, tuple) else str(gkey)
    unit = " (m)" if env_name.startswith(_METRE_ENVS) else ""
    x = f"{name} x{unit}, {column}[0]"
    y = f"{name} y{unit}, {column}[1]" if goal_dim > 1 else "(one-dimensional goal: drawn at 0)"
    return x, y


def _save(fig, path: str) -> str:
    """Writes ``fig`` to ``path`` through a hidden sibling: a failed write (a full disk) leaves no half PNG."""
    tmp = partial_path(path)
    try:
        fig.savefig(tmp, dpi=110, format="png")
        os.replace(tmp, path)
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="the memory (opened read-only)")
    parser.add_argument("--out", default=".", help="directory for the PNG files (default: the current directory)")
    parser.add_argument("--window", type=int, default=None,
                        help="episodes in the rolling success mean (default: min(50, max(1, episodes // 10)) per env)")
    parser.add_argument("--max-points", type=int, default=20_000, help="rows in the goal scatter, at most")


def run(args: argparse.Namespace) -> int:
    if (args.window is not None and args.window < 1) or args.max_points < 1:
        raise CLIError(f"--window and --max-points must be >= 1, got {args.window} and {args.max_points}")
    try:
        import matplotlib  # noqa: F401
    except ImportError as err:
        raise CLIError(f"robotmem plot needs matplotlib ({err}): pip install 'torchrl_robotmem[plots]'") from err
    for path in plot_memory(args.path, args.out, window=args.window, max_points=args.max_points):
        print(path)
    return 0
