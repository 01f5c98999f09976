"""One module per ``frfcal`` sub-command (see :mod:`frfcal.cli`)."""
