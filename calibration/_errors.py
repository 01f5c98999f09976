"""The error type of the calibration layer."""

from __future__ import annotations


class CalibrationError(ValueError):
    """Bad calibration input: the message names the channel, parameter, field or file at fault."""
