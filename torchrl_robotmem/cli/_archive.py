"""Reading an ``.npz`` without trusting it: every header checked before anything is allocated.

An ``.npz`` is a zip of ``.npy`` members, and both layers declare sizes: the
zip's central directory (compressed and uncompressed bytes per member) and each
``.npy`` header (shape and dtype, which size the array NumPy allocates before
it reads a byte). :func:`inspect_npz` reads only those headers and checks them
against the file itself:

* a member lies inside the file (``offset + compressed size <= file size``);
* its uncompressed size is one its compressed bytes can hold (stored: equal;
  deflate: at most :data:`DEFLATE_RATIO` times larger, the format's own limit);
* its ``.npy`` header parses, holds no Python objects, and declares an array
  (``shape * itemsize``) that fits in the member's uncompressed size.

What an import then needs in RAM (the arrays it reads, and the RAM mirror of
the memory it creates: ``max_size`` rows) is compared with what this process
can still get (:func:`available_memory`: free memory and swap, the cgroup's
limit, ``ulimit -v`` / ``-d``) by :func:`check_memory`. Each failure is one
:class:`~torchrl_robotmem.cli.CLIError` naming the file and the member, raised
before the target is created; damage found only while reading (a bad CRC, a
corrupt deflate stream, a cut-off member) is turned into the same kind of line
by :func:`read_member`.

Example:
    >>> import os, tempfile, numpy as np
    >>> from torchrl_robotmem.cli._archive import inspect_npz
    >>> f = os.path.join(tempfile.mkdtemp(), "x.npz")
    >>> np.savez_compressed(f, a=np.zeros((4, 3), np.float32))
    >>> m = inspect_npz(f)["a"]
    >>> m.member, m.shape, m.dtype, m.nbytes
    ('a.npy', (4, 3), dtype('float32'), 48)
"""
from __future__ import annotations

import math
import os
import resource
import zipfile
import zlib
from typing import Any, NamedTuple

import numpy as np

from .errors import CLIError

__all__ = ["DEFLATE_RATIO", "Member", "available_memory", "check_fits", "check_memory", "inspect_npz", "read_member",
           "size_text"]

#: deflate expands at most about 1032:1 (258-byte matches coded in 2 bits); a little slack for headers
DEFLATE_RATIO = 1032
_SLACK = 4096
#: what reading a damaged member raises (zip, zlib and NumPy's own checks), besides running out of memory
READ_ERRORS = (OSError, ValueError, KeyError, EOFError, RuntimeError, NotImplementedError, zipfile.BadZipFile,
               zlib.error)
_ZIP_METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate", zipfile.ZIP_BZIP2: "bzip2",
                zipfile.ZIP_LZMA: "lzma"}


class Member(NamedTuple):
    """One ``.npy`` member of an npz, as its headers declare it (checked by :func:`inspect_npz`)."""

    key: str  #: the array's name (``np.load(...)[key]``)
    member: str  #: the zip member (``key + ".npy"``)
    shape: tuple
    dtype: np.dtype
    nbytes: int  #: ``prod(shape) * itemsize``: what reading it allocates

    def row_bytes(self, itemsize: int | None = None) -> int:
        """Bytes of one entry along the first dimension (``itemsize``: the dtype it is stored as)."""
        return math.prod(self.shape[1:]) * (self.dtype.itemsize if itemsize is None else itemsize)


def size_text(n: float) -> str:
    """``n`` bytes for people: ``'1.5 GiB'``.

    Example:
        >>> size_text(3 * 2**30 // 2), size_text(512)
        ('1.5 GiB', '512 B')
    """
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} B"  # pragma: no cover


def _kind(err: BaseException) -> str:
    """The error's class for a message: ``BadZipFile``, ``zlib.error`` (a bare ``error`` says nothing)."""
    name = type(err).__name__
    return f"{type(err).__module__}.{name}" if name.islower() else name


def _damaged(src: str, member: str, why: str) -> CLIError:
    return CLIError(f"{src!r}: member {member!r} {why}; the file is damaged or not a real npz, nothing was created")


def _npy_header(f) -> tuple[tuple, bool, np.dtype]:
    fmt = np.lib.format
    version = fmt.read_magic(f)
    reader = getattr(fmt, "_read_array_header", None)
    if reader is not None:
        return reader(f, version)
    if version == (1, 0):  # pragma: no cover - NumPy without the private reader
        return fmt.read_array_header_1_0(f)
    return fmt.read_array_header_2_0(f)  # pragma: no cover


