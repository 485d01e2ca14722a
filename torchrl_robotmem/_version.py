"""The library version, on the ground floor: every module reads it from here, none from the package root."""
from __future__ import annotations

__version__ = "0.1.0"
