"""Print what a memory holds: rows, episodes, runs, envs, success rates, goal coverage, size, schema.

``robotmem inspect PATH [--json] [--cell 0.05] [--goal-key next/achieved_goal]``.
The memory is opened read-only (no writer lock): it can be inspected while a
writer process appends to it. :func:`summarize` is the same summary as a dict.
"""
from __future__ import annotations

import argparse
import json
import math
import os
from typing import Any

import numpy as np

from ._memory import (
    DONE_KEY,
    SUCCESS_KEY,
    flat_column,
    goal_key,
    has_key,
    is_full,
    open_memory,
    root_attrs,
)

__all__ = ["summarize", "add_arguments", "run"]


def summarize(path: Any, *, cell: float = 0.05, goal: str | None = None) -> dict[str, Any]:
    """The summary of a memory as a JSON-serialisable dict.

    Episode success is read at the last row of each finished episode (``("next",
    "done")``): ``("next", "is_success") > 0.5``. Episodes still open (a writer
    mid-episode, or the oldest episode cut by a full ring) are counted in
    ``episodes`` but not in the success rates. Goal coverage is reported on
    the achieved goals of every row: per-dimension min / max and the number of
    occupied cells of a grid of side ``cell`` (in goal units; 0.05 is Fetch's
    success threshold, 5 cm).

    Args:
        path (str or os.PathLike or ZarrStorage): the memory (a store path or URL,
            opened read-only), or an open :class:`~torchrl_robotmem.ZarrStorage`.

    Keyword Args:
        cell (float): side of the coverage grid's cells. Defaults to 0.05.
        goal (str, optional): the achieved-goal column (``"next/achieved_goal"``);
            defaults to ``("next", "achieved_goal")``, else ``"achieved_goal"``.

    Returns:
        a dict with ``path``, ``format``, ``rows``, ``max_size``, ``episodes``,
        ``runs``, ``envs`` (per env: rows, episodes, success), ``per_run``,
        ``success``, ``goal_coverage``, ``bytes_on_disk`` and ``schema``.

    Raises:
        CLIError: when ``path`` is not a torchrl_robotmem memory.

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.cli.inspect import summarize
        >>> path = tempfile.mkdtemp() + "/m.zarr"
        >>> st = ZarrStorage(path, 100, env="FetchReach-v4", background=False)
        >>> done = torch.tensor([False, True, False, True]).unsqueeze(-1)
        >>> st.set(slice(0, 4), TensorDict({"next": {"done": done, "is_success": torch.tensor([0.0, 1.0, 0.0, 0.0]),
        ...     "achieved_goal": torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.5, 0.5, 0.5], [0.5, 0.5, 0.6]])}}, [4]))
        >>> st.close()
        >>> s = summarize(path)
        >>> s["rows"], s["episodes"], s["success"]["episode_success_rate"], s["goal_coverage"]["cells"]
        (4, 2, 0.5, 3)
        >>> s["envs"][0]["name"], s["envs"][0]["episodes"]
        ('FetchReach-v4', 2)
    """
    if not (math.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be a finite size > 0, got {cell}.")
    from torchrl_robotmem.storage import ZarrStorage

    storage = path if isinstance(path, ZarrStorage) else open_memory(path)
    try:
        return _summarize(storage, cell=cell, goal=goal)
    finally:
        if storage is not path:
            storage.close()


def _summarize(storage, *, cell: float, goal) -> dict[str, Any]:
    from torchrl_robotmem.storage import store_size_bytes
    from torchrl_robotmem.storage.format import FORMAT_MARKER

    attrs = root_attrs(storage)
    schema = attrs.get("schema") or {}
    env_names = list(storage.env_names)
    out: dict[str, Any] = {
        "path": str(storage.path),
        "format": attrs.get(FORMAT_MARKER),
        "kind": (attrs.get("kind") or {}).get("kind", "tensordict") if schema else None,
        "ndim": int(attrs.get("ndim", 1)),
        "rows": len(storage),
        "max_size": int(storage.max_size) if storage.bounded else None,  # None: no declared capacity (grows)
        "capacity": int(storage.capacity),
        "full": bool(is_full(storage)),
        "write_count": int(attrs.get("write_count", 0)),
        "chunk_rows": attrs.get("chunk_rows"),
        "journal_pending": bool(attrs.get("journal")),
        "env_names": env_names,
        "episodes": 0,
        "finished_episodes": 0,
        "runs": 0,
        "envs": [],
        "per_run": [],
        "success": None,
        "goal_coverage": None,
        "bytes_on_disk": store_size_bytes(storage.local_dir),
        "schema": _schema(storage, schema),
    }
    if not len(storage) or not has_key(storage, "episode"):
        return out
    episode = flat_column(storage, "episode")
    # len counts the elements of the first ndim dims; items stored whole (ndim < batch dims) count once
    n = len(storage) if storage.ndim == storage.view().get("episode").ndim else len(episode)
    episode, run, env = episode[:n], flat_column(storage, "run")[:n], flat_column(storage, "env")[:n]
    done = flat_column(storage, DONE_KEY)[:n].reshape(n, -1).any(-1) if has_key(storage, DONE_KEY) else None
    success = flat_column(storage, SUCCESS_KEY)[:n].reshape(n, -1)[:, 0] > 0.5 if has_key(storage, SUCCESS_KEY) else None
    ends = np.flatnonzero(done) if done is not None else np.zeros(0, dtype=np.int64)

    out["episodes"] = int(len(np.unique(episode)))
    out["finished_episodes"] = int(len(np.unique(episode[ends])))
    out["runs"] = int(len(np.unique(run)))
    if success is not None:
        out["success"] = {
            "transition_success_rate": float(success.mean()),
            "episode_success_rate": float(success[ends].mean()) if len(ends) else None,
            "successful_episodes": int(success[ends].sum()),
        }

    def group(mask: np.ndarray) -> dict[str, Any]:
        rows = int(mask.sum())
        e = ends[mask[ends]]
        g = {"rows": rows, "episodes": int(len(np.unique(episode[mask]))), "finished_episodes": int(len(e))}
        if success is not None:
            g["episode_success_rate"] = float(success[e].mean()) if len(e) else None
            g["transition_success_rate"] = float(success[mask].mean()) if rows else None
        return g

    for code in np.unique(env):
        name = env_names[code] if 0 <= code < len(env_names) else None
        out["envs"].append({"code": int(code), "name": name, **group(env == code)})
    for r in np.unique(run):
        mask = run == r
        names = [env_names[c] if 0 <= c < len(env_names) else None for c in np.unique(env[mask])]
        out["per_run"].append({"run": int(r), "envs": names, **group(mask)})

    gkey = goal_key(storage, goal)
    if gkey is not None:
        goals = flat_column(storage, gkey)[:n].reshape(n, -1).astype(np.float64)
        out["goal_coverage"] = _coverage(goals, cell, gkey)
        for entry in out["envs"]:
            entry["goal_coverage"] = _coverage(goals[env == entry["code"]], cell, gkey)
    return out


def _coverage(goals: np.ndarray, cell: float, key) -> dict[str, Any]:
    finite = goals[np.isfinite(goals).all(-1)]
    cov: dict[str, Any] = {"key": "/".join(key) if isinstance(key, tuple) else key, "dims": int(goals.shape[-1]),
                           "cell": cell, "min": None, "max": None, "cells": 0}
    if len(finite):
        cov["min"] = finite.min(0).tolist()
        cov["max"] = finite.max(0).tolist()
        scaled = np.floor(finite.astype(np.float64) / cell)
        if not (np.isfinite(scaled).all() and np.abs(scaled).max() < 2.0**62):
            raise ValueError(f"cell {cell} is too small for goals of magnitude up to {np.abs(finite).max():g}: "
                             f"more cells a side than can be counted; give a larger cell.")
        cov["cells"] = int(len(np.unique(scaled.astype(np.int64), axis=0)))
    return cov


def _schema(storage, schema: dict) -> list[dict[str, Any]]:
    """``[{key, dtype, shape, bytes}]``: ``shape`` per row, ``bytes`` on disk (local stores)."""
    local = storage.local_dir
    out = []
    for path in sorted(schema):
        entry = {"key": path, "dtype": schema[path]["dtype"], "shape": list(schema[path]["shape"])}
        if local is not None:
            entry["bytes"] = _dir_bytes(os.path.join(local, path))
        out.append(entry)
    return out


def _dir_bytes(directory: str) -> int:
    """Bytes of one Zarr array's directory: its ``zarr.json`` and its chunk files (``c.<c>.0``, or ``c/<c>/0`` in
    a store created before 2026-12)."""
    total = 0
    for root, _, files in os.walk(directory):
        total += sum(os.path.getsize(os.path.join(root, f)) for f in files)
    return total


# -- command line ---------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="the memory (a Zarr store directory, *.zip or store URL)")
    parser.add_argument("--json", action="store_true", help="print one JSON object (for scripts)")
    parser.add_argument("--cell", type=float, default=0.05, help="side of the goal coverage grid's cells (default 0.05)")
    parser.add_argument("--goal-key", default=None, help="achieved-goal column, e.g. next/achieved_goal (the default)")


def run(args: argparse.Namespace) -> int:
    from .errors import CLIError

    if not (math.isfinite(args.cell) and args.cell > 0):
        raise CLIError(f"--cell must be a finite size > 0, got {args.cell}")
    try:
        summary = summarize(args.path, cell=args.cell, goal=args.goal_key)
    except ValueError as err:
        if "too small for goals" not in str(err):
            raise
        raise CLIError(f"--cell {args.cell}: {err}") from None
    if args.json:
        print(json.dumps(summary))
    else:
        print(format_summary(summary))
    return 0


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


def _size(n: int | None) -> str:
    if n is None:
        return "unknown (not a local store)"
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def format_summary(s: dict[str, Any]) -> str:
    """The text ``robotmem inspect`` prints for a :func:`summarize` dict."""
    fmt = s.get("format") or {}
    lines = [
        f"memory        {s['path']}",
        f"format        v{fmt.get('format_version')} (torchrl_robotmem {fmt.get('library_version')}, "
        f"torchrl {fmt.get('torchrl_version')}, zarr {fmt.get('zarr_version')})",
        (f"rows          {s['rows']:,} of {s['max_size']:,}{' (full ring)' if s['full'] else ''}; "
         if s["max_size"] is not None else
         f"rows          {s['rows']:,} (no declared capacity: grows; {s.get('capacity', 0):,} allocated); ")
        +
        f"{s['write_count']:,} written; chunk {s['chunk_rows']} rows",
        f"episodes      {s['episodes']:,} ({s['finished_episodes']:,} finished)",
        f"runs          {s['runs']}",
        f"size on disk  {_size(s['bytes_on_disk'])}",
    ]
    if s["journal_pending"]:
        lines.append("journal       pending (a writer is mid-commit, or crashed: the next writer replays it)")
    if s["success"]:
        lines.append(
            f"success       {_pct(s['success']['episode_success_rate'])} of finished episodes "
            f"({s['success']['successful_episodes']:,}); {_pct(s['success']['transition_success_rate'])} of rows"
        )
    if s["envs"]:
        lines.append("")
        lines.append(f"{'env':<28} {'rows':>10} {'episodes':>9} {'success':>8}  goal cells")
        for e in s["envs"]:
            cov = e.get("goal_coverage") or {}
            lines.append(f"{e['name'] or '(unknown)':<28} {e['rows']:>10,} {e['episodes']:>9,} "
                         f"{_pct(e.get('episode_success_rate')):>8}  {cov.get('cells', '-')}")
    if s["per_run"]:
        lines.append("")
        lines.append(f"{'run':>4} {'env':<28} {'rows':>10} {'episodes':>9} {'success':>8}")
        for r in s["per_run"]:
            envs = ",".join(x or "(unknown)" for x in r["envs"])
            lines.append(f"{r['run']:>4} {envs:<28} {r['rows']:>10,} {r['episodes']:>9,} "
                         f"{_pct(r.get('episode_success_rate')):>8}")
    cov = s["goal_coverage"]
    if cov and cov["min"] is not None:
        lines.append("")
        lines.append(f"goal coverage ({cov['key']}, {cov['dims']}-d): {cov['cells']:,} occupied cells of side {cov['cell']:g}")
        lo = ", ".join(f"{x:.3f}" for x in cov["min"])
        hi = ", ".join(f"{x:.3f}" for x in cov["max"])
        lines.append(f"  min [{lo}]")
        lines.append(f"  max [{hi}]")
    if s["schema"]:
        lines.append("")
        lines.append(f"{'key':<32} {'dtype':<8} {'shape':<10} {'on disk':>12}")
        for k in s["schema"]:
            size = _size(k["bytes"]) if "bytes" in k else "-"
            lines.append(f"{k['key']:<32} {k['dtype']:<8} {str(k['shape']):<10} {size:>12}")
    return "\n".join(lines)
