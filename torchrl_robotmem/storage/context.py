"""The context a memory needs to be recalled by: a success column and an env name, and the advice when missing.

A stock TorchRL script (``GymEnv("FetchReach-v4")``, no ``env=``) writes rows that
``ZarrStorage`` stores whole, but without ``("next", "is_success")`` and without an
env name: ``recall(success_only=True)``, ``recall(env=...)`` and the success rates of
``robotmem inspect`` / ``plot`` then have nothing to read. This module says so, with
the fix, in one wording: the warning at a store's first write
(:func:`missing_context`, given by ``MemoryStore.register``) and the errors of a
recall that needs the missing column (:func:`success_advice`, :func:`env_advice`).
Rows of an env that has no success flag (MaMuJoCo, any non-goal env) are written
with ``ZarrStorage(..., goal_conditioned=False)``: the success column is then not
asked for (an env name still is).

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem.storage.context import missing_context
    >>> rows = TensorDict({"observation": torch.zeros(2, 3)}, [2])
    >>> print(missing_context(rows, torch.full((2,), -1), "m.zarr").splitlines()[0])
    ZarrStorage at 'm.zarr': the rows written have no ('next', 'is_success') column and no env name, so:
    >>> missing_context(rows.set(("next", "is_success"), torch.ones(2)), torch.zeros(2), "m.zarr") is None
    True
    >>> missing_context(rows.exclude("next"), torch.zeros(2), "m.zarr", goal_conditioned=False) is None
    True
"""
from __future__ import annotations

import inspect
import os
from typing import Any

import torch
from tensordict import TensorDictBase

from .tags import UNKNOWN_ENV

__all__ = ["SUCCESS_KEY", "env_advice", "missing_context", "success_advice", "user_stacklevel"]

#: The success column read by ``recall(success_only=True)``, the summary and ``robotmem plot``.
SUCCESS_KEY = ("next", "is_success")

_SUCCESS_FIX = (
    "build the env with torchrl_robotmem.make_env('FetchReach-v4') (it reads is_success from the step "
    "info), or on your own torchrl GymEnv call env.set_info_dict_reader(default_info_dict_reader(['is_success'])) "
    "(from torchrl.envs import default_info_dict_reader)"
)
_ENV_FIX = (
    "name the env of the rows with ZarrStorage(path, ..., env='FetchReach-v4') (RobotMemory(path, env=...); or "
    "storage.env = 'FetchReach-v4' "
    "before writing)"
)


def success_advice() -> str:
    """How to get a ``("next", "is_success")`` column into the rows written from now on."""
    return f"To record it, {_SUCCESS_FIX}."


def env_advice() -> str:
    """How to tag the rows written from now on with an env name."""
    return f"To record it, {_ENV_FIX}."


def missing_context(rows: TensorDictBase, env: torch.Tensor | None, path: Any, *,
                    goal_conditioned: bool = True) -> str | None:
    """The warning for rows written without a success column or an env name, or ``None`` if they have both.

    Args:
        rows (TensorDictBase): the rows of a write (TensorDict data).
        env (torch.Tensor or None): their env codes (``-1``: no env name); ``None`` for data without tags.
        path: the store, named in the message.

    Keyword Args:
        goal_conditioned (bool, optional): the rows come from a goal env, which has a success flag to
            record. ``False`` (``ZarrStorage(..., goal_conditioned=False)``: MaMuJoCo, any env without
            one): a missing success column is not reported. Defaults to ``True``.
    """
    if env is None:
        return None
    no_success = goal_conditioned and rows.get(SUCCESS_KEY, None) is None
    no_env = bool((torch.as_tensor(env) == UNKNOWN_ENV).any())
    if not (no_success or no_env):
        return None
    what = " and ".join(w for w, missing in ((f"no {SUCCESS_KEY} column", no_success), ("no env name", no_env))
                        if missing)
    lost = [line for line, missing in (
        ("  - recall(success_only=True), the success rates of `robotmem inspect` / `robotmem plot` and "
         "success-filtered sampling have no success flag to read;", no_success),
        ("  - recall(env=...) and cross-env filters cannot tell this env's rows apart;", no_env)) if missing]
    fixes = [fix for fix, missing in ((_SUCCESS_FIX, no_success), (_ENV_FIX, no_env)) if missing]
    return "\n".join([
        f"ZarrStorage at {str(path)!r}: the rows written have {what}, so:", *lost,
        "The rows are stored all the same. To keep that context: " + "; and ".join(fixes) + ". "
        "docs/swap.md shows both for a stock TorchRL script. (Said once per storage, at its first write.)",
        *(["An env without a success flag (MaMuJoCo, any env that is not goal-conditioned): "
           "ZarrStorage(path, ..., goal_conditioned=False) says so, and this is not asked again."] if no_success else []),
    ])


def user_stacklevel() -> int:
    """The ``stacklevel`` of a ``warnings.warn`` made by the caller that points at the first frame outside
    torchrl, tensordict and this package (the user's ``rb.extend`` line), so the warning names it."""
    import tensordict
    import torchrl

    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # torchrl_robotmem/
    roots = tuple(d + os.sep for d in (os.path.dirname(torchrl.__file__), os.path.dirname(tensordict.__file__), package))
    frame, level = inspect.currentframe(), 0
    while frame is not None and (level < 2 or frame.f_code.co_filename.startswith(roots)):
        frame, level = frame.f_back, level + 1
    return max(level, 1)
