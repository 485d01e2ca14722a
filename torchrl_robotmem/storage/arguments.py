"""The checks of ``ZarrStorage``'s constructor arguments, made before anything is opened.

Example:
    >>> from torchrl_robotmem.storage.arguments import check_arguments
    >>> check_arguments("memory://a", 0, chunk_rows=None, commit_interval=1.0, ndim=1, shared_init=False,
    ...                 compressor="blosc", compression_level=1, on_damage="raise", read_only=False)
    Traceback (most recent call last):
    ...
    ValueError: max_size must be a positive integer, got 0.
"""
from __future__ import annotations

import numpy as np

from . import _backend

__all__ = ["check_arguments"]


def check_arguments(path, max_size, *, chunk_rows, commit_interval, ndim, shared_init, compressor,
                    compression_level, on_damage, read_only, goal_conditioned=None) -> None:
    """Raises, saying what to pass instead, on constructor arguments ``ZarrStorage`` refuses.

    Args:
        path: the store's path (a number is refused: the first argument is no ``max_size``).
        max_size (int or None): the capacity.

    Keyword Args:
        chunk_rows, commit_interval, ndim, shared_init, compressor, compression_level, on_damage, read_only,
            goal_conditioned: ``ZarrStorage``'s arguments of those names.

    Example:
        >>> check_arguments("memory://a", 10, chunk_rows=None, commit_interval=1.0, ndim=1, shared_init=False,
        ...                 compressor="blosc", compression_level=1, on_damage="raise", read_only=False)
    """
    if isinstance(path, (int, np.integer)) and not isinstance(path, bool):
        raise TypeError(
            f"ZarrStorage's first argument is the store's path; got the number {path}. "
            f"Use ZarrStorage(path, max_size), e.g. functools.partial(ZarrStorage, 'memory/run.zarr')."
        )
    if max_size is not None and int(max_size) <= 0:
        raise ValueError(f"max_size must be a positive integer, got {max_size}.")
    if chunk_rows is not None and int(chunk_rows) <= 0:
        raise ValueError(f"chunk_rows must be a positive integer, got {chunk_rows}.")
    if commit_interval <= 0:
        raise ValueError(f"commit_interval must be > 0 seconds, got {commit_interval}.")
    if int(ndim) < 1:
        raise ValueError(f"ndim must be >= 1, got {ndim}.")
    if shared_init:
        raise ValueError(
            "ZarrStorage(shared_init=True) is not supported: a store has one writer process. "
            "Write from the main process (iterate the collector there and call rb.extend), and "
            "give other processes read-only handles: pickle the storage (it arrives read_only) "
            "or open ZarrStorage(path, read_only=True) there."
        )
    _backend.make_compressors(compressor, compression_level, 4)  # validates the name
    if on_damage not in ("raise", "warn") or (on_damage == "warn" and not read_only):
        raise ValueError(
            f"on_damage must be 'raise', or 'warn' with read_only=True (a damaged store is not "
            f"opened for writing: run `robotmem repair PATH`), got {on_damage!r} with read_only={read_only}."
        )
    if goal_conditioned is not None and not isinstance(goal_conditioned, (bool, np.bool_)):
        raise TypeError(f"goal_conditioned must be True, False or None (as the store records), got {goal_conditioned!r}.")
