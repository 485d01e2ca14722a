"""A memory as a Minari dataset: :func:`export_minari` writes one, :func:`import_minari` reads one into a new memory.

One Minari episode per stored episode (write order): observations (``T + 1``
steps: the root values of each transition, then the last ``next`` values) are
a ``Dict`` of the keys stored both at the root and under ``next``
(``observation``, ``achieved_goal``, ``desired_goal``, ...), actions, rewards,
terminations, truncations and ``infos["is_success"]``. The memory's env names,
each episode's env and run and the source schema go in the dataset's metadata
under ``"torchrl_robotmem"``. ``import`` reads a local dataset (a directory, or
an id under ``MINARI_DATASETS_PATH``; nothing is downloaded) episode by episode
into transitions with ``next`` keys.

Both build their output beside the target and rename it into place
(:mod:`._build`). A dataset that is cut off or damaged (a truncated HDF5 file,
a ``metadata.json`` that disagrees with the episodes present) is one
:class:`~torchrl_robotmem.cli.CLIError` naming the file, and nothing is created.
"""
from __future__ import annotations

import json
import os
import re
import warnings
from typing import Any

import numpy as np

from ._build import atomic_target, check_target, new_store, progress
from ._memory import DONE_KEY, SUCCESS_KEY, TAGS, column, has_key, open_settled, root_attrs, write_order
from .errors import CLIError
from .transitions import cast_float64

__all__ = ["export_minari", "import_minari", "open_minari"]

# stored at the root and under "next" but not observations
_NOT_OBS = {"done", "terminated", "truncated", "reward", "is_success", "step_count"}
_MINARI_NAME = re.compile(r"^[-_\w]+?-v\d+$")


def _path(key: Any) -> str:
    return key if isinstance(key, str) else "/".join(key)


# -- export ------------------------------------------------------------------------------------------


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
    check_target(out)
    root, dataset_id = _minari_target(out)
    c = _read_transitions(path, obs_keys)
    buffers, ep_env, ep_run = _episode_buffers(c)
    meta = {"env_names": c["env_names"], "episode_env": ep_env, "episode_run": ep_run, "obs_keys": c["keys"],
            "schema": c["schema"], "source": str(path)}
    _write_dataset(root, dataset_id, buffers, c, meta, description=f"exported by torchrl_robotmem from {path}")
    return {"dataset_id": dataset_id, "episodes": len(buffers), "steps": int(c["n"]), "obs_keys": c["keys"]}


def _read_transitions(path: Any, obs_keys: list[str] | None) -> dict[str, Any]:
    """The columns a Minari export needs, in write order, read from the memory at ``path``."""
    storage = open_settled(path)
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
        n = len(order)

        def flag(key, default):
            return column(storage, key, order).reshape(n, -1).any(-1) if has_key(storage, key) else default

        c: dict[str, Any] = {"keys": keys, "n": n}
        c["cols"] = {k: column(storage, k, order) for k in keys}
        c["nxt"] = {k: column(storage, ("next", k), order) for k in keys}
        c["action"] = column(storage, "action", order)
        c["reward"] = column(storage, ("next", "reward"), order).reshape(n) \
            if has_key(storage, ("next", "reward")) else np.zeros(n, np.float32)
        done = column(storage, DONE_KEY, order).reshape(n, -1).any(-1)
        c["trunc"] = flag(("next", "truncated"), np.zeros(n, bool))
        c["term"] = flag(("next", "terminated"), None)
        c["term"] = done & ~c["trunc"] if c["term"] is None else c["term"]
        c["success"] = column(storage, SUCCESS_KEY, order).reshape(n, -1)[:, 0] if has_key(storage, SUCCESS_KEY) \
            else None
        c["episode"], c["run"], c["env"] = (column(storage, k, order) for k in TAGS)
        c["env_names"] = list(storage.env_names)
        c["schema"] = root_attrs(storage).get("schema") or {}
    finally:
        storage.close()
    return c


