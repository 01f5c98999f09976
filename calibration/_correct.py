"""A re-basis without a new factorization: the basis corrected by its own residuals at the new point.

A calibration cycle ends at a point p away from the basis point p_b; the
fixed basis T is then re-made at p. :func:`calibration.build_surrogate` does
that by refactorizing K(p) + s M(p) and one block inverse iteration of T
(about 10 s at 200k DOF, most of it the factorization and the block solve
of every basis column). :func:`corrected_surrogate` keeps T and adds, with
the factorization an earlier build left (usually at p_b), the corrections
of what T gets wrong at p:

* for each mode of the surrogate at p up to the basis cut-off (Ritz pair
  lambda, phi = T x), the residual r = K(p) phi - lambda M(p) phi, solved
  with that (K + s M)^-1: a preconditioned (Davidson) correction, one
  step of inverse iteration on phi with the basis point's operator;
* for each drive and sensor load b, the residual of the reduced static
  solution x = T (K_r(p) + s M_r(p))^-1 T^T b, r = (K(p) + s M(p)) x - b,
  solved the same way (the residual flexibility of the modes above the
  cut-off follows p).

The new vectors are M-orthonormalized against T at p_b and only their blocks
of the reduced terms are formed (:func:`calibration._extend.bordered`), so
the surrogate stays exact in p on the larger basis and its basis point stays
p_b. The sizes of the residuals in the norm of the solver come with it:
``eta`` (about the relative eigenvalue error of each Ritz mode, as
:func:`calibration._surrogate.basis_residuals`) and the relative energy
error of each static solution, both measured before the round (what it
corrects). Each round adds its vectors: the basis grows from cycle to cycle
(docs/calibration.md, "a re-basis without a new factorization").

:func:`compressed` cuts a basis back to what a cold build at p would hold
(modes up to the cut-off, static and first-moment load solutions, the
parameter-derivative solutions of the in-band modes), made inside its span
in reduced coordinates: no solve at full size, one (n, r) x (r, r') product.
A corrected round followed by it (``rebasis="compressed"``) re-bases
without a factorization and without growth.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from calibration._errors import CalibrationError
from calibration._extend import bordered
from calibration._surrogate import (
    FRFModel,
    BASIS_FACTOR,
    DENSE_BELOW,
    Surrogate,
    _sym,
    assembled,
    basis_layout,
    build_surrogate,
    default_shift_hz,
    reduced_modes,
)


@dataclass(frozen=True)
class Correction:
    """What one :func:`corrected_surrogate` round found and added.

    Attributes
    ----------
    eta_max : float
        Largest energy-norm Ritz residual of the corrected modes at p before
        the round (about the relative eigenvalue error, as ``BasisCheck.eta``).
    static_max : float
        Largest relative energy error of the reduced static solutions at p before the round.
    added : int
        Columns added to the basis.
    size : int
        Basis size after the round.
    time_s : float
    compressed_to : int or None
        Basis size after :func:`compressed` (``rebasis="compressed"``), else None.
    note : str
        Why a wanted compression was not made ("" otherwise).
    """

    eta_max: float
    static_max: float
    added: int
    size: int
    time_s: float
    compressed_to: int | None = None
    note: str = ""

    def describe(self) -> str:
        cut = "" if self.compressed_to is None else f", compressed to {self.compressed_to}"
        cut += f", {self.note}" if self.note else ""
        return (f"Ritz residual {self.eta_max:.2e}, static energy error {self.static_max:.2e}: "
                f"+{self.added} vectors -> {self.size}{cut} ({self.time_s:.1f} s)")

    def to_dict(self) -> dict:
        return {"eta_max": self.eta_max, "static_max": self.static_max, "added": self.added, "size": self.size,
                "time_s": self.time_s, "compressed_to": self.compressed_to, "note": self.note}


def corrected_surrogate(model: FRFModel, sur: Surrogate, basis: np.ndarray, p, band_hz, basis_factor: float = BASIS_FACTOR,
                        vector_rtol: float = 1e-10, min_novelty: float = 1e-6):
    """One round of residual correction of ``sur``'s basis at ``p`` (module docstring).

    Parameters
    ----------
    model : FRFModel (the full-order model of ``sur``)
    sur : Surrogate, basis : (n, r) its M-orthonormal basis (at ``sur.p_basis``)
    p : (n_p,) the point the basis is corrected for
    band_hz : (low, high); the modes up to ``basis_factor`` x high are corrected
    vector_rtol, min_novelty : see :func:`calibration._extend.bordered`

    Returns
    -------
    (Surrogate, basis (n, r + k), Correction), or None when ``model`` keeps no
    factorization (``model.factor_cache["last_solve"]``, left by the last
    basis build): the caller then rebuilds the basis. The kept factorization
    serves as the preconditioner wherever it was made; the new vectors are
    M-orthonormalized at ``sur.p_basis``.
    """
    t0 = time.perf_counter()
    p = np.asarray(p, float)
    kept = model.factor_cache.get("last_solve")
    if kept is None:
        return None
    T = np.asarray(basis, float)
    if T.shape != (model.K.shape[0], sur.size):
        raise CalibrationError(f"basis is {T.shape}, expected ({model.K.shape[0]}, {sur.size})")
    _, s, solve = kept
    p_b = sur.p_basis
    lam, X = reduced_modes(sur, p)
    fhz = np.sqrt(np.clip(lam, 0.0, None)) / (2 * np.pi)
    sel = np.flatnonzero((fhz > sur.rigid_hz) & (fhz <= basis_factor * float(band_hz[1])))
    K, M = assembled(model, p)
    Phi = T @ X[:, sel]
    R = np.asarray(K @ Phi) - np.asarray(M @ Phi) * lam[sel][None, :]
    del Phi
    B = model.inputs.toarray() if sp.issparse(model.inputs) else np.asarray(model.inputs, float)
    C = model.outputs.toarray() if sp.issparse(model.outputs) else np.asarray(model.outputs, float)
    loads = np.hstack([B, C.T])
    reduced_loads = np.hstack([sur.inputs, sur.outputs.T])  # T^T loads
    Y = np.linalg.solve(sur.K.at(p) + s * sur.M.at(p), reduced_loads)
    Xs = T @ Y
    Rs = np.asarray(K @ Xs) + s * np.asarray(M @ Xs) - loads
    W = solve(np.hstack([R, Rs]))
    m = R.shape[1]
    eta = np.abs(np.einsum("ij,ij->j", R, W[:, :m])) / lam[sel] if m else np.zeros(0)
    energy = np.einsum("ij,ij->j", reduced_loads, Y)
    static = np.abs(np.einsum("ij,ij->j", Rs, W[:, m:])) / np.maximum(np.abs(energy), np.finfo(float).tiny)
    del R, Rs, Xs
    M0 = M if np.array_equal(p_b, p) else model.mass(p_b)
    Kr, Mr, inputs, outputs, Te, k = bordered(sur, T, model, W, p_b, M0, vector_rtol, column_scaled=True,
                                              min_novelty=min_novelty)
    out = replace(sur, K=Kr, M=Mr, inputs=inputs, outputs=outputs, n_enrich=sur.n_enrich + k)  # appended last
    info = Correction(float(eta.max(initial=0.0)), float(static.max(initial=0.0)), k, out.size,
                      time.perf_counter() - t0)
    return out, Te, info


def compressed(sur: Surrogate, basis: np.ndarray, p, band_hz, basis_factor: float = BASIS_FACTOR,
               enrich: bool = True, enrich_factor: float = 1.25, enrich_tol: float = 1e-4,
               static_tol: float = 1e-10):
    """``sur`` and its basis cut to a cold build's vectors at ``p``, made inside the basis's span.

    In reduced coordinates (the surrogate is exact in p on its span), with
    A = K_r(p) + s M_r(p) at the default shift s:

    * the modes up to ``basis_factor`` x band top;
    * the static solutions A^-1 b of every drive and sensor load and their
      first moments A^-1 M_r(p) A^-1 b (the dynamic part of the residual
      flexibility of the modes above the cut-off, which a static solution
      alone misses in the band), each column scaled to unit M-norm; the
      statics and the moments are two groups, each cut at ``static_tol`` on
      its own scale;
    * the parameter-derivative solutions A^-1 (dK_r/dp_j - lambda_i dM_r/dp_j) x_i
      of the elastic modes up to ``enrich_factor`` x band top, cut at
      ``enrich_tol`` as in :func:`calibration.build_surrogate` (none with
      ``enrich=False``).

    Each group is made M-orthonormal against the ones before it. The result
    is M-orthonormal at ``p`` (its new basis point); its terms are the old
    ones under the congruence, so it stays exact in p. No full-size solve: the
    only n-sized work is the product ``basis @ Z``.

    Returns (Surrogate, basis (n, r')).
    """
    p = np.asarray(p, float)
    high = float(band_hz[1])
    Kp, Mp = _sym(sur.K.at(p)), _sym(sur.M.at(p))
    lam, X = reduced_modes(sur, p)
    fhz = np.sqrt(np.clip(lam, 0.0, None)) / (2 * np.pi)
    keep = fhz <= basis_factor * high
    Phi = X[:, keep]
    s = (2 * np.pi * default_shift_hz(band_hz)) ** 2
    A = Kp + s * Mp
    loads = np.hstack([sur.inputs, sur.outputs.T])
    S1 = np.linalg.solve(A, loads)
    S2 = np.linalg.solve(A, Mp @ S1)

    def unit(S):
        return S / np.maximum(np.sqrt(np.abs(np.einsum("ij,ij->j", S, Mp @ S))), np.finfo(float).tiny)[None, :]

    sel = np.flatnonzero((fhz <= enrich_factor * high) & (fhz > sur.rigid_hz) & (lam > 0))
    R = []
    for j in range(sur.n_params):
        dK, dM = np.asarray(sur.K.derivative(p, j)), np.asarray(sur.M.derivative(p, j))
        if np.any(dK) or np.any(dM):
            R.append(dK @ X[:, sel] - (dM @ X[:, sel]) * lam[sel][None, :])
    E = np.linalg.solve(A, np.hstack(R)) if enrich and R and sel.size else np.zeros((sur.size, 0))
    # M-orthonormal groups in the Euclidean coordinates y = L^T z of M_r(p) = L L^T: projected off the
    # groups before twice, then an SVD cut (the singular values squared are the Gram eigenvalues the cold
    # build cuts); directions that were already in the span (round-off after the projection) are dropped
    Lm = np.linalg.cholesky(Mp)
    Q = Lm.T @ Phi
    sizes = []
    # the moments are a group of their own, cut on their own scale: beside the modes and statics their new
    # directions are ~1e-6 of a unit column, which a cut on the statics' scale would drop (build_surrogate's
    # _moment_directions; docs/calibration.md, stop 38)
    for G, tol in ((unit(S1), static_tol), (unit(S2), static_tol), (E, enrich_tol)):
        Y = Lm.T @ G
        scale = float(np.linalg.norm(Y, axis=0).max(initial=0.0))
        for _ in range(2):
            Y = Y - Q @ (Q.T @ Y)
        U, sv, _ = np.linalg.svd(Y, full_matrices=False)
        k = int(np.count_nonzero((sv**2 > tol * sv.max(initial=0.0) ** 2) & (sv > 1e-10 * scale)))
        Q = np.hstack([Q, U[:, :k]])
        sizes.append(k)
    n_static, n_enrich = sizes[0] + sizes[1], sizes[2]
    Z = sla.solve_triangular(Lm.T, Q, lower=False)  # Z^T M_r(p) Z = Q^T Q = I

    def cut(Ar):
        return replace(Ar, matrices=tuple(_sym(Z.T @ np.asarray(m) @ Z) for m in Ar.matrices))

    out = replace(sur, K=cut(sur.K), M=cut(sur.M), inputs=Z.T @ sur.inputs, outputs=sur.outputs @ Z,
                  p_basis=p.copy(), basis_frequencies_hz=fhz[keep], n_static=n_static, n_enrich=n_enrich)
    return out, np.asarray(basis) @ Z


def rebased(model: FRFModel, sur: Surrogate, basis: np.ndarray | None, p, band_hz, basis_factor: float = BASIS_FACTOR,
            enrich: bool = True, rebasis: str = "iterated", refresh: bool = True):
    """The basis re-made at ``p`` after a calibration cycle: (Surrogate, basis, Correction or None).

    ``rebasis="corrected"`` adds one round of residual corrections
    (:func:`corrected_surrogate`, no new factorization; the basis grows by
    those vectors); ``"compressed"`` then cuts the corrected basis back to a
    cold build's vectors at ``p`` (:func:`compressed`; no growth; where the
    reduced mass is not definite at ``p`` the corrected basis is kept uncut,
    and the report says so in its ``note``). The other
    kinds, both of those when the model keeps no factorization from an
    earlier build, and "compressed" on a model small enough for dense
    solutions (a rebuild costs less there), rebuild the basis at ``p``
    (:func:`calibration.build_surrogate`; "corrected" and "compressed" then as
    "iterated"; ``refresh=False``: a cold build).
    """
    small = model.K.shape[0] <= DENSE_BELOW
    if rebasis in ("corrected", "compressed") and basis is not None and not (rebasis == "compressed" and small):
        got = corrected_surrogate(model, sur, basis, p, band_hz, basis_factor)
        if got is not None and rebasis == "compressed":
            t0 = time.perf_counter()
            new, T, info = got
            try:
                new, T = compressed(new, T, p, band_hz, basis_factor, enrich=enrich)
            except (np.linalg.LinAlgError, CalibrationError):  # reduced mass not definite at p: keep it uncut
                return new, T, replace(info, note="not compressed (the reduced mass is not definite at p)")
            return new, T, replace(info, compressed_to=new.size, time_s=info.time_s + time.perf_counter() - t0)
        if got is not None:
            return got
    kind = "iterated" if rebasis in ("corrected", "compressed") else rebasis
    new, T = build_surrogate(model, p, band_hz, basis_factor, enrich=enrich,
                             previous_basis=basis if refresh else None, rebasis=kind,
                             previous_layout=basis_layout(sur))
    return new, T, None
