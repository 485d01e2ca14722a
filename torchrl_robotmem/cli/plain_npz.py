"""A plain ``.npz`` of transitions (any tool's, no ``__robotmem__`` record) into a new memory.

One row per transition, rows in time order, episodes contiguous. Arrays
(``N`` rows each; a flag or reward may be ``[N]`` or ``[N, 1]``):

=====================================  ========  ==================================================
array                                  needed    stored as
=====================================  ========  ==================================================
``observation``, ``next_observation``  yes       ``observation``, ``("next", "observation")``
``action``                             yes       ``action``
``reward``                             yes       ``("next", "reward")`` ``[N, 1]`` float32
``terminated`` / ``truncated`` /       one of    ``("next", "terminated" | "truncated" | "done")``;
``done`` / ``episode``                 them      ``episode`` (ids): a new episode where the id changes
``achieved_goal``,                     together  ``achieved_goal``, ``("next", "achieved_goal")``,
``next_achieved_goal``,                          ``desired_goal`` and ``("next", "desired_goal")``
``desired_goal``                                 (``next_desired_goal`` if given, else ``desired_goal``)
``is_success``                         no        ``("next", "is_success")``: success after the step;
                                                 without it, recomputed from ``--env``'s ``compute_reward``
=====================================  ========  ==================================================

An episode end with neither ``terminated`` nor ``truncated`` set (a ``done``
or an ``episode`` change alone) is stored as truncated; the last row always
ends an episode. Other arrays are ignored (and named, not read). The file is read with
``allow_pickle=False``, and only after the headers of the arrays read are
checked against the file and what the import allocates (the arrays, the RAM
mirror of ``max_size`` rows) against the memory left (:mod:`._archive`).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ._archive import check_fits, inspect_npz, read_member
from .errors import CLIError
from .transitions import cast_float64, episode_flags, success_from_env, write_transitions

__all__ = ["PLAIN_KEYS", "import_plain_npz", "plain_columns"]

#: every array a plain npz may hold
PLAIN_KEYS = ("observation", "next_observation", "action", "reward", "terminated", "truncated", "done", "episode",
              "achieved_goal", "next_achieved_goal", "desired_goal", "next_desired_goal", "is_success")
_GOALS = ("achieved_goal", "next_achieved_goal", "desired_goal")
_ENDS = ("terminated", "truncated", "done", "episode")


def _flag(a: np.ndarray, key: str, src: str, n: int) -> np.ndarray:
    if a.shape not in ((n,), (n, 1)):
        raise CLIError(f"{src!r}: array {key!r} has shape {list(a.shape)}; a plain npz holds it as [{n}] or [{n}, 1]")
    return a.reshape(n)


def plain_columns(arrays: dict[str, np.ndarray], *, src: str, env: str | None = None,
                  notes: list[str] | None = None) -> dict[str, np.ndarray]:
    """The memory's columns (flat keys, ``/`` nesting) of a plain npz's ``arrays``; a :class:`CLIError` names a bad one.

    Args:
        arrays (dict): name -> array, as in the file (an ignored array may be ``None``: not read).

    Keyword Args:
        src (str): the file, named in errors.
        env (str, optional): the env whose ``compute_reward`` recomputes a missing ``is_success``.
        notes (list, optional): what was ignored or recomputed is appended here (one line each).

    Example:
        >>> import numpy as np
        >>> from torchrl_robotmem.cli.plain_npz import plain_columns
        >>> n = 4
        >>> cols = plain_columns({"observation": np.zeros((n, 3)), "next_observation": np.ones((n, 3)),
        ...                       "action": np.zeros((n, 2)), "reward": np.zeros(n), "done": np.arange(n) % 2 == 1},
        ...                      src="x.npz")
        >>> sorted(cols)[:4], cols["next/done"][:, 0].tolist()
        (['action', 'done', 'next/done', 'next/observation'], [False, True, False, True])
    """
    notes = notes if notes is not None else []
    ignored = sorted(k for k in arrays if k not in PLAIN_KEYS)  # named only (the importer does not read them)
    arrays = {k: a for k, a in arrays.items() if k in PLAIN_KEYS}
    missing = [k for k in ("observation", "next_observation", "action", "reward") if k not in arrays]
    if not any(k in arrays for k in _ENDS):
        missing.append("one of " + "/".join(_ENDS))
    goals = [k for k in _GOALS if k in arrays]
    if goals and len(goals) < len(_GOALS):
        missing += [k for k in _GOALS if k not in arrays]
    if missing:
        raise CLIError(f"{src!r} is a plain npz (no '__robotmem__' record) without the arrays {missing}; a plain "
                       f"npz holds {', '.join(PLAIN_KEYS)} (see `robotmem import --help` / docs/cli.md)")
    n = len(arrays["observation"]) if arrays["observation"].ndim else 0
    for key in PLAIN_KEYS:
        a = arrays.get(key)
        if a is not None and (a.ndim == 0 or len(a) != n):
            raise CLIError(f"{src!r}: array {key!r} has shape {list(a.shape)}; every array holds one row per "
                           f"transition ({n}, as 'observation')")
    for key, ref in (("next_observation", "observation"), ("next_achieved_goal", "achieved_goal"),
                     ("next_desired_goal", "desired_goal")):
        if key in arrays and ref in arrays and arrays[key].shape != arrays[ref].shape:
            raise CLIError(f"{src!r}: array {key!r} has shape {list(arrays[key].shape)}, {ref!r} "
                           f"{list(arrays[ref].shape)}: they must match")
    if ignored:
        notes.append(f"ignored arrays not in the plain-npz layout: {', '.join(ignored)}")
    flags = {k: _flag(arrays[k], k, src, n).astype(bool) for k in ("terminated", "truncated", "done") if k in arrays}
    ends = np.zeros(n, bool)
    for f in flags.values():
        ends |= f
    if "episode" in arrays:
        ep = _flag(arrays["episode"], "episode", src, n)
        ends[:-1] |= ep[1:] != ep[:-1]
    term, trunc = episode_flags(ends, flags.get("terminated", np.zeros(n, bool)),
                                flags.get("truncated", np.zeros(n, bool)))
    action = arrays["action"] if arrays["action"].ndim > 1 else arrays["action"].reshape(n, 1)
    cols: dict[str, np.ndarray] = {"observation": arrays["observation"], "action": action,
                                   "done": np.zeros((n, 1), bool), "next/observation": arrays["next_observation"],
                                   "next/reward": _flag(arrays["reward"], "reward", src, n).reshape(n, 1),
                                   "next/terminated": term[:, None], "next/truncated": trunc[:, None],
                                   "next/done": (term | trunc)[:, None]}
    if goals:
        cols.update({"achieved_goal": arrays["achieved_goal"], "desired_goal": arrays["desired_goal"],
                     "next/achieved_goal": arrays["next_achieved_goal"],
                     "next/desired_goal": arrays.get("next_desired_goal", arrays["desired_goal"])})
    if "is_success" in arrays:
        cols["next/is_success"] = _flag(arrays["is_success"], "is_success", src, n).astype(np.float32)
    elif goals and env is not None:
        cols["next/is_success"] = success_from_env(env, cols["next/achieved_goal"], cols["desired_goal"], src=src)
        notes.append(f"is_success recomputed from {env}'s compute_reward for {n:,} rows")
    else:
        notes.append("no is_success stored (the file has none" + ("; pass --env ENV_ID to recompute it from the "
                                                                   "env's compute_reward)" if goals else ")"))
    if cols["next/reward"].dtype != np.float64:
        cols["next/reward"] = cols["next/reward"].astype(np.float32)
    return cols


def _check_fits(members: dict, src: str, max_size: int | None, keep_float64: bool) -> None:
    """The arrays read and the new memory's RAM mirror (``max_size`` rows) against the memory left."""
    obs = members.get("observation")
    n = obs.shape[0] if obs is not None and obs.shape else 0

    def per_row(m) -> int:
        return m.row_bytes(4 if m.dtype == np.float64 and not keep_float64 else None)

    row = sum(per_row(m) for m in members.values()) + 64  # + flags, tags and is_success
    if "desired_goal" in members and "next_desired_goal" not in members:
        row += per_row(members["desired_goal"])  # stored twice: at the root and under next
    capacity = int(max_size or n)
    check_fits(members, src, capacity * row, capacity, "--max-size" if max_size else "")


