"""The constructor arguments of the TorchRL storages ``ZarrStorage`` replaces, and what each means here.

A TorchRL script swaps its storage in one line: ``LazyMemmapStorage(max_size,
scratch_dir=..., device=..., ndim=..., existsok=..., compilable=...,
shared_init=..., auto_cleanup=...)`` or ``LazyTensorStorage(max_size, device=...,
ndim=..., compilable=..., consolidated=..., shared_init=..., cleanup_memmap=...)``
(TorchRL 0.14) becomes ``ZarrStorage(path, max_size, ...)`` with the same keyword
arguments. ``device``, ``ndim``, ``compilable`` and ``shared_init`` are
``ZarrStorage``'s own (``shared_init=True`` is refused: one writer process). The
others cannot mean what they mean for a memmap storage, and
:func:`check_replaced_arguments` says so where it matters:

========================  =====================================================================
``scratch_dir``           ignored, with a ``UserWarning``: the store at ``path`` is where the rows live
``existsok=True``         a ``UserWarning``: an existing store is reopened and appended to, never
                          overwritten from row 0 (``rb.empty()`` starts over). ``False``: silent
``auto_cleanup=True``     a ``UserWarning``: a store is never deleted at exit. ``None``/``False``: silent
``consolidated``          silent: the RAM mirror is always one packed buffer
``cleanup_memmap``        silent: there are no memmap files to clean up
========================  =====================================================================

Example:
    >>> import warnings
    >>> from torchrl_robotmem.storage.compat import check_replaced_arguments
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     check_replaced_arguments("m.zarr", scratch_dir="/tmp/rb")
    >>> "scratch_dir is ignored" in str(caught[0].message)
    True
"""
from __future__ import annotations

import os
import warnings
from typing import Any

__all__ = ["check_replaced_arguments"]


def check_replaced_arguments(path: Any, scratch_dir: str | os.PathLike | None = None, existsok: bool = False,
                             auto_cleanup: bool | None = None, consolidated: bool = False,
                             cleanup_memmap: bool = True) -> None:
    """Warns about the arguments of ``LazyMemmapStorage`` / ``LazyTensorStorage`` that mean something else here.

    Args:
        path: the store (named in the messages).

        scratch_dir, existsok, auto_cleanup: ``LazyMemmapStorage``'s arguments of those names.
        consolidated, cleanup_memmap: ``LazyTensorStorage``'s arguments of those names (accepted, no effect).
    """
    del consolidated, cleanup_memmap  # the mirror is one packed buffer; there are no memmap files
    where = f"ZarrStorage({str(path)!r}, ...)"
    if scratch_dir is not None:
        warnings.warn(
            f"{where} got scratch_dir={str(scratch_dir)!r}: scratch_dir is ignored. The store path is where the "
            f"data lives (written through from RAM, kept after the process, reopened by ZarrStorage(path)); "
            f"nothing is written to scratch_dir. Drop the argument to silence this warning.",
            UserWarning, stacklevel=3)
    if existsok:
        warnings.warn(
            f"{where} got existsok=True: LazyMemmapStorage would overwrite existing files from row 0; ZarrStorage "
            f"reopens an existing store and appends after its rows (its length and cursor are restored). "
            f"To start over, call rb.empty() or use a new path.", UserWarning, stacklevel=3)
    if auto_cleanup:
        warnings.warn(
            f"{where} got auto_cleanup=True: a ZarrStorage store is never deleted at exit (keeping it is the "
            f"point); delete the directory yourself when it is no longer wanted.", UserWarning, stacklevel=3)
