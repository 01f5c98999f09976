"""Hardware drivers: VISA instruments (:mod:`.visa`) and NI-DAQmx (:mod:`.ni`).

Importing this package is cheap: pyvisa and nidaqmx are imported only when a
driver opens its hardware, with an error naming the missing extra
(``pip install 'frfcal[visa]'`` or ``'frfcal[ni]'``).
"""

from acquisition._driver import DriverError


class DriverUnavailable(DriverError, ValueError):
    """The driver's software stack is missing: the Python extra or the vendor runtime.

    A :class:`~acquisition.DriverError` (the controller treats it as a driver
    fault) and a ``ValueError`` (the CLI prints it as one line).
    """


__all__ = ["DriverUnavailable"]
