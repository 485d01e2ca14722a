"""Export a memory to ``.npz`` or a Minari dataset, and import one into a new memory.

``robotmem export PATH OUT`` and ``robotmem import SRC PATH``; the format is
taken from the name (``*.npz``: NumPy, anything else: a Minari dataset
directory named ``NAME-vVERSION``) or from ``--format``.

* **npz**: one array per stored key (nested keys joined with ``/``, e.g.
  ``next/observation``), rows in write order (oldest first), the tag columns
  ``episode`` / ``run`` / ``env`` among them, and ``__robotmem__``: a 0-d
  string array holding JSON (env names, data kind, ``ndim``, ``max_size``,
  ``rows``). Nothing is pickled. ``import`` restores every column and tag, so
  npz -> memory -> npz is bit-exact.
* **Minari**: one Minari episode per stored episode (write order):
  observations (``T + 1`` steps: the root values of each transition, then the
  last ``next`` values) are a ``Dict`` of the keys stored both at the root and
  under ``next`` (``observation``, ``achieved_goal``, ``desired_goal``, ...),
  actions, rewards, terminations, truncations and ``infos["is_success"]``. The
  memory's env names, each episode's env and run and the source schema go in
  the dataset's metadata under ``"torchrl_robotmem"``. ``import`` reads a local
  dataset (a directory, or an id under ``MINARI_DATASETS_PATH``; nothing is
  downloaded) episode by episode into transitions with ``next`` keys.

Every command that creates something (the memory of ``import``, the ``.npz``
or dataset directory of ``export``) builds it in a hidden sibling
``.NAME.partial-PID`` of the target and renames it into place once it is
complete: a command killed at any moment leaves nothing at the target, only
that sibling, which the next run on the same target removes (once its process
is gone). A target that is a store URL (``s3://...``, ``memory://...``) cannot
be renamed into place and is written directly. A source that is cut off or
damaged (a truncated ``.npz`` or HDF5 file, a ``metadata.json`` that
disagrees with the episodes present) is one error line naming the file, and
nothing is created.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import warnings
import zipfile
import zlib
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from . import CLIError

if TYPE_CHECKING:
    from torchrl_robotmem.storage import ZarrStorage
from ._memory import (
    DONE_KEY,
    SUCCESS_KEY,
    column,
    has_key,
    open_memory,
    partial_builds,
    partial_path,
    root_attrs,
    write_order,
)

__all__ = ["export_npz", "import_npz", "export_minari", "import_minari", "add_arguments", "run"]

HELP = {
    "export": "Export a memory to .npz or a Minari dataset directory.",
    "import": "Import a .npz file or a local Minari dataset into a new memory.",
}
META_KEY = "__robotmem__"
NPZ_FORMAT = "torchrl_robotmem.npz"
NPZ_VERSION = 1
TAGS = ("episode", "run", "env")
# stored at the root and under "next" but not observations
_NOT_OBS = {"done", "terminated", "truncated", "reward", "is_success", "step_count"}
_MINARI_NAME = re.compile(r"^[-_\w]+?-v\d+$")


def _progress(iterable, **kwargs):
    from tqdm.auto import tqdm

    return tqdm(iterable, disable=None, leave=False, **kwargs)  # disable=None: only on a terminal


def _check_target(path: str) -> None:
    if os.path.lexists(path):
        raise CLIError(f"{path!r} exists; refusing to overwrite it. Remove it or choose another name.")


# -- atomic targets ----------------------------------------------------------------------------------


def _is_local(path: Any) -> bool:
    from torchrl_robotmem.storage._backend import is_url, normalize_path

    name = normalize_path(path)
    return isinstance(name, str) and not is_url(name)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _remove(path: str) -> None:
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path)
    else:
        os.unlink(path)


def _remove_stale_partials(path: str) -> list[str]:
    """Removes the partial builds of ``path`` whose process is gone (killed); returns their paths.

    Only names of the form ``.NAME.partial-PID`` in the target's own directory
    are considered; nothing else is touched.
    """
    removed = []
    for partial, pid in partial_builds(path):
        if pid == os.getpid() or _pid_alive(pid):
            continue
        _remove(partial)
        removed.append(partial)
    return removed


@contextlib.contextmanager
def _atomic_target(path: str, *, inner: str | None = None) -> Iterator[str]:
    """Yields the hidden sibling to build ``path`` in; renames it to ``path`` if the block succeeds.

    ``inner``: the block builds ``SIBLING/inner`` (a Minari dataset inside its
    datasets root), which is what becomes ``path``. On any error, and on a
    ``KeyboardInterrupt``, the sibling is removed; a SIGKILL leaves it, and the
    next command on ``path`` removes it.
    """
    parent = os.path.dirname(os.path.abspath(path))
    missing = []  # the directories made for the target, deepest first: removed again if it is not made
    d = parent
    while not os.path.isdir(d) and os.path.dirname(d) != d:
        missing.append(d)
        d = os.path.dirname(d)
    os.makedirs(parent, exist_ok=True)
    _remove_stale_partials(path)
    tmp = partial_path(path)
    if os.path.lexists(tmp):  # this pid's own leftover (pids are reused): no live process owns it
        _remove(tmp)
    done = False
    try:
        yield tmp
        _check_target(path)  # created meanwhile by someone else: theirs is kept
        os.rename(os.path.join(tmp, inner) if inner else tmp, path)
        done = True
    finally:
        if os.path.lexists(tmp):
            _remove(tmp)
        for d in missing if not done else ():
            try:
                os.rmdir(d)
            except OSError:  # not empty: something else was put there meanwhile
                break


def _path(key: Any) -> str:
    return key if isinstance(key, str) else "/".join(key)


# -- npz ---------------------------------------------------------------------------------------------


def export_npz(path: Any, out: str) -> dict[str, Any]:
    """Writes every column of the memory at ``path`` to ``out`` (``.npz``), rows in write order.

    Args:
        path: the memory (opened read-only).
        out (str): the ``.npz`` file to create (refused if it exists).

    Returns:
        the JSON metadata written under ``__robotmem__``.

    Example:
        >>> import tempfile, numpy as np, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.cli.transfer import export_npz
        >>> d = tempfile.mkdtemp()
        >>> st = ZarrStorage(d + "/m.zarr", 10, env="FetchReach-v4", background=False)
        >>> st.set(slice(0, 3), TensorDict({"obs": torch.arange(3.0), ("next", "done"): torch.ones(3, 1, dtype=torch.bool)}, [3]))
        >>> st.close()
        >>> meta = export_npz(d + "/m.zarr", d + "/m.npz")
        >>> sorted(np.load(d + "/m.npz").files)
        ['__robotmem__', 'env', 'episode', 'next/done', 'obs', 'run']
        >>> np.load(d + "/m.npz")["episode"].tolist(), meta["env_names"]
        ([0, 1, 2], ['FetchReach-v4'])
    """
    _check_target(out)
    if not out.endswith(".npz"):
        raise CLIError(f"{out!r}: an npz export's name ends with .npz")
    storage = open_memory(path)
    try:
        attrs = root_attrs(storage)
        schema = attrs.get("schema") or {}
        if META_KEY in schema:
            raise CLIError(f"the memory has a key named {META_KEY!r}, which the npz format reserves")
        order = write_order(storage)
        arrays = {p: column(storage, tuple(p.split("/")) if "/" in p else p, order)
                  for p in _progress(sorted(schema), desc="export", unit="key")}
        meta = {
            "format": NPZ_FORMAT,
            "version": NPZ_VERSION,
            "source": str(storage.path),
            "env_names": list(storage.env_names),
            "kind": attrs.get("kind"),
            "ndim": int(attrs.get("ndim", 1)),
            "max_size": int(storage.max_size),
            "rows": len(storage),
            "schema": schema,
        }
    finally:
        storage.close()
    with _atomic_target(out) as tmp:
        np.savez(tmp, **arrays, **{META_KEY: np.array(json.dumps(meta))})
    return meta


def import_npz(src: str, path: str, *, max_size: int | None = None, env: str | None = None) -> int:
    """Creates the memory ``path`` from an ``.npz`` written by :func:`export_npz`; returns its rows.

    Args:
        src (str): the ``.npz`` file (loaded with ``allow_pickle=False``).
        path (str): the memory to create (refused if it exists).

    Keyword Args:
        max_size (int, optional): capacity; defaults to the exported memory's.
        env (str, optional): tag every row with this env instead of the exported env tags.

    Example:
        >>> import tempfile, numpy as np, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.cli.transfer import export_npz, import_npz
        >>> d = tempfile.mkdtemp()
        >>> st = ZarrStorage(d + "/a.zarr", 10, background=False)
        >>> st.set(slice(0, 4), TensorDict({"obs": torch.arange(4.0)}, [4]))
        >>> st.close()
        >>> _ = export_npz(d + "/a.zarr", d + "/a.npz")
        >>> import_npz(d + "/a.npz", d + "/b.zarr")
        4
        >>> ZarrStorage(d + "/b.zarr", read_only=True)["obs"].tolist()
        [0.0, 1.0, 2.0, 3.0]
    """
    import torch
    from tensordict import TensorDict


    _check_target(path)
    if not os.path.isfile(src):
        raise CLIError(f"{src!r} is not a file")
    data, meta = _open_npz(src)
    if meta.get("format") != NPZ_FORMAT or int(meta.get("version", 0)) > NPZ_VERSION:
        raise CLIError(f"{src!r}: unknown npz format {meta.get('format')!r} version {meta.get('version')!r}")
    keys = [k for k in data.files if k != META_KEY]
    schema = meta.get("schema") or {}
    missing = sorted(set(schema) - set(keys))
    if missing:
        raise CLIError(f"{src!r} lacks the arrays {missing} its metadata lists (a cut-off export?); export it again")
    arrays = {k: _read_npz_array(data, src, k) for k in _progress(keys, desc="read", unit="key")}
    rows = int(meta.get("rows", 0))
    ndim = int(meta.get("ndim", 1))
    lead = None
    for k, a in arrays.items():
        spec = schema.get(k)
        if spec is not None and (str(a.dtype) != spec["dtype"] or
                                 list(a.shape[a.ndim - len(spec["shape"]):]) != spec["shape"]):
            raise CLIError(f"{src!r}: array {k!r} has dtype {a.dtype} and shape {list(a.shape)}, "
                           f"its metadata says {spec['dtype']} {spec['shape']} per row")
        n0 = a.shape[0] if a.ndim else None
        if n0 is None or (lead is not None and n0 != lead[1]) or (ndim == 1 and n0 != rows):
            raise CLIError(f"{src!r}: array {k!r} holds {n0} rows, but "
                           + (f"{lead[0]!r} holds {lead[1]}" if lead is not None and n0 != lead[1]
                              else f"the metadata says {rows}") + " (a cut-off or edited export); export it again")
        lead = lead or (k, n0)
    capacity = int(max_size or meta.get("max_size") or rows)
    if capacity < rows:
        raise CLIError(f"--max-size {capacity} is smaller than the {rows} rows in {src!r}")
    with _new_store(path, capacity, ndim=ndim, background=False) as storage:
        if rows:
            tag_arrays = {k: arrays.pop(k) for k in TAGS if k in arrays}
            lead = next(iter(tag_arrays.values())).shape if tag_arrays else None
            body = {k: torch.from_numpy(a) for k, a in arrays.items()}
            td = TensorDict.from_dict(_nest(body), batch_size=lead or [len(next(iter(body.values())))],
                                      auto_batch_size=False)
            env_names = list(meta.get("env_names", []))
            zarr_meta: dict[str, Any] = {"kind": meta.get("kind"), "ndim": ndim, "env_names": env_names}
            if tag_arrays:
                tags = {k: torch.from_numpy(a) for k, a in tag_arrays.items()}
                if env is not None:
                    zarr_meta["env_names"] = [env]
                    tags["env"] = torch.zeros_like(tags["env"])
                zarr_meta["tags"] = TensorDict(tags, batch_size=lead).state_dict()
            try:
                storage.load_state_dict({"_storage": td, "_len": rows, "initialized": True, "zarr": zarr_meta})
            except (ValueError, TypeError, KeyError) as err:  # what the storage refuses: a reserved key, a bad env code...
                raise CLIError(f"{src!r}: {err}") from None
        elif env is not None:
            storage.env = env
    return rows


#: What reading a truncated or damaged npz member raises (zlib, zip and numpy's own checks).
_NPZ_READ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error)


def _open_npz(src: str):
    """``(NpzFile, metadata dict)`` of an npz export, or a :class:`CLIError` naming the file."""
    try:
        data = np.load(src, allow_pickle=False)
    except _NPZ_READ_ERRORS as err:
        raise CLIError(f"{src!r} is not an npz export of a torchrl_robotmem memory (it cannot be read as npz: "
                       f"{type(err).__name__}: {err}; a truncated file?)") from None
    if not hasattr(data, "files"):
        raise CLIError(f"{src!r} is not an npz export of a torchrl_robotmem memory (one .npy array, not an npz)")
    try:
        meta = json.loads(str(_read_npz_array(data, src, META_KEY)))
    except CLIError:
        if META_KEY in data.files:
            raise
        raise CLIError(f"{src!r} is not an npz export of a torchrl_robotmem memory (no {META_KEY!r} array)") from None
    except ValueError as err:
        raise CLIError(f"{src!r}: its {META_KEY!r} array is not JSON ({err})") from None
    if not isinstance(meta, dict):
        raise CLIError(f"{src!r}: its {META_KEY!r} array is not a JSON object")
    return data, meta


def _read_npz_array(data, src: str, key: str) -> np.ndarray:
    if key not in data.files:
        raise CLIError(f"{src!r} has no array {key!r}")
    try:
        return data[key]
    except _NPZ_READ_ERRORS as err:
        raise CLIError(f"{src!r}: array {key!r} cannot be read ({type(err).__name__}: {err}); the file is "
                       f"truncated or damaged: export it again") from None


def _nest(flat: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for path, value in flat.items():
        node = out
        parts = path.split("/")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


@contextlib.contextmanager
def _new_store(path: str, capacity: int, **kwargs) -> Iterator[ZarrStorage]:
    """A new store for an import, built beside ``path`` and renamed to it once closed (see :func:`_atomic_target`).

    If the import fails, or is killed, nothing is at ``path``. A store URL is
    written in place (an object store has no rename) and left as it is on failure.
    """
    from torchrl_robotmem.storage import ZarrStorage

    with _atomic_target(path) if _is_local(path) else contextlib.nullcontext(path) as target:
        storage = ZarrStorage(target, capacity, **kwargs)
        try:
            yield storage
        finally:
            storage.close()


# -- Minari ------------------------------------------------------------------------------------------


def _minari_target(out: str) -> tuple[str, str]:
    """``(datasets_root, dataset_id)`` of a Minari dataset directory ``out`` (``ROOT/NAME-vN``)."""
    out = os.path.abspath(out)
    name = os.path.basename(out.rstrip("/"))
    if not _MINARI_NAME.match(name):
        raise CLIError(f"{out!r}: a Minari dataset directory is named NAME-vVERSION, e.g. exports/fetchpush-v0")
    return os.path.dirname(out), name


def _obs_keys(storage, requested: list[str] | None) -> list[str]:
    keys = storage.view().keys()  # top-level keys
    if requested:
        bad = [k for k in requested if k not in keys or ("next", k) not in storage.view().keys(True, True)]
        if bad:
            raise CLIError(f"--obs-keys {bad}: not stored both at the root and under 'next'")
        return list(requested)
    return [k for k in sorted(keys) if k not in _NOT_OBS and k not in TAGS and k != "next"
            and not hasattr(storage.view().get(k), "keys") and ("next", k) in storage.view().keys(True, True)]


def export_minari(path: Any, out: str, *, obs_keys: list[str] | None = None) -> dict[str, Any]:
    """Writes the memory at ``path`` as a Minari dataset in the directory ``out`` (``ROOT/NAME-vN``).

    Uses :func:`minari.create_dataset_from_buffers` with ``MINARI_DATASETS_PATH``
    set to ``ROOT`` while it runs (nothing is downloaded; no env is created:
    the spaces are ``Box`` spaces of the stored shapes and dtypes).

    Args:
        path: the memory (opened read-only); its rows must be TensorDicts with
            ``action`` and ``("next", "done")``.
        out (str): the dataset directory to create (refused if it exists).

    Keyword Args:
        obs_keys (list of str, optional): the observation keys; defaults to every
            key stored both at the root and under ``next`` except flags, rewards
            and step counters.

    Returns:
        ``{"dataset_id", "episodes", "steps", "obs_keys"}``.
    """
    import gymnasium as gym

    _check_target(out)
    root, dataset_id = _minari_target(out)
    storage = open_memory(path)
    try:
        if not has_key(storage, "episode") or storage.ndim != 1 or storage.view().get("episode").ndim != 1:
            raise CLIError("only memories of flat transitions (TensorDict rows, ndim=1) export to Minari")
        for key in ("action", DONE_KEY):
            if not has_key(storage, key):
                raise CLIError(f"the memory has no {_path(key)!r} column; a Minari export needs it")
        keys = _obs_keys(storage, obs_keys)
        if not keys:
            raise CLIError("no observation keys (stored both at the root and under 'next'); pass --obs-keys")
        order = write_order(storage)
        cols = {k: column(storage, k, order) for k in keys}
        nxt = {k: column(storage, ("next", k), order) for k in keys}
        action = column(storage, "action", order)
        n = len(order)
        reward = column(storage, ("next", "reward"), order).reshape(n) if has_key(storage, ("next", "reward")) \
            else np.zeros(n, np.float32)
        done = column(storage, DONE_KEY, order).reshape(n, -1).any(-1)
        trunc = column(storage, ("next", "truncated"), order).reshape(n, -1).any(-1) \
            if has_key(storage, ("next", "truncated")) else np.zeros(n, bool)
        term = column(storage, ("next", "terminated"), order).reshape(n, -1).any(-1) \
            if has_key(storage, ("next", "terminated")) else done & ~trunc
        success = column(storage, SUCCESS_KEY, order).reshape(n, -1)[:, 0] if has_key(storage, SUCCESS_KEY) else None
        episode, run, env = (column(storage, k, order) for k in TAGS)
        env_names = list(storage.env_names)
        schema = root_attrs(storage).get("schema") or {}
    finally:
        storage.close()

    from minari.data_collector.episode_buffer import EpisodeBuffer

    # episodes in order of first appearance (rows of one episode are contiguous in write order
    # unless a ring cut them; np.unique groups them either way, keeping write order inside)
    ids, first = np.unique(episode, return_index=True)
    ids = ids[np.argsort(first)]
    by_episode = _group_rows(episode)
    buffers, ep_env, ep_run = [], [], []
    for i, e in enumerate(_progress(ids, desc="export", unit="episode")):
        rows = by_episode[e]
        last = rows[-1:]
        obs = {k: np.concatenate([cols[k][rows], nxt[k][last]]) for k in keys}
        truncations = trunc[rows].copy()
        if not (term[last] | trunc[last]).any():
            truncations[-1] = True  # an open (or ring-cut) episode ends here
        infos = {}
        if success is not None:
            infos["is_success"] = np.concatenate([np.zeros(1, success.dtype), success[rows]])
        buffers.append(EpisodeBuffer(
            id=i, observations=obs if len(keys) > 1 else obs[keys[0]], actions=action[rows],
            rewards=reward[rows], terminations=term[rows], truncations=truncations, infos=infos or None))
        ep_env.append(int(env[rows[0]]))
        ep_run.append(int(run[rows[0]]))

    def box(a: np.ndarray):
        return gym.spaces.Box(-np.inf, np.inf, a.shape[1:], a.dtype)

    obs_space = gym.spaces.Dict({k: box(cols[k]) for k in keys}) if len(keys) > 1 else box(cols[keys[0]])
    old = os.environ.get("MINARI_DATASETS_PATH")
    # built in a hidden datasets root beside `out` (ROOT/.NAME-vN.partial-PID/NAME-vN), moved to `out` when complete
    with _atomic_target(os.path.join(root, dataset_id), inner=dataset_id) as build_root:
        os.makedirs(build_root)
        os.environ["MINARI_DATASETS_PATH"] = build_root
        try:
            import minari

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # minari's "author is None" etc.
                ds = minari.create_dataset_from_buffers(
                    dataset_id, buffers, observation_space=obs_space, action_space=box(action),
                    algorithm_name="torchrl_robotmem export", description=f"exported by torchrl_robotmem from {path}",
                    data_format="hdf5",
                )
                ds.storage.update_metadata({"torchrl_robotmem": {
                    "env_names": env_names, "episode_env": ep_env, "episode_run": ep_run, "obs_keys": keys,
                    "schema": schema, "source": str(path)}})
        finally:
            if old is None:
                os.environ.pop("MINARI_DATASETS_PATH", None)
            else:
                os.environ["MINARI_DATASETS_PATH"] = old
    return {"dataset_id": dataset_id, "episodes": len(buffers), "steps": int(n), "obs_keys": keys}


def _group_rows(values: np.ndarray) -> dict[int, np.ndarray]:
    order = np.argsort(values, kind="stable")
    uniq, starts = np.unique(values[order], return_index=True)
    return {u: g for u, g in zip(uniq, np.split(order, starts[1:]))}


def _open_minari(src: str):
    """``(MinariDataset, data directory)`` of a local dataset, or a :class:`CLIError` naming what is wrong."""
    import minari

    candidates = [os.path.join(src, "data"), src] if os.path.isdir(src) else []
    data_dir = next((c for c in candidates if os.path.isfile(os.path.join(c, "metadata.json"))), None)
    if data_dir is None:
        if os.path.exists(src):
            raise CLIError(f"{src!r} is not a Minari dataset (no data/metadata.json)")
        root = os.environ.get("MINARI_DATASETS_PATH") or os.path.join(os.path.expanduser("~"), ".minari", "datasets")
        local = os.path.join(root, src)
        if not os.path.isfile(os.path.join(local, "data", "metadata.json")):
            raise CLIError(f"{src!r} is neither a Minari dataset directory nor a local dataset id (looked in "
                           f"{local}); nothing is downloaded: pass the dataset directory")
        data_dir = os.path.join(local, "data")
    try:
        ds = minari.MinariDataset(data_dir)
    except json.JSONDecodeError as err:
        raise CLIError(f"{os.path.join(data_dir, 'metadata.json')!r} is not valid JSON ({err}): the dataset was "
                       f"cut off or damaged; export it again") from None
    except Exception as err:  # noqa: BLE001 - whatever minari / h5py raise on a damaged dataset: one line, no traceback
        raise CLIError(f"{data_dir!r}: the Minari dataset cannot be opened ({type(err).__name__}: {err}); a "
                       f"cut-off or damaged export? Export it again") from None
    _check_minari_complete(ds, data_dir)
    return ds, data_dir


def _check_minari_complete(ds, data_dir: str) -> None:
    """Refuses an HDF5 dataset whose ``metadata.json`` and ``main_data.hdf5`` disagree (a cut-off export).

    Minari writes ``metadata.json`` (with 0 episodes) first, then the episodes,
    then the final counts: a run cut in between leaves episodes the metadata
    does not count, or the reverse.
    """
    meta_file = os.path.join(data_dir, "metadata.json")
    try:
        episodes, steps = int(ds.total_episodes), int(ds.total_steps)
        data_format = ds.storage.metadata.get("data_format", "hdf5")
    except (KeyError, TypeError, ValueError) as err:
        raise CLIError(f"{meta_file!r}: no valid episode / step counts ({type(err).__name__}: {err})") from None
    data_file = os.path.join(data_dir, "main_data.hdf5")
    if data_format != "hdf5" or not os.path.isfile(data_file):
        return
    import h5py

    try:
        with h5py.File(data_file, "r") as f:
            names = set(f.keys())
            expected = {f"episode_{i}" for i in range(episodes)}
            missing = sorted(expected - names, key=lambda n: int(n.rsplit("_", 1)[1]))
            held = sum(int(f[n].attrs.get("total_steps", 0)) for n in expected & names)
            held_all = sum(int(f[n].attrs.get("total_steps", 0)) for n in names)
    except Exception as err:  # noqa: BLE001 - h5py's errors on a truncated file are OSError, KeyError, ...
        raise CLIError(f"{data_file!r} cannot be read ({type(err).__name__}: {err}): the dataset was cut off or "
                       f"damaged; export it again") from None
    if missing or len(names) != episodes or held != steps:
        raise CLIError(
            f"{meta_file!r} lists {episodes} episodes ({steps} steps) but {data_file!r} holds {len(names)} "
            f"episodes ({held_all} steps{'; missing ' + ', '.join(missing[:3]) if missing else ''}): the export "
            f"was cut off or the files were changed; export it again"
        )


def import_minari(src: str, path: str, *, max_size: int | None = None, env: str | None = None) -> int:
    """Creates the memory ``path`` from a local Minari dataset, episode by episode; returns its rows.

    Each episode of ``T`` steps becomes ``T`` transitions: the observation keys
    at the root (steps ``0..T-1``) and under ``next`` (steps ``1..T``),
    ``action``, ``("next", "reward")``, ``("next", "terminated")``, ``("next",
    "truncated")``, ``("next", "done")`` (their or), ``done`` (False) and,
    when the infos carry it, ``("next", "is_success")``. An episode ending
    with neither flag is marked truncated at its last step. Rows are tagged
    with ``env`` (default: the env the export recorded per episode, else the
    dataset's env id).

    A dataset whose files disagree (``metadata.json`` against the episodes in
    ``main_data.hdf5``: a cut-off export) or cannot be read is refused with a
    :class:`CLIError` naming the file and the episode; nothing is created.

    Args:
        src (str): the dataset directory (``ROOT/NAME-vN`` or its ``data/``), or a
            dataset id under ``MINARI_DATASETS_PATH`` (never downloaded).
        path (str): the memory to create (refused if it exists).

    Keyword Args:
        max_size (int, optional): capacity; defaults to the dataset's step count.
        env (str, optional): the env name to tag every row with.
    """
    import torch
    from tensordict import TensorDict
    from torchrl.data import ReplayBuffer

    _check_target(path)
    ds, data_dir = _open_minari(src)
    meta = ds.storage.metadata.get("torchrl_robotmem") or {}
    schema = meta.get("schema") or {}
    env_names = meta.get("env_names") or []
    episode_env = meta.get("episode_env")
    spec_env = getattr(getattr(ds.spec, "env_spec", None), "id", None)
    steps = int(ds.total_steps)
    if steps == 0 and not max_size:
        raise CLIError(f"{src!r} holds no steps: nothing to import (pass --max-size N to create an empty memory)")
    capacity = int(max_size or steps)
    if capacity < steps:
        raise CLIError(f"--max-size {capacity} is smaller than the {steps} steps of {src!r}")

    def cast(key: str, value: np.ndarray, dtype, shape) -> torch.Tensor:
        spec = schema.get(key)
        t = torch.from_numpy(np.ascontiguousarray(value))
        if spec is not None:
            from torchrl_robotmem.storage._backend import torch_dtype

            return t.to(torch_dtype(spec["dtype"])).reshape(len(t), *spec["shape"])
        return t.to(dtype).reshape(len(t), *shape) if dtype is not None else t

    def transitions(ep) -> TensorDict | None:
        T = len(ep.actions) if not isinstance(ep.actions, dict) else len(next(iter(ep.actions.values())))
        if T == 0:
            return None
        obs = ep.observations if isinstance(ep.observations, dict) else {"observation": ep.observations}
        term = np.asarray(ep.terminations, bool).reshape(T)
        trunc = np.asarray(ep.truncations, bool).reshape(T).copy()
        if not (term[-1] or trunc[-1]):
            trunc[-1] = True
        td = {"action": cast("action", np.asarray(ep.actions), None, None),
              "done": torch.zeros(T, 1, dtype=torch.bool)}
        nxt = {"reward": cast("next/reward", np.asarray(ep.rewards), torch.float32, (1,)),
               "terminated": cast("next/terminated", term, torch.bool, (1,)),
               "truncated": cast("next/truncated", trunc, torch.bool, (1,)),
               "done": cast("next/done", term | trunc, torch.bool, (1,))}
        for k, v in obs.items():
            v = np.asarray(v)
            if len(v) != T + 1:
                raise ValueError(f"observations {k!r} hold {len(v)} steps, an episode of {T} actions needs {T + 1}")
            td[k] = cast(k, v[:-1], None, None)
            nxt[k] = cast(f"next/{k}", v[1:], None, None)
        infos = ep.infos or {}
        succ = infos.get("is_success", infos.get("success"))
        if succ is not None and len(succ) == T + 1:
            nxt["is_success"] = cast("next/is_success", np.asarray(succ)[1:], torch.float32, ())
        td["next"] = nxt
        return TensorDict(td, batch_size=[T])

    episodes = ds.iterate_episodes()
    where = os.path.join(data_dir, "main_data.hdf5") if os.path.isfile(os.path.join(data_dir, "main_data.hdf5")) \
        else data_dir
    with _new_store(path, capacity, background=True) as storage:
        rb = ReplayBuffer(storage=storage, batch_size=1)
        for i in _progress(range(ds.total_episodes), desc="import", unit="episode"):
            try:
                ep = next(episodes)
            except StopIteration:
                raise CLIError(f"{src!r}: episode {i} is missing ({ds.total_episodes} listed): a cut-off "
                               f"export? Export it again") from None
            except Exception as err:  # noqa: BLE001 - minari / h5py on a damaged file: one line, no traceback
                raise CLIError(f"{src!r}: episode {i} cannot be read from {where!r} ({type(err).__name__}: "
                               f"{err}); the dataset was cut off or damaged: export it again") from None
            try:
                td = transitions(ep)
                if td is None:
                    continue
                name = env
                if (name is None and episode_env is not None and i < len(episode_env)
                        and 0 <= episode_env[i] < len(env_names)):
                    name = env_names[episode_env[i]]
                storage.env = name if name is not None else spec_env
                rb.extend(td)
            except (ValueError, TypeError, KeyError, IndexError, RuntimeError) as err:
                raise CLIError(f"{src!r}: episode {i} cannot be imported ({type(err).__name__}: {err})") from None
        rows = len(storage)
    return rows


# -- command line ------------------------------------------------------------------------------------


def _format(name: str, given: str | None) -> str:
    if given:
        return given
    return "npz" if name.endswith(".npz") else "minari"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    command = parser.get_default("command")
    if command == "export":
        parser.add_argument("path", help="the memory to export (opened read-only)")
        parser.add_argument("out", help="OUT.npz, or a Minari dataset directory ROOT/NAME-vVERSION")
        parser.add_argument("--obs-keys", default=None,
                            help="Minari: comma-separated observation keys (default: keys stored at the root and under next)")
    else:
        parser.add_argument("src", help="SRC.npz, a Minari dataset directory, or a local Minari dataset id")
        parser.add_argument("path", help="the memory to create (must not exist)")
        parser.add_argument("--max-size", type=int, default=None, help="capacity (default: what is imported)")
        parser.add_argument("--env", default=None, help="tag every imported row with this env name")
    parser.add_argument("--format", choices=("npz", "minari"), default=None,
                        help="default: npz for *.npz names, else minari")


def run(args: argparse.Namespace) -> int:
    if args.command == "export":
        fmt = _format(args.out, args.format)
        if fmt == "npz":
            meta = export_npz(args.path, args.out)
            print(f"exported {meta['rows']:,} rows ({len(meta['schema'])} keys) to {args.out}")
        else:
            keys = args.obs_keys.split(",") if args.obs_keys else None
            info = export_minari(args.path, args.out, obs_keys=keys)
            print(f"exported {info['episodes']:,} episodes ({info['steps']:,} steps, observations "
                  f"{', '.join(info['obs_keys'])}) to the Minari dataset {args.out}")
        return 0
    if args.max_size is not None and args.max_size <= 0:
        raise CLIError(f"--max-size must be a positive integer, got {args.max_size}")
    fmt = _format(args.src, args.format)
    importer = import_npz if fmt == "npz" else import_minari
    rows = importer(args.src, args.path, max_size=args.max_size, env=args.env)
    print(f"imported {rows:,} rows into {args.path}")
    return 0
