"""The write planner: validates and normalises one ``set`` into a :class:`WritePlan`, changing nothing.

A write may be a TensorDict (lazy stacks, nested keys), a list of them, a tensor,
a tensorclass or a pytree. :func:`plan_write` turns it into the TensorDict the
RAM mirror stores, checks it against the store (kind, keys, dtypes, item
shape, non-tensor entries, reserved names) and computes the tag columns. It
reads the store through a :class:`StoreView` and writes nothing: what a plan
changes in the store (env names to register, the data kind to record, the
episode ids and run to draw, a warning to give once) is carried by the plan
and done by the storage when it applies it.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem.storage.mirror import RamMirror
    >>> from torchrl_robotmem.storage.planner import StoreView, plan_write
    >>> from torchrl_robotmem.storage.schema import DataKind
    >>> view = StoreView("m.zarr", 1, False, RamMirror(10), DataKind(), {}, [], -1)
    >>> plan = plan_write(view, slice(0, 3), TensorDict({"x": torch.zeros(3, 2)}, [3]), set_cursor=True)
    >>> plan.n, sorted(plan.data.keys()), plan.draw is not None
    (3, ['x'], True)
"""
from __future__ import annotations

import unicodedata
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch
from tensordict import LazyStackedTensorDict, TensorDict, TensorDictBase, is_tensor_collection
from tensordict.base import _is_leaf_nontensor

from . import _backend
from .format import UNBOUNDED_SIZE
from .schema import DataKind, check_against, same_constant, split_constants
from .tags import TAG_KEYS, UNKNOWN_ENV, check_user_keys, check_user_tag, env_names_of

__all__ = ["MAX_NAME_BYTES", "StoreView", "WritePlan", "check_constants", "check_key_names", "completes_chunk",
           "counts_from_the_end", "cursor_rows", "is_int_cursor", "key_name_problem", "check_rows", "plan_write", "validate",
           "write_span"]

DONE_KEY = ("next", "done")
TRAJ_KEY = ("collector", "traj_ids")
# Written into the caller's TensorDict by TorchRL's TensorDictRoundRobinWriter;
# it equals the row position, so it is not stored (sample() adds it back).
DROPPED_KEYS = ("index",)
#: the longest key name (one path component), in UTF-8 bytes: what ext4, APFS, NTFS and most others hold
MAX_NAME_BYTES = 255
#: characters a Windows (NTFS, exFAT, SMB) file name cannot hold, besides control characters and separators
_WINDOWS_CHARS = frozenset('<>:"|?*')
#: names Windows gives to devices, with or without an extension, in any letter case
_DEVICE_NAMES = frozenset({"CON", "PRN", "AUX", "NUL", *(f"COM{i}" for i in range(1, 10)),
                           *(f"LPT{i}" for i in range(1, 10))})
_NAME_RULE = (f"every key name becomes a folder name in the store, so it must be a portable file name: not empty, "
              f"'.' or '..', at most {MAX_NAME_BYTES} bytes in UTF-8, without '/', '\\', control characters or "
              f"any of <>:\"|?*, not ending in '.' or ' ', not a Windows device name (CON, NUL, COM1, ...)")


class StoreView(NamedTuple):
    """What a plan reads of the store (nothing here is changed by planning).

    Args:
        path: the store's path (for messages).
        ndim (int): leading batch dimensions one stored item spans.
        initialized (bool): whether the store holds a schema and a RAM mirror.
        mirror (RamMirror): the RAM mirror (schema, item shape, stored tags).
        kind (DataKind): the store's data kind.
        constants (dict): the store's non-tensor entries.
        env_names (list): the store's env names (index = env code).
        env_code (int): the env code of rows written without an env entry.
    """

    path: Any
    ndim: int
    initialized: bool
    mirror: Any
    kind: DataKind
    constants: dict
    env_names: list
    env_code: int

    @classmethod
    def of(cls, path: Any, ndim: int, initialized: bool, schema, tags) -> StoreView:
        """The view of an open store, from its ``StoreSchema`` (mirror, kind, constants) and ``TagRegistry``."""
        return cls(path, ndim, initialized, schema.mirror, schema.kind, schema.constants, tags.env_names, tags.env_code)


