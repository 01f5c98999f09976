"""FE model layer: Nastran bulk data and matrices in, sparse K and M and modes out.

Public API is re-exported here; each concept lives in its own private module.
"""

from femodel._affine import AffineMatrix

__all__ = ["AffineMatrix"]
