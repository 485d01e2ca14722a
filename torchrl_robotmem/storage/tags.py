"""Episode / run / env tags: the functions and the registry a store draws them from. No Zarr, no TorchRL.

Every stored row carries three int64 tags written by the storage itself:
``episode`` (unique across runs), ``run`` (one per writing session) and ``env``
(an index into the store's env-name table). The functions here compute them
over tensors and arrays (:class:`EpisodeTagger`, :func:`open_episode_ends`),
and say which names user data may not take (:func:`check_user_keys`,
:func:`check_user_tag`): a column named like a tag would be replaced by the
tag, and a key named like the store's own bookkeeping would break it.

:class:`TagRegistry` is the state the tags are drawn from, as the commit
record keeps it (``env_names``, ``env``, ``episode_next``, ``runs``). Nothing
here locks or writes: the storage marks its commit record dirty when a method
says the state changed.

Example:
    >>> from torchrl_robotmem.storage.tags import TagRegistry
    >>> reg = TagRegistry(["FetchPush-v4"], runs=2)
    >>> reg.code("FetchReach-v4", create=True), reg.current_run()
    ((1, True), (2, True))
    >>> reg.record()["env_names"], reg.record()["runs"]
    (['FetchPush-v4', 'FetchReach-v4'], 3)
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import NonTensorData, NonTensorStack

__all__ = [
    "RESERVED_PARTS", "TAG_KEYS", "UNKNOWN_ENV", "EpisodeTagger", "TagRegistry", "check_user_keys", "check_user_tag",
    "open_episode_ends",
]

#: Row tags written by the storage itself (int64 scalars per row).
TAG_KEYS = ("episode", "run", "env")
#: The env code of rows written without an env name.
UNKNOWN_ENV = -1
#: Key components no stored key may hold: each key is a directory path inside the store.
RESERVED_PARTS = frozenset({".", "..", "zarr.json"})

_TAG_MEANING = {
    "episode": "a global episode id the storage draws from done flags or collector trajectory ids",
    "run": "the writing session",
    "env": "the env code",
}


# -- reserved names -------------------------------------------------------------


def check_user_keys(keys, *, allowed=()) -> None:
    """Raises ``ValueError`` naming the first key a store cannot hold under its name.

    A store keeps its own bookkeeping under top-level names starting with
    ``_`` (``_journal/`` holds a ring overwrite in flight, ``_repair_backup/``
    what ``robotmem repair`` replaced), and every key is a directory path inside
    the store, so no component may be ``.``, ``..`` or ``zarr.json``.

    Args:
        keys: the keys of the data (strings or tuples of strings, nested keys included).

    Keyword Args:
        allowed: top-level names that may start with ``_`` (the data kinds' own
            ``_tensor`` / ``_pytree``).

    Example:
        >>> check_user_keys(["observation", ("next", "reward"), ("collector", "traj_ids")])
        >>> check_user_keys(["_journal"])
        Traceback (most recent call last):
        ...
        ValueError: Key '_journal' is reserved: top-level names starting with '_' hold the store's own bookkeeping ...
    """
    for key in keys:
        parts = (key,) if isinstance(key, str) else tuple(key)
        if not parts:
            continue
        if parts[0].startswith("_") and parts[0] not in allowed:
            new = "user" + parts[0] if len(parts) == 1 else ("user" + parts[0], *parts[1:])
            raise ValueError(
                f"Key {key!r} is reserved: top-level names starting with '_' hold the store's own bookkeeping "
                f"('_journal', '_repair_backup', ...). Rename it before writing, e.g. "
                f"td.rename_key_({key!r}, {new!r})."
            )
        bad = [p for p in parts if p in RESERVED_PARTS]
        if bad:
            raise ValueError(
                f"Key {key!r} holds the name {bad[0]!r}, which a store cannot use (each key is a directory path "
                f"inside the store; '.', '..' and 'zarr.json' are reserved). Rename it before writing."
            )


def check_user_tag(key: str, value, stored: torch.Tensor | None) -> None:
    """Raises ``ValueError`` unless the data's own column ``key`` (a tag name) equals the tags it would get.

    ``episode`` and ``run`` are drawn by the storage, so a column of that name
    in the data would be silently replaced. It is accepted only where it
    equals the stored tags of the rows written (``stored``: rows read with
    ``sample_tags=True`` and written back in place, or rows copied from another
    store); otherwise it is refused, and the fix is to rename it.

    Args:
        key (str): ``"episode"``, ``"run"`` or ``"env"``.
        value: the data's column.
        stored (torch.Tensor, optional): the tags the rows get (``[*lead]``),
            ``None`` when they are not drawn yet (an append).

    Example:
        >>> check_user_tag("episode", torch.tensor([3, 3]), torch.tensor([3, 3]))  # a round trip
        >>> check_user_tag("episode", torch.tensor([0, 1]), None)
        Traceback (most recent call last):
        ...
        ValueError: Key 'episode' is a tag column the storage writes itself ...
    """
    if stored is not None and isinstance(value, torch.Tensor) and not value.dtype.is_floating_point:
        v = value.reshape(*stored.shape, -1) if value.numel() % max(stored.numel(), 1) == 0 else None
        if v is not None and stored.numel() and bool((v == stored.to(v.device).unsqueeze(-1)).all()):
            return
    raise ValueError(
        f"Key {key!r} is a tag column the storage writes itself ({_TAG_MEANING[key]}): a column of that name "
        f"in the data would be replaced by it. Rename it before writing, e.g. "
        f"td.rename_key_({key!r}, 'user_{key}'), or drop it with td.exclude({key!r}); the stored tags read "
        f"back as storage[{key!r}]."
    )


# -- tags ----------------------------------------------------------------------------


def env_names_of(value: Any, n: int) -> list[str] | None:
    """Env names carried by a non-tensor ``"env"`` entry, else ``None``."""
    if isinstance(value, NonTensorStack):
        return [str(x) for x in value.tolist()]
    if isinstance(value, NonTensorData):
        return [str(value.data)] * n
    return None


class EpisodeTagger:
    """Assigns global episode ids to batches of transitions, continuing episodes across batches.

    Episodes come from the collector's ``("collector", "traj_ids")`` when the
    batch has them (mapped past every id already handed out, since trajectory
    ids restart at 0 with every collector), else from one stream of
    transitions split after each ``done``. An episode left open at the end of a
    batch continues in the next one.

    Args:
        next_id (int): the first id this tagger may hand out.

    Example:
        >>> import numpy as np
        >>> tagger = EpisodeTagger(next_id=10)
        >>> tagger.assign(np.array([False, True, False]), None).tolist()
        [10, 10, 11]
        >>> tagger.assign(np.array([True, False]), None).tolist()  # 11 continues
        [11, 12]
    """

    def __init__(self, next_id: int = 0) -> None:
        self.next_id = int(next_id)
        self._open: dict[int, int] = {}  # stream key -> id of its open episode

    def close_stream(self) -> None:
        """The done-split stream's open episode ends here (a boundary learnt late)."""
        self._open.pop(-1, None)

    def reset(self) -> None:
        self._open = {}

    def assign(self, done: np.ndarray, traj: np.ndarray | None, *, continue_open: bool = True) -> torch.Tensor:
        """Episode ids (int64 tensor) for ``n`` transitions in write order.

        Args:
            done (np.ndarray): bool ``[n]``, True on the last transition of an episode.
            traj (np.ndarray, optional): int ``[n]`` collector trajectory ids.
            continue_open (bool): whether episodes open from earlier batches may continue.
        """
        n = len(done)
        if not continue_open:
            self._open = {}
        open_ = self._open
        for k in [k for k in open_ if k < -1]:  # a done-split stream only continues its -1
            open_.pop(k)
        if traj is None:
            return torch.from_numpy(self._assign_stream(np.asarray(done, dtype=bool)))
        # numpy, not torch: these arrays are tiny and this runs on every extend
        keys = traj.astype(np.int64)
        uniq, first, inv = np.unique(keys, return_index=True, return_inverse=True)
        last = n - 1 - np.unique(keys[::-1], return_index=True)[1]
        ids = np.empty(len(uniq), dtype=np.int64)
        next_id = self.next_id
        order = np.argsort(first)
        for j in order:  # new ids in order of first appearance
            key = int(uniq[j])
            if key in open_:
                ids[j] = open_[key]
            else:
                ids[j] = next_id
                next_id += 1
        open_.pop(-1, None)
        for j in order:  # in order of appearance: the batch's last segment wins
            key = int(uniq[j])
            if done[last[j]]:
                open_.pop(key, None)
            elif key >= 0 or last[j] == n - 1:
                open_[-1 if key < 0 else key] = int(ids[j])
        self.next_id = next_id
        return torch.from_numpy(ids[inv.reshape(-1)])

    def _assign_stream(self, done: np.ndarray) -> np.ndarray:
        """Ids of one stream of transitions split after each ``done`` (no trajectory ids): no Python loop.

        Segment ``s`` (the rows after the ``s``-th done) is a new episode, except the first, which
        continues the stream's open episode if there is one; the last stays open unless it ends done.
        """
        n = len(done)
        if n == 0:
            return np.empty(0, dtype=np.int64)
        seg = np.cumsum(done, dtype=np.int64)
        seg -= done  # the segment of each row: 0, 0, 1, ... (a done row ends its segment)
        segments = int(seg[-1]) + 1
        cont = self._open.pop(-1, None)
        if cont is None:
            seg_ids = np.arange(self.next_id, self.next_id + segments, dtype=np.int64)
        else:
            seg_ids = np.arange(self.next_id - 1, self.next_id + segments - 1, dtype=np.int64)
            seg_ids[0] = cont
        self.next_id = int(seg_ids[-1]) + 1 if segments > 1 or cont is None else self.next_id
        if not done[-1]:
            self._open[-1] = int(seg_ids[-1])
        return seg_ids[seg]


