"""A Stable-Baselines3 replay buffer (``model.save_replay_buffer(path)``) into a new memory.

The file is a pickle of a ``ReplayBuffer``, ``DictReplayBuffer`` or
``HerReplayBuffer``: loading it **executes code from the file**, so
:func:`import_sb3` refuses unless ``trust_pickle`` (``--trust-pickle``) says
the file is one you made yourself. Nothing else in torchrl_robotmem unpickles.

SB3 keeps ``[buffer_size, n_envs, ...]`` arrays filled as a ring up to
``pos`` (``full``: every slot, the oldest at ``pos``). Each env's rows are
read oldest first and written one env after the other, so every episode is
contiguous. Fields map to the memory's layout (the rows
:func:`~torchrl_robotmem.envs.make_env` gives):

* ``observations[k]`` / ``next_observations[k]`` -> ``k`` / ``("next", k)``
  (``observation``, ``achieved_goal``, ``desired_goal`` of a goal env; a
  ``Box`` observation becomes ``observation``). SB3 stores the raw
  observations (with ``VecNormalize``, the unnormalised ones) and, at an
  episode end, the true final observation as the next one;
* ``actions`` -> ``action``; ``rewards`` -> ``("next", "reward")`` ``[1]``;
* ``dones`` and ``timeouts`` -> ``("next", "terminated")`` (done, not a
  time-out) and ``("next", "truncated")`` (a time-out), ``("next", "done")``;
* episode ends: where ``ep_start`` changes (``HerReplayBuffer``), else the
  ``dones``; an episode still open at the newest row ends there, truncated;
* ``("next", "is_success")``: the ``infos``' ``is_success`` when the buffer
  kept them (``HerReplayBuffer(copy_info_dict=True)``), else recomputed from
  the env's ``compute_reward`` (``env``, ``--env``; the output says so).

float64 observations (Gymnasium-Robotics' own dtype) are stored as float32
unless ``keep_float64``.
"""
from __future__ import annotations

import os
import pickle
from typing import Any

import numpy as np

from ._build import check_target
from .errors import CLIError
from .transitions import cast_float64, episode_flags, success_from_env, write_transitions

__all__ = ["PICKLE_REFUSAL", "import_sb3", "load_sb3_buffer", "sb3_columns"]

#: why an SB3 buffer is not loaded without ``--trust-pickle``
PICKLE_REFUSAL = ("is an SB3 replay buffer, a pickle: loading it executes code stored in the file. Pass "
                  "--trust-pickle only for files you made yourself (or trust as much as a program you run); "
                  "nothing was created")


def load_sb3_buffer(src: str, *, trust_pickle: bool = False):
    """Unpickles the SB3 replay buffer ``src``, only when ``trust_pickle``; else a :class:`CLIError` saying why.

    Args:
        src (str): the ``.pkl`` written by ``model.save_replay_buffer``.

    Keyword Args:
        trust_pickle (bool): the file is yours: unpickling it (running its code) is fine.

    Example:
        >>> from torchrl_robotmem.cli import CLIError
        >>> from torchrl_robotmem.cli.sb3_io import load_sb3_buffer
        >>> try:
        ...     load_sb3_buffer("buffer.pkl")
        ... except CLIError as err:
        ...     print(str(err)[:60])
        'buffer.pkl' is an SB3 replay buffer, a pickle: loading it e
    """
    if not trust_pickle:
        raise CLIError(f"{src!r} {PICKLE_REFUSAL}")
    if not os.path.isfile(src):
        raise CLIError(f"{src!r} is not a file")
    from stable_baselines3.common.buffers import ReplayBuffer

    try:
        with open(src, "rb") as f:
            buf = pickle.load(f)  # noqa: S301 - only with --trust-pickle, see PICKLE_REFUSAL
    except Exception as err:  # noqa: BLE001 - whatever a damaged or foreign pickle raises: one line
        raise CLIError(f"{src!r} cannot be loaded as an SB3 replay buffer ({type(err).__name__}: {err})") from None
    if not isinstance(buf, ReplayBuffer):
        raise CLIError(f"{src!r} holds a {type(buf).__name__}, not an SB3 ReplayBuffer / DictReplayBuffer / "
                       f"HerReplayBuffer (write it with model.save_replay_buffer(path))")
    if getattr(buf, "optimize_memory_usage", False):
        raise CLIError(f"{src!r} was saved with optimize_memory_usage=True (no next observations stored); "
                       f"import buffers made without it")
    return buf


def _order(buf) -> np.ndarray:
    """The buffer's filled slots, oldest first."""
    if buf.full:
        return np.r_[buf.pos:buf.buffer_size, 0:buf.pos]
    return np.arange(buf.pos)


