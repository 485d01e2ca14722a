"""A store's summary: rows, episodes, runs, success rates, env names and size on disk.

:meth:`ZarrStorage.summary <torchrl_robotmem.storage.zarr_storage.ZarrStorage.summary>`
calls :func:`summarize` with its RAM mirror and plain values; the statistics are
computed here, from the mirror's columns.

Example:
    >>> from torchrl_robotmem.storage.summary import summarize
    >>> summarize(None, n=0, path="memory://empty", max_size=10, env_names=("FetchPush-v4",))["episodes"]
    0
"""
from __future__ import annotations

from typing import Any

import torch

from . import _backend
from .mirror import DONE_KEY

__all__ = ["summarize"]

_SUCCESS_KEY = ("next", "is_success")


def summarize(mirror, *, n: int, path: Any, max_size: int, env_names: tuple[str, ...],
              constants: dict[str, Any] | None = None, local_dir: str | None = None) -> dict[str, Any]:
    """Rows, episodes, runs, success rates, env names and size on disk, as a dict.

    ``success_rate`` is the fraction of transitions with ``("next", "is_success")``;
    ``episode_success_rate`` the fraction of finished episodes that ended in success.

    Args:
        mirror (RamMirror or None): the store's RAM rows (``None`` or no views: no rows yet).

    Keyword Args:
        n (int): transitions stored.
        path: the store's path, as given back.
        max_size (int): the store's capacity.
        env_names (tuple of str): the env-name table.
        constants (dict, optional): the store's non-tensor entries, by column path.
        local_dir (str, optional): the store's local directory (``None``: 0 bytes on disk).

    Example:
        >>> summarize(None, n=0, path="p", max_size=4, env_names=())["rows"]
        0
    """
    out: dict[str, Any] = {"path": path, "rows": n, "max_size": max_size}
    views = None if mirror is None else mirror.views
    keys = set(views.keys(True, True)) if views is not None else set()
    if n and "episode" in keys:
        cols = mirror.flat_columns([k for k in ("episode", "run", _SUCCESS_KEY, DONE_KEY) if k in keys], n)
        out["episodes"] = int(torch.unique(cols["episode"]).numel())
        out["runs"] = int(torch.unique(cols["run"]).numel())
        if _SUCCESS_KEY in cols:
            success = cols[_SUCCESS_KEY].reshape(n, -1)[:, 0] > 0.5
            out["success_rate"] = float(success.float().mean())
            if DONE_KEY in cols:
                ends = cols[DONE_KEY].reshape(n, -1).any(-1)
                if ends.any():  # success at the last step of each finished episode
                    out["episode_success_rate"] = float(success[ends].float().mean())
    else:
        out["episodes"] = out["runs"] = 0
    out["envs"] = env_names
    if constants:
        out["constants"] = {str(_backend.path_to_key(p)): v for p, v in constants.items()}
    out["bytes_on_disk"] = _backend.store_size_bytes(local_dir)
    return out