def open_episode_ends(
    run: torch.Tensor, episode: torch.Tensor, done: torch.Tensor, *, cursor: int, full: bool
) -> torch.Tensor:
    """Rows that end an episode of the latest run without being marked done.

    A run that stopped or crashed mid-episode would otherwise merge that episode
    with the next run's first one (hindsight relabelling works within episodes).

    Args:
        run, episode (torch.Tensor): int64 ``[n]`` tags of the stored rows.
        done (torch.Tensor): bool ``[n]``, ``("next", "done")`` of the rows.
        cursor (int): the writer's cursor (where a full ring starts).
        full (bool): whether the storage is a full ring.

    Returns:
        the row positions (int64) to mark done and truncated.

    Example:
        >>> run = torch.tensor([0, 1, 1, 1, 1]); episode = torch.tensor([0, 1, 1, 2, 2])
        >>> done = torch.tensor([True, False, True, False, False])
        >>> open_episode_ends(run, episode, done, cursor=5, full=False).tolist()
        [4]
    """
    n = run.numel()
    if n == 0:
        return torch.zeros(0, dtype=torch.long)
    rows = (run == run.max()).nonzero().squeeze(-1)
    order = (rows - cursor) % n if full else rows  # write order: a full ring starts at the cursor
    ids = episode[rows]
    lo, hi = int(ids.min()), int(ids.max())
    if hi - lo <= 4 * ids.numel():  # ids dense enough to index by (no sort)
        inv = ids - lo
    else:
        _, inv = torch.unique(ids, return_inverse=True)
    last = torch.full((int(inv.max()) + 1,), -1, dtype=torch.long).scatter_reduce(0, inv, order, reduce="amax")
    last = last[last >= 0]  # ids between the stored ones that no row holds
    last_rows = (last + cursor) % n if full else last
    return last_rows[~done[last_rows]]


# -- the registry --------------------------------------------------------------------


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
