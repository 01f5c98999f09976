"""frfcal: the application layer (CLI, campaign files, pipeline, reports).

The numerical layers live in their own top-level packages (``femodel``,
``pretest``, ``acquisition``, ``identification``, ``calibration``); this package
ties them together.
"""

__version__ = "0.1.0"
