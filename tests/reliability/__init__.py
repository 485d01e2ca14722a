"""Hardening suite: SIGKILL loops, property tests, bad inputs, tailing readers (docs/reliability.md)."""
