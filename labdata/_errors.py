"""Errors of the shared lab-data definitions."""

from __future__ import annotations

__all__ = ["LabDataError", "LayoutError"]


class LabDataError(ValueError):
    """Input that breaks one of the shared definitions (shapes, quantity names, ...)."""


class LayoutError(LabDataError):
    """The layout file is malformed; the message names the file and the entry at fault."""