@dataclass
class WritePlan:
    """One validated write, ready to apply.

    Args:
        data (TensorDictBase): the rows to store, with a first dimension even for a
            single-row cursor (:meth:`rows` drops it), the tags set unless
            :attr:`draw` asks for them (then :meth:`set_tags` sets them).
        n (int): transitions written.
        single (bool): an integer cursor (one item).
        lead (torch.Size): the dims the tags are per element of.
        kind (DataKind): the data kind the store records at its first write.
        new_paths (list): paths of keys the store does not hold yet.
        new_constants (dict): non-tensor entries the store does not hold yet.
        new_env_names (list): env names to register, in order (their codes are
            already in ``data["env"]``).
        draw (tuple, optional): ``(done, traj, continue_open)``: the episode ids
            (and this session's run) are drawn from these when the plan is applied.
        warning (str, optional): advice given once per store when applied.
        env (torch.Tensor, optional): the rows' env codes (per element of :attr:`lead`).
    """

    data: TensorDictBase
    n: int
    single: bool
    lead: torch.Size
    kind: DataKind
    new_paths: list = field(default_factory=list)
    new_constants: dict = field(default_factory=dict)
    new_env_names: list = field(default_factory=list)
    draw: tuple | None = None
    warning: str | None = None
    env: torch.Tensor | None = None

    def set_tags(self, episode: torch.Tensor, run: torch.Tensor) -> None:
        """Sets the ``episode`` / ``run`` / ``env`` columns (``episode`` and ``run`` per element of :attr:`lead`)."""
        batch = self.data.batch_size
        self.data.set("episode", expand_tag(episode, self.lead, batch))
        self.data.set("run", expand_tag(run, self.lead, batch))
        self.data.set("env", expand_tag(self.env, self.lead, batch))

    def rows(self) -> TensorDictBase:
        """The TensorDict to write at the cursor."""
        return self.data[0] if self.single else self.data


# -- cursors --------------------------------------------------------------------------


def is_int_cursor(cursor) -> bool:
    """Whether ``cursor`` names one item (an int or a 0-d tensor)."""
    return isinstance(cursor, (int, np.integer)) or (isinstance(cursor, torch.Tensor) and cursor.ndim == 0)


def cursor_rows(cursor, max_size: int) -> torch.Tensor:
    """The first-dimension rows a cursor touches (a tuple cursor indexes several dims), as rows of ``max_size``.

    A negative index counts from the end, as the write into the rows does (``-1``: row ``max_size - 1``): the
    rows marked dirty and committed are the rows written.

    Example:
        >>> cursor_rows(-1, 10), cursor_rows(torch.tensor([-2, 3]), 10), cursor_rows(slice(-3, None), 10)
        (tensor([9]), tensor([8, 3]), tensor([7, 8, 9]))
    """
    if isinstance(cursor, tuple):
        first = cursor[0] if cursor else slice(None)
        rows = cursor_rows(first, max_size)
        return rows.unique() if rows.numel() > 1 else rows
    if isinstance(cursor, slice):
        return torch.arange(*cursor.indices(max_size), dtype=torch.long)
    if is_int_cursor(cursor):
        rows = torch.tensor([int(cursor)], dtype=torch.long)
    elif isinstance(cursor, range):
        rows = torch.tensor(list(cursor), dtype=torch.long)
    else:
        rows = torch.as_tensor(cursor, dtype=torch.long).reshape(-1).cpu()
    return torch.where(rows < 0, rows + max_size, rows)


def counts_from_the_end(cursor) -> bool:
    """Whether ``cursor`` names a row by a negative index (or a slice bound), counted from the end of the rows.

    Example:
        >>> counts_from_the_end(-1), counts_from_the_end(slice(2, None)), counts_from_the_end(torch.tensor([3, -2]))
        (True, False, True)
    """
    if isinstance(cursor, tuple):
        return bool(cursor) and counts_from_the_end(cursor[0])
    if isinstance(cursor, slice):
        return any(b is not None and int(b) < 0 for b in (cursor.start, cursor.stop))
    if is_int_cursor(cursor):
        return int(cursor) < 0
    rows = torch.as_tensor(list(cursor) if isinstance(cursor, range) else cursor).reshape(-1)
    return bool(rows.numel()) and bool((rows < 0).any())


