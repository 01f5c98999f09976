"""FE model layer: Nastran bulk data and matrices in, sparse K and M and modes out.

Public API is re-exported here; each concept lives in its own private module.
"""

from femodel._affine import AffineMatrix
from femodel._assembly import Assembly, MatrixTerm, assemble
from femodel._dofs import DofMap
from femodel._matrices import ImportedMatrices, read_dmig, read_matrices, read_op2_matrices, read_op4
from femodel._model import CoordSystem, FEModel, ModelError, RBE2, RBE3, Table
from femodel._factor import (BackendInfo, Factorization, FactorizationError, NotPositiveDefiniteError,
                             analyze_ahead, available_backends, default_backend, factorize)
from femodel._modes import Modes, normal_modes, solve_modes, start_vector
from femodel._pattern import union_pattern
from femodel._reader import read_bdf
from femodel._sensors import MassProperties, mass_properties, rigid_body_vectors, sensor_matrix
from femodel._units import UNIT_SYSTEMS, UnitSystem, unit_system
from femodel._elements_shell import ElementGeometryError, laminate_abd, orthotropic_q, shell_mass, shell_stiffness
from femodel._elements_solid import solid_mass, solid_stiffness
from femodel._params import Parameter, ParameterError, ParameterSet, read_parameters
from femodel._parametric import ParametricModel, SeriesAffineMatrix, parametric_model
from femodel._terms import AddedMass, AddedSpring, ElementFactor, ExtendedAffineMatrix
from femodel._candidates import (CANDIDATE_FAMILIES, COMPOUND_EFFECTS, Candidate, CandidateContext,
                                 CandidateOptions, POINT_FAMILIES, PointFamily, REGION_FAMILIES,
                                 candidate_context, candidate_regions, compound_candidates, contact_on_pairs,
                                 candidate_pairs, generate_candidates, point_coverage, register_family,
                                 zoom_candidates)
from femodel._writeback import fixed_field_card, write_bdf
from femodel._example import SubframeExample, example_subframe
from femodel._example_frame import FrameExample, example_frame

__all__ = [
    "Assembly", "MatrixTerm", "assemble", "DofMap", "ImportedMatrices", "read_dmig", "read_matrices",
    "read_op2_matrices", "read_op4", "CoordSystem", "FEModel", "ModelError", "RBE2", "RBE3", "Table",
    "Modes", "normal_modes", "solve_modes", "start_vector", "read_bdf", "MassProperties", "mass_properties",
    "rigid_body_vectors", "sensor_matrix", "UNIT_SYSTEMS", "UnitSystem", "unit_system",
    "AffineMatrix", "ElementGeometryError", "shell_stiffness", "shell_mass", "solid_stiffness", "solid_mass", "laminate_abd", "orthotropic_q",
    "Parameter", "ParameterError", "ParameterSet", "read_parameters", "ParametricModel", "SeriesAffineMatrix", "parametric_model",
    "write_bdf", "fixed_field_card", "SubframeExample", "example_subframe", "FrameExample", "example_frame",
    "AddedMass", "AddedSpring", "ElementFactor", "ExtendedAffineMatrix", "BackendInfo", "Factorization",
    "FactorizationError", "NotPositiveDefiniteError", "analyze_ahead", "available_backends", "default_backend", "factorize",
    "CANDIDATE_FAMILIES", "COMPOUND_EFFECTS", "Candidate", "CandidateContext", "CandidateOptions",
    "candidate_context", "compound_candidates", "generate_candidates", "register_family", "POINT_FAMILIES",
    "PointFamily", "REGION_FAMILIES", "candidate_regions", "contact_on_pairs", "candidate_pairs", "zoom_candidates",
    "point_coverage", "union_pattern"]
