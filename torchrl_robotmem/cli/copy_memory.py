"""Copy a memory between a local path and a store URL (``s3://...``), or between two of either: ``robotmem copy``.

``robotmem copy SRC DST`` copies every file (object) of the memory ``SRC``,
as it is, to ``DST``, which must not exist, then opens the copy and checks it
(:func:`torchrl_robotmem.storage.integrity.verify`: every chunk read and
decoded, checksums where the store has them; the row count and env names
compared with ``SRC``). A local ``DST`` is built in the hidden sibling
``.NAME.partial-PID`` and renamed into place only once it verified
(:mod:`._build`): a killed copy leaves nothing at ``DST``. An object store has
no rename: a URL ``DST`` is written in place with the root ``zarr.json`` (the
commit record, which makes it a store) written **last**, so nothing opens it
as a memory before every other object is there; a copy that fails or does not
verify removes what it wrote under ``DST`` (nothing else is touched). URLs
are opened with fsspec (``s3://`` through s3fs, credentials and endpoint from
its usual environment variables, e.g. ``AWS_ENDPOINT_URL``).

``SRC`` is read, never written; a process appending to it meanwhile makes the
copy fail (its commit record changed), not a mixed copy.
"""
from __future__ import annotations

import argparse
import os
import shutil
from typing import Any

from ..storage.rowfile import ROWS_DIR
from ._build import atomic_target, check_target, is_local, write_failed
from ._memory import open_memory
from .errors import CLIError

__all__ = ["HELP", "add_arguments", "copy_memory", "run"]

HELP = {"copy": "Copy a memory local <-> s3:// (or any fsspec URL): DST must not exist; the copy is verified."}
_RECORD = "zarr.json"
_BLOCK = 8 << 20


def _fs(path: str):
    """``(filesystem, root)`` of a local path or URL (URLs: no listing reused, no instance shared)."""
    from fsspec.core import url_to_fs

    from torchrl_robotmem.storage import is_url, normalize_path

    name = normalize_path(path)
    if is_url(name):
        return url_to_fs(name, use_listings_cache=False, skip_instance_cache=True)
    return url_to_fs(name)


def _files(fs, root: str) -> list[str]:
    """The store's files relative to ``root``, the root ``zarr.json`` last (``[""]``: a single-file store).

    The row file (``_rows/``) is left out: a cache of the chunks, filled again at the copy's first open.
    """
    if fs.isfile(root):
        return [""]
    rel = sorted(p[len(root.rstrip("/")) + 1:] for p in fs.find(root, withdirs=False))
    for p in rel:  # an object store's keys are any strings: one naming a place outside the copy is refused
        if not p or p.startswith("/") or "\\" in p or any(part in ("", ".", "..") for part in p.split("/")):
            raise CLIError(f"the memory at {root!r} holds a file named {p!r}, which would be written outside the "
                           f"copy ('..', '.', an empty or absolute part): nothing was copied. Remove that key.")
    # ``*.partial``: a write in flight (renamed away any moment) or one a killed writer left, never the store's
    rel = [p for p in rel if not p.startswith(ROWS_DIR + "/") and not p.endswith(".partial")]
    return [p for p in rel if p != _RECORD] + ([_RECORD] if _RECORD in rel else [])


def _join(root: str, rel: str) -> str:
    return f"{root.rstrip('/')}/{rel}" if rel else root


def _copy_files(src_fs, src_root: str, files: list[str], dst_fs, dst_root: str) -> int:
    """Streams ``files`` from ``src_root`` to ``dst_root``; returns the bytes copied."""
    total = 0
    for rel in files:
        target = _join(dst_root, rel)
        protocols = dst_fs.protocol if isinstance(dst_fs.protocol, tuple) else (dst_fs.protocol,)
        if "file" in protocols:
            os.makedirs(os.path.dirname(target) or ".", exist_ok=True)
        try:
            fi = src_fs.open(_join(src_root, rel), "rb")
        except FileNotFoundError:  # listed, then gone: a writer replaced it
            raise CLIError(f"{src_root!r} changed while it was copied (a process is writing it: {rel!r} is gone); "
                           f"copy it when no process writes it. Nothing was left at the target") from None
        with fi, dst_fs.open(target, "wb") as fo:
            shutil.copyfileobj(fi, fo, _BLOCK)
            total += fi.tell()
    return total


