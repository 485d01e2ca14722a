"""Check a memory for damage (``verify``) and make a damaged one writable again (``repair``).

``robotmem verify PATH [--json]`` reads every chunk below the committed length
(checksums verified where the store has them), every array's metadata and the
commit record, and prints what is wrong. Exit status: 0 intact, 1 damaged,
2 not a memory. Nothing is written. The hidden ``.NAME.partial-PID`` build of
an interrupted ``import`` / ``export`` is never intact (exit 1), and a missing
``NAME`` beside such a build says so (exit 2).

``robotmem repair PATH [--dry-run] [--json]`` backs the metadata up into
``PATH/_repair_backup/<time>/``, rebuilds damaged metadata, and truncates the
committed length before the first damaged chunk (rows after it are dropped,
never invented; see :func:`torchrl_robotmem.storage.integrity.repair`). Exit
status: 0 when the store verifies clean afterwards (or needed nothing), 1 when
damage remains (or ``--dry-run`` found some, or it refused), 2 not a memory.
It takes the writer lock first: a process writing the store is an error naming
it. It refuses, changing nothing, a store whose records point outside it (a
schema key with ``..``, a symbolic link) or disagree (an array's ``zarr.json``
against the schema: both are named; restore the right one from a copy).

Example:
    >>> import tempfile, torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.cli import main
    >>> path = tempfile.mkdtemp() + "/memory.zarr"
    >>> with ZarrStorage(path, 100) as storage:
    ...     storage.set(slice(0, 10), TensorDict({"obs": torch.ones(10, 3)}, [10]))
    >>> main(["verify", path])  # doctest: +ELLIPSIS
    /...memory.zarr: intact (10 rows, 4 arrays, ... chunks read, checksums on)
    0
"""
from __future__ import annotations

import argparse
import json

from .errors import CLIError

__all__ = ["HELP", "add_arguments", "run"]

HELP = {
    "verify": "Check every chunk, array and attribute of a memory; exit 0 intact, 1 damaged, 2 not a memory.",
    "repair": "Make a damaged memory openable and writable again (truncating before the first damaged chunk).",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="the memory: a Zarr store directory, *.zip or URL")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    if parser.get_default("command") == "repair":
        parser.add_argument("--dry-run", action="store_true", help="say what would be done, write nothing")
    else:
        parser.add_argument("--rows", action="store_true",
                            help="also compare the sealed row file (_rows/) with the committed chunks, row for row")


def run(args: argparse.Namespace) -> int:
    from torchrl_robotmem.storage.integrity import IntegrityError, NotAMemoryError, repair, verify

    from ._memory import incomplete_build_error

    incomplete = incomplete_build_error(args.path, code=1)
    if incomplete is not None:
        raise incomplete
    try:
        if args.command == "verify":
            report = verify(args.path)
            rows = []
            if getattr(args, "rows", False) and report.ok:
                from torchrl_robotmem.storage.integrity.rows import row_file_problems

                rows = row_file_problems(args.path)
            if args.json:
                print(json.dumps({**report.to_dict(), "rows": [str(p) for p in rows]}, indent=2))
            else:
                print(report)
                for p in rows:
                    print(f"  row file: {p}")
                if getattr(args, "rows", False) and report.ok and not rows:
                    print("  row file: matches the committed chunks (or there is none to serve)")
            return 0 if report.ok and not any(p.severity == "error" for p in rows) else 1
        result = repair(args.path, dry_run=args.dry_run)
    except NotAMemoryError as err:
        raise CLIError(f"{args.path!r} is not a torchrl_robotmem memory: {err}", code=2) from None
    except IntegrityError as err:
        raise CLIError(str(err), code=1) from None
    except RuntimeError as err:  # the writer lock is held
        raise CLIError(str(err), code=1) from None
    if args.json:
        print(json.dumps({"actions": result.actions, "backup": result.backup, "before": result.before.to_dict(),
                          "after": result.after.to_dict() if result.after else None}, indent=2))
    else:
        print(result)
    if args.dry_run:
        return 0 if result.before.ok else 1
    return 0 if result.ok else 1