def write_span(cursor, data, rows: torch.Tensor) -> tuple[Any, torch.Tensor | slice]:
    """The cursor to write ``data`` at and the rows to mark dirty: contiguous ``rows`` become a slice.

    A slice cursor is a view copy (about 2x an index_put); tuple cursors and lazy
    stacks keep theirs.

    Example:
        >>> import torch
        >>> write_span(torch.arange(2, 5), None, torch.arange(2, 5))
        (slice(2, 5, None), slice(2, 5, None))
    """
    flat = rows.cpu().numpy()  # numpy: its small-array ops skip the dispatch of torch ops
    if isinstance(cursor, slice) and len(flat) == 1:  # one row of a slice (its stop may be left out): made explicit
        one = slice(int(flat[0]), int(flat[0]) + 1)
        return one, one
    if len(flat) > 1 and int(flat[-1]) - int(flat[0]) == len(flat) - 1 and bool((np.diff(flat) == 1).all()):
        dirty = slice(int(flat[0]), int(flat[-1]) + 1)
        if not isinstance(cursor, tuple) and not isinstance(data, LazyStackedTensorDict):
            cursor = dirty
        return cursor, dirty
    return cursor, rows


def check_rows(view: StoreView, data: TensorDictBase) -> None:
    """Raises, naming the key, unless ``data`` (batch ``[N]``) could be written to the store of ``view``.

    The tag columns (``episode``, ``run``, ``env``) are ignored; a store with no rows
    yet accepts any supported dtypes.
    """
    data = data.exclude(*TAG_KEYS, *DROPPED_KEYS)
    check_constants(view, split_constants(data))
    validate(view, data, False)


def completes_chunk(rows: torch.Tensor, chunk_rows: int) -> bool:
    """Whether a write at ``rows`` completed a chunk: only then is the commit thread woken (its timer covers the rest).

    Example:
        >>> import torch
        >>> completes_chunk(torch.arange(0, 3), 4), completes_chunk(torch.arange(1, 4), 4)
        (False, True)
    """
    first, last = int(rows[0]), int(rows[-1])
    return (last + 1) % chunk_rows == 0 or len(rows) > chunk_rows or first // chunk_rows != last // chunk_rows


def expand_tag(value, lead: torch.Size, batch: torch.Size) -> torch.Tensor:
    """A tag per element of ``lead``, repeated over the item dims past it."""
    if not (isinstance(value, torch.Tensor) and value.dtype == torch.long and value.shape == lead):
        value = torch.as_tensor(value, dtype=torch.long).reshape(lead)
    extra = len(batch) - len(lead)
    return value.reshape(*lead, *([1] * extra)).expand(batch).clone() if extra else value


# -- the plan -------------------------------------------------------------------------