def import_plain_npz(data, src: str, path: str, *, max_size: int | None = None, env: str | None = None,
                     keep_float64: bool = False, notes: list[str] | None = None) -> int:
    """Creates the memory ``path`` from the plain npz ``data`` (an open ``NpzFile``); returns its rows.

    Args:
        data: ``np.load(src, allow_pickle=False)``.
        src (str): the file, named in errors.
        path (str): the memory to create (refused if it exists).

    Keyword Args:
        max_size (int, optional): capacity (default: the rows imported).
        env (str, optional): tag every row with this env; recomputes a missing ``is_success``.
        keep_float64 (bool): keep float64 arrays (default: stored as float32).
        notes (list, optional): what was cast, ignored or recomputed is appended here.

    Example:
        >>> import tempfile, numpy as np
        >>> from torchrl_robotmem.cli.plain_npz import import_plain_npz
        >>> d = tempfile.mkdtemp()
        >>> np.savez(d + "/t.npz", observation=np.zeros((6, 3)), next_observation=np.ones((6, 3)),
        ...          action=np.zeros((6, 2)), reward=np.zeros(6), episode=np.repeat([0, 1], 3))
        >>> notes = []
        >>> import_plain_npz(np.load(d + "/t.npz"), d + "/t.npz", d + "/m.zarr", env="FetchReach-v4", notes=notes)
        6
        >>> notes[-1]
        'float64 stored as float32 (--keep-float64 keeps it): action, next/observation, next/reward, observation'
    """
    notes = notes if notes is not None else []
    keys = [k for k in data.files if k in PLAIN_KEYS]
    members = inspect_npz(src, keys)
    not_npy = [k for k in keys if k not in members]
    if not_npy:
        raise CLIError(f"{src!r}: member {not_npy[0]!r} is not an .npy array; the file is damaged or not an npz")
    _check_fits(members, src, max_size, keep_float64)
    arrays: dict[str, Any] = {k: read_member(data, src, k) for k in keys}
    arrays.update({k: None for k in data.files if k not in PLAIN_KEYS})  # named as ignored, never read
    cols = plain_columns(arrays, src=src, env=env, notes=notes)
    cast = cast_float64(cols, keep_float64=keep_float64)
    if cast:
        notes.append(f"float64 stored as float32 (--keep-float64 keeps it): {', '.join(sorted(cast))}")
    return write_transitions(path, cols, capacity=max_size, env=env, src=src, notes=notes)
