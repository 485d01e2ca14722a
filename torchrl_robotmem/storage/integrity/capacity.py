"""What a store's sizes cost: sizes no process on this machine could hold, found before anything is allocated.

A commit record claiming a ``max_size`` of 10^15 rows (or a row of a petabyte)
would make an open allocate its RAM mirror, and ``verify`` decode a chunk, until
the machine gives up; :func:`capacity_problem` names the attribute at fault first.

Example:
    >>> from torchrl_robotmem.storage.integrity.capacity import capacity_problem
    >>> attrs = {"max_size": 10**15, "chunk_rows": 1000, "schema": {"obs": {"dtype": "float32", "shape": [3]}}}
    >>> capacity_problem(attrs).what.split(":")[0]
    "attribute 'max_size' (1000000000000000)"
"""
from __future__ import annotations

import math
import os

from .. import _backend
from ..errors import Problem
from ..format import dims
from ..layout import PackedLayout

__all__ = ["capacity_problem"]


def _memory_limit() -> int | None:
    """Bytes this process could ever allocate: RAM + swap, or its address-space / data limit if lower."""
    limit = None
    try:
        limit = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("SwapTotal:"):
                    limit += int(line.split()[1]) * 1024
    except (ValueError, OSError, AttributeError):
        pass
    try:
        import resource

        for which in (resource.RLIMIT_AS, resource.RLIMIT_DATA):
            soft = resource.getrlimit(which)[0]
            if soft != resource.RLIM_INFINITY and soft > 0:
                limit = soft if limit is None else min(limit, soft)
    except (ImportError, OSError, ValueError):
        pass
    return limit


#: what a mapping may span where no limit says less (x86-64 user space is 128 TiB; leave room for the rest)
_ADDRESS_SPACE = 1 << 45


def _address_limit() -> int:
    """Bytes this process may map: its address-space limit, at most 32 TiB."""
    limit = _ADDRESS_SPACE
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY and soft > 0:
            limit = min(limit, soft)
    except (ImportError, OSError, ValueError):
        pass
    return limit


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n} B"


def capacity_problem(attrs: dict, *, mirror: bool = True, mapped: bool = False) -> Problem | None:
    """Sizes of sane attributes that no process here could hold, as a problem naming the field; else ``None``.

    ``mirror``: the rows a ``ZarrStorage`` allocates (``max_size`` rows); otherwise one chunk (what
    ``verify`` decodes at a time). ``mapped``: those rows are mapped from a file (the row tier), so what
    bounds them is the address space this process may map, not RAM (the disk is taken as rows arrive).
    """
    if not attrs.get("schema"):
        return None
    max_dim0, _, inner = dims(attrs)
    chunk_rows = int(attrs["chunk_rows"])
    per_row = max(math.prod(inner), 1) * PackedLayout(attrs["schema"]).row_bytes
    rows = max(max_dim0, chunk_rows) if mirror else chunk_rows
    limit = _address_limit() if mirror and mapped else _memory_limit()
    if limit is None or rows * per_row <= limit:
        return None

    def leaf(spec):
        return _backend.numpy_dtype(_backend.torch_dtype(spec["dtype"])).itemsize * math.prod(spec["shape"])

    path, spec = max(attrs["schema"].items(), key=lambda kv: leaf(kv[1]))
    if leaf(spec) * max(math.prod(inner), 1) * 1024 > limit:
        field = f"attribute 'schema' entry {path!r} (shape {spec['shape']})"
    elif inner and math.prod(inner) * 1024 > limit:
        field = f"attribute 'inner_shape' ({list(inner)})"
    elif chunk_rows >= max_dim0 or not mirror:
        field = f"attribute 'chunk_rows' ({chunk_rows})"
    else:
        field = f"attribute 'max_size' ({attrs['max_size']})"
    what = ("its row file" if mapped else "its RAM mirror") if mirror else "one chunk"
    return Problem("capacity", f"{field}: {what} of {rows} rows of {per_row} bytes would take {_size(rows * per_row)}, "
                   f"more than this machine can allocate ({_size(limit)}: "
                   f"{'the address space this process may map' if mirror and mapped else 'RAM + swap, or this process limit'})",
                   key="zarr.json")


