"""Which stored rows a recall may return: one value object shared by every reader.

:class:`RowFilter` holds the ``success_only`` / ``env`` / ``run`` filters of
:meth:`GoalIndex.search <torchrl_robotmem.recall.GoalIndex.search>`,
:class:`~torchrl_robotmem.GoalSimilaritySampler`,
:class:`~torchrl_robotmem.RecallTransform` and
:class:`~torchrl_robotmem.RobotMemory`, checked once, when it is made.
:meth:`RowFilter.resolve` turns env names into the integer codes of a storage's
``env`` column; the result, a :class:`FilterKey`, names one filtered view of an
index and computes its membership mask.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

__all__ = ["FilterKey", "RowFilter"]


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


@dataclass(frozen=True)
class RowFilter:
    """Filters on stored rows, combined with AND.

    Args:
        success_only (bool): only rows whose success flag is ``> 0.5``.
            Defaults to ``False``.
        env (str, int or sequence of them, optional): only rows of these envs,
            by name (mapped through the storage's ``env_names``) or integer code
            of the ``env`` column. Defaults to every env.
        run (int or sequence of int, optional): only rows of these runs (the
            ``run`` column). Defaults to every run.

    Example:
        >>> from torchrl_robotmem.recall import RowFilter
        >>> flt = RowFilter(success_only=True, env=["FetchPush-v4", "FetchSlide-v4"])
        >>> flt.env
        ('FetchPush-v4', 'FetchSlide-v4')
        >>> flt.resolve(("FetchPush-v4", "FetchSlide-v4"))
        FilterKey(success_only=True, envs=(0, 1), runs=None)
        >>> RowFilter().matches_all
        True
    """

    success_only: bool = False
    env: str | int | Sequence[str | int] | None = None
    run: int | Sequence[int] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.success_only, (bool, np.bool_)):
            raise ValueError(f"success_only must be a bool, got {self.success_only!r}.")
        object.__setattr__(self, "success_only", bool(self.success_only))
        env = self.env
        if env is not None:
            items = (env,) if isinstance(env, str) or _is_int(env) else _as_tuple(env, "env")
            if not items or not all(isinstance(e, str) and e or _is_int(e) for e in items):
                raise ValueError(
                    f"env must be a name, a code or a non-empty list of them, got {env!r}."
                )
            object.__setattr__(self, "env", tuple(e if isinstance(e, str) else int(e) for e in items))
        run = self.run
        if run is not None:
            items = (run,) if _is_int(run) else _as_tuple(run, "run")
            if not items or not all(_is_int(r) for r in items):
                raise ValueError(f"run must be an int or a non-empty list of ints, got {run!r}.")
            object.__setattr__(self, "run", tuple(int(r) for r in items))

    @classmethod
    def of(cls, value: RowFilter | None = None, **kwargs) -> RowFilter:
        """``value`` itself, or a filter made of the keywords (``None`` values left out)."""
        if value is not None:
            if not isinstance(value, RowFilter):
                raise TypeError(f"filter must be a RowFilter, got {type(value).__name__}.")
            if any(v not in (None, False) for v in kwargs.values()):
                raise ValueError(f"pass either filter= or {sorted(kwargs)}, not both.")
            return value
        return cls(**{k: v for k, v in kwargs.items() if v is not None})

    @property
    def matches_all(self) -> bool:
        """Whether the filter keeps every row."""
        return not self.success_only and self.env is None and self.run is None

    def resolve(self, env_names: Sequence[str] | None) -> FilterKey:
        """The filter with env names replaced by the codes of ``env_names``.

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
                        raise ValueError(f"unknown env {item!r}; known envs: {list(env_names)}.")
                    codes.add(list(env_names).index(item))
                else:
                    codes.add(item)
            envs = tuple(sorted(codes))
        runs = None if self.run is None else tuple(sorted(set(self.run)))
        return FilterKey(self.success_only, envs, runs)

    def __repr__(self) -> str:
        args = [f"{name}={getattr(self, name)!r}" for name in ("success_only", "env", "run")
                if getattr(self, name) not in (None, False)]
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


def _as_tuple(value, name: str) -> tuple:
    try:
        return tuple(value)
    except TypeError:
        raise ValueError(f"{name} must be a value or a list of values, got {value!r}.") from None
