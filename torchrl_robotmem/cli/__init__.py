"""The ``robotmem`` command line: ``python -m torchrl_robotmem COMMAND ...``.

Commands are registered in :data:`COMMANDS`, which maps a command name to the
dotted name of the module implementing it. A command module provides two
functions::

    def add_arguments(parser: argparse.ArgumentParser) -> None: ...
    def run(args: argparse.Namespace) -> int: ...   # the process exit code

The module is imported when the parser is built, so keep its top-level imports
light (import matplotlib, minari, ... inside ``run``); a module that fails to
import leaves only its own commands unusable. The command's one-line help is
``module.HELP[name]`` if the module defines that dict, else the first line of
its docstring. One module may implement several commands
(``transfer`` implements ``export`` and ``import``): before ``add_arguments`` is
called the sub-parser's default ``command`` is set to the command's name, so
``parser.get_default("command")`` and ``args.command`` say which one is meant.

To add a command, add one entry to :data:`COMMANDS`, e.g.
``COMMANDS["verify"] = "torchrl_robotmem.cli.verify"``.

Errors the user can fix (a path that is not a memory, an output that exists)
are raised as :class:`CLIError`; :func:`main` prints its message without a
traceback and returns its exit code (2 unless given). A write that finds no
room (a full disk, a quota, ``ulimit -f``) or no memory, in any command, is
one line too (:func:`._build.write_failed`: the command, its target, the cause
and what is left at the target), exit code 1; :data:`TARGETS` says which
argument names a command's target.

Example:
    >>> from torchrl_robotmem.cli import main
    >>> main(["inspect", "/nonexistent/memory.zarr"])
    2
"""
from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from .errors import CLIError  # re-exported: `from torchrl_robotmem.cli import CLIError`

__all__ = ["COMMANDS", "CLIError", "TARGETS", "build_parser", "main"]

#: command name -> module implementing it (``add_arguments(parser)``, ``run(args) -> int``).
COMMANDS: dict[str, str] = {
    "inspect": "torchrl_robotmem.cli.inspect",
    "plot": "torchrl_robotmem.cli.plot",
    "export": "torchrl_robotmem.cli.transfer",
    "import": "torchrl_robotmem.cli.transfer",
    "verify": "torchrl_robotmem.cli.verify", "repair": "torchrl_robotmem.cli.verify",
    "copy": "torchrl_robotmem.cli.copy_memory",
}

#: command -> ``(argument naming what it writes, whether it builds that beside it and renames it into place)``
TARGETS: dict[str, tuple[str, bool]] = {
    "import": ("path", True), "export": ("out", True), "copy": ("dst", True),
    "repair": ("path", False), "plot": ("out", False),
}


# optional dependencies a command may need, and the extra (pyproject.toml) that installs each
EXTRAS = {"matplotlib": "plots", "minari": "minari", "h5py": "minari", "jax": "minari", "s3fs": "s3",
          "stable_baselines3": "sb3"}


def _local_target(args: argparse.Namespace) -> None:
    """A command's target spelled as a local URL (``file://PATH``, ``local://PATH``) becomes ``PATH`` (it was built
    under ``./file:/PATH``); an empty one is refused (it named the current directory's parent's sibling)."""
    arg = TARGETS.get(args.command, (None, False))[0]
    value = getattr(args, arg, None) if arg else None
    if not isinstance(value, str):
        return
    if not value.strip():
        raise CLIError(f"the target ({arg.upper()}) is empty: name the file or memory to write")
    for local in ("file://", "local://"):
        if value.startswith(local) and "::" not in value:
            setattr(args, arg, value[len(local):])


def build_parser() -> argparse.ArgumentParser:
    """The ``robotmem`` argument parser with one sub-command per :data:`COMMANDS` entry."""
    parser = argparse.ArgumentParser(
        prog="robotmem",
        description="Inspect, plot, export and import torchrl_robotmem memories (Zarr stores).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in COMMANDS.items():
        try:
            module = importlib.import_module(module_name)
        except ImportError as err:  # one broken command must not take the others down
            p = sub.add_parser(name, help=f"(unavailable: {err})", add_help=False)
            p.set_defaults(command=name, _unavailable=f"{module_name} cannot be imported: {err}")
            p.add_argument("_rest", nargs=argparse.REMAINDER)
            continue
        doc = (module.__doc__ or "").strip()
        help_line = getattr(module, "HELP", {}).get(name) or (doc.splitlines()[0] if doc else None)
        p = sub.add_parser(name, help=help_line, description=help_line)
        p.set_defaults(command=name)
        module.add_arguments(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``robotmem`` command line.

    Args:
        argv: the arguments after the program name (default: ``sys.argv[1:]``).

    Returns:
        The process exit code: 0 on success, 2 for a usage error or a
        :class:`CLIError` without its own code.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2): a return code, not an exit, for main([...])
        return int(e.code or 0)
    try:
        if getattr(args, "_unavailable", None):
            raise CLIError(args._unavailable, code=1)
        _local_target(args)
        return int(importlib.import_module(COMMANDS[args.command]).run(args) or 0)
    except CLIError as e:
        print(f"robotmem {args.command}: error: {e}", file=sys.stderr)
        return e.code
    except ModuleNotFoundError as e:
        extra = EXTRAS.get((e.name or "").split(".")[0])
        if extra is None:
            raise
        print(f"robotmem {args.command}: error: this needs {e.name}, an optional dependency: "
              f"pip install 'torchrl_robotmem[{extra}]'", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"robotmem {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `robotmem inspect --json PATH | head`: the reader left; not an error
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return 141
    except Exception as e:  # noqa: BLE001 - only a write without room or memory, or a chained store name, here
        from torchrl_robotmem.storage.errors import ChainedLocalPathError

        from ._build import no_room, write_failed

        if isinstance(e, ChainedLocalPathError):  # a store name, refused wherever a command first reads it
            print(f"robotmem {args.command}: error: {e}", file=sys.stderr)
            return 2
        if no_room(e) is None:
            raise
        arg, built = TARGETS.get(args.command, (None, False))
        target = getattr(args, arg, None) if arg else None
        err = write_failed(target, e, built=built, what=None if target else "the command")
        print(f"robotmem {args.command}: error: {err}", file=sys.stderr)
        return err.code