def _episode_buffers(c: dict[str, Any]) -> tuple[list, list[int], list[int]]:
    """``(EpisodeBuffers, env code per episode, run per episode)``, episodes in order of first appearance."""
    from minari.data_collector.episode_buffer import EpisodeBuffer

    keys, episode, trunc, term, success = c["keys"], c["episode"], c["trunc"], c["term"], c["success"]
    # episodes in order of first appearance (rows of one episode are contiguous in write order
    # unless a ring cut them; np.unique groups them either way, keeping write order inside)
    ids, first = np.unique(episode, return_index=True)
    ids = ids[np.argsort(first)]
    by_episode = _group_rows(episode)
    buffers, ep_env, ep_run = [], [], []
    for i, e in enumerate(progress(ids, desc="export", unit="episode")):
        rows = by_episode[e]
        last = rows[-1:]
        obs = {k: np.concatenate([c["cols"][k][rows], c["nxt"][k][last]]) for k in keys}
        truncations = trunc[rows].copy()
        if not (term[last] | trunc[last]).any():
            truncations[-1] = True  # an open (or ring-cut) episode ends here
        infos = {}
        if success is not None:
            infos["is_success"] = np.concatenate([np.zeros(1, success.dtype), success[rows]])
        buffers.append(EpisodeBuffer(
            id=i, observations=obs if len(keys) > 1 else obs[keys[0]], actions=c["action"][rows],
            rewards=c["reward"][rows], terminations=term[rows], truncations=truncations, infos=infos or None))
        ep_env.append(int(c["env"][rows[0]]))
        ep_run.append(int(c["run"][rows[0]]))
    return buffers, ep_env, ep_run


def _write_dataset(root: str, dataset_id: str, buffers: list, c: dict[str, Any], meta: dict[str, Any], *,
                   description: str) -> None:
    """Creates the dataset ``ROOT/dataset_id`` from ``buffers``, built in a hidden datasets root and moved into place."""
    import gymnasium as gym

    def box(a: np.ndarray):
        return gym.spaces.Box(-np.inf, np.inf, a.shape[1:], a.dtype)

    keys = c["keys"]
    obs_space = gym.spaces.Dict({k: box(c["cols"][k]) for k in keys}) if len(keys) > 1 else box(c["cols"][keys[0]])
    old = os.environ.get("MINARI_DATASETS_PATH")
    # built in a hidden datasets root beside `out` (ROOT/.NAME-vN.partial-PID/NAME-vN), moved to `out` when complete
    with atomic_target(os.path.join(root, dataset_id), inner=dataset_id) as build_root:
        os.makedirs(build_root)
        os.environ["MINARI_DATASETS_PATH"] = build_root
        try:
            import minari

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # minari's "author is None" etc.
                ds = minari.create_dataset_from_buffers(
                    dataset_id, buffers, observation_space=obs_space, action_space=box(c["action"]),
                    algorithm_name="torchrl_robotmem export", description=description, data_format="hdf5",
                )
                ds.storage.update_metadata({"torchrl_robotmem": meta})
        finally:
            if old is None:
                os.environ.pop("MINARI_DATASETS_PATH", None)
            else:
                os.environ["MINARI_DATASETS_PATH"] = old


def _group_rows(values: np.ndarray) -> dict[int, np.ndarray]:
    order = np.argsort(values, kind="stable")
    uniq, starts = np.unique(values[order], return_index=True)
    return {u: g for u, g in zip(uniq, np.split(order, starts[1:]))}


# -- import ------------------------------------------------------------------------------------------


