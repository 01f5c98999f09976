"""Acquisition layer: run files, sweep plans, the stepped-sine controller and drivers."""

from acquisition._driver import (
    ChannelSpec,
    Driver,
    DriverError,
    DriverInfo,
    PhasorBlock,
    SampleBlock,
)

__all__ = ["ChannelSpec", "Driver", "DriverError", "DriverInfo", "PhasorBlock", "SampleBlock"]