def plan_write(view: StoreView, cursor, data, *, set_cursor: bool, as_kind: DataKind | None = None,
               keep_tags: bool = False) -> WritePlan:
    """Validates ``data`` for a write at ``cursor`` and adds the tag columns (no side effects).

    Args:
        view (StoreView): the store.
        cursor: where the rows go (int, slice, range, tensor, or a tuple for
            element-wise writes into a multi-dim storage).
        data: the rows.

    Keyword Args:
        set_cursor (bool): an append by the buffer's writer (``False``: an in-place
            write, which keeps the rows' tags).
        as_kind (DataKind, optional): ``data`` is a TensorDict holding rows of this
            kind (loading another storage's state): recorded as the store's kind.
        keep_tags (bool): ``data`` carries ``episode`` / ``run`` tags to keep (rows
            copied from another store).
    """
    plan = _plan_append(view, cursor, data) if set_cursor and as_kind is None and not keep_tags else None
    if plan is not None:
        _check_cursor_count(view, cursor, plan.data)
        return plan
    single = is_int_cursor(cursor)
    kind, td, warning = _normalise(view, data, single, as_kind)
    multi = isinstance(cursor, tuple)  # an element-wise write into a multi-dim storage
    if multi and set_cursor:
        raise ValueError("ZarrStorage appends along the first dimension only; tuple cursors are for in-place writes.")
    mirror = view.mirror
    inner = tuple(td.batch_size[1:])
    if mirror.schema is not None and inner != mirror.inner_shape and not multi:
        raise ValueError(
            f"The store at {view.path!r} holds items of batch shape {list(mirror.inner_shape)} "
            f"(after the first dimension); got {list(inner)}."
        )
    if td.shape[0] == 0:
        raise ValueError("Cannot write an empty TensorDict.")
    if not multi and not single:
        _check_cursor_count(view, cursor, td)
    # the dims that count in len; tags are per element of these
    lead = td.batch_size if multi else td.batch_size[: view.ndim]
    for key in DROPPED_KEYS:
        td.pop(key, None)
    tags = kind.tag_columns and (as_kind or kind).tag_columns
    env, new_names = _env_column(view, td, lead) if tags else (None, [])
    episode = run = None
    if tags and keep_tags:  # rows copied from another store keep their tags
        episode, run = td.get("episode", None), td.get("run", None)
    if tags and not set_cursor and episode is None:
        episode, run, env = _stored_tags(view, cursor, td, lead, env)
    for key in TAG_KEYS:  # env codes / names are input; episode and run are drawn here (reserved names)
        value = td.pop(key, None)
        if value is not None and not (tags and key == "env"):
            check_user_tag(key, value, episode if key == "episode" else run if key == "run" else None)
    fast = matches_schema(view, td)  # the hot path: the keys, dtypes and shapes the store holds, no more
    new_constants = {} if fast else check_constants(view, split_constants(td))
    new_paths = [] if fast else validate(view, td, single)
    clash = [p for p in new_paths if p in view.constants]
    if clash:
        raise TypeError(
            f"Key {_backend.path_to_key(clash[0])!r} is a tensor here, but the store at {view.path!r} holds it as "
            f"a non-tensor value ({view.constants[clash[0]]!r}); every write must keep a key's kind."
        )
    plan = WritePlan(td, lead.numel(), single, lead, as_kind or kind, new_paths, new_constants, new_names,
                     warning=warning, env=env)
    if tags:
        if episode is None:  # drawn when the plan is applied, once nothing can fail
            plan.draw = _episode_inputs(view, td, plan.n)
        else:
            plan.set_tags(episode, run)
    return plan


