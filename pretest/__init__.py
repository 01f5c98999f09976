"""pretest layer (see ARCHITECTURE.md): sensor and shaker placement before a modal test.

Kernels on arrays (:func:`effective_independence`, :func:`layout_metrics`,
:func:`rank_drive_points`, :func:`mass_loading_shifts`) plus the model-level
planner (:func:`plan_pretest`) and the layout file (:func:`write_layout`,
:func:`read_layout`; format in ``docs/layout.md``).
"""

from pretest._candidates import (
    CandidateSet,
    candidate_grids,
    candidate_set,
    parse_direction,
    select_target_modes,
    surface_normals,
)
from pretest._efi import EfIResult, effective_independence, exhaustive_best_subset, fim_logdet
from pretest._errors import PretestError
from pretest._figures import plot_automac, plot_layout
from pretest._layout import LayoutChannel, LayoutFile, layout_dict, read_layout, write_layout
from pretest._massload import DEFAULT_SENSOR_MASS_KG, MassLoading, mass_loading_shifts
from pretest._metrics import LayoutMetrics, automac, layout_metrics, mac
from pretest._plan import (
    PretestConfig,
    PretestResult,
    TargetModes,
    compute_target_modes,
    evaluate_channels,
    plan_pretest,
)
from pretest._refine import RefineResult, refine_automac
from pretest._shaker import DriveRanking, rank_drive_points

__all__ = [
    "CandidateSet", "candidate_grids", "candidate_set", "parse_direction", "select_target_modes",
    "surface_normals", "EfIResult", "effective_independence", "exhaustive_best_subset", "fim_logdet",
    "PretestError", "plot_automac", "plot_layout", "LayoutChannel", "LayoutFile", "layout_dict",
    "read_layout", "write_layout", "DEFAULT_SENSOR_MASS_KG", "MassLoading", "mass_loading_shifts",
    "LayoutMetrics", "automac", "layout_metrics", "mac", "PretestConfig", "PretestResult", "TargetModes",
    "compute_target_modes", "evaluate_channels", "plan_pretest", "DriveRanking", "rank_drive_points",
    "RefineResult", "refine_automac",
]
