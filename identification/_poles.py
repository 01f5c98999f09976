"""Poles, their labels, and modal parameters."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labdata import mac

from ._errors import IdentificationError

#: Labels a pole can carry; only "physical" poles are modes of the structure.
LABELS = ("physical", "out-of-band", "real", "overdamped", "unstable", "negligible")


def _frozen(arr, dtype=None) -> np.ndarray:
    a = np.array(arr, dtype=dtype)
    a.setflags(write=False)
    return a


def pole_frequency_hz(lam: np.ndarray) -> np.ndarray:
    """Undamped natural frequency ``|lambda| / 2 pi`` [Hz]."""
    return np.abs(lam) / (2.0 * np.pi)


def pole_damping(lam: np.ndarray) -> np.ndarray:
    """Damping ratio ``zeta = -Re(lambda) / |lambda|`` (1 for a real stable pole, < 0 if unstable)."""
    lam = np.asarray(lam)
    mag = np.abs(lam)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(mag > 0, -lam.real / np.where(mag > 0, mag, 1.0), 0.0)


@dataclass(frozen=True)
class Poles:
    """One entry per real pole or per complex-conjugate pair (the ``Im > 0`` member).

    Attributes
    ----------
    eigenvalues : ndarray, complex (n_p,)
        Poles [rad/s], ``Im >= 0``; sorted by frequency.
    frequency_hz : ndarray (n_p,)
        Undamped natural frequency ``|lambda|/2pi`` [Hz].
    damping : ndarray (n_p,)
        Damping ratio ``-Re(lambda)/|lambda|`` [-].
    labels : tuple of str (n_p,)
        One of :data:`LABELS` each.
    contribution : ndarray (n_p,)
        Largest ratio, over the data lines in band, of the pole's own FRF term
        to the data (Frobenius norms over channels, outputs weighted) [-].
    importance : ndarray (n_p,)
        Relative increase of the weighted residual sum of squares when the
        pole is removed and ``B, D`` are refitted [-].
    """

    eigenvalues: np.ndarray
    labels: tuple[str, ...]
    contribution: np.ndarray
    importance: np.ndarray

    def __post_init__(self) -> None:
        lam = _frozen(self.eigenvalues, complex).reshape(-1)
        labels = tuple(str(s) for s in self.labels)
        if len(labels) != lam.size:
            raise IdentificationError(f"Poles: {len(labels)} labels for {lam.size} eigenvalues")
        bad = [s for s in labels if s not in LABELS]
        if bad:
            raise IdentificationError(f"Poles: unknown label(s) {sorted(set(bad))}; allowed {LABELS}")
        object.__setattr__(self, "eigenvalues", lam)
        object.__setattr__(self, "labels", labels)
        for name in ("contribution", "importance"):
            v = _frozen(getattr(self, name), float).reshape(-1)
            if v.size != lam.size:
                raise IdentificationError(f"Poles: {v.size} {name} values for {lam.size} eigenvalues")
            object.__setattr__(self, name, v)

    def __len__(self) -> int:
        return self.eigenvalues.size

    @property
    def frequency_hz(self) -> np.ndarray:
        return pole_frequency_hz(self.eigenvalues)

    @property
    def damping(self) -> np.ndarray:
        return pole_damping(self.eigenvalues)

    @property
    def label(self) -> tuple[str, ...]:
        """Alias of :attr:`labels` (one label per pole)."""
        return self.labels

    @property
    def physical(self) -> np.ndarray:
        """Boolean mask of the poles labelled ``"physical"``."""
        return np.array([s == "physical" for s in self.labels], dtype=bool)

    def count(self, label: str) -> int:
        return sum(1 for s in self.labels if s == label)


@dataclass(frozen=True)
class ModalParameters:
    """Modal parameters of the physical poles.

    The contribution of mode ``r`` to the FRF is
    ``R_r / (i omega - lambda_r) + conj(R_r) / (i omega - conj(lambda_r))`` with
    residue ``R_r = outer(shapes[:, r], participation[r, :])``.

    Attributes
    ----------
    eigenvalues : complex (n_modes,) [rad/s]
    frequency_hz : (n_modes,) undamped natural frequency [Hz]
    damping : (n_modes,) damping ratio [-]
    shapes : complex (n_out, n_modes)
        Mode shapes at the sensors, in the FRF's response quantity, scaled to
        unit largest component with that component real and positive.
    participation : complex (n_modes, n_in)
        Modal participation of each input (residue = shape x participation).
    """

    eigenvalues: np.ndarray
    shapes: np.ndarray
    participation: np.ndarray

    def __post_init__(self) -> None:
        lam = _frozen(self.eigenvalues, complex).reshape(-1)
        shapes = _frozen(self.shapes, complex)
        part = _frozen(self.participation, complex)
        if shapes.ndim != 2 or shapes.shape[1] != lam.size:
            raise IdentificationError(f"ModalParameters.shapes must be (n_out, {lam.size}), got {shapes.shape}")
        if part.ndim != 2 or part.shape[0] != lam.size:
            raise IdentificationError(
                f"ModalParameters.participation must be ({lam.size}, n_in), got {part.shape}"
            )
        object.__setattr__(self, "eigenvalues", lam)
        object.__setattr__(self, "shapes", shapes)
        object.__setattr__(self, "participation", part)

    @property
    def frequency_hz(self) -> np.ndarray:
        return pole_frequency_hz(self.eigenvalues)

    @property
    def damping(self) -> np.ndarray:
        return pole_damping(self.eigenvalues)

    @property
    def n_modes(self) -> int:
        return self.eigenvalues.size


def normalize_shapes(shapes: np.ndarray, participation: np.ndarray):
    """Scale each shape to unit largest component (real, positive); keep the residue."""
    shapes = np.array(shapes, dtype=complex)
    part = np.array(participation, dtype=complex)
    for r in range(shapes.shape[1]):
        k = int(np.argmax(np.abs(shapes[:, r])))
        c = shapes[k, r]
        if c != 0:
            shapes[:, r] /= c
            part[r, :] *= c
    return shapes, part


def label_poles(
    lam: np.ndarray,
    contribution: np.ndarray,
    importance: np.ndarray,
    was_unstable: np.ndarray,
    band_hz: tuple[float, float],
    zeta_max: float,
    min_contribution: float,
    min_importance: float,
) -> tuple[str, ...]:
    """Label each pole; the first failing test in this order wins:
    unstable, real, overdamped (zeta > zeta_max), out-of-band, negligible
    (contribution < min_contribution or importance < min_importance)."""
    labels = []
    f = pole_frequency_hz(lam)
    zeta = pole_damping(lam)
    for i in range(lam.size):
        if was_unstable[i] or lam[i].real > 0:
            labels.append("unstable")
        elif lam[i].imag == 0.0:
            labels.append("real")
        elif zeta[i] > zeta_max:
            labels.append("overdamped")
        elif not (band_hz[0] <= f[i] <= band_hz[1]):
            labels.append("out-of-band")
        elif contribution[i] < min_contribution or importance[i] < min_importance:
            labels.append("negligible")
        else:
            labels.append("physical")
    return tuple(labels)
