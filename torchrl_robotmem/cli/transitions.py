"""Transitions from other tools' data, written into a new memory: what the ``sb3`` and plain-``npz`` imports share.

An importer reads its source into flat numpy columns (nested keys joined with
``/``), one row per transition, episodes contiguous and in time order, and
calls :func:`write_transitions`. The memory gets the layout the recipes and
:func:`~torchrl_robotmem.envs.make_env` rows use: the observation keys
(``observation``, ``achieved_goal``, ``desired_goal``) at the root and under
``next``, ``action``, ``done`` (False), ``("next", "reward")`` ``[1]``,
``("next", "terminated")`` / ``("next", "truncated")`` / ``("next", "done")``
``[1]`` bool and, where known, ``("next", "is_success")`` (float32, per row).

float64 columns are stored as float32 unless ``keep_float64``
(:func:`cast_float64`, which every import calls), and a missing success flag
can be recomputed from the env's own ``compute_reward``
(:func:`success_from_env`).
"""
from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from ._build import new_store, progress
from .errors import CLIError

__all__ = ["cast_float64", "episode_flags", "success_from_env", "write_transitions"]

#: rows per ``extend`` when writing an import (bounded RAM for the tensors built per call)
_CHUNK = 50_000


def cast_float64(columns: dict[str, Any], *, keep_float64: bool = False) -> list[str]:
    """Casts every float64 column of ``columns`` (numpy arrays or tensors) to float32 in place; returns their keys.

    Args:
        columns (dict): key -> array; changed in place.

    Keyword Args:
        keep_float64 (bool): cast nothing (``--keep-float64``).

    Example:
        >>> import numpy as np
        >>> from torchrl_robotmem.cli.transitions import cast_float64
        >>> cols = {"observation": np.zeros((2, 3)), "action": np.zeros((2, 4), np.float32)}
        >>> cast_float64(cols), cols["observation"].dtype
        (['observation'], dtype('float32'))
    """
    if keep_float64:
        return []
    import torch

    cast = []
    for key, value in columns.items():
        if value.dtype in (np.float64, torch.float64):
            columns[key] = value.astype(np.float32) if isinstance(value, np.ndarray) else value.float()
            cast.append(key)
    return cast


