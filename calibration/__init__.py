"""calibration layer (see ARCHITECTURE.md)."""

from calibration._errors import CalibrationError
from calibration._metric import log_deviation, square_deviation, stacked
from calibration._sampling import half_bandwidth_frequencies
from calibration._surrogate import (
    FRFModel,
    Surrogate,
    build_surrogate,
    full_modes,
    full_order_frf,
    modal_frf,
    reduced_modes,
    surrogate_frf,
    surrogate_frf_jacobian,
)

__all__ = [
    "CalibrationError",
    "FRFModel",
    "Surrogate",
    "build_surrogate",
    "full_modes",
    "full_order_frf",
    "half_bandwidth_frequencies",
    "log_deviation",
    "modal_frf",
    "reduced_modes",
    "square_deviation",
    "stacked",
    "surrogate_frf",
    "surrogate_frf_jacobian",
]
