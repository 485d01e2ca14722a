"""Which stored rows a recall may return: the one filter argument of every reader.

:class:`RowFilter` holds the filters of
:meth:`GoalIndex.search <torchrl_robotmem.goal_index.GoalIndex.search>`,
:func:`~torchrl_robotmem.recall`,
:class:`~torchrl_robotmem.GoalSimilaritySampler`,
:class:`~torchrl_robotmem.RecallTransform` and
:class:`~torchrl_robotmem.RobotMemory`: which rows (``success_only`` / ``env``
/ ``run``) and how a search picks among them (``max_distance``,
``one_per_episode``), checked once, when it is made. Each of those readers
takes ``filter=`` or the same names as keywords and turns them into one
:class:`RowFilter` with :meth:`RowFilter.coerce`. :meth:`RowFilter.resolve`
turns env names into the integer codes of a storage's ``env`` column; the
result, a :class:`FilterKey`, names one filtered view of an index and computes
its membership mask.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numpy as np

from torchrl_robotmem.storage.context import env_advice

__all__ = ["FILTER_KEYWORDS", "FilterKey", "RowFilter"]

#: The keywords every reader accepts in place of ``filter=RowFilter(...)``.
FILTER_KEYWORDS = ("success_only", "env", "run", "max_distance", "one_per_episode")


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


@dataclass(frozen=True)
class RowFilter:
    """Which stored rows a search may return, combined with AND.

    Every reader (:class:`~torchrl_robotmem.GoalIndex`,
    :func:`~torchrl_robotmem.recall`, :class:`~torchrl_robotmem.GoalSimilaritySampler`,
    :class:`~torchrl_robotmem.RecallTransform`, :class:`~torchrl_robotmem.RobotMemory`)
    takes one as ``filter=``, or its fields as keywords (``success_only=True``,
    ...), made into one by :meth:`coerce`. Plain values only, so a Hydra config
    builds it with ``_target_: torchrl_robotmem.goal_index.RowFilter``.

    Args:
        success_only (bool): only rows whose success flag is ``> 0.5``.
            Defaults to ``False``.
        env (str, int or sequence of them, optional): only rows of these envs,
            by name (mapped through the storage's ``env_names``) or integer code
            of the ``env`` column. Defaults to every env.
        run (int or sequence of int, optional): only rows of these runs (the
            ``run`` column). Defaults to every run.
        max_distance (float, optional): only matches at most this far from the
            query goal. Defaults to no limit.
        one_per_episode (bool): the matches come from different episodes (the
            nearest row of each of the nearest episodes; the ``episode``
            column). Defaults to ``False``.

    ``success_only``, ``env`` and ``run`` decide which rows take part (and are
    all that :meth:`GoalIndex.member_rows
    <torchrl_robotmem.goal_index.GoalIndex.member_rows>` and a sampler's
    uniform draws read); ``max_distance`` and ``one_per_episode`` decide which
    of them a search returns.

    Example:
        >>> from torchrl_robotmem.goal_index import RowFilter
        >>> flt = RowFilter(success_only=True, env=["FetchPush-v4", "FetchSlide-v4"])
        >>> flt.env
        ('FetchPush-v4', 'FetchSlide-v4')
        >>> flt.resolve(("FetchPush-v4", "FetchSlide-v4"))
        FilterKey(success_only=True, envs=(0, 1), runs=None)
        >>> RowFilter.coerce(success_only=True, env=["FetchPush-v4", "FetchSlide-v4"]) == flt
        True
        >>> RowFilter.coerce({"max_distance": 0.05})
        RowFilter(max_distance=0.05)
        >>> RowFilter().matches_all
        True
    """

    success_only: bool = False
    env: str | int | Sequence[str | int] | None = None
    run: int | Sequence[int] | None = None
    max_distance: float | None = None
    one_per_episode: bool = False

    def __post_init__(self) -> None:
        _set = object.__setattr__
        _set(self, "success_only", _check_bool(self.success_only, "success_only"))
        _set(self, "one_per_episode", _check_bool(self.one_per_episode, "one_per_episode"))
        env = self.env
        if env is not None:
            items = (env,) if isinstance(env, str) or _is_int(env) else _as_tuple(env, "env")
            if not items or not all(isinstance(e, str) and e or _is_int(e) for e in items):
                raise ValueError(
                    f"env must be a name, a code or a non-empty list of them, got {env!r}."
                )
            _set(self, "env", tuple(e if isinstance(e, str) else int(e) for e in items))
        run = self.run
        if run is not None:
            items = (run,) if _is_int(run) else _as_tuple(run, "run")
            if not items or not all(_is_int(r) for r in items):
                raise ValueError(f"run must be an int or a non-empty list of ints, got {run!r}.")
            _set(self, "run", tuple(int(r) for r in items))
        if self.max_distance is not None:
            _set(self, "max_distance", _check_max_distance(self.max_distance))

    @classmethod
    def coerce(cls, filter: RowFilter | Mapping[str, Any] | None = None, **keywords: Any) -> RowFilter:
        """The one filter of a call: ``filter`` itself, or a filter made of the keywords.

        Args:
            filter (RowFilter, mapping or None): a filter, or a mapping of
                filter keywords (e.g. a Hydra ``DictConfig``).
            **keywords: ``success_only``, ``env``, ``run``, ``max_distance``,
                ``one_per_episode``, as for :class:`RowFilter`. ``None`` (and
                ``False``) mean "not given".

        Raises:
            TypeError: for an unknown keyword (naming it) or a ``filter`` of
                another type.
            ValueError: for a bad value (naming the keyword), or ``filter=``
                together with a keyword.
        """
        if filter is None and not keywords:
            return _NO_FILTER
        for name in keywords:
            if name not in FILTER_KEYWORDS:
                raise TypeError(
                    f"unknown filter keyword {name!r}; the filter keywords are "
                    f"{', '.join(FILTER_KEYWORDS)} (or filter=RowFilter(...))."
                )
        given = {k: v for k, v in keywords.items() if v is not None and v is not False}
        if filter is None:
            return cls(**given) if given else _NO_FILTER
        if isinstance(filter, Mapping):
            filter = cls.coerce(None, **{str(k): v for k, v in filter.items()})
        elif not isinstance(filter, RowFilter):
            raise TypeError(
                f"filter must be a RowFilter, a mapping of filter keywords or None, got {type(filter).__name__}."
            )
        if given:
            names = ", ".join(f"{k}=" for k in given)
            raise ValueError(f"pass either filter= or {names}, not both (filter={filter!r}).")
        return filter

    @property
    def matches_all(self) -> bool:
        """Whether every stored row takes part (no ``success_only`` / ``env`` / ``run`` filter)."""
        return not self.success_only and self.env is None and self.run is None

    @property
    def distance_limit(self) -> float:
        """``max_distance``, or ``inf`` without one."""
        return math.inf if self.max_distance is None else self.max_distance

    def to_dict(self) -> dict[str, Any]:
        """The fields as plain JSON values (lists for tuples): ``RowFilter(**flt.to_dict()) == flt``."""
        return {f.name: list(v) if isinstance(v, tuple) else v
                for f in fields(self) for v in (getattr(self, f.name),)}

    def resolve(self, env_names: Sequence[str] | None) -> FilterKey:
        """The row filter (``success_only`` / ``env`` / ``run``) with env names replaced by the codes of ``env_names``.

        Raises ``ValueError`` for a name missing from ``env_names`` (listing
        the known ones) or when names are used and no names are known.
        """
        envs = None
        if self.env is not None:
            codes = set()
            for item in self.env:
                if isinstance(item, str):
                    if env_names is None:
                        raise ValueError(
                            f"cannot filter on env {item!r}: no env names are known; pass "
                            "env_names= to GoalIndex (or use a storage with env_names)."
                        )
                    if item not in env_names:
                        raise ValueError(_unknown_env(item, env_names))
                    codes.add(list(env_names).index(item))
                else:
                    codes.add(item)
            envs = tuple(sorted(codes))
        runs = None if self.run is None else tuple(sorted(set(self.run)))
        return FilterKey(self.success_only, envs, runs)

    def __repr__(self) -> str:
        args = [f"{f.name}={getattr(self, f.name)!r}" for f in fields(self)
                if getattr(self, f.name) is not None and getattr(self, f.name) is not False]
        return f"RowFilter({', '.join(args)})"


class FilterKey(NamedTuple):
    """A :class:`RowFilter` resolved against one storage: env codes, sorted run ids."""

    success_only: bool
    envs: tuple[int, ...] | None
    runs: tuple[int, ...] | None

    def mask(self, column: Callable[[str], np.ndarray], goals: np.ndarray) -> np.ndarray:
        """Rows passing the filter, among the rows of ``goals [N, goal_dim]`` (non-finite goals never pass).

        ``column(name)`` returns the ``[N]`` values of ``"success"``, ``"env"``
        or ``"run"`` for the same rows.
        """
        mask = np.isfinite(goals).all(1) if goals.dtype.kind == "f" else np.ones(goals.shape[0], dtype=bool)
        if self.success_only:
            mask &= column("success") > 0.5
        if self.envs is not None:
            mask &= np.isin(column("env"), self.envs)
        if self.runs is not None:
            mask &= np.isin(column("run"), self.runs)
        return mask


def _unknown_env(name: str, env_names: Sequence[str]) -> str:
    """The error of an env filter naming an env the storage does not know (with the fix when it knows none)."""
    if env_names:
        return f"unknown env {name!r}; known envs: {list(env_names)}."
    return (f"cannot filter on env {name!r}: no row of this storage carries an env name (known envs: []; rows "
            f"written without one have env code -1). {env_advice()}")


def _check_bool(value, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be a bool, got {value!r}.")
    return bool(value)


def _check_max_distance(value) -> float:
    try:
        limit = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"max_distance must be a number >= 0 or None, got {value!r}.") from None
    if math.isnan(limit) or limit < 0:
        raise ValueError(f"max_distance must be >= 0, got {limit}.")
    return limit


def _as_tuple(value, name: str) -> tuple:
    try:
        return tuple(value)
    except TypeError:
        raise ValueError(f"{name} must be a value or a list of values, got {value!r}.") from None


_NO_FILTER = RowFilter()