def _env_columns(buf, e: int, order: np.ndarray) -> tuple[dict[str, np.ndarray], bool]:
    """The columns of env ``e``'s rows (oldest first) and whether its newest episode was still open."""
    obs = buf.observations if isinstance(buf.observations, dict) else {"observation": buf.observations}
    nxt = buf.next_observations if isinstance(buf.next_observations, dict) else {"observation": buf.next_observations}
    n = len(order)
    dones = buf.dones[order, e] > 0.5
    timeouts = buf.timeouts[order, e] > 0.5
    ends = dones.copy()
    if hasattr(buf, "ep_start"):  # HerReplayBuffer: a new episode where ep_start changes
        start = buf.ep_start[order, e]
        ends[:-1] |= start[1:] != start[:-1]
    still_open = bool(n) and not ends[-1]
    term, trunc = episode_flags(ends, dones & ~timeouts, timeouts)
    action = buf.actions[order, e]
    cols = {"action": action.reshape(n, -1), "done": np.zeros((n, 1), bool),
            "next/reward": buf.rewards[order, e].astype(np.float32).reshape(n, 1),
            "next/terminated": term[:, None], "next/truncated": trunc[:, None], "next/done": (term | trunc)[:, None]}
    for k in obs:
        cols[k] = obs[k][order, e]
        cols[f"next/{k}"] = nxt[k][order, e]
    infos = getattr(buf, "infos", None)
    if infos is not None and n and all("is_success" in i for i in infos[order, e]):
        cols["next/is_success"] = np.array([float(i["is_success"]) for i in infos[order, e]], np.float32)
    return cols, still_open


def sb3_columns(buf, *, src: str, env: str | None = None, notes: list[str] | None = None) -> dict[str, np.ndarray]:
    """The memory's columns (flat keys, ``/`` nesting) of the SB3 buffer ``buf``, env after env, oldest first.

    Args:
        buf: an SB3 ``ReplayBuffer`` (``DictReplayBuffer``, ``HerReplayBuffer``).

    Keyword Args:
        src (str): the file, named in errors and notes.
        env (str, optional): the env whose ``compute_reward`` recomputes ``is_success``
            when the buffer kept none (needed then for a goal env's buffer).
        notes (list, optional): what was recomputed or closed is appended here (one line each).
    """
    notes = notes if notes is not None else []
    order = _order(buf)
    parts, still_open = [], []
    for e in range(buf.n_envs):
        cols, open_ = _env_columns(buf, e, order)
        parts.append(cols)
        if open_:
            still_open.append(e)
    keys = set.intersection(*(set(p) for p in parts)) if parts else set()
    cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k in keys} if parts else {}
    n = len(cols.get("action", ()))
    if still_open:
        notes.append(f"the newest episode of env {', '.join(map(str, still_open))} was still running: "
                     f"stored as truncated at its last row")
    if "next/is_success" not in cols and {"desired_goal", "next/achieved_goal"} <= set(cols):
        cols["next/is_success"] = success_from_env(env, cols["next/achieved_goal"], cols["desired_goal"], src=src)
        notes.append(f"is_success recomputed from {env}'s compute_reward for {n:,} rows (the buffer's infos "
                     f"kept none)")
    elif "next/is_success" in cols:
        notes.append(f"is_success from the buffer's infos for {n:,} rows")
    else:
        notes.append("no is_success stored (the buffer has no goals and its infos kept none)")
    return cols


def import_sb3(src: str, path: str, *, trust_pickle: bool = False, max_size: int | None = None,
               env: str | None = None, keep_float64: bool = False, notes: list[str] | None = None) -> int:
    """Creates the memory ``path`` from an SB3 replay buffer file; returns its rows (see the module docstring).

    Refused, creating nothing, without ``trust_pickle``: loading the file
    unpickles it, which executes code from the file.

    Args:
        src (str): the ``.pkl`` written by ``model.save_replay_buffer(path)``.
        path (str): the memory to create (refused if it exists).

    Keyword Args:
        trust_pickle (bool): ``--trust-pickle``: the file is yours.
        max_size (int, optional): capacity (default: the rows imported).
        env (str, optional): tag every row with this env id; recomputes ``is_success``
            from its ``compute_reward`` when the buffer kept none.
        keep_float64 (bool): keep float64 fields (default: stored as float32).
        notes (list, optional): what was cast or recomputed is appended here.

    Example:
        >>> import os, tempfile
        >>> from torchrl_robotmem.cli import CLIError
        >>> from torchrl_robotmem.cli.sb3_io import import_sb3
        >>> d = tempfile.mkdtemp()
        >>> try:
        ...     import_sb3(d + "/buffer.pkl", d + "/m.zarr")
        ... except CLIError as err:
        ...     print("--trust-pickle" in str(err), os.listdir(d))
        True []
    """
    check_target(path)
    buf = load_sb3_buffer(src, trust_pickle=trust_pickle)
    notes = notes if notes is not None else []
    cols: dict[str, Any] = sb3_columns(buf, src=src, env=env, notes=notes)
    cast = cast_float64(cols, keep_float64=keep_float64)
    if cast:
        notes.append(f"float64 stored as float32 (--keep-float64 keeps it): {', '.join(sorted(cast))}")
    return write_transitions(path, cols, capacity=max_size, env=env, src=src, notes=notes)
