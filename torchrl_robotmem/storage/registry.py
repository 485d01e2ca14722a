"""A store's tag registry: the env-name table, the env rows are tagged with, the episode and run counters.

The tags themselves are computed by :mod:`.tags` (pure functions); this is the
state they are drawn from, as the commit record keeps it (``env_names``,
``env``, ``episode_next``, ``runs``). Nothing here locks or writes: the storage
marks its commit record dirty when a method says the state changed.

Example:
    >>> from torchrl_robotmem.storage.registry import TagRegistry
    >>> reg = TagRegistry(["FetchPush-v4"], runs=2)
    >>> reg.code("FetchReach-v4", create=True), reg.current_run()
    ((1, True), (2, True))
    >>> reg.record()["env_names"], reg.record()["runs"]
    (['FetchPush-v4', 'FetchReach-v4'], 3)
"""
from __future__ import annotations

import numpy as np
import torch

from .tags import UNKNOWN_ENV, EpisodeTagger

__all__ = ["TagRegistry"]


class TagRegistry:
    """The env names, this session's env and run, and the next episode id of one store.

    Args:
        env_names (list of str): the env-name table (index = env code).

    Keyword Args:
        episode_next (int): the next global episode id.
        runs (int): writing sessions so far.
        read_only (bool): a reader's registry (registering a name is refused).

    Example:
        >>> reg = TagRegistry()
        >>> reg.env_code = reg.code("FetchPush-v4", create=True)[0]
        >>> reg.env, reg.env_code
        ('FetchPush-v4', 0)
    """

    def __init__(self, env_names=(), *, episode_next: int = 0, runs: int = 0, read_only: bool = False) -> None:
        self.read_only = bool(read_only)
        self.env_names: list[str] = list(env_names)
        self.env_code = UNKNOWN_ENV  # the code of rows written from now on without an env entry
        self.tagger = EpisodeTagger(int(episode_next))
        self.runs = int(runs)
        self.run: int | None = None  # this session's run, allocated at its first write

    def sync(self, attrs: dict) -> None:
        """Takes the table and counters from a commit record (at open, refresh, journal replay)."""
        self.env_names = list(attrs.get("env_names", []))
        self.tagger = EpisodeTagger(int(attrs.get("episode_next", 0)))
        self.runs = int(attrs.get("runs", 0))

    def record(self) -> dict:
        """The registry's part of the commit record."""
        return {"episode_next": self.tagger.next_id, "runs": self.runs, "env_names": list(self.env_names),
                "env": self.env}

    # -- envs -------------------------------------------------------------------------------

    @property
    def env(self) -> str | None:
        """The env name rows written from now on are tagged with."""
        return None if self.env_code == UNKNOWN_ENV else self.env_names[self.env_code]

    def code(self, name: str, *, create: bool = False) -> tuple[int, bool]:
        """The integer code of an env name, and whether it was registered now.

        Args:
            name (str): the environment name, e.g. ``"FetchPush-v4"``.

        Keyword Args:
            create (bool): register the name if it is new (writers only).
        """
        if not isinstance(name, str) or not name:
            raise TypeError(f"An environment name must be a non-empty string, got {name!r}.")
        if name in self.env_names:
            return self.env_names.index(name), False
        if not create:
            raise ValueError(f"Unknown env {name!r}; this store knows {self.env_names}.")
        if self.read_only:
            raise RuntimeError(f"Cannot register env {name!r} in a store opened read_only.")
        self.env_names.append(name)
        return len(self.env_names) - 1, True

    # -- episodes and runs --------------------------------------------------------------------

    def current_run(self) -> tuple[int, bool]:
        """This session's run id, and whether it was allocated now."""
        if self.run is not None:
            return self.run, False
        self.run = self.runs
        self.runs += 1
        return self.run, True

    def draw(self, done: np.ndarray, traj: np.ndarray | None, *, continue_open: bool) -> torch.Tensor:
        """Global episode ids for rows with ``done`` flags and trajectory ids (see :class:`EpisodeTagger`).

        ``continue_open=False`` ([items, time...] layouts): nothing continues across writes.
        """
        ids = self.tagger.assign(done, traj, continue_open=continue_open)
        if not continue_open:
            self.tagger.reset()
        return ids

    def tag_rows(self, plan) -> bool:
        """Draws the episode ids and this session's run for a write plan's rows (``plan.set_tags``).

        Returns whether the run was allocated now (the record changed).
        """
        done, traj, continue_open = plan.draw
        episode = self.draw(done, traj, continue_open=continue_open)
        run, new = self.current_run()
        plan.set_tags(episode.reshape(plan.lead), torch.full(plan.lead, run, dtype=torch.long))
        return new

    def note_stored(self, episode_max: int, run_max: int) -> None:
        """Never hands out an id that a stored row already uses (rows past the committed record)."""
        self.tagger.next_id = max(self.tagger.next_id, int(episode_max) + 1)
        self.runs = max(self.runs, int(run_max) + 1)