def open_minari(src: str):
    """``(MinariDataset, data directory)`` of a local dataset, or a :class:`CLIError` naming what is wrong.

    Args:
        src (str): the dataset directory (``ROOT/NAME-vN`` or its ``data/``), or a
            dataset id under ``MINARI_DATASETS_PATH`` (never downloaded).

    Example:
        >>> import tempfile
        >>> from torchrl_robotmem.cli import CLIError
        >>> from torchrl_robotmem.cli.minari_io import open_minari
        >>> try:
        ...     open_minari(tempfile.mkdtemp())
        ... except CLIError as err:
        ...     print(str(err).split(" is ")[1])
        not a Minari dataset (no data/metadata.json)
    """
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
    _refuse_outside_data(os.path.join(data_dir, "main_data.hdf5"))
    return ds, data_dir


def _refuse_outside_data(h5_path: str) -> None:
    """Raises a :class:`CLIError` naming them if datasets of the HDF5 file keep their bytes outside it.

    HDF5 lets a dataset read another file: external raw storage (any path), a virtual dataset over other
    files, an external link. An import would read that file into the new memory, so a dataset made by
    someone else could carry any file the user can read into a memory they later share. Soft links
    name objects of the same file and are followed.
    """
    if not os.path.isfile(h5_path):
        return  # another storage format (arrow): its columns are the dataset's own files
    import h5py

    bad: list[str] = []
    with h5py.File(h5_path, "r") as f:
        stack = [f]
        while stack:
            group = stack.pop()
            for name in group:
                path = f"{group.name.rstrip('/')}/{name}"
                link = group.get(name, getlink=True)
                if isinstance(link, h5py.ExternalLink):
                    bad.append(f"{path} (a link to {link.filename}:{link.path})")
                    continue
                if isinstance(link, h5py.SoftLink):
                    continue  # an object of this file, checked where it lies
                obj = group[name]
                if isinstance(obj, h5py.Group):
                    stack.append(obj)
                elif isinstance(obj, h5py.Dataset) and obj.external:
                    bad.append(f"{path} (its bytes in {obj.external[0][0]!r})")
                elif isinstance(obj, h5py.Dataset) and obj.is_virtual:
                    bad.append(f"{path} (a virtual dataset over other files)")
    if bad:
        shown = ", ".join(sorted(bad)[:3]) + (f" and {len(bad) - 3} more" if len(bad) > 3 else "")
        raise CLIError(f"{h5_path!r} holds {len(bad)} dataset(s) whose bytes lie outside it ({shown}): importing "
                       f"would copy another file into the memory, so nothing was imported. Export the dataset "
                       f"again with its data inside the file.")


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