def _check_copy(target: str, rows: int, env_names: list[str], *, single_file: bool = False) -> str:
    """Opens the copy at ``target`` and verifies every chunk; returns the verify line, or raises a :class:`CLIError`.

    A single-file store (``*.zip``) is compared byte for byte by the caller; here it is only opened
    (``verify`` does not read zip stores).
    """
    from torchrl_robotmem.storage import ZarrStorage
    from torchrl_robotmem.storage.integrity import verify

    storage = ZarrStorage(target, read_only=True)
    try:
        got, names = len(storage), list(storage.env_names)
        if single_file and got:
            storage[got - 1:got]  # the newest row reads back
    finally:
        storage.close()
    if got != rows or names != env_names:
        raise CLIError(f"the copy holds {got} rows of envs {names}, the source {rows} of {env_names}")
    if single_file:
        return f"opens ({got} rows), the same bytes as the source"
    report = verify(target)
    if not report.ok:
        raise CLIError(f"the copy does not verify: {report}")
    return str(report).split(": ", 1)[-1]


def _checked_copy(src: Any, dst: Any, target: str, rows: int, env_names: list[str], *, single_file: bool) -> str:
    """:func:`_check_copy`; where the copy is damaged because the source is (a damaged chunk a sealed source's open
    did not read), the error names the source and what mends it."""
    from torchrl_robotmem.storage.integrity import IntegrityError, verify

    try:
        return _check_copy(target, rows, env_names, single_file=single_file)
    except (IntegrityError, CLIError):
        if single_file:
            raise
        try:
            report = verify(src)
        except Exception:  # noqa: BLE001 - the source cannot be verified: the copy's own error stands
            report = None
        if report is None or report.ok:
            raise
        first = report.errors[0] if report.errors else report
        raise CLIError(f"{src!r} is damaged ({len(report.errors)} problem(s), first: {first}), so a copy of it is "
                       f"too; nothing was left at {dst!r}. Run `robotmem verify {src}` for the report and "
                       f"`robotmem repair {src}` to mend it, then copy again.", code=1) from None


def _refuse_existing(dst: str) -> None:
    if is_local(dst):
        check_target(dst)
        return
    fs, root = _fs(dst)
    if fs.exists(root):
        raise CLIError(f"{dst!r} exists; refusing to overwrite it. Remove it or choose another name.")


