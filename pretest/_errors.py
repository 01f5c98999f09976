"""Errors raised by the pretest layer."""

from __future__ import annotations


class PretestError(ValueError):
    """Bad pretest input: names the grid, candidate, option or field at fault."""
