"""``python -m torchrl_robotmem``: the ``robotmem`` command line (see :mod:`torchrl_robotmem.cli`)."""
from __future__ import annotations

import sys

from torchrl_robotmem.cli import main

if __name__ == "__main__":
    sys.exit(main())