def import_minari(src: str, path: str, *, max_size: int | None = None, env: str | None = None,
                  keep_float64: bool = False, notes: list[str] | None = None) -> int:
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
        keep_float64 (bool): keep float64 fields (default: stored as float32, as the recipes' envs write them).
        notes (list, optional): what was cast is appended here (one line).
    """
    from torchrl.data import ReplayBuffer

    check_target(path)
    ds, data_dir = open_minari(src)
    meta = ds.storage.metadata.get("torchrl_robotmem") or {}
    schema = meta.get("schema") or {}
    spec_env = getattr(getattr(ds.spec, "env_spec", None), "id", None)
    steps = int(ds.total_steps)
    if steps == 0 and not max_size:
        raise CLIError(f"{src!r} holds no steps: nothing to import (pass --max-size N to create an empty memory)")
    capacity = int(max_size or steps)
    if capacity < steps:
        raise CLIError(f"--max-size {capacity} is smaller than the {steps} steps of {src!r}")
    episodes = ds.iterate_episodes()
    where = os.path.join(data_dir, "main_data.hdf5") if os.path.isfile(os.path.join(data_dir, "main_data.hdf5")) \
        else data_dir
    cast: set[str] = set()
    with new_store(path, capacity, background=True) as storage:
        rb = ReplayBuffer(storage=storage, batch_size=1)
        for i in progress(range(ds.total_episodes), desc="import", unit="episode"):
            try:
                ep = next(episodes)
            except StopIteration:
                raise CLIError(f"{src!r}: episode {i} is missing ({ds.total_episodes} listed): a cut-off "
                               f"export? Export it again") from None
            except Exception as err:  # noqa: BLE001 - minari / h5py on a damaged file: one line, no traceback
                raise CLIError(f"{src!r}: episode {i} cannot be read from {where!r} ({type(err).__name__}: "
                               f"{err}); the dataset was cut off or damaged: export it again") from None
            try:
                td = _transitions(ep, schema)
                if td is None:
                    continue
                leaves = dict(td.items(True, True))
                for key in cast_float64(leaves, keep_float64=keep_float64):
                    td.set(key, leaves[key])
                    cast.add(_path(key))
                storage.env = _episode_env(i, env, meta, spec_env)
                rb.extend(td)
            except (ValueError, TypeError, KeyError, IndexError, RuntimeError) as err:
                raise CLIError(f"{src!r}: episode {i} cannot be imported ({type(err).__name__}: {err})") from None
        rows = len(storage)
    if cast and notes is not None:
        notes.append(f"float64 stored as float32 (--keep-float64 keeps it): {', '.join(sorted(cast))}")
    return rows


def _episode_env(i: int, env: str | None, meta: dict[str, Any], spec_env: str | None) -> str | None:
    """The env name episode ``i`` is tagged with: ``env``, else the one the export recorded, else the dataset's."""
    env_names = meta.get("env_names") or []
    episode_env = meta.get("episode_env")
    name = env
    if name is None and episode_env is not None and i < len(episode_env) and 0 <= episode_env[i] < len(env_names):
        name = env_names[episode_env[i]]
    return name if name is not None else spec_env


def _cast(schema: dict[str, Any], key: str, value: np.ndarray, dtype, shape):
    """``value`` as a tensor of the source schema's dtype and row shape for ``key``, else of ``dtype`` / ``shape``."""
    import torch

    from torchrl_robotmem.storage import torch_dtype

    spec = schema.get(key)
    t = torch.from_numpy(np.ascontiguousarray(value))
    if spec is not None:
        return t.to(torch_dtype(spec["dtype"])).reshape(len(t), *spec["shape"])
    return t.to(dtype).reshape(len(t), *shape) if dtype is not None else t


def _transitions(ep, schema: dict[str, Any]):
    """The ``T`` transitions (a TensorDict with ``next`` keys) of one Minari episode, or ``None`` if it is empty."""
    import torch
    from tensordict import TensorDict

    T = len(ep.actions) if not isinstance(ep.actions, dict) else len(next(iter(ep.actions.values())))
    if T == 0:
        return None
    obs = ep.observations if isinstance(ep.observations, dict) else {"observation": ep.observations}
    term = np.asarray(ep.terminations, bool).reshape(T)
    trunc = np.asarray(ep.truncations, bool).reshape(T).copy()
    if not (term[-1] or trunc[-1]):
        trunc[-1] = True
    td = {"action": _cast(schema, "action", np.asarray(ep.actions), None, None),
          "done": torch.zeros(T, 1, dtype=torch.bool)}
    nxt = {"reward": _cast(schema, "next/reward", np.asarray(ep.rewards), torch.float32, (1,)),
           "terminated": _cast(schema, "next/terminated", term, torch.bool, (1,)),
           "truncated": _cast(schema, "next/truncated", trunc, torch.bool, (1,)),
           "done": _cast(schema, "next/done", term | trunc, torch.bool, (1,))}
    for k, v in obs.items():
        v = np.asarray(v)
        if len(v) != T + 1:
            raise ValueError(f"observations {k!r} hold {len(v)} steps, an episode of {T} actions needs {T + 1}")
        td[k] = _cast(schema, k, v[:-1], None, None)
        nxt[k] = _cast(schema, f"next/{k}", v[1:], None, None)
    infos = ep.infos or {}
    succ = infos.get("is_success", infos.get("success"))
    if succ is not None and len(succ) == T + 1:
        nxt["is_success"] = _cast(schema, "next/is_success", np.asarray(succ)[1:], torch.float32, ())
    td["next"] = nxt
    return TensorDict(td, batch_size=[T])
