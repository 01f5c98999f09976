"""Continuous-time state-space model and its evaluation at any frequency."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labdata import FRF_QUANTITIES

from ._errors import IdentificationError

QUANTITIES = FRF_QUANTITIES


def _as_real_matrix(name: str, value, shape: tuple[int | None, int | None]) -> np.ndarray:
    arr = np.asarray(value)
    if arr.ndim != 2:
        raise IdentificationError(f"StateSpace.{name} must be a 2-D matrix, got shape {arr.shape}")
    for axis, want in enumerate(shape):
        if want is not None and arr.shape[axis] != want:
            raise IdentificationError(
                f"StateSpace.{name} has shape {arr.shape}; axis {axis} must be {want}"
            )
    if np.iscomplexobj(arr):
        if np.any(np.abs(arr.imag) > 1e-9 * max(1.0, float(np.abs(arr).max(initial=0.0)))):
            raise IdentificationError(f"StateSpace.{name} must be real (continuous-time, real realization)")
        arr = arr.real
    arr = np.array(arr, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise IdentificationError(f"StateSpace.{name} holds NaN or Inf")
    arr.setflags(write=False)
    return arr


def frequency_grid(freq_hz, name: str = "freq_hz") -> np.ndarray:
    """Validate a frequency vector in Hz and return it as a float array ``(n_f,)``."""
    f = np.asarray(freq_hz, dtype=float)
    if f.ndim == 0:
        f = f[None]
    if f.ndim != 1:
        raise IdentificationError(f"{name} must be a 1-D array of frequencies in Hz, got shape {f.shape}")
    if not np.all(np.isfinite(f)):
        raise IdentificationError(f"{name} holds NaN or Inf")
    if np.any(f < 0):
        raise IdentificationError(f"{name} holds negative frequencies (min {f.min():g} Hz)")
    return f


@dataclass(frozen=True)
class StateSpace:
    """Real continuous-time model ``H(s) = C (sI - A)^-1 B + D``, ``s = i 2 pi f``.

    Parameters
    ----------
    A : ndarray, shape (n, n)
        State matrix [1/s].
    B : ndarray, shape (n, n_in)
        Input matrix.
    C : ndarray, shape (n_out, n)
        Output matrix.
    D : ndarray, shape (n_out, n_in)
        Direct term, in the units of the FRF (e.g. (m/s^2)/N for accelerance).
    quantity : str
        FRF quantity the model reproduces: ``"accelerance"``, ``"mobility"``
        or ``"receptance"``.

    Notes
    -----
    Time dependence is e^{+i omega t} (docs/conventions.md).
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    quantity: str = "accelerance"

    def __post_init__(self) -> None:
        A = _as_real_matrix("A", self.A, (None, None))
        n = A.shape[0]
        if A.shape[1] != n:
            raise IdentificationError(f"StateSpace.A must be square, got shape {A.shape}")
        B = _as_real_matrix("B", self.B, (n, None))
        C = _as_real_matrix("C", self.C, (None, n))
        D = _as_real_matrix("D", self.D, (C.shape[0], B.shape[1]))
        if self.quantity not in QUANTITIES:
            raise IdentificationError(
                f"StateSpace.quantity must be one of {QUANTITIES}, got {self.quantity!r}"
            )
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "B", B)
        object.__setattr__(self, "C", C)
        object.__setattr__(self, "D", D)

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    @property
    def n_out(self) -> int:
        return self.C.shape[0]

    @property
    def n_in(self) -> int:
        return self.B.shape[1]

    def poles(self) -> np.ndarray:
        """Eigenvalues of ``A`` [rad/s], complex ``(n,)``, sorted by ``|Im|`` then ``Im``."""
        lam = np.linalg.eigvals(self.A)
        return lam[np.lexsort((lam.imag, np.abs(lam.imag)))]

    def diagonal(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Diagonal (modal) realization, paper Eq. 2.8-2.9.

        Returns
        -------
        lam : ndarray, complex (n,)
            Poles [rad/s].
        CX : ndarray, complex (n_out, n)
            ``C X``: output coefficients of each modal coordinate.
        XiB : ndarray, complex (n, n_in)
            ``X^-1 B``: input coefficients of each modal coordinate.
        """
        lam, X = np.linalg.eig(self.A)
        XiB = np.linalg.solve(X, self.B.astype(complex))
        return lam, self.C @ X, XiB

    def frf(self, freq_hz) -> np.ndarray:
        """Evaluate the model at any frequencies.

        Parameters
        ----------
        freq_hz : array_like, shape (n_f,)
            Frequencies [Hz].

        Returns
        -------
        ndarray, complex, shape (n_f, n_out, n_in)
        """
        f = frequency_grid(freq_hz)
        s = 2j * np.pi * f
        lam, X = np.linalg.eig(self.A)
        if self.n_states and np.linalg.cond(X) < 1e10:
            XiB = np.linalg.solve(X, self.B.astype(complex))
            CX = self.C @ X
            g = 1.0 / (s[:, None] - lam[None, :])
            H = np.einsum("on,fn,ni->foi", CX, g, XiB, optimize=True)
        else:  # defective or nearly defective A: solve each line directly
            eye = np.eye(self.n_states)
            H = np.empty((f.size, self.n_out, self.n_in), dtype=complex)
            for k, sk in enumerate(s):
                H[k] = self.C @ np.linalg.solve(sk * eye - self.A, self.B)
        return H + self.D[None, :, :]

    def transposed(self) -> StateSpace:
        """Dual model ``H^T`` (inputs and outputs swapped)."""
        return StateSpace(self.A.T, self.C.T, self.B.T, self.D.T, self.quantity)
