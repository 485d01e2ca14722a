"""``verify``: every array and every chunk below the committed length of a store, read and checked.

Example:
    >>> import tempfile, torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity import verify
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> report = verify(path)
    >>> report.ok, report.rows, report.checksums
    (True, 10, True)
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import zarr

from .. import _backend
from ..errors import LinkError, NotAMemoryError, Problem
from ..format import FORMAT_MARKER, decode_chunks, dims
from .arrays import check_arrays, check_journal, decode_journal_chunks
from .attributes import check_attributes
from .capacity import capacity_problem
from .files import array_metas, open_any, read_group_attrs

__all__ = ["IntegrityReport", "verify"]


@dataclass
class IntegrityReport:
    """What :func:`verify` found.

    Attributes:
        path: the store.
        problems: every :class:`Problem`, errors and warnings.
        rows: the committed length (``None`` if the commit record is unreadable).
        arrays: arrays checked.
        chunks: chunks read and decoded.
        checksums: whether every array carries the ``crc32c`` codec.
    """

    path: str
    problems: list[Problem] = field(default_factory=list)
    rows: int | None = None
    arrays: int = 0
    chunks: int = 0
    checksums: bool | None = None

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "error"]

    @property
    def ok(self) -> bool:
        """No damage found (warnings allowed)."""
        return not self.errors

    def to_dict(self) -> dict:
        return {"path": self.path, "ok": self.ok, "rows": self.rows, "arrays": self.arrays,
                "chunks": self.chunks, "checksums": self.checksums, "problems": [asdict(p) for p in self.problems]}

    def __str__(self) -> str:
        head = (f"{self.path}: {'intact' if self.ok else 'DAMAGED'} ({self.rows} rows, {self.arrays} arrays, "
                f"{self.chunks} chunks read, checksums {'on' if self.checksums else 'off'})")
        return "\n".join([head] + [f"  {p.severity}: {p}" for p in self.problems])


def verify(path: Any, *, storage_options: dict | None = None) -> IntegrityReport:
    """Checks every array and every chunk below the committed length of a store.

    Every chunk is read and decoded (checksums verified where the store has
    them), every array's metadata compared with the recorded schema, the
    commit record's attributes checked, and a pending journal's chunks read.
    A symbolic link below a local store's root is damage (kind ``"link"``, one
    problem per link) and nothing is read then: a link may name any file.
    Nothing is written; a writer may be running (what it commits meanwhile may
    or may not be seen).

    Args:
        path: the store (a directory, ``*.zip`` or URL), as for ``ZarrStorage``.

    Keyword Args:
        storage_options (dict, optional): fsspec options for URL stores.

    Returns:
        An :class:`IntegrityReport`; ``report.ok`` is ``False`` if anything is damaged.

    Raises:
        NotAMemoryError: nothing at ``path`` is a torchrl_robotmem store.

    Example:
        >>> import tempfile
        >>> from torchrl_robotmem.storage.integrity import verify
        >>> try:
        ...     verify(tempfile.mkdtemp())
        ... except ValueError as err:
        ...     print("not a memory")
        not a memory
    """
    store, local_dir = open_any(path, storage_options)
    name = str(_backend.normalize_path(path))
    report = IntegrityReport(name)
    links = _backend.links_below(local_dir) if local_dir is not None else []
    if links:  # nothing is read through them: a link may name any file, of this store or not
        report.problems += LinkError(name, links).problems
        return report
    attrs, problem = read_group_attrs(store)
    if problem is not None:
        if not array_metas(store, local_dir):
            raise NotAMemoryError(f"{name!r} is not a torchrl_robotmem memory ({problem.what}).")
        report.problems.append(problem)
        return report
    if FORMAT_MARKER not in attrs:
        raise NotAMemoryError(f"{name!r} is a Zarr group without the {FORMAT_MARKER!r} attribute.")
    report.problems += check_attributes(attrs)
    if report.problems:
        return report
    report.rows = int(attrs.get("len", 0))
    capacity = capacity_problem(attrs, mirror=False)
    if capacity is not None:  # no chunk of it could be decoded here
        report.problems.append(capacity)
        return report

    def get_array(p):
        return zarr.open_array(store, path=p, mode="r", zarr_format=3)

    present: dict = {}
    more, arrays = check_arrays(get_array, attrs, store=store, local_dir=local_dir, present=present)
    report.problems += more
    report.arrays = len(attrs.get("schema") or {})
    report.checksums = bool(arrays) and all(
        any(type(c).__name__ == "Crc32cCodec" for c in arr.metadata.codecs) for arr in arrays.values())
    if attrs.get("schema"):
        _, n0, _ = dims(attrs)
        for p, arr in arrays.items():
            found, n = decode_chunks(arr, p, n0, int(attrs["chunk_rows"]), present.get(p))
            report.problems += found
            report.chunks += n
        journal = attrs.get("journal")
        if journal:
            report.problems += check_journal(get_array, attrs, arrays, present)
            report.problems += decode_journal_chunks(lambda p: zarr.open_array(store, path=p, mode="r"), attrs)
    return report


