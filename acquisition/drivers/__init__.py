"""Hardware drivers: VISA instruments (:mod:`.visa`) and NI-DAQmx (:mod:`.ni`).

Importing this package is cheap: pyvisa and nidaqmx are imported only when a
driver opens its hardware, with an error naming the missing extra
(``pip install 'frfcal[visa]'`` or ``'frfcal[ni]'``).
"""