def episode_flags(ends: np.ndarray, terminated: np.ndarray, truncated: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(terminated, truncated)`` with every episode end flagged: an end with neither flag is marked truncated.

    The last row always ends an episode (an episode still open in the source
    ends there, truncated), so the storage's episode tags (drawn from
    ``("next", "done")``) match the source's episodes.

    Args:
        ends (np.ndarray): bool ``[N]``, True at the last row of each episode.
        terminated (np.ndarray): bool ``[N]``, the source's terminal flags.
        truncated (np.ndarray): bool ``[N]``, the source's time-limit flags.

    Example:
        >>> import numpy as np
        >>> from torchrl_robotmem.cli.transitions import episode_flags
        >>> z = np.zeros(4, bool)
        >>> term, trunc = episode_flags(np.array([0, 1, 0, 0], bool), z, z)
        >>> term.tolist(), trunc.tolist()
        ([False, False, False, False], [False, True, False, True])
    """
    ends = np.asarray(ends, bool).copy()
    if len(ends):
        ends[-1] = True
    terminated = np.asarray(terminated, bool) & ends
    truncated = (np.asarray(truncated, bool) & ends) | (ends & ~terminated)
    return terminated, truncated


def success_from_env(env: str | None, next_achieved: np.ndarray, desired: np.ndarray, *, src: str) -> np.ndarray:
    """``is_success`` per row (float32 0/1) from the env's ``compute_reward``: the goal reached at ``t + 1``.

    Uses :class:`~torchrl_robotmem.envs.GoalRewardFn` (the unwrapped
    Gymnasium-Robotics env: ``compute_reward(...) == 0`` for sparse ids, its
    ``_is_success`` with the env's ``distance_threshold`` for dense ones),
    evaluated in float64 as the env does.

    Args:
        env (str): the Gymnasium-Robotics env id (``--env``); ``None`` is a
            :class:`CLIError` saying to pass it.
        next_achieved (np.ndarray): ``[N, goal_dim]``, the achieved goal after each step.
        desired (np.ndarray): ``[N, goal_dim]``, the goal pursued.

    Keyword Args:
        src (str): the source, named in errors.
    """
    import torch
    from tensordict import TensorDict

    from torchrl_robotmem.envs import GoalRewardFn

    if env is None:
        raise CLIError(f"{src!r} records no is_success; pass --env ENV_ID (e.g. --env FetchReach-v4) to recompute "
                       f"it from that env's compute_reward")
    try:
        fn = GoalRewardFn(env)
        td = TensorDict({"desired_goal": torch.from_numpy(np.asarray(desired, np.float64)),
                         ("next", "achieved_goal"): torch.from_numpy(np.asarray(next_achieved, np.float64))},
                        [len(desired)])
        return fn.success(td).numpy().astype(np.float32)
    except CLIError:
        raise
    except Exception as err:  # noqa: BLE001 - an unknown id, an env without compute_reward, goals of another size
        raise CLIError(f"--env {env!r}: cannot recompute is_success for {src!r} with that env's compute_reward "
                       f"({type(err).__name__}: {err}); pass the Gymnasium-Robotics id the data came from") from None


def write_transitions(path: str, columns: dict[str, np.ndarray], *, capacity: int | None = None,
                      env: str | None = None, src: str = "", notes: list[str] | None = None) -> int:
    """Creates the memory ``path`` holding ``columns`` (flat keys, ``/`` for nesting), one row per transition.

    Rows must be in time order with each episode contiguous and its last row
    flagged by ``next/done`` (the storage draws its episode tags from it). The
    memory is built beside ``path`` and renamed into place (:func:`~._build.new_store`).

    Args:
        path (str): the memory to create (refused if it exists).
        columns (dict): key -> ``[N, ...]`` array.

    Keyword Args:
        capacity (int, optional): ``max_size`` (default: ``N``).
        env (str, optional): the env name every row is tagged with.
        src (str): the source, named in errors.
        notes (list, optional): without ``env``, a line saying the rows carry no env name is appended here
            (the importers note a missing success flag: the storage's warning is not shown).

    Returns:
        The number of rows written.

    Example:
        >>> import tempfile, numpy as np
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.cli.transitions import write_transitions
        >>> d = tempfile.mkdtemp()
        >>> done = np.array([[False], [True], [False], [True]])
        >>> write_transitions(d + "/m.zarr", {"observation": np.zeros((4, 2), np.float32), "next/done": done})
        4
        >>> ZarrStorage(d + "/m.zarr", read_only=True)["episode"].unique().numel()
        2
    """
    import torch
    from tensordict import TensorDict
    from torchrl.data import ReplayBuffer

    n = len(next(iter(columns.values()))) if columns else 0
    capacity = int(capacity or n)
    if capacity < n:
        raise CLIError(f"--max-size {capacity} is smaller than the {n} rows of {src!r}")
    if n == 0:
        raise CLIError(f"{src!r} holds no transitions: nothing to import")
    nested: dict[str, Any] = {}
    for key, value in columns.items():
        node = nested
        *parents, leaf = key.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = torch.from_numpy(np.ascontiguousarray(value))
    td = TensorDict(nested, batch_size=[n])
    with new_store(path, capacity, background=True, env=env) as storage, warnings.catch_warnings():
        if env is None or "next/is_success" not in columns:  # the notes say it, naming the flag, not the hidden
            warnings.filterwarnings("ignore", message="ZarrStorage at .*: the rows written have no",  # build's path
                                    category=UserWarning)
        rb = ReplayBuffer(storage=storage, batch_size=1)
        try:
            for start in progress(range(0, n, _CHUNK), desc="import", unit="chunk"):
                rb.extend(td[start:start + _CHUNK])
        except (ValueError, TypeError, KeyError, RuntimeError) as err:  # what the storage refuses: a reserved key...
            raise CLIError(f"{src!r}: {err}") from None
        rows = len(storage)
    if env is None and notes is not None:
        notes.append("the rows carry no env name (pass --env ENV_ID to tag them; recall(env=...) and per-env "
                     "statistics need it)")
    return rows
