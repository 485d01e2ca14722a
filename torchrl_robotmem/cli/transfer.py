"""Export a memory to ``.npz`` or a Minari dataset, and import one into a new memory.

``robotmem export PATH OUT`` and ``robotmem import SRC PATH``; the format is
taken from the name (``*.npz``: NumPy, anything else: a Minari dataset
directory named ``NAME-vVERSION``) or from ``--format``. This module is the
command line only; each format has its own module:

* :mod:`.npz_io`: :func:`export_npz` / :func:`import_npz`, one array per stored
  key (nested keys joined with ``/``), rows in write order, the tags among them
  and a JSON ``__robotmem__`` record; nothing is pickled and
  npz -> memory -> npz is bit-exact.
* :mod:`.minari_io`: :func:`export_minari` / :func:`import_minari`, one Minari
  episode per stored episode; ``import`` reads a local dataset (a directory,
  or an id under ``MINARI_DATASETS_PATH``; nothing is downloaded).
* :mod:`._build`: what both share: every command that creates something (the
  memory of ``import``, the ``.npz`` or dataset directory of ``export``)
  builds it in a hidden sibling ``.NAME.partial-PID`` of the target and
  renames it into place once it is complete: a command killed at any moment
  leaves nothing at the target, only that sibling, which the next run on the
  same target removes (once its process is gone). A target that is a store
  URL (``s3://...``, ``memory://...``) cannot be renamed into place and is
  written directly.

A source that is cut off or damaged (a truncated ``.npz`` or HDF5 file, a
``metadata.json`` that disagrees with the episodes present) is one error line
naming the file, and nothing is created.
"""
from __future__ import annotations

import argparse

from . import CLIError
from .minari_io import export_minari, import_minari
from .npz_io import export_npz, import_npz

__all__ = ["export_npz", "import_npz", "export_minari", "import_minari", "add_arguments", "run"]

HELP = {
    "export": "Export a memory to .npz or a Minari dataset directory.",
    "import": "Import a .npz file or a local Minari dataset into a new memory.",
}


# -- command line ------------------------------------------------------------------------------------


def _format(name: str, given: str | None) -> str:
    if given:
        return given
    return "npz" if name.endswith(".npz") else "minari"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    command = parser.get_default("command")
    if command == "export":
        parser.add_argument("path", help="the memory to export (opened read-only)")
        parser.add_argument("out", help="OUT.npz, or a Minari dataset directory ROOT/NAME-vVERSION")
        parser.add_argument("--obs-keys", default=None,
                            help="Minari: comma-separated observation keys (default: keys stored at the root and under next)")
    else:
        parser.add_argument("src", help="SRC.npz, a Minari dataset directory, or a local Minari dataset id")
        parser.add_argument("path", help="the memory to create (must not exist)")
        parser.add_argument("--max-size", type=int, default=None, help="capacity (default: what is imported)")
        parser.add_argument("--env", default=None, help="tag every imported row with this env name")
    parser.add_argument("--format", choices=("npz", "minari"), default=None,
                        help="default: npz for *.npz names, else minari")


def run(args: argparse.Namespace) -> int:
    if args.command == "export":
        fmt = _format(args.out, args.format)
        if fmt == "npz":
            meta = export_npz(args.path, args.out)
            print(f"exported {meta['rows']:,} rows ({len(meta['schema'])} keys) to {args.out}")
        else:
            keys = args.obs_keys.split(",") if args.obs_keys else None
            info = export_minari(args.path, args.out, obs_keys=keys)
            print(f"exported {info['episodes']:,} episodes ({info['steps']:,} steps, observations "
                  f"{', '.join(info['obs_keys'])}) to the Minari dataset {args.out}")
        return 0
    if args.max_size is not None and args.max_size <= 0:
        raise CLIError(f"--max-size must be a positive integer, got {args.max_size}")
    fmt = _format(args.src, args.format)
    importer = import_npz if fmt == "npz" else import_minari
    rows = importer(args.src, args.path, max_size=args.max_size, env=args.env)
    print(f"imported {rows:,} rows into {args.path}")
    return 0
