"""robotmem transfer (work in progress)."""
from __future__ import annotations

import argparse

from . import CLIError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path")
    parser.add_argument("rest", nargs="*")


def run(args: argparse.Namespace) -> int:
    raise CLIError(f"{args.path!r} is not a torchrl_robotmem memory (command not implemented yet)")