def _check_cursor_count(view: StoreView, cursor, td: TensorDictBase) -> None:
    """Raises unless ``cursor`` names as many first-dimension rows as ``td`` holds, as ``LazyTensorStorage`` does.

    A row is never repeated to fill the rows a cursor names (``set(slice(5, None), one_row)`` is refused, as
    TorchRL's storages refuse it), and a write of more rows than its cursor names is refused before anything
    changes. An open slice counts to the end of the memory: of a memory without a declared capacity, to
    TorchRL's ``max_size`` for it (so an open stop never matches).
    """
    mirror = view.mirror
    if isinstance(cursor, slice):
        if mirror.unbounded:
            size = UNBOUNDED_SIZE
        elif view.initialized:
            size = mirror.max_dim0
        else:  # the first write: the rows along the first dimension, as TorchRL's storages count them
            size = -(-mirror.max_size // max(1, int(np.prod(td.batch_size[1:view.ndim], dtype=np.int64))))
        named = len(range(*cursor.indices(size)))
    elif isinstance(cursor, torch.Tensor):
        named = cursor.numel()
    else:
        try:
            named = len(cursor)
        except TypeError:
            return  # another index kind: the write itself checks it
    if named != td.batch_size[0]:
        raise ValueError(
            f"The cursor {_show_cursor(cursor)} names {named} rows along the first dimension, and the data holds "
            f"{td.batch_size[0]} (batch_size {list(td.batch_size)}): a cursor names one row per row written, as in "
            f"LazyTensorStorage.set. Nothing was written."
        )


def _show_cursor(cursor) -> str:
    if isinstance(cursor, torch.Tensor) and cursor.numel() > 8:
        return f"tensor of {cursor.numel()} indices"
    if isinstance(cursor, (list, tuple)) and len(cursor) > 8:
        return f"list of {len(cursor)} indices"
    return repr(cursor)


def _plan_append(view: StoreView, cursor, data) -> WritePlan | None:
    """The plan of the common append, made in one pass over the leaves; ``None``: :func:`plan_write` checks it all.

    An append of a plain, unlocked TensorDict to a store of TensorDicts without constants, with the
    store's batch dims and item shape, no tag entry, and exactly the store's keys, dtypes and row shapes
    (:func:`_same_leaves`): every check of the full path passes for it, and this is the plan the full
    path makes of it. Anything else (a first write, a new key, a dtype or shape change, an ``env``
    entry, a non-tensor entry) returns ``None``, and the full path checks it and names what is wrong.
    Nothing is cached: the schema a write is checked against is the one the view holds now.

    Args:
        view (StoreView): the store.
        cursor: where the rows go (an append's: a slice, range or tensor of rows).
        data: the rows.
    """
    mirror = view.mirror
    specs = mirror.key_specs  # None before the first write
    if (type(data) is not TensorDict or specs is None or view.constants or view.kind.kind != "tensordict"
            or isinstance(cursor, tuple) or is_int_cursor(cursor) or data.is_locked):
        return None
    batch = data.batch_size
    if len(batch) != view.ndim or not batch[0] or tuple(batch[1:]) != mirror.inner_shape:
        return None
    if _same_leaves(data, specs, len(batch), ()) != len(specs):
        return None
    td = data.exclude(*DROPPED_KEYS)  # a new TensorDict: the tags set on it do not reach the caller's
    plan = WritePlan(td, batch.numel(), False, batch, view.kind,
                     env=torch.full(batch, view.env_code, dtype=torch.long))
    plan.draw = _episode_inputs(view, td, plan.n)
    return plan


def _same_leaves(td: TensorDict, specs: dict, dims: int, prefix: tuple) -> int:
    """How many tensor leaves of ``td`` have their key's dtype and row shape in ``specs``; -1 on any other entry.

    Nested plain TensorDicts are walked and the dropped keys skipped. A key not in ``specs`` (a tag
    entry is none), a dtype or row shape that differs, or another kind of leaf or node (a non-tensor
    entry, a lazy stack, a tensorclass) returns -1.

    Args:
        td (TensorDict): the rows (or a nested TensorDict of them).
        specs (dict): ``{key: (dtype, row shape)}`` of the store (``RamMirror.key_specs``).
        dims (int): the batch dims of the rows (a row's shape starts after them).
        prefix (tuple): the key of ``td`` inside the rows (``()``: the rows themselves).
    """
    seen = 0
    for name, value in td.items():
        if not prefix and name in DROPPED_KEYS:
            continue
        key = (*prefix, name) if prefix else name
        if isinstance(value, torch.Tensor):
            spec = specs.get(key)
            if spec is None or value.dtype != spec[0] or value.shape[dims:] != spec[1]:
                return -1
            seen += 1
        elif type(value) is TensorDict:
            more = _same_leaves(value, specs, dims, key if prefix else (name,))
            if more < 0:
                return -1
            seen += more
        else:
            return -1
    return seen


def _normalise(view: StoreView, data, single: bool, as_kind: DataKind | None) -> tuple[DataKind, TensorDictBase, str | None]:
    """``data`` as a shallow TensorDict copy with a first dimension; its kind, checked against the store's."""
    if isinstance(data, list):
        if not data:
            raise ValueError("Cannot write an empty TensorDict.")
        try:
            data = torch.stack(data, 0) if all(is_tensor_collection(d) for d in data) else _stack_trees(data)
        except Exception as err:  # TorchRL's wording, so callers can match it
            raise RuntimeError(
                f"Stacking the elements of the list resulted in an error ({err}). ZarrStorage expects all "
                f"elements of the list to have the same structure and shapes (a list passed to extend is "
                f"one item per element)."
            ) from err
    # rows loaded as TensorDicts into a store of another kind are checked as TensorDicts
    kind = DataKind.of(data) if as_kind is None else DataKind()
    stored = view.kind if as_kind is None else DataKind()
    if view.mirror.schema is not None and kind.kind == stored.kind and not kind.same_as(stored):
        raise ValueError(
            f"This {kind.kind}'s structure differs from the one the store at {view.path!r} holds "
            f"({kind.meta} vs {stored.meta}); every write must have the same structure."
        )
    if view.mirror.schema is not None and not kind.same_as(stored):
        raise TypeError(
            f"The store at {view.path!r} holds {stored.kind} data; got {kind.kind}. Every "
            f"write to one store must be of the same kind."
        )
    expected_dims = view.ndim - (1 if single else 0)
    td = kind.to_tensordict(data, expected_dims)
    if td.batch_dims < expected_dims:
        raise ValueError(
            f"ZarrStorage(ndim={view.ndim}) expects data with at least {expected_dims} batch "
            f"dimension(s); got batch_size {list(td.batch_size)}."
        )
    warning = None
    if td.batch_dims > expected_dims and kind.kind == "tensordict" and view.ndim == 1:
        warning = (
            f"ZarrStorage(ndim=1) got a TensorDict with batch_size {list(td.batch_size)}: each of its "
            f"{td.batch_size[0]} items is stored whole, as LazyTensorStorage does (episode tags are per "
            f"item). For collector output, one row per transition is usually meant: pass "
            f"data.reshape(-1) (Collector(..., postproc=lambda td: td.reshape(-1))), or create the "
            f"store with ndim={td.batch_dims} for a [num_envs, time] layout."
        )
    if isinstance(td, LazyStackedTensorDict) and td.stack_dim == 0 and not td.is_locked and not single:
        td = td.copy()  # kept lazy: TorchRL writes each stacked TensorDict in place (update_at_)
    elif not isinstance(td, TensorDict) or td.is_locked:
        td = td.to_tensordict()
    else:
        td = td.copy()  # shallow: tags must not leak into the caller's TensorDict
    if single:
        td = td.unsqueeze(0)
    return kind, td, warning


def _stored_tags(view: StoreView, cursor, td: TensorDictBase, lead: torch.Size, env):
    """The tags an in-place write keeps: the rows' own (past len: a placeholder, as the rows are)."""
    mirror = view.mirror
    rows = cursor_rows(cursor, mirror.max_dim0 if view.initialized else mirror.max_size)
    held = view.initialized and "episode" in mirror.schema
    if isinstance(cursor, tuple) and held:
        episode = mirror.views.get("episode")[cursor].reshape(lead)
        run = mirror.views.get("run")[cursor].reshape(lead)
        env = mirror.views.get("env")[cursor].reshape(lead) if td.get("env", None) is None else env
    elif held and bool((rows < mirror.max_dim0).all()):
        episode = mirror.lead(mirror.views.get("episode"))[rows]
        run = mirror.lead(mirror.views.get("run"))[rows]
    else:
        episode = torch.full(lead, -1, dtype=torch.long)
        run = torch.full(lead, -1, dtype=torch.long)
    return episode, run, env


def _env_column(view: StoreView, data: TensorDictBase, batch: torch.Size) -> tuple[torch.Tensor, list[str]]:
    """The env codes of the rows, and the names among them the store must register (codes already given)."""
    env = data.get("env", None)
    if env is None:
        return torch.full(batch, view.env_code, dtype=torch.long), []
    names = env_names_of(env, batch.numel())
    if names is not None:
        known = list(view.env_names)
        new = [x for x in dict.fromkeys(names) if x not in known]
        for name in new:
            if not isinstance(name, str) or not name:
                raise TypeError(f"An environment name must be a non-empty string, got {name!r}.")
        table = {x: i for i, x in enumerate(known + new)}
        return torch.tensor([table[x] for x in names], dtype=torch.long).reshape(batch), new
    env = torch.as_tensor(env)
    if env.dtype.is_floating_point or env.dtype == torch.bool:
        raise ValueError(f"Key 'env' must hold integer env codes or names, got dtype {env.dtype}.")
    env = env.reshape(batch).long()
    bad = (env < UNKNOWN_ENV) | (env >= len(view.env_names))
    if bad.any():
        raise ValueError(
            f"Key 'env' holds codes {env[bad].unique().tolist()} unknown to this store "
            f"(known: {dict(enumerate(view.env_names))}). Use storage.env_code(name, create=True)."
        )
    return env, []


def _episode_inputs(view: StoreView, data: TensorDictBase, n: int) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """What global episode ids are drawn from: done flags and collector ``traj_ids`` (``(done, traj, continue_open)``)."""
    done = data.get(DONE_KEY, None)
    done = np.zeros(n, dtype=bool) if done is None else done.reshape(n, -1).any(-1).cpu().numpy()
    traj = data.get(TRAJ_KEY, None)
    if traj is not None and traj.numel() != n:  # per-step ids of whole stored items: their first
        traj = traj.reshape(n, -1)[:, 0] if traj.numel() % n == 0 else None
    traj = traj.reshape(n).long().cpu().numpy() if traj is not None else None
    if view.ndim == 1:
        return done, traj, True
    # [items, time...] layouts: each item is its own stream; nothing continues across writes
    if traj is None:
        per_item = done.reshape(data.shape[0], -1)
        seg = np.cumsum(per_item, 1) - per_item
        traj = (np.arange(per_item.shape[0])[:, None] * (per_item.shape[1] + 1) + seg).reshape(-1)
    return done, traj, False


# -- checks against the store -----------------------------------------------------------


def check_constants(view: StoreView, found: dict[str, Any]) -> dict[str, Any]:
    """The non-tensor entries of a write against the store's; returns the new ones."""
    schema, constants = view.mirror.schema, view.constants
    new = {}
    for path, value in found.items():
        key = _backend.path_to_key(path)
        if schema is not None and path in schema:
            raise TypeError(
                f"Key {key!r} holds a non-tensor value ({value!r}), but the store at {view.path!r} holds it "
                f"as a tensor of dtype {schema[path]['dtype']}; every write must keep a key's kind."
            )
        if path not in constants:
            check_key_names([key])
            new[path] = value
        elif not same_constant(constants[path], value):
            raise ValueError(
                f"Key {key!r} holds {value!r}, but the store at {view.path!r} holds {constants[path]!r} "
                f"for it. ZarrStorage keeps a non-tensor entry as one value shared by every row (in the "
                f"store's metadata, as LazyMemmapStorage does); store per-row values as a tensor (e.g. "
                f"integer codes), or use another store."
            )
    missing = [p for p in constants if p not in found]
    if missing and schema is not None:
        raise KeyError(
            f"The data does not match the schema of the store at {view.path!r}: missing non-tensor keys "
            f"{[_backend.path_to_key(p) for p in missing]} (held as {[constants[p] for p in missing]}). "
            f"Every write must carry the keys the store holds."
        )
    return new


def matches_schema(view: StoreView, data: TensorDictBase) -> bool:
    """Whether ``data`` holds exactly the store's tensor keys, dtypes and row shapes (no constants)."""
    fast = view.mirror.key_specs
    if fast is None or view.constants:
        return False
    seen = 0
    dims = 1 + len(view.mirror.inner_shape)
    # one dict lookup and two comparisons per leaf; a non-tensor leaf is a leaf here (never in ``fast``)
    for key, value in data.items(include_nested=True, leaves_only=True, is_leaf=_is_leaf_nontensor):
        spec = fast.get(key)
        if spec is None or value.dtype != spec[0] or value.shape[dims:] != spec[1]:
            return False
        seen += 1
    return seen == len(fast)


def validate(view: StoreView, data: TensorDictBase, single: bool) -> list[str]:
    """Raises, naming the key, on a dtype / shape change or a new key name a store cannot hold; returns new paths."""
    if matches_schema(view, data):
        return []
    check_user_keys(data.keys(include_nested=True), allowed=(DataKind.TENSOR_KEY, DataKind.PYTREE_KEY))
    if view.mirror.schema is None:
        keys = []
        for key, value in data.items(include_nested=True, leaves_only=True, is_leaf=_is_leaf_nontensor):
            if not isinstance(value, torch.Tensor):
                raise TypeError(f"Key {key!r} holds {type(value).__name__}; ZarrStorage stores tensors only.")
            _backend.torch_dtype_name(value.dtype)
            keys.append(key)
        check_key_names(keys, held=TAG_KEYS)
        for key in keys:
            _backend.key_to_path(key)
        return []
    schema = {p: spec for p, spec in view.mirror.schema.items() if p not in TAG_KEYS}
    new, missing = check_against(schema, data, data.batch_dims, repr(view.path))
    if new:  # a key's name is checked once, at the write that brings it: the keys a store holds are not
        check_key_names([_backend.path_to_key(p) for p in new], held=view.mirror.schema)
    if missing:
        raise KeyError(
            f"The TensorDict does not match the schema of the store at {view.path!r}: missing keys "
            f"{[_backend.path_to_key(p) for p in missing]}. Every write must carry the keys the "
            f"store holds (new keys may be added)."
        )
    return new


def _short(key: Any) -> str:
    text = repr(key)
    return text if len(text) <= 80 else f"{text[:60]}... ({len(text)} characters)"


def key_name_problem(name: Any) -> str | None:
    r"""Why ``name`` (one component of a key) cannot be a folder name on every file system; ``None``: it can.

    A stored key is a path of folders inside the store (``("next", "observation")``
    -> ``next/observation/``), and a store is copied between Linux, macOS,
    Windows and object stores: a name one of them cannot hold is refused at the
    write that brings it, before anything is written.

    Example:
        >>> key_name_problem("observation") is None, key_name_problem("a\\b")
        (True, "holds a path separator ('\\\\')")
    """
    if not isinstance(name, str):
        return f"is not a string ({type(name).__name__})"
    if not name:
        return "is empty"
    if name in (".", ".."):
        return "names a folder itself"
    try:
        size = len(name.encode("utf-8"))
    except UnicodeEncodeError:
        return "is not valid Unicode text (it holds a lone surrogate)"
    if size > MAX_NAME_BYTES:
        return f"is {size} bytes long in UTF-8, over the {MAX_NAME_BYTES} a file name may hold"
    for label, bad in (("a path separator", lambda ch: ch in "/\\"),
                       ("a control character", lambda ch: unicodedata.category(ch) == "Cc"),
                       ("a character Windows file names cannot hold", lambda ch: ch in _WINDOWS_CHARS)):
        found = next((ch for ch in name if bad(ch)), None)
        if found is not None:
            return f"holds {label} ({found!r})"
    if name[-1] in ". ":
        return f"ends in {name[-1]!r}, which Windows drops from file names"
    if name.split(".")[0].rstrip(" ").upper() in _DEVICE_NAMES:
        return "is a Windows device name"
    if name.casefold() == "zarr.json":
        return "is the name of the store's metadata files"
    return None


def _fold(path: str) -> str:
    """What a case-insensitive, normalisation-insensitive file system (macOS, Windows) sees of ``path``."""
    return unicodedata.normalize("NFC", path).casefold()


def check_key_names(keys, *, held=()) -> None:
    r"""Raises ``ValueError`` naming the first key a store cannot hold portably (see :func:`key_name_problem`).

    Args:
        keys: the new keys (strings or tuples of strings, as TensorDict keys).

    Keyword Args:
        held: the paths the store holds already; a new key equal to one of them
            but for letter case or Unicode normalisation (``Obs`` beside ``obs``)
            is refused, as macOS and Windows see one folder.

    Example:
        >>> check_key_names([("next", "observation")], held=["observation"])
        >>> check_key_names(["tab\tkey"])
        Traceback (most recent call last):
        ...
        ValueError: Key 'tab\tkey' cannot be stored: its name 'tab\tkey' holds a control character ('\t'); ...
    """
    seen: dict[str, str] = {}
    for path in held:
        parts = path.split("/")
        for i in range(1, len(parts) + 1):
            seen.setdefault(_fold("/".join(parts[:i])), "/".join(parts[:i]))
    for key in keys:
        parts = (key,) if isinstance(key, str) else tuple(key)
        for part in parts:
            why = key_name_problem(part)
            if why is not None:
                what = "its name" if len(parts) == 1 else "its component"
                raise ValueError(f"Key {_short(key)} cannot be stored: {what} {_short(part)} {why}; {_NAME_RULE}. "
                                 f"Rename it before writing (td.rename_key_(old, new)); nothing was written.")
        for i in range(1, len(parts) + 1):
            prefix = "/".join(parts[:i])
            other = seen.setdefault(_fold(prefix), prefix)
            if other != prefix:
                raise ValueError(
                    f"Key {_short(key)} cannot be stored: {_short(prefix)} differs from {_short(other)} (a key of "
                    f"the store or of this write) only in letter case or Unicode normalisation, and macOS and "
                    f"Windows file systems see one folder for both. Rename it before writing; nothing was written.")


def _stack_trees(items: list) -> Any:
    from torch.utils._pytree import tree_map

    first = items[0]
    if isinstance(first, torch.Tensor):
        return torch.stack(items, 0)
    return tree_map(lambda *xs: torch.stack(xs, 0), first, *items[1:])