def _check_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, src: str, file_size: int) -> Member:
    name = info.filename
    if info.flag_bits & 0x1:
        raise _damaged(src, name, "is encrypted")
    method = _ZIP_METHODS.get(info.compress_type)
    if method is None:
        raise _damaged(src, name, f"uses zip compression method {info.compress_type}, which NumPy does not read")
    if info.header_offset + info.compress_size > file_size:
        raise _damaged(src, name, f"declares {info.compress_size:,} compressed bytes at offset {info.header_offset:,}, "
                                  f"past the end of the {file_size:,}-byte file (a cut-off file)")
    if method == "stored" and info.file_size != info.compress_size:
        raise _damaged(src, name, f"is stored uncompressed but declares {info.file_size:,} bytes in "
                                  f"{info.compress_size:,}")
    if method == "deflate" and info.file_size > info.compress_size * DEFLATE_RATIO + _SLACK:
        raise _damaged(src, name, f"declares {size_text(info.file_size)} uncompressed from "
                                  f"{size_text(info.compress_size)} of deflate data, more than deflate can expand "
                                  f"({DEFLATE_RATIO}:1)")
    try:
        with zf.open(info) as f:
            shape, _fortran, dtype = _npy_header(f)
            header = f.tell()
    except READ_ERRORS as err:  # a bad .npy header, or (a small member read whole) a bad CRC, corrupt deflate data
        raise _unreadable(src, name[:-4], name, err) from None
    if dtype.hasobject:
        raise _damaged(src, name, f"holds Python objects (dtype {dtype}), which only unpickling reads")
    nbytes = math.prod(shape) * dtype.itemsize
    if header + nbytes > info.file_size:
        raise _damaged(src, name, f"declares an array of shape {list(shape)} {dtype} ({size_text(nbytes)}: "
                                  f"{nbytes:,} bytes), but the member holds {max(info.file_size - header, 0):,} bytes")
    return Member(name[:-4], name, tuple(shape), dtype, nbytes)


def inspect_npz(src: str, keys=None) -> dict[str, Member]:
    """The ``.npy`` members of the npz ``src`` as their headers declare them, each checked against the file.

    Only headers are read (a few hundred bytes per member), nothing is allocated
    from a declared size. Members that are not ``.npy`` files are left out.

    Args:
        src (str): the ``.npz`` file.
        keys (iterable, optional): only these arrays (the ones an import reads); default: all.

    Returns:
        ``{array name: Member}``; a :class:`CLIError` naming the file and the member if one is damaged.

    Example: see the module docstring.
    """
    try:
        file_size = os.path.getsize(src)
        zf = zipfile.ZipFile(src)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise CLIError(f"{src!r} cannot be read as npz ({_kind(err)}: {err}; a truncated file?); nothing "
                       f"was created") from None
    wanted = None if keys is None else set(keys)
    out = {}
    with zf:
        for info in zf.infolist():
            if not info.filename.endswith(".npy") or (wanted is not None and info.filename[:-4] not in wanted):
                continue
            member = _check_member(zf, info, src, file_size)
            out[member.key] = member
    return out


def read_member(data, src: str, key: str) -> np.ndarray:
    """``data[key]`` (``data``: an open ``NpzFile``), its damage or a lack of memory one :class:`CLIError` line.

    Call it only for members :func:`inspect_npz` checked (their size is then bounded by the file's).
    """
    member = key + ".npy" if key + ".npy" in data.zip.namelist() else key
    try:
        return data[key]
    except MemoryError:
        raise CLIError(f"{src!r}: member {member!r} does not fit in the memory this process can get; nothing was "
                       f"created") from None
    except READ_ERRORS as err:
        raise _unreadable(src, key, member, err) from None


def _unreadable(src: str, key: str, member: str, err: BaseException) -> CLIError:
    return CLIError(f"{src!r}: array {key!r} cannot be read ({_kind(err)}: {err}) from member {member!r}; the file "
                    f"is truncated or damaged: export it again; nothing was created")


def _meminfo() -> dict[str, int]:
    out = {}
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                name, _, rest = line.partition(":")
                parts = rest.split()
                if parts and parts[0].isdigit():
                    out[name] = int(parts[0]) * 1024
    except OSError:
        pass
    return out


