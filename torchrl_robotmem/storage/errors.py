"""The error types of a store, on the ground floor: nothing in ``storage/`` is imported here.

* :class:`Problem`: one thing found wrong with a store (an array, a chunk, an attribute);
* :class:`IntegrityError`: a store is damaged, with the problems that say where;
* :class:`NotAMemoryError`: the path holds no torchrl_robotmem store.

Example:
    >>> from torchrl_robotmem.storage.errors import IntegrityError, Problem
    >>> err = IntegrityError("memory.zarr", [Problem("missing_chunk", "chunk file missing", array="obs", chunk=3)])
    >>> print(str(err).splitlines()[1])
      - array 'obs' chunk 3: chunk file missing
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["ChainedLocalPathError", "IntegrityError", "LinkError", "NotAMemoryError", "Problem"]

#: what every damage message ends with: the commands that say more and mend the store
HINT = "Run `robotmem verify {path}` for a full report and `robotmem repair {path}` to make it writable again."


@dataclass(frozen=True)
class Problem:
    """One thing found wrong with a store.

    Args:
        kind (str): ``"missing_chunk"``, ``"checksum"``, ``"undecodable"`` (a chunk),
            ``"metadata"`` (a ``zarr.json``), ``"attribute"`` (the commit record),
            ``"format"`` (a newer format), ``"journal"`` (a pending journal that cannot be
            replayed as it is), ``"capacity"`` (sizes no machine here can hold), ``"link"`` (a symbolic
            link inside the store) or ``"rows"`` (the row file disagrees with the chunks: ``verify --rows``).
        what (str): what is wrong, in words.
        array (str, optional): the array path (``"next/observation"``).
        chunk (int, optional): the chunk index along the rows.
        key (str, optional): the store key of the file at fault (``"observation/c/1/0"``).
        rows (tuple, optional): the rows ``[lo, hi)`` (first dimension) the chunk holds.
        severity (str): ``"error"`` (damage) or ``"warning"`` (cannot be told from damage).

    Example:
        >>> print(Problem("checksum", "checksum mismatch", array="obs", chunk=1, key="obs/c/1/0", rows=(100, 200)))
        array 'obs' chunk 1 (obs/c/1/0, rows 100-199): checksum mismatch
    """

    kind: str
    what: str
    array: str | None = None
    chunk: int | None = None
    key: str | None = None
    rows: tuple[int, int] | None = None
    severity: str = "error"

    def __str__(self) -> str:
        where = []
        if self.array is not None:
            where.append(f"array {self.array!r}")
        if self.chunk is not None:
            where.append(f"chunk {self.chunk}")
        loc = " ".join(where)
        extra = ", ".join(x for x in (self.key, self.rows and f"rows {self.rows[0]}-{self.rows[1] - 1}") if x)
        head = f"{loc} ({extra})" if loc and extra else loc or extra
        return f"{head}: {self.what}" if head else self.what


class IntegrityError(ValueError):
    """A store is damaged; ``problems`` lists what was found. Nothing was written to it."""

    def __init__(self, path: Any, problems: list[Problem], *, read_only: bool = True, action: str | None = None,
                 hint: str | None = None):
        self.path = path
        self.problems = list(problems)
        errors = [p for p in self.problems if p.severity == "error"] or self.problems
        lines = [f"The store at {path!r} is damaged ({len(errors)} problem{'s' if len(errors) != 1 else ''}):"]
        lines += [f"  - {p}" for p in errors[:8]]
        if len(errors) > 8:
            lines.append(f"  - ... and {len(errors) - 8} more")
        if action is None:
            action = ("Nothing was changed." if read_only else
                      "Refusing to open it for writing; nothing was changed.")
        if hint is None:
            hint = HINT.format(path=path)
            if read_only:
                hint += " ZarrStorage(path, read_only=True, on_damage='warn') reads the intact rows."
        lines.append(f"{action} {hint}")
        super().__init__("\n".join(lines))


class LinkError(IntegrityError):
    """A local store holds symbolic links below its root: refused, since they could serve, copy or write files outside it.

    The message is one line (the command line prints it as it is); ``problems`` has one
    ``"link"`` :class:`Problem` per link, its ``key`` the link's path in the store.

    Example:
        >>> err = LinkError("m.zarr", [("obs/c/1", "/etc/passwd")])
        >>> err.problems[0].key, "obs/c/1 -> '/etc/passwd'" in str(err), len(str(err).splitlines())
        ('obs/c/1', True, 1)
    """

    def __init__(self, path: Any, links: list[tuple[str, str]]):
        special = [target.startswith("<") and target.endswith(">") for _, target in links]
        problems = [Problem("link", f"not a regular file ({target[1:-1]}): a store holds files and folders only"
                            if odd else f"a symbolic link (to {target!r}): a store's files must lie inside it", key=key)
                    for (key, target), odd in zip(links, special)]
        shown = ", ".join(f"{key} ({target[1:-1]})" if odd else f"{key} -> {target!r}"
                          for (key, target), odd in list(zip(links, special))[:3])
        more = f" and {len(links) - 3} more" if len(links) > 3 else ""
        what = "symbolic link" if not any(special) else "symbolic link or special file"
        ValueError.__init__(
            self,
            f"{path!r} holds {len(links)} {what}{'s' if len(links) != 1 else ''} ({shown}{more}): a memory's "
            f"files must lie inside it, so it is refused (nothing was read through the links, nothing written). "
            f"Replace each link by a copy of the file it names if you trust that file "
            f"(cp --remove-destination \"$(readlink -f LINK)\" LINK), or remove it and run `robotmem repair {path}`.")
        self.path, self.problems = path, problems


class NotAMemoryError(ValueError):
    """The path holds no torchrl_robotmem store."""


class ChainedLocalPathError(ValueError):
    """A local store named through an fsspec chain (``simplecache::file://PATH``): refused, naming ``PATH``.

    A local store is opened by its path, so that links below its root are refused; through a chain the
    local file system would follow them.

    Example:
        >>> str(ChainedLocalPathError("simplecache::file:///m.zarr", "simplecache", "/m.zarr")).endswith("open '/m.zarr' instead.")
        True
    """

    def __init__(self, name: str, chain: str, local: str) -> None:
        super().__init__(f"{name!r} reaches a local store through an fsspec chain ({chain}::): a local store is "
                         f"opened by its path, so that links below its root are refused; open {local!r} instead.")
        self.local = local

