"""Term families added to a parametric model: springs, lumped masses, element-subset factors.

A parametric model is a sum of term families. The deck's own cards give the
families of :func:`femodel.parametric_model` (a field of an existing card,
P = P0 (1 + p)). The families here add an effect the deck does not have, or
change part of a property group:

========================  ====================  =======================  =========================
family                    physical value        coefficient of its term  written back as
========================  ====================  =======================  =========================
:class:`AddedSpring`      k = scale * p (N/m    p                        CELAS2 per DOF pair
                          or N m/rad), p >= 0                            (to ground: G2 blank)
:class:`AddedMass`        m = scale * p (kg),   p                        CONM2 per grid
                          p >= 0
:class:`ElementFactor`    f = 1 + p             p * (the subset's terms  property (and MAT1) copies
                          (dimensionless)       with their own P0 (1+p)  with E, G (or RHO, NSM)
                                                coefficients)            times f; elements re-pointed
========================  ====================  =======================  =========================

An added spring or mass starts from zero (p = 0 is the deck as it is), so its
parameter is an absolute magnitude in units of ``scale``; choose ``scale``
near the expected magnitude so that p ~ O(1) for the optimizer. An element
factor adds ``p`` times the stiffness (or mass) of its elements, so p = 0 is
again the deck as it is and ``1 + p`` the factor.

:class:`ExtendedAffineMatrix` carries the coefficients: each term is a
(series) monomial in (1 + p) times, optionally, one parameter p_l linearly;
derivatives stay exact by the product rule.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from femodel._params import ParameterError
from femodel._parametric import SeriesAffineMatrix

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")


@dataclass(frozen=True)
class ExtendedAffineMatrix(SeriesAffineMatrix):
    """A :class:`~femodel.SeriesAffineMatrix` whose terms may also scale with one parameter linearly.

    Term k has the coefficient

        c_k(p) = s_k(p) * p_l(k)   if ``linear[k] = l >= 0``,
        c_k(p) = s_k(p)            if ``linear[k] = -1``,

    with s_k the series/monomial coefficient of :class:`SeriesAffineMatrix`.
    An added spring or mass term has s_k = 1 and l its own parameter; a term of
    an element-subset factor keeps the s_k of the subset's elements.

    Parameters
    ----------
    matrices, exponents, series_exponents, series_ratio
        As :class:`SeriesAffineMatrix`.
    linear : (n_terms,) int array
        Index of the parameter each term is multiplied by, or -1.
    """

    linear: np.ndarray = None

    def __post_init__(self) -> None:
        super().__post_init__()
        n = len(self.matrices)
        lin = -np.ones(n, dtype=np.int64) if self.linear is None else np.asarray(self.linear, dtype=np.int64)
        if lin.shape != (n,) or np.any(lin < -1) or np.any(lin >= self.n_params):
            raise ValueError(f"ExtendedAffineMatrix: linear must be (n_terms={n},) indices in -1..{self.n_params - 1}")
        object.__setattr__(self, "linear", lin)

    def _linear_factor(self, p) -> np.ndarray:
        has = self.linear >= 0
        return np.where(has, p[np.where(has, self.linear, 0)], 1.0)

    def coefficients(self, p) -> np.ndarray:
        p = self._check(p)
        return SeriesAffineMatrix.coefficients(self, p) * self._linear_factor(p)

    def coefficient_jacobian(self, p) -> np.ndarray:
        p = self._check(p)
        base = SeriesAffineMatrix.coefficients(self, p)
        jac = SeriesAffineMatrix.coefficient_jacobian(self, p) * self._linear_factor(p)[:, None]
        rows = np.flatnonzero(self.linear >= 0)
        jac[rows, self.linear[rows]] += base[rows]
        return jac

    def projected(self, basis) -> "ExtendedAffineMatrix":
        reduced = SeriesAffineMatrix.projected(self, basis)
        return ExtendedAffineMatrix(reduced.matrices, self.exponents.copy(), self.series_exponents.copy(),
                                    self.series_ratio.copy(), self.linear.copy())


def _check_name(cls: str, name: str) -> None:
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ParameterError(f"{cls}: name {name!r} must start with a letter or _ and hold letters, digits, _ . -")


def _check_bounds(cls: str, name: str, lower: float, upper: float, floor: float) -> None:
    lo, hi = float(lower), float(upper)
    if not (np.isfinite(lo) and np.isfinite(hi) and floor <= lo < hi):
        raise ParameterError(f"{cls} {name!r}: need {floor} <= lower < upper (finite), got [{lower}, {upper}]")


def _check_scale(cls: str, name: str, scale: float) -> None:
    if not (np.isfinite(float(scale)) and float(scale) > 0.0):
        raise ParameterError(f"{cls} {name!r}: scale must be positive and finite, got {scale!r}")


def _grid_dofs(fe, grids, components, what: str) -> np.ndarray:
    """g-set rows of (grid, component) pairs; components are in the grids' CD systems (1..6)."""
    comps = np.asarray(components, dtype=np.int64)
    bad = comps[(comps < 1) | (comps > 6)]
    if bad.size:
        raise ParameterError(f"{what}: component {int(bad[0])} must be 1..6")
    try:
        rows = fe.grid_index(np.asarray(grids, dtype=np.int64), what=what)
    except ValueError as exc:
        raise ParameterError(str(exc)) from None
    return 6 * rows + comps - 1