def copy_memory(src: Any, dst: str) -> dict[str, Any]:
    """Copies the memory ``src`` to ``dst`` (a new local path or store URL) and verifies the copy.

    Args:
        src: the memory (a directory, ``*.zip`` or store URL); only read.
        dst (str): where the copy goes; refused if anything is there.

    Returns:
        ``{"rows", "files", "bytes", "verified"}``.

    Example:
        >>> import os, tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_robotmem import ZarrStorage
        >>> from torchrl_robotmem.cli.copy_memory import copy_memory
        >>> d = tempfile.mkdtemp()
        >>> with ZarrStorage(d + "/a.zarr", 10) as st:
        ...     st.set(slice(0, 3), TensorDict({"obs": torch.arange(3.0)}, [3]))
        >>> copy_memory(d + "/a.zarr", d + "/b.zarr")["rows"]
        3
        >>> sorted(os.listdir(d)), ZarrStorage(d + "/b.zarr", read_only=True)["obs"].tolist()
        (['a.zarr', 'b.zarr'], [0.0, 1.0, 2.0])
    """
    from torchrl_robotmem.storage import normalize_path, refuse_links

    storage = open_memory(src)
    try:
        rows, env_names = len(storage), list(storage.env_names)
    finally:
        storage.close()
    s, d = str(normalize_path(src)), str(normalize_path(dst))
    if is_local(src) and is_local(dst):  # the places themselves: '..' and links resolved
        s, d = os.path.realpath(s), os.path.realpath(d)
    if s == d or d.startswith(s.rstrip("/") + "/") or s.startswith(d.rstrip("/") + "/"):
        raise CLIError(f"{dst!r} is {src!r} or inside it (or the reverse): copy to another place")
    _refuse_existing(dst)
    src_fs, src_root = _fs(src)
    if is_local(src) and os.path.isdir(src_root):  # checked at the open too: this is the listing the copy follows
        refuse_links(src_root, s)
    files = _files(src_fs, src_root)
    if (files == [""]) != str(dst).rstrip("/").endswith(".zip"):  # the files are copied as they are
        raise CLIError(f"copy keeps a memory's layout, and {src!r} is "
                       f"{'a single *.zip file' if files == [''] else 'a directory of files'} while {dst!r} "
                       f"{'is not' if files == [''] else 'is'} a *.zip path: copy "
                       f"{'to a path ending in .zip' if files == [''] else 'to a path not ending in .zip'}. Nothing "
                       f"was copied.")
    record = src_fs.cat_file(_join(src_root, files[-1]))
    if is_local(dst):
        with atomic_target(dst) as tmp:
            dst_fs, dst_root = _fs(tmp)
            size = _copy_files(src_fs, src_root, files, dst_fs, dst_root)
            _unchanged(src_fs, src_root, files[-1], record, src)
            if files == [""] and not _same_bytes(src_fs, src_root, dst_fs, dst_root):
                raise CLIError(f"the copy of {src!r} differs from it byte for byte (a write meanwhile?)")
            verified = _checked_copy(src, dst, tmp, rows, env_names, single_file=files == [""])
        return {"rows": rows, "files": len(files), "bytes": size, "verified": verified}
    dst_fs, dst_root = _fs(dst)
    try:
        size = _copy_files(src_fs, src_root, files, dst_fs, dst_root)
        _unchanged(src_fs, src_root, files[-1], record, src)
        if files == [""] and not _same_bytes(src_fs, src_root, dst_fs, dst_root):
            raise CLIError(f"the copy of {src!r} differs from it byte for byte (a write meanwhile?)")
        verified = _checked_copy(src, dst, dst, rows, env_names, single_file=files == [""])
    except BaseException:
        if dst_fs.exists(dst_root):  # only what this copy wrote: dst did not exist before it
            dst_fs.rm(dst_root, recursive=True)
        raise
    return {"rows": rows, "files": len(files), "bytes": size, "verified": verified}


def _same_bytes(src_fs, src_path: str, dst_fs, dst_path: str) -> bool:
    import hashlib

    digests = []
    for fs, path in ((src_fs, src_path), (dst_fs, dst_path)):
        h = hashlib.sha256()
        with fs.open(path, "rb") as f:
            for block in iter(lambda: f.read(_BLOCK), b""):  # noqa: B023 - f is used within its own iteration
                h.update(block)
        digests.append(h.digest())
    return digests[0] == digests[1]


def _unchanged(fs, root: str, last: str, record: bytes, src: Any) -> None:
    if fs.cat_file(_join(root, last)) != record:
        raise CLIError(f"{src!r} changed while it was copied (a process is writing it); copy it when no process "
                       f"writes it. Nothing was left at the target")


# -- command line ------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="the memory to copy: a Zarr store directory, *.zip or store URL (only read)")
    parser.add_argument("dst", help="the copy: a new local path or store URL (s3://bucket/name.zarr); must not exist")


def run(args: argparse.Namespace) -> int:
    try:
        info = copy_memory(args.src, args.dst)
    except (OSError, ValueError, MemoryError) as err:  # a missing bucket, no credentials, no room: one line
        raise write_failed(args.dst, err, what=f"copying {args.src!r} to {args.dst!r}", url_cleaned=True) from None
    print(f"copied {info['rows']:,} rows ({info['files']:,} files, {info['bytes'] / 2**20:.1f} MiB) from {args.src} "
          f"to {args.dst}; verified: {info['verified']}")
    return 0
