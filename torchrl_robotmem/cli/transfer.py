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

``import`` also reads other tools' data (:mod:`.plain_npz`: a plain ``.npz``
of transitions without the ``__robotmem__`` record; :mod:`.sb3_io`: a
Stable-Baselines3 replay buffer, ``--format sb3``, only with
``--trust-pickle`` since loading it unpickles it). float64 data is stored as
float32 unless ``--keep-float64``; what was cast, ignored or recomputed is
printed. A ``SRC`` that is itself a memory is refused with the command that
copies it (``robotmem copy``, :mod:`.copy_memory`).

A source that is cut off or damaged (a truncated ``.npz`` or HDF5 file, a
``metadata.json`` that disagrees with the episodes present) is one error line
naming the file, and nothing is created.
"""
from __future__ import annotations

import argparse
import os

import numpy as np

from .errors import CLIError
from .minari_io import export_minari, import_minari
from .npz_io import export_npz, import_npz
from .sb3_io import import_sb3

__all__ = ["export_npz", "import_npz", "export_minari", "import_minari", "import_sb3", "add_arguments", "run"]

HELP = {
    "export": "Export a memory to .npz or a Minari dataset directory.",
    "import": "Import an .npz (robotmem's export or a plain one), a local Minari dataset or an SB3 replay buffer "
              "(--format sb3 --trust-pickle) into a new memory.",
}


# -- command line ------------------------------------------------------------------------------------


def _format(name: str, given: str | None) -> str:
    if given:
        return given
    if name.endswith(".pkl"):
        return "sb3"
    return "npz" if name.endswith(".npz") else "minari"


def _refuse_memory_source(src: str) -> None:
    """A ``SRC`` that is a memory is copied, not imported: say which command does it."""
    from torchrl_robotmem.storage import is_url, normalize_path, store_exists

    name = normalize_path(src)
    local_store = not is_url(name) and (name.endswith(".zip") or os.path.isfile(os.path.join(name, "zarr.json")))
    if (local_store or is_url(name)) and store_exists(src):
        raise CLIError(f"{src!r} is a torchrl_robotmem memory; to copy it use: robotmem copy {src} DST")


def _episodes(path: str) -> int | None:
    """Episodes the memory at ``path`` holds (``None``: its rows carry no episode ids, a tensor or pytree memory)."""
    from torchrl_robotmem.storage import ZarrStorage

    from ._memory import flat_column, has_key

    storage = ZarrStorage(path, read_only=True)
    try:
        if not len(storage):
            return 0
        if not has_key(storage, "episode"):
            return None
        return int(np.unique(flat_column(storage, "episode")).size)
    finally:
        storage.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    command = parser.get_default("command")
    if command == "export":
        parser.add_argument("path", help="the memory to export (opened read-only)")
        parser.add_argument("out", help="OUT.npz, or a Minari dataset directory ROOT/NAME-vVERSION")
        parser.add_argument("--obs-keys", default=None,
                            help="Minari: comma-separated observation keys (default: keys stored at the root and under next)")
    else:
        parser.add_argument("src", help="SRC.npz (robotmem's export or a plain npz of transitions), a Minari "
                                        "dataset directory or local dataset id, or an SB3 replay buffer .pkl")
        parser.add_argument("path", help="the memory to create (must not exist)")
        parser.add_argument("--max-size", type=int, default=None, help="capacity (default: what is imported)")
        parser.add_argument("--env", default=None,
                            help="tag every imported row with this env name; for data without is_success (SB3, "
                                 "plain npz), the Gymnasium-Robotics id whose compute_reward recomputes it")
        parser.add_argument("--keep-float64", action="store_true",
                            help="keep float64 data as float64 (default: stored as float32, as the envs write it)")
        parser.add_argument("--trust-pickle", action="store_true",
                            help="sb3: load the pickled buffer. Unpickling executes code from the file: only for "
                                 "files you made yourself")
    parser.add_argument("--format", choices=("npz", "minari") if command == "export" else ("npz", "minari", "sb3"),
                        default=None, help="default: npz for *.npz names, sb3 for *.pkl (import), else minari")


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
    _refuse_memory_source(args.src)
    fmt = _format(args.src, args.format)
    notes: list[str] = []
    kwargs = {"max_size": args.max_size, "env": args.env, "keep_float64": args.keep_float64, "notes": notes}
    if fmt == "sb3":
        rows = import_sb3(args.src, args.path, trust_pickle=args.trust_pickle, **kwargs)
    else:
        rows = (import_npz if fmt == "npz" else import_minari)(args.src, args.path, **kwargs)
    for note in notes:
        print(note)
    episodes = _episodes(args.path)
    print(f"imported {rows:,} rows" + (f" ({episodes:,} episodes)" if episodes is not None else "") + f" into {args.path}")
    return 0