def _g_csr(entries: dict, fe) -> dict:
    """{kind: (rows, cols, vals)} g-set entries as (n_g, n_g) CSR matrices (duplicates summed)."""
    n = 6 * fe.n_grids
    return {k: sp.csr_matrix((v, (r, c)), shape=(n, n)) for k, (r, c, v) in entries.items()}


@dataclass(frozen=True)
class AddedSpring:
    """Scalar springs of one common rate between DOF pairs or to ground.

    A contact or joint spring between two parts lists the DOF pairs it
    connects (e.g. the three translations of two facing grids); a boundary
    spring lists ``(grid, component, 0, 0)``. Every pair gets the same rate
    k = ``scale`` * p, written back as one CELAS2 each.

    Parameters
    ----------
    name : str
        Parameter name.
    dofs : tuple of (g1, c1, g2, c2)
        Grid ids and components (1..6, in each grid's displacement system);
        g2 = 0 grounds the spring (c2 ignored). All translational (rate in
        N/m) or all rotational (N m/rad).
    scale : float
        Rate per unit p, SI (N/m or N m/rad).
    lower, upper : float
        Bounds on p (0 <= lower < upper).
    description : str
    """

    name: str
    dofs: tuple
    scale: float
    lower: float = 0.0
    upper: float = 10.0
    description: str = ""

    absolute = True
    nominal = 0.0

    def __post_init__(self) -> None:
        _check_name("AddedSpring", self.name)
        _check_scale("AddedSpring", self.name, self.scale)
        _check_bounds("AddedSpring", self.name, self.lower, self.upper, 0.0)
        pairs = tuple(tuple(int(x) for x in d) for d in self.dofs)
        if not pairs or any(len(d) != 4 for d in pairs):
            raise ParameterError(f"AddedSpring {self.name!r}: dofs must be a non-empty list of (g1, c1, g2, c2)")
        comps = set()
        for g1, c1, g2, c2 in pairs:
            comps.add(c1)
            if g2:
                comps.add(c2)
            if g2 and (g1, c1) == (g2, c2):
                raise ParameterError(f"AddedSpring {self.name!r}: pair {(g1, c1, g2, c2)} connects a DOF to itself")
        if not (comps <= {1, 2, 3} or comps <= {4, 5, 6}):
            raise ParameterError(f"AddedSpring {self.name!r}: components {sorted(comps)} mix translations and "
                                 "rotations; the rate's unit would be ambiguous (use two terms)")
        object.__setattr__(self, "dofs", pairs)

    @property
    def rotational(self) -> bool:
        return self.dofs[0][1] >= 4

    @property
    def unit(self) -> str:
        return "N m/rad" if self.rotational else "N/m"

    def value(self, p: float) -> float:
        """The rate at normalized ``p``, SI."""
        return float(self.scale) * float(p)

    def normalized(self, value: float) -> float:
        """The p of a rate (SI)."""
        return float(value) / float(self.scale)

    def g_entries(self, fe) -> dict:
        """{"K": (rows, cols, vals)}: the g-set entries at p = 1 (``scale`` times the unit springs), pair by
        pair: (i, i) for a spring to ground, (i, i), (i, j), (j, i), (j, j) between two DOF (duplicates are
        to be summed)."""
        d = np.asarray(self.dofs, dtype=np.int64).reshape(-1, 4)
        what = f"added spring {self.name!r} grid"
        two = d[:, 2] != 0
        i = _grid_dofs(fe, d[:, 0], d[:, 1], what)
        j = np.zeros_like(i)
        j[two] = _grid_dofs(fe, d[two, 2], d[two, 3], what)
        rows = np.stack([i, i, j, j], axis=1)
        cols = np.stack([i, j, i, j], axis=1)
        vals = np.tile([1.0, -1.0, -1.0, 1.0], (d.shape[0], 1))
        use = np.ones((d.shape[0], 4), dtype=bool)
        use[~two, 1:] = False
        return {"K": (rows[use], cols[use], float(self.scale) * vals[use])}

    def g_matrices(self, fe) -> dict:
        """{"K": g-set matrix at p = 1} (``scale`` times the unit springs), (n_g, n_g)."""
        return _g_csr(self.g_entries(fe), fe)

    def write_cards(self, value: float, editor) -> None:
        """CELAS2 cards of rate ``value`` (SI) for every pair (fresh element ids), small field (the rate
        rounded to its 8-character spelling: a relative change below 1e-4)."""
        from femodel._writeback import small_field_value

        k = small_field_value(editor.deck_value(value, "rot_spring" if self.rotational else "trans_spring"))
        for g1, c1, g2, c2 in self.dofs:
            editor.add(["CELAS2", editor.new_id("element"), k, g1, c1, g2 or None, c2 if g2 else None])