def _status(field: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _read_int(path: str) -> int | None:
    try:
        with open(path) as f:
            text = f.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def available_memory() -> tuple[int | None, str]:
    """``(bytes, what bounds them)``: what this process can still allocate; ``(None, "")`` where nothing says.

    The smallest of: free memory and swap (``MemAvailable + SwapFree``), the
    cgroup's ``memory.max`` less its ``memory.current``, and the address-space
    (``ulimit -v``) and data-size (``ulimit -d``) limits less what this process
    maps already.

    Example:
        >>> n, why = available_memory()
        >>> n is None or n >= 0
        True
    """
    found: list[tuple[int, str]] = []
    info = _meminfo()
    if "MemAvailable" in info:
        found.append((info["MemAvailable"] + info.get("SwapFree", 0), "free memory and swap"))
    limit, used = _read_int("/sys/fs/cgroup/memory.max"), _read_int("/sys/fs/cgroup/memory.current")
    if limit is not None and used is not None:
        found.append((limit - used, "the cgroup's memory limit"))
    for rlimit, field, why in ((resource.RLIMIT_AS, "VmSize", "the address-space limit (ulimit -v)"),
                               (resource.RLIMIT_DATA, "VmData", "the data-size limit (ulimit -d)")):
        soft = resource.getrlimit(rlimit)[0]
        mapped = _status(field)
        if soft != resource.RLIM_INFINITY and mapped is not None:
            found.append((soft - mapped, why))
    if not found:
        return None, ""
    n, why = min(found)
    return max(n, 0), why


def check_memory(need: int, src: str, what: str, *, hint: str = "") -> None:
    """Raises a :class:`CLIError` naming ``src`` if ``need`` bytes exceed :func:`available_memory`.

    Args:
        need (int): the bytes the import is about to allocate.
        src (str): the file, named in the error.
        what (str): what needs them (``"its arrays (…) and a memory of max_size …"``).

    Keyword Args:
        hint (str): how to need less, appended.

    Example:
        >>> from torchrl_robotmem.cli._archive import check_memory
        >>> check_memory(1, "x.npz", "one byte")  # fits
    """
    avail, why = available_memory()
    if avail is not None and need > avail:
        raise CLIError(f"{src!r}: {what} need {size_text(need)} of RAM, more than the {size_text(avail)} {why} "
                       f"leaves this process; nothing was created{hint}")


def check_fits(members: dict[str, Member], src: str, mirror: int, capacity: int, origin: str) -> None:
    """:func:`check_memory` for an import: the ``members`` it reads and the RAM mirror of ``capacity`` rows.

    Args:
        members (dict): what :func:`inspect_npz` returned for the arrays read.
        src (str): the file.
        mirror (int): bytes of the new memory's RAM mirror.
        capacity (int): its ``max_size``.
        origin (str): where ``capacity`` comes from (``"--max-size"``, ``"its record's max_size"``).

    Example:
        >>> from torchrl_robotmem.cli._archive import check_fits
        >>> check_fits({}, "x.npz", 1024, 8, "--max-size")  # fits
    """
    read = sum(m.nbytes for m in members.values())
    largest = max(members.values(), key=lambda m: m.nbytes, default=None)
    arrays = f"its arrays ({size_text(read)}" + (f"; the largest, member {largest.member!r}: "
                                                 f"{size_text(largest.nbytes)})" if largest is not None else ")")
    check_memory(read + mirror, src, f"{arrays} and the RAM mirror of a memory of {origin + ' ' if origin else ''}"
                 f"{capacity:,} rows "
                 f"({size_text(mirror)})", hint="; pass a smaller --max-size" if mirror > read else "")


def as_count(value: Any, src: str, name: str) -> int:
    """A non-negative integer from an npz's JSON record (``1e13`` is read as 10000000000000); else a :class:`CLIError`.

    Example:
        >>> as_count(1e3, "x.npz", "max_size")
        1000
    """
    ok = isinstance(value, int) and not isinstance(value, bool)
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value, ok = int(value), True
    if not ok or value < 0:
        raise CLIError(f"{src!r}: its record's {name!r} is {value!r}, not a non-negative integer (an edited "
                       f"export?); nothing was created")
    return value
