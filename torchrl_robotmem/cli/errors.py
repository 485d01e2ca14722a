"""The command line's one error type, on the ground floor of ``cli/`` (it imports nothing of the package).

Example:
    >>> from torchrl_robotmem.cli.errors import CLIError
    >>> err = CLIError("no such memory", code=2)
    >>> str(err), err.code
    ('no such memory', 2)
"""
from __future__ import annotations

__all__ = ["CLIError"]


class CLIError(Exception):
    """An error the user can fix; printed as one line, no traceback.

    Args:
        message: what went wrong and, where possible, how to fix it.
        code: the process exit code (default 2, like argparse's usage errors).
    """

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code