@dataclass(frozen=True)
class AddedMass:
    """Lumped masses of one common value on grids (sensor, shaker or attachment masses).

    Each grid gets a point mass m = ``scale`` * p on its three translations
    (no offset, no rotary inertia), written back as one CONM2 each.

    Parameters
    ----------
    name : str
    grids : tuple of int
    scale : float
        Mass per unit p, kg.
    lower, upper : float
        Bounds on p (0 <= lower < upper).
    description : str
    """

    name: str
    grids: tuple
    scale: float
    lower: float = 0.0
    upper: float = 10.0
    description: str = ""

    absolute = True
    nominal = 0.0
    unit = "kg"

    def __post_init__(self) -> None:
        _check_name("AddedMass", self.name)
        _check_scale("AddedMass", self.name, self.scale)
        _check_bounds("AddedMass", self.name, self.lower, self.upper, 0.0)
        grids = tuple(int(g) for g in self.grids)
        if not grids or len(set(grids)) != len(grids):
            raise ParameterError(f"AddedMass {self.name!r}: grids must be a non-empty list of distinct ids")
        object.__setattr__(self, "grids", grids)

    def value(self, p: float) -> float:
        return float(self.scale) * float(p)

    def normalized(self, value: float) -> float:
        return float(value) / float(self.scale)

    def g_entries(self, fe) -> dict:
        """{"M": (rows, cols, vals)}: the g-set entries at p = 1 (kg on the three translations of each grid)."""
        g = np.repeat(np.asarray(self.grids, dtype=np.int64), 3)
        idx = _grid_dofs(fe, g, np.tile([1, 2, 3], len(self.grids)), f"added mass {self.name!r} grid")
        return {"M": (idx, idx, np.full(idx.size, float(self.scale)))}

    def g_matrices(self, fe) -> dict:
        """{"M": g-set matrix at p = 1}, (n_g, n_g), kg."""
        return _g_csr(self.g_entries(fe), fe)

    def write_cards(self, value: float, editor) -> None:
        """CONM2 cards of mass ``value`` (kg) on every grid (fresh element ids, CID 0), small field (the mass
        rounded to its 8-character spelling: a relative change below 1e-4)."""
        from femodel._writeback import small_field_value

        m = small_field_value(editor.deck_value(value, "mass"))
        for g in self.grids:
            editor.add(["CONM2", editor.new_id("element"), g, 0, m])


