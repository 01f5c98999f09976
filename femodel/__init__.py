"""FE model layer: Nastran bulk data and matrices in, sparse K and M and modes out.

Public API is re-exported here; each concept lives in its own private module.
"""

from femodel._affine import AffineMatrix
from femodel._elements_shell import ElementGeometryError, shell_mass, shell_stiffness
from femodel._elements_solid import solid_mass, solid_stiffness

__all__ = ["AffineMatrix", "ElementGeometryError", "shell_stiffness", "shell_mass", "solid_stiffness", "solid_mass"]
