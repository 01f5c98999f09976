"""calibration layer (see ARCHITECTURE.md)."""

from calibration._campaign import Campaign, campaign_from_dict, load_campaign
from calibration._crossval import CrossValidation, cross_validate, split_halves
from calibration._ensemble import Grouping, group_articles, grouping, pairwise_sd
from calibration._errors import CalibrationError
from calibration._extend import extended_surrogate
from calibration._executor import DaskExecutor, Executor, ProcessExecutor, SerialExecutor, make_executor
from calibration._identifiability import Identifiability, identifiability
from calibration._fit import (
    Calibration,
    CycleResult,
    FitData,
    Objective,
    StartOutcome,
    calibrate,
    calibrate_cycles,
    latin_hypercube_starts,
    run_start,
)
from calibration._metric import log_deviation, square_deviation, stacked
from calibration._sampling import half_bandwidth_frequencies
from calibration._pipeline import build_model, load_articles, run_campaign
from calibration._validation import (
    IdentifiedModes,
    Validation,
    holdout_sd,
    mac,
    mapped_damping,
    noise_floor_sd,
    pair_modes,
    validate,
)
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
    "Campaign",
    "build_model",
    "campaign_from_dict",
    "load_articles",
    "load_campaign",
    "run_campaign",
    "CrossValidation",
    "Identifiability",
    "IdentifiedModes",
    "identifiability",
    "Validation",
    "cross_validate",
    "Grouping",
    "group_articles",
    "grouping",
    "holdout_sd",
    "mac",
    "mapped_damping",
    "noise_floor_sd",
    "pair_modes",
    "pairwise_sd",
    "split_halves",
    "validate",
    "Calibration",
    "CycleResult",
    "DaskExecutor",
    "Executor",
    "FitData",
    "Objective",
    "ProcessExecutor",
    "SerialExecutor",
    "StartOutcome",
    "calibrate",
    "calibrate_cycles",
    "latin_hypercube_starts",
    "make_executor",
    "run_start",
    "CalibrationError",
    "FRFModel",
    "Surrogate",
    "build_surrogate",
    "extended_surrogate",
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
