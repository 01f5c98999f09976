"""Linear plants for the simulated lab: modal parameters or a state-space model.

A plant is held in complex-diagonal (first-order modal) form

.. math:: \\dot z = \\Lambda z + B_z u, \\qquad y = C_z z + D u,

which gives the exact FRF at any frequency and the exact time response to a
sinusoidal input (used by :class:`acquisition.SimulatedLab`). Time dependence
e^{+iwt}; inputs are forces in N, outputs in SI of the declared quantity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labdata import FRF_QUANTITIES, quantity_factor, quantity_power

QUANTITIES = FRF_QUANTITIES


class PlantError(ValueError):
    """A plant definition is inconsistent (shapes, damping, quantity)."""


def _as_2d(name: str, value, n_modes: int) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != n_modes:
        raise PlantError(f"{name} must be (n, {n_modes}) (one column per mode), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise PlantError(f"{name} holds non-finite values")
    return arr


@dataclass(frozen=True, eq=False)
class ModalPlant:
    """A linear structure with proportional (modal) viscous damping, or a general state-space model.

    Parameters
    ----------
    frequencies_hz : (n_modes,) float
        Undamped natural frequencies, Hz.
    damping : (n_modes,) float or float
        Modal damping ratios (0.001 = 0.1 %).
    shapes_out : (n_out, n_modes) float
        Mass-normalized mode shapes at the response sensors (projected on the
        sensor directions), m/sqrt(kg).
    shapes_in : (n_in, n_modes) float
        Mass-normalized mode shapes at the drive points, m/sqrt(kg).
    quantity : {"accelerance", "mobility", "receptance"}
        What the outputs measure (acceleration m/s^2, velocity m/s, displacement m).
    rigid_out : (n_out, n_rigid) float or None
        Mass-normalized rigid-body mode shapes (0 Hz, free-free) at the sensors, m/sqrt(kg).
    rigid_in : (n_in, n_rigid) float or None
        The same at the drive points.
    residual : (n_terms, n_out, n_in) float or None
        Receptance of the modes above the kept ones as the series
        ``sum_j (residual_shift + w^2)^j residual[j]``, m/N (``frfcal.synth.ArticleTruth.residual``).
    residual_shift : float
        Shift s of that series, rad^2/s^2.

    Notes
    -----
    Receptance :math:`H(\\omega) = \\sum_r \\phi_{o,r}\\phi_{i,r}^T/(\\omega_r^2-\\omega^2+2i\\zeta_r\\omega_r\\omega)`
    + rigid-body and higher-mode terms (:meth:`feedthrough`);
    mobility = iw x receptance, accelerance = -w^2 x receptance.
    The rigid-body modes (receptance :math:`-\\phi_o\\phi_i^T/\\omega^2`, the
    accelerance mass line) and the higher modes are frequency-dependent
    feedthrough terms, not states: a free-free structure has no stable
    state-space form, and the higher modes respond quasi-instantaneously. The
    simulated lab applies them at the drive frequency to the delivered force.
    Use :meth:`from_state_space` for a general ``(A, B, C, D)`` model.
    """

    frequencies_hz: np.ndarray
    damping: np.ndarray
    shapes_out: np.ndarray
    shapes_in: np.ndarray
    quantity: str = "accelerance"
    rigid_out: np.ndarray | None = None
    rigid_in: np.ndarray | None = None
    residual: np.ndarray | None = None
    residual_shift: float = 0.0
    _poles: np.ndarray | None = None
    _bz: np.ndarray | None = None
    _cz: np.ndarray | None = None
    _d: np.ndarray | None = None
    _abcd: tuple | None = None
    _cdrive: np.ndarray | None = None
    _cdrive_physical: np.ndarray | None = None

    def __post_init__(self):
        if self.quantity not in QUANTITIES:
            raise PlantError(f"quantity must be one of {QUANTITIES}, got {self.quantity!r}")
        if self._poles is not None:
            return
        f = np.atleast_1d(np.asarray(self.frequencies_hz, dtype=float))
        n = f.size
        z = np.broadcast_to(np.asarray(self.damping, dtype=float), (n,)).copy()
        if n == 0:
            raise PlantError("a plant needs at least one mode")
        if np.any(f <= 0) or not np.all(np.isfinite(f)):
            raise PlantError(f"frequencies_hz must be positive and finite, got {f}")
        if np.any(z <= 0) or np.any(z >= 1):
            raise PlantError(f"damping ratios must lie in (0, 1), got {z}")
        po = _as_2d("shapes_out", self.shapes_out, n)
        pi = _as_2d("shapes_in", self.shapes_in, n)
        object.__setattr__(self, "frequencies_hz", f)
        object.__setattr__(self, "damping", z)
        object.__setattr__(self, "shapes_out", po)
        object.__setattr__(self, "shapes_in", pi)
        w = 2 * np.pi * f
        wd = w * np.sqrt(1 - z**2)
        lam = -z * w + 1j * wd
        # q_r'' + 2 z w q' + w^2 q = phi_in^T u; q = sum over the pole pair of
        # residues a/(s - lam) + conj; a = 1/(lam - conj(lam)) = 1/(2 i wd).
        a = 1.0 / (2j * wd)
        poles = np.concatenate([lam, lam.conj()])
        bz = np.concatenate([pi.T, pi.T]).astype(complex)  # (2n, n_in)
        res = np.concatenate([a, a.conj()])
        # displacement of pole j: res_j * z_j ; velocity: lam_j res_j z_j ;
        # acceleration: lam_j^2 res_j z_j + phi_o phi_i^T u (feedthrough).
        power = quantity_power(self.quantity)
        cz = np.concatenate([po, po], axis=1) * (res * poles**power)[None, :]
        if power == 2:
            d = po @ pi.T
        else:
            d = np.zeros((po.shape[0], pi.shape[0]))
        object.__setattr__(self, "_poles", poles)
        object.__setattr__(self, "_bz", bz)
        object.__setattr__(self, "_cz", cz)
        object.__setattr__(self, "_d", d)
        object.__setattr__(self, "_cdrive", np.concatenate([pi, pi], axis=1) * res[None, :])
        self._check_feedthrough(po.shape[0], pi.shape[0])

    def _check_feedthrough(self, n_out: int, n_in: int) -> None:
        """Validate and store the rigid-body and higher-mode terms (see the class notes)."""
        if (self.rigid_out is None) != (self.rigid_in is None):
            raise PlantError("give both rigid_out and rigid_in, or neither")
        if self.rigid_out is not None:
            ro = np.asarray(self.rigid_out, dtype=float).reshape(n_out, -1)
            ri = np.asarray(self.rigid_in, dtype=float)
            if ri.ndim != 2 or ri.shape != (n_in, ro.shape[1]):
                raise PlantError(f"rigid_in must be ({n_in}, {ro.shape[1]}) like rigid_out, got {ri.shape}")
            if not (np.all(np.isfinite(ro)) and np.all(np.isfinite(ri))):
                raise PlantError("rigid_out/rigid_in hold non-finite values")
            object.__setattr__(self, "rigid_out", ro)
            object.__setattr__(self, "rigid_in", ri)
        if self.residual is not None:
            r = np.asarray(self.residual, dtype=float)
            if r.ndim != 3 or r.shape[1:] != (n_out, n_in) or r.shape[0] < 1:
                raise PlantError(f"residual must be (n_terms, {n_out}, {n_in}), got {r.shape}")
            if not np.all(np.isfinite(r)):
                raise PlantError("residual holds non-finite values")
            if r.shape[0] > 1 and not (np.isfinite(self.residual_shift) and self.residual_shift > 0):
                raise PlantError(f"a residual series needs residual_shift > 0 (rad^2/s^2), got {self.residual_shift}")
            object.__setattr__(self, "residual", r)
            object.__setattr__(self, "residual_shift", float(self.residual_shift))

    @property
    def has_feedthrough(self) -> bool:
        """True when rigid-body or higher-mode terms are present."""
        return self.rigid_out is not None or self.residual is not None

    def feedthrough(self, frequency_hz) -> np.ndarray:
        """Rigid-body plus higher-mode FRF of the plant's quantity, ``(n_f, n_out, n_in)`` complex SI.

        Receptance ``-phi_o phi_i^T / w^2`` per rigid mode plus
        ``sum_j (s + w^2)^j residual[j]``, times iw (mobility) or -w^2 (accelerance).
        Zero when the plant has neither.
        """
        f = np.atleast_1d(np.asarray(frequency_hz, dtype=float))
        out = np.zeros((f.size, self.n_out, self.n_in), dtype=complex)
        if not self.has_feedthrough:
            return out
        if np.any(f <= 0):
            raise PlantError("the rigid-body/higher-mode feedthrough is defined for frequencies > 0 Hz")
        w = 2 * np.pi * f
        if self.rigid_out is not None:
            out += (-1.0 / w**2)[:, None, None] * (self.rigid_out @ self.rigid_in.T)[None]
        if self.residual is not None:
            powers = (self.residual_shift + w[:, None] ** 2) ** np.arange(self.residual.shape[0])[None, :]
            out += np.einsum("fj,joi->foi", powers, self.residual)
        return quantity_factor(self.quantity, w)[:, None, None] * out

    # ------------------------------------------------------------------ ctors
    @classmethod
    def from_state_space(cls, A, B, C, D=None, quantity: str = "accelerance", C_drive=None) -> "ModalPlant":
        """Build a plant from a real state-space model ``x' = A x + B u, y = C x + D u``.

        Parameters
        ----------
        A : (n, n), B : (n, n_in), C : (n_out, n), D : (n_out, n_in) or None
            SI units; ``u`` forces in N, ``y`` of the stated ``quantity``.
        C_drive : (n_in, n) or None
            Displacement (m) of each drive point along its force direction;
            needed for the shaker/structure interaction of the simulated lab
            (without it the simulated shaker is an ideal force source).
        """
        A = np.asarray(A, dtype=float)
        B = np.asarray(B, dtype=float)
        C = np.asarray(C, dtype=float)
        n = A.shape[0]
        if A.shape != (n, n) or B.ndim != 2 or B.shape[0] != n or C.ndim != 2 or C.shape[1] != n:
            raise PlantError(f"state-space shapes do not agree: A {A.shape}, B {B.shape}, C {C.shape}")
        D = np.zeros((C.shape[0], B.shape[1])) if D is None else np.asarray(D, dtype=float)
        if D.shape != (C.shape[0], B.shape[1]):
            raise PlantError(f"D must be {(C.shape[0], B.shape[1])}, got {D.shape}")
        lam, V = np.linalg.eig(A)
        if np.any(lam.real >= 0):
            raise PlantError(f"state-space model is not asymptotically stable (max Re(pole) = {lam.real.max():.3g})")
        if np.linalg.cond(V) > 1e10:
            raise PlantError("state-space A is defective or nearly so (eigenvector condition > 1e10)")
        bz = np.linalg.solve(V, B.astype(complex))
        cz = C @ V
        wn = np.abs(lam)
        upper = lam.imag > 0
        plant = cls.__new__(cls)
        for name, value in dict(
            frequencies_hz=wn[upper] / (2 * np.pi),
            damping=-lam.real[upper] / wn[upper],
            shapes_out=np.zeros((C.shape[0], 0)),
            shapes_in=np.zeros((B.shape[1], 0)),
            quantity=quantity,
            _poles=lam,
            _bz=bz,
            _cz=cz,
            _d=D,
            _abcd=(A, B, C, D),
            _cdrive=None if C_drive is None else np.asarray(C_drive, dtype=float) @ V,
            _cdrive_physical=None if C_drive is None else np.asarray(C_drive, dtype=float),
        ).items():
            object.__setattr__(plant, name, value)
        if quantity not in QUANTITIES:
            raise PlantError(f"quantity must be one of {QUANTITIES}, got {quantity!r}")
        return plant

    # ------------------------------------------------------------ properties
    @property
    def n_out(self) -> int:
        return self._cz.shape[0]

    @property
    def n_in(self) -> int:
        return self._bz.shape[1]

    @property
    def poles(self) -> np.ndarray:
        """Complex poles (rad/s) of the first-order form, ``(n_states,)``."""
        return self._poles.copy()

    def drive_point_form(self) -> np.ndarray | None:
        """``(n_in, n_s)`` complex map from diagonal states to drive-point displacement (m), or None."""
        return self._cdrive

    def diagonal_form(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(poles (n_s,), Bz (n_s, n_in), Cz (n_out, n_s), D (n_out, n_in))`` complex-diagonal form."""
        return self._poles, self._bz, self._cz, self._d

    def frf(self, frequency_hz) -> np.ndarray:
        """Exact steady-state FRF of the plant's quantity (feedthrough included), ``(n_f, n_out, n_in)`` complex SI."""
        f = np.atleast_1d(np.asarray(frequency_hz, dtype=float))
        s = 2j * np.pi * f
        g = 1.0 / (s[:, None] - self._poles[None, :])  # (n_f, n_s)
        h = np.einsum("os,fs,si->foi", self._cz, g, self._bz) + self._d[None]
        if self.has_feedthrough:
            h = h + self.feedthrough(f)
        return h

    def state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """A real ``(A, B, C, D)`` realization with states ``[q, q']`` per mode (modal plants)."""
        if self._abcd is not None:
            return self._abcd
        w = 2 * np.pi * self.frequencies_hz
        z = self.damping
        n = w.size
        A = np.zeros((2 * n, 2 * n))
        A[:n, n:] = np.eye(n)
        A[n:, :n] = -np.diag(w**2)
        A[n:, n:] = -np.diag(2 * z * w)
        B = np.vstack([np.zeros((n, self.n_in)), self.shapes_in.T])
        po = self.shapes_out
        if self.quantity == "receptance":
            C = np.hstack([po, np.zeros_like(po)])
            D = np.zeros((po.shape[0], self.n_in))
        elif self.quantity == "mobility":
            C = np.hstack([np.zeros_like(po), po])
            D = np.zeros((po.shape[0], self.n_in))
        else:
            C = np.hstack([-po * w**2, -po * 2 * z * w])
            D = po @ self.shapes_in.T
        return A, B, C, D

    def time_constants_s(self) -> np.ndarray:
        """Decay time constants 1/(zeta w) of the modes, s."""
        upper = self._poles.imag > 0
        return 1.0 / -self._poles.real[upper]