@dataclass(frozen=True)
class ElementFactor:
    """A factor 1 + p on the stiffness (or mass) of a chosen set of elements.

    The term is p times the K (or M) terms of these elements, with the
    coefficients their properties already have (a thickness parameter of
    their PSHELL still acts), so p = 0 is the deck as it is. Written back as
    copies of the elements' properties and MAT1 cards with E and G (or RHO
    and the property's NSM) times 1 + p, and the elements re-pointed to them.

    Parameters
    ----------
    name : str
    elements : tuple of int
        Element ids (CQUAD4, CTRIA3, CBAR, CBEAM, CROD, solids with PSHELL,
        PBAR/PBARL, PBEAM/PBEAML, PROD or PSOLID properties and MAT1 materials).
    kind : {"K", "M"}
    lower, upper : float
        Bounds on p (-1 < lower < upper).
    description : str
    """

    name: str
    elements: tuple
    kind: str = "K"
    lower: float = -0.5
    upper: float = 1.0
    description: str = ""

    absolute = False
    nominal = 1.0
    unit = ""

    def __post_init__(self) -> None:
        _check_name("ElementFactor", self.name)
        if self.kind not in ("K", "M"):
            raise ParameterError(f"ElementFactor {self.name!r}: kind must be 'K' or 'M', got {self.kind!r}")
        _check_bounds("ElementFactor", self.name, self.lower, self.upper, -1.0)
        if float(self.lower) <= -1.0:
            raise ParameterError(f"ElementFactor {self.name!r}: lower must be > -1 (a factor 1 + p > 0)")
        els = tuple(int(e) for e in self.elements)
        if not els or len(set(els)) != len(els):
            raise ParameterError(f"ElementFactor {self.name!r}: elements must be a non-empty list of distinct ids")
        object.__setattr__(self, "elements", els)

    def value(self, p: float) -> float:
        """The factor 1 + p."""
        return 1.0 + float(p)

    def normalized(self, value: float) -> float:
        return float(value) - 1.0

    def submodel(self, fe):
        """The FE model with only this subset's elements (same grids, properties, constraints)."""
        from dataclasses import replace

        from femodel._model import Table

        wanted = np.asarray(self.elements, dtype=np.int64)
        found = np.zeros(wanted.size, dtype=bool)
        elements, bare = {}, []
        for card, tab in fe.elements.items():
            if len(tab) == 0:
                continue
            sel = np.isin(tab.ids, wanted)
            if not np.any(sel):
                continue
            if card in ("CONM1", "CONM2", "CMASS1", "CMASS2", "CELAS1", "CELAS2", "CBUSH", "CONROD"):
                # a factor scales a property's material: these cards have none. pyNastran keeps masses and
                # springs apart from the elements, so a deck may reuse an element's id for a CONM2: the
                # element with a property is meant then, and only an id found nowhere else is an error
                bare.append((card, tab.ids[sel]))
                continue
            found |= np.isin(wanted, tab.ids[sel])
            elements[card] = Table(card, tab.ids[sel], {k: np.asarray(v)[sel] for k, v in tab.fields.items()})
        for card, ids in bare:
            alone = ids[~np.isin(ids, wanted[found])]
            if alone.size:
                raise ParameterError(f"ElementFactor {self.name!r}: {card} {alone[:5].tolist()} have no "
                                     "property card with a MAT1 to copy (use the card's own field parameter)")
        if not np.all(found):
            src = f" of {fe.path}" if fe.path else ""
            raise ParameterError(f"ElementFactor {self.name!r}: elements {wanted[~found][:10].tolist()} are not "
                                 f"elements{src}")
        return replace(fe, elements=elements)

    def write_cards(self, value: float, editor) -> None:
        """Scaled property/material copies with factor ``value``; the elements re-pointed to them."""
        editor.scaled_copies(self.elements, self.kind, float(value), self.name)


#: The term families :meth:`femodel.ParametricModel.with_terms` accepts.
TERM_FAMILIES = (AddedSpring, AddedMass, ElementFactor)
