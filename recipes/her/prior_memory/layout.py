"""What a run reads from a prior memory, checked against its own task before training; and each prior's summary.

A prior memory recorded from a raw Gymnasium-Robotics env, or imported from
Minari or SB3, keeps float64 observations and goals, where the run's env (and
its own memory) holds float32: without a cast the actor fails deep in its first
layer (``mat1 and mat2 must have the same dtype``). :func:`check_prior_layout`
compares every key a batch reads (:data:`~.mix.TRANSITION_KEYS`) of a prior
with one transition of the run's task:

* a floating-point key stored with another floating dtype (float64, float16)
  is cast to the run's dtype when its rows are read (:func:`cast_rows`), with
  one printed line naming the key and both dtypes;
* anything else that differs (a missing key, another shape, an integer or bool
  column where the run reads floats, a float flag where it reads bool) is
  refused with an error naming the prior, the key, and what was expected and found.
"""
from __future__ import annotations

import math

from tensordict import TensorDictBase

__all__ = ["cast_rows", "check_prior_layout", "describe_prior", "key_name", "prior_summary"]


def key_name(key) -> str:
    """A (nested) key as the store's schema names it: ``("next", "done")`` is ``next/done``."""
    return key if isinstance(key, str) else "/".join(key)


def check_prior_layout(storage, example: TensorDictBase, keys: list, env_name: str = "this task",
                       log=print) -> dict:
    """Checks the keys, shapes and dtypes of a prior memory against one transition of the run's task.

    Args:
        storage: the prior memory (a read-only :class:`~torchrl_robotmem.ZarrStorage`), with rows.
        example (TensorDictBase): one transition (or a batch) of the run's task, e.g. ``env.fake_tensordict()``.
        keys (list): the keys the run reads from the prior's rows.
        env_name (str): the run's task, for the error message.
        log: where the cast notes go (one line a cast key); ``None``: nowhere.

    Returns:
        ``{key: dtype}``: the run's dtype of each key, for :func:`cast_rows` (only the keys that need a cast).

    Raises:
        ValueError: naming the prior, and for each key at fault what was expected and found.

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> prior = ZarrStorage(tempfile.mkdtemp() + "/p.zarr", max_size=4, env="FetchReach-v4")
        >>> prior.set(range(2), TensorDict({"observation": torch.zeros(2, 3, dtype=torch.float64),
        ...                                 ("next", "is_success"): torch.zeros(2)}, [2]))
        >>> run = TensorDict({"observation": torch.zeros(1, 3)}, [1])
        >>> check_prior_layout(prior, run, ["observation"], log=None)
        {'observation': torch.float32}
        >>> check_prior_layout(prior, TensorDict({"observation": torch.zeros(1, 4)}, [1]), ["observation"])
        Traceback (most recent call last):
        ...
        ValueError: the prior memory ... (missing []; shapes ['observation: expected torch.float32 [4], found torch.float64 [3]']): ...
    """
    path = getattr(storage, "path", storage)
    if not len(storage):
        raise ValueError(f"the prior memory {path!r} holds no transitions.")
    row = storage[0:1]
    have = set(row.keys(True, True))
    missing = [key_name(k) for k in keys if k not in have]
    shapes, dtypes, casts = [], [], {}
    for key in keys:
        if key not in have or key not in example.keys(True, True):
            continue
        got, want = row.get(key), example.get(key)
        got_shape, want_shape = list(got.shape[1:]), list(want.shape[example.batch_dims:])
        name = key_name(key)
        if got_shape != want_shape:
            shapes.append(f"{name}: expected {want.dtype} {want_shape}, found {got.dtype} {got_shape}")
        elif got.dtype != want.dtype:
            if got.dtype.is_floating_point and want.dtype.is_floating_point:
                casts[key] = want.dtype
            else:
                dtypes.append(f"{name}: expected {want.dtype} {want_shape}, found {got.dtype} {got_shape}")
    if missing or shapes:
        raise ValueError(
            f"the prior memory {path!r} was written for another observation layout than {env_name}'s "
            f"(missing {missing}; shapes {shapes}{'; dtypes ' + str(dtypes) if dtypes else ''}): e.g. FetchReach's "
            "10-d observation vs FetchPush's 25-d. Use memories of tasks with the same layout."
        )
    if dtypes:
        raise ValueError(
            f"the prior memory {path!r} holds columns of another dtype than {env_name}'s that cannot be cast "
            f"safely: {dtypes}. Only floating-point columns are cast (e.g. float64 -> float32); convert the "
            "others when writing the memory (flags such as done as bool, observations as floats)."
        )
    if log is not None:
        for key, dtype in casts.items():
            log(f"prior memory {path}: {key_name(key)} is stored as {row.get(key).dtype}, "
                f"cast to {dtype} (this run's) when read")
    return casts


def cast_rows(rows: TensorDictBase, dtypes: dict | None) -> TensorDictBase:
    """``rows`` with each key of ``dtypes`` it holds cast to that dtype (in place; returns ``rows``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> rows = TensorDict({"observation": torch.zeros(2, 3, dtype=torch.float64)}, [2])
        >>> cast_rows(rows, {"observation": torch.float32})["observation"].dtype
        torch.float32
    """
    for key, dtype in (dtypes or {}).items():
        value = rows.get(key, None)
        if value is not None and value.dtype != dtype:
            rows.set(key, value.to(dtype))
    return rows


def prior_summary(storage) -> dict:
    """A prior memory's path, rows, episodes and success rate (``None`` when it records no success).

    The success rate is that of its finished episodes (``("next", "is_success")`` at each episode's
    last step, from ``ZarrStorage.summary``); ``success_column`` says whether the memory has one.

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> prior = ZarrStorage(tempfile.mkdtemp() + "/p.zarr", max_size=4, env="FetchReach-v4")
        >>> prior.set(range(2), TensorDict({"observation": torch.zeros(2, 3),
        ...                                 ("next", "is_success"): torch.tensor([0.0, 1.0]),
        ...                                 ("next", "done"): torch.tensor([[False], [True]])}, [2]))
        >>> s = prior_summary(prior)
        >>> s["rows"], s["episodes"], s["success_rate"], s["success_column"]
        (2, 1, 1.0, True)
    """
    info = storage.summary() if hasattr(storage, "summary") else {"rows": len(storage)}
    rate = info.get("episode_success_rate")
    return {
        "path": str(getattr(storage, "path", "")),
        "rows": int(info.get("rows", len(storage))),
        "episodes": int(info.get("episodes", 0)),
        "success_rate": None if rate is None or math.isnan(rate) else round(float(rate), 4),
        "success_column": rate is not None,
    }


def describe_prior(summary: dict) -> str:
    """One line for :func:`prior_summary`'s dict.

    Example:
        >>> describe_prior({"path": "p.zarr", "rows": 100, "episodes": 2, "success_rate": None,
        ...                 "success_column": False})
        'prior memory p.zarr: 100 rows, 2 episodes, success rate n/a (no next/is_success column)'
    """
    rate = (f"success rate {summary['success_rate']:.2f}" if summary["success_rate"] is not None
            else "success rate n/a (no next/is_success column)")
    return f"prior memory {summary['path']}: {summary['rows']} rows, {summary['episodes']} episodes, {rate}"

