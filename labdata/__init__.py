"""Ground floor of frfcal: lab-data definitions shared by every layer (numpy only).

Each definition lives here once and the layers re-export it:

* the layout file (``docs/layout.md``): :class:`LayoutChannel`, :class:`LayoutFile`,
  the one reader :func:`read_layout_file` (and :func:`layout_from_dict`), the one
  writer :func:`layout_document` + :func:`write_layout_file`, :class:`LayoutError`;
* FRF quantities: :data:`FRF_QUANTITIES`, :data:`RESPONSE_QUANTITY`,
  :data:`CHANNEL_UNITS`, :func:`frf_quantity_of`, :func:`quantity_power`,
  :func:`quantity_factor` (q = -w^2, i w, 1);
* :func:`mac`, the Modal Assurance Criterion with its edge cases;
* report figures: :data:`FIGURE_DPI`, :data:`FIGURE_FORMAT`, :func:`save_figure`.

This package imports no other frfcal layer (import-linter contract).
"""

from labdata._errors import LabDataError, LayoutError
from labdata._figures import FIGURE_DPI, FIGURE_FORMAT, save_figure
from labdata._layout import (
    LAYOUT_FORMAT,
    LAYOUT_VERSION,
    LayoutChannel,
    LayoutFile,
    layout_document,
    layout_from_dict,
    read_layout_file,
    write_layout_file,
)
from labdata._mac import mac
from labdata._quantities import (
    CHANNEL_UNITS,
    FRF_QUANTITIES,
    RESPONSE_QUANTITY,
    check_frf_quantity,
    frf_quantity_of,
    quantity_factor,
    quantity_power,
)

__all__ = [
    "LabDataError", "LayoutError",
    "FIGURE_DPI", "FIGURE_FORMAT", "save_figure",
    "LAYOUT_FORMAT", "LAYOUT_VERSION", "LayoutChannel", "LayoutFile", "layout_document", "layout_from_dict",
    "read_layout_file", "write_layout_file",
    "mac",
    "CHANNEL_UNITS", "FRF_QUANTITIES", "RESPONSE_QUANTITY", "check_frf_quantity", "frf_quantity_of",
    "quantity_factor", "quantity_power",
]
