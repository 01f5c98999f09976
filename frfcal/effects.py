"""Undeclared effects for synthetic truth data: what the test article has and the calibration model lacks.

An :class:`Effect` is one physical addition to a deck, expressed as a term of
femodel's term families (:class:`femodel.AddedSpring`,
:class:`femodel.AddedMass`, :class:`femodel.ElementFactor`) at a physical
value, on some or all articles of a synthetic campaign
(:func:`frfcal.synth.synthesize`). The truth of an article is the deck's
parametric model extended by the terms of its effects
(:meth:`femodel.ParametricModel.with_terms`); the calibration model is the deck
without them.

The effects are defined by the physical truth (a spring between two named
facing grids, a mass on named grids, a factor on named elements), never by a
candidate generator of the diagnosis path under test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class EffectError(ValueError):
    """An invalid effect (the message names the effect and the field at fault)."""


@dataclass(frozen=True)
class Effect:
    """One undeclared physical effect of the test articles.

    Parameters
    ----------
    term : femodel.AddedSpring, femodel.AddedMass or femodel.ElementFactor
        Where and how the effect acts (its ``scale`` and bounds only matter to
        a calibration that would fit it; here the ``value`` is imposed).
    value : float
        Physical value, SI: spring rate (N/m or N m/rad, > 0), mass (kg,
        > 0), or the factor 1 + p of an element subset (> 0, != 1).
    articles : sequence of int or str, optional
        Article indices (0-based) or names that have the effect; None = all.
    family : str, optional
        A label of the physical family (e.g. ``"contact_spring"``); default
        the term's class name.
    """

    term: object
    value: float
    articles: tuple | None = None
    family: str = ""

    def __post_init__(self) -> None:
        from femodel._terms import TERM_FAMILIES, ElementFactor

        if not isinstance(self.term, TERM_FAMILIES):
            raise EffectError(f"Effect: term must be one of {', '.join(c.__name__ for c in TERM_FAMILIES)}, "
                              f"got {type(self.term).__name__}")
        v = float(self.value)
        name = self.term.name
        if not np.isfinite(v) or v <= 0.0:
            raise EffectError(f"Effect {name!r}: value must be positive and finite, got {self.value!r}")
        if isinstance(self.term, ElementFactor) and v == 1.0:
            raise EffectError(f"Effect {name!r}: a factor of exactly 1 changes nothing")
        object.__setattr__(self, "value", v)
        if self.articles is not None:
            arts = tuple(a if isinstance(a, str) else int(a) for a in self.articles)
            if not arts:
                raise EffectError(f"Effect {name!r}: articles must be None (all) or a non-empty list")
            object.__setattr__(self, "articles", arts)
        if not self.family:
            object.__setattr__(self, "family", type(self.term).__name__)

    @property
    def name(self) -> str:
        return self.term.name

    @property
    def p(self) -> float:
        """The term's normalized parameter at ``value``."""
        return float(self.term.normalized(self.value))

    @property
    def unit(self) -> str:
        return self.term.unit or "factor"

    def applies_to(self, index: int, name: str) -> bool:
        """Whether the article with 0-based ``index`` and ``name`` has the effect."""
        return self.articles is None or index in self.articles or name in self.articles

    def record(self, articles) -> dict:
        """JSON-able description: family, term, name, value, unit, where it acts, description, articles.

        Parameters
        ----------
        articles : sequence of str
            The campaign's article names (the record lists those that have it).
        """
        from femodel._terms import AddedMass, AddedSpring

        t = self.term
        out = {"family": self.family, "term": type(t).__name__, "name": t.name, "value": self.value,
               "unit": self.unit, "description": t.description}
        if isinstance(t, AddedSpring):
            out["dofs"] = [list(d) for d in t.dofs]
            out["grids"] = sorted({g for d in t.dofs for g in (d[0], d[2]) if g})
        elif isinstance(t, AddedMass):
            out["grids"] = list(t.grids)
        else:
            out["elements"] = list(t.elements)
            out["kind"] = t.kind
        out["articles"] = [a for i, a in enumerate(articles) if self.applies_to(i, a)]
        return out


def resolve_articles(effects, articles) -> list[tuple[int, ...]]:
    """Per article (in order), the indices into ``effects`` of the effects it has.

    Raises :class:`EffectError` for an article index or name not in ``articles``
    or two effects with the same term name.
    """
    effects = tuple(effects)
    names = [e.name for e in effects]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise EffectError(f"effects: term name(s) {dup} used twice")
    for e in effects:
        if not isinstance(e, Effect):
            raise EffectError(f"effects: expected Effect entries, got {type(e).__name__}")
        for a in e.articles or ():
            if (isinstance(a, str) and a not in articles) or (isinstance(a, int) and not 0 <= a < len(articles)):
                raise EffectError(f"Effect {e.name!r}: article {a!r} is not one of {list(articles)}")
    return [tuple(k for k, e in enumerate(effects) if e.applies_to(i, a)) for i, a in enumerate(articles)]


# ----------------------------------------------------------------------------
# one effect of each family for a given deck
# ----------------------------------------------------------------------------
#: the element cards whose properties an ElementFactor can copy
_FACTOR_CARDS = ("CQUAD4", "CTRIA3", "CBAR", "CBEAM", "CROD", "CHEXA", "CPENTA", "CTETRA")
#: stiffness factor of the element cluster
CLUSTER_FACTOR = 0.7
#: radius of the element cluster, in element sizes
CLUSTER_RADIUS_ELEMENTS = 2.0
#: the shaker's axial support (armature suspension in series with the stinger) is soft: its spring is sized for
#: this fraction of ``shift``, so the attachment's mass dominates as it does on a free-free test
STINGER_SHIFTS = 0.25
#: a closed gap is stiff: its contact springs are sized for this many times ``shift`` (first order; the exact
#: shift saturates where the contact is stiffer than the parts around it)
CONTACT_SHIFTS = 10.0


@dataclass(frozen=True)
class _Ref:
    """The nominal deck's elastic modes the effects are scaled against (mass-normalized, a-set)."""

    p: np.ndarray
    lam: np.ndarray  # (n,) rad^2/s^2
    phi: np.ndarray  # (n_a, n)
    f_hz: np.ndarray


def _reference_modes(pm, p, band_hz, n_modes) -> _Ref:
    from frfcal.synth import modes_up_to

    K, M = pm.stiffness(p), pm.mass(p)
    if band_hz is not None:
        modes, _ = modes_up_to(K, M, float(band_hz[1]), dofs=pm.aset)
        keep = (modes.frequencies_hz >= float(band_hz[0])) & (modes.frequencies_hz <= float(band_hz[1]))
    else:
        modes = pm.modes(p, int(n_modes) + 6)
        keep = np.flatnonzero(modes.frequencies_hz > 1e-2)[:int(n_modes)]
    phi = modes.shapes[:, keep]
    f = modes.frequencies_hz[keep]
    if f.size == 0:
        raise EffectError(f"standard_effects: {pm.bdf}: no elastic mode in {band_hz} Hz to scale the effects by")
    phi = phi / np.sqrt(np.einsum("ik,ik->k", phi, M @ phi))
    return _Ref(p, (2 * np.pi * f) ** 2, phi, f)


def first_order_shifts(pm, term, value, ref) -> np.ndarray:
    """Relative frequency shifts df/f of the reference modes, to first order, for ``term`` at ``value``.

    df_k/f_k = (1/2) p phi_k^T (dK/dp - lambda_k dM/dp) phi_k / lambda_k with
    mass-normalized phi_k, p = ``term.normalized(value)``; exact derivatives
    from :meth:`femodel.ParametricModel.with_terms`.
    """
    pe = pm.with_terms([term])
    q = np.concatenate([ref.p, [0.0]])
    j = pe.n_params - 1
    dK, dM = pe.dK(q, j), pe.dM(q, j)
    dlam = np.einsum("ik,ik->k", ref.phi, dK @ ref.phi) - ref.lam * np.einsum("ik,ik->k", ref.phi, dM @ ref.phi)
    return 0.5 * term.normalized(value) * dlam / ref.lam


def _scaled(pm, cls, name, where, ref, shift, description, **kw):
    """A spring or mass term whose value makes the largest first-order shift of the reference modes ``shift``."""
    unit_term = cls(name, where, scale=1.0, **kw)
    rel = first_order_shifts(pm, unit_term, 1.0, ref)
    peak = float(np.max(np.abs(rel)))
    if not peak > 0:
        raise EffectError(f"standard_effects: {name!r} on {where} does not move any reference mode")
    value = float(shift) / peak
    return cls(name, where, scale=value, description=description.format(value=value), **kw), value


def _structural_grids(fe) -> np.ndarray:
    """Ids of the grids an element of a property-carrying card connects (not RBE/CONM2-only grids)."""
    ids = [np.asarray(t.fields["nodes"]).ravel() for c, t in fe.elements.items() if c in _FACTOR_CARDS and len(t)]
    ids = np.unique(np.concatenate(ids))
    return ids[ids > 0]


def _component(direction, what) -> int:
    d = np.abs(np.asarray(direction, float))
    c = int(np.argmax(d))
    if d[c] < 0.7 * np.linalg.norm(d):
        raise EffectError(f"standard_effects: {what} direction {tuple(direction)} is not near a coordinate axis "
                          "(a scalar spring acts along one component)")
    return c + 1


def _cluster(fe, card, pid):
    """Elements of property ``pid`` within CLUSTER_RADIUS_ELEMENTS element sizes of its element nearest its centroid.

    Returns (element ids, centre of the cluster's middle element (m), element size (m)); the model is SI.
    """
    t = fe.elements[card]
    same = np.asarray(t.fields["pid"]) == pid
    nodes = np.asarray(t.fields["nodes"])[same]
    xyz = fe.xyz[fe.grid_index(nodes.ravel()).reshape(nodes.shape)]
    centre = xyz.mean(axis=1)
    h = float(np.median(np.linalg.norm(xyz[:, 1] - xyz[:, 0], axis=1)))
    k = int(np.argmin(np.linalg.norm(centre - centre.mean(axis=0), axis=1)))
    near = np.linalg.norm(centre - centre[k], axis=1) <= CLUSTER_RADIUS_ELEMENTS * h * (1 + 1e-9)
    return tuple(int(e) for e in t.ids[same][near]), centre[k], h


def standard_effects(pm, sensors, drives, *, gap=None, band_hz=None, n_modes: int = 10, shift: float = 0.01,
                     p=None) -> dict:
    """One physically plausible undeclared effect of each family for a deck (docs/synth.md).

    Springs and masses are placed by the deck's own geometry and test set-up
    and sized by one rule: the largest first-order relative shift of the
    reference modes (the elastic modes in ``band_hz``, else the first
    ``n_modes``) is ``shift`` (1 %: five half-power bandwidths at 0.1 %
    damping). The element cluster has the fixed factor 0.7.

    ==================  ============================================================================
    family              effect
    ==================  ============================================================================
    sensor_mass         one common mass on every sensor grid (accelerometer, block, cable)
    shaker_attachment   a mass at the first drive grid (force gauge, armature share) and a soft
                        stinger/armature spring to ground along the drive direction (two Effects;
                        the spring sized for a quarter of ``shift``)
    contact_spring      springs along the gap between every facing pair of ``gap`` (a closed gap;
                        sized for ten times ``shift``); only when ``gap`` is given
    ground_spring       a suspension spring to ground in z at the structural grid farthest from the
                        grid centroid
    element_cluster     stiffness factor 0.7 on the elements of the largest property group (most
                        elements) within 2 element sizes of its element nearest its centroid
    lumped_mass         an unmodelled mass at the structural grid farthest from every sensor and drive
    ==================  ============================================================================

    Parameters
    ----------
    pm : femodel.ParametricModel
        The calibration model (the deck).
    sensors, drives : sequences of frfcal.synth.SynthChannel
    gap : sequence of (int, int), optional
        Facing grid pairs of an air gap (``SubframeExample.gap_pairs``,
        ``FrameExample.gap_pairs``).
    band_hz : (float, float), optional
        Band whose elastic modes are the reference; default the first ``n_modes``.
    n_modes : int
    shift : float
        Largest first-order relative frequency shift of each spring or mass effect.
    p : (n_params,) float, optional
        Deck parameters of the reference modes (default 0: the deck as it is).

    Returns
    -------
    dict
        family -> tuple of :class:`Effect` (one each; two for shaker_attachment),
        all on every article (``articles=None``; use :func:`dataclasses.replace`
        to restrict). Each term's ``scale`` is its value, so p = 1 is the effect.
    """
    from femodel._terms import AddedMass, AddedSpring, ElementFactor

    sensors, drives = tuple(sensors), tuple(drives)
    if not sensors or not drives:
        raise EffectError("standard_effects: at least one sensor and one drive are needed")
    if not 0 < shift < 0.2:
        raise EffectError(f"standard_effects: shift must be in (0, 0.2), got {shift!r}")
    p = np.zeros(pm.n_params) if p is None else np.asarray(p, float)
    fe = pm.assembly.model
    ref = _reference_modes(pm, p, band_hz, n_modes)
    out = {}

    grids = tuple(dict.fromkeys(int(s.grid) for s in sensors))
    term, m = _scaled(pm, AddedMass, "sensor_mass", grids, ref, shift,
                      f"undeclared sensor mass {{value:.4g}} kg on each of the {len(grids)} sensor grids")
    out["sensor_mass"] = (Effect(term, m, family="sensor_mass"),)

    d = drives[0]
    c = _component(d.direction, f"drive {d.name!r}")
    tm, m = _scaled(pm, AddedMass, "shaker_mass", (int(d.grid),), ref, shift,
                    f"shaker attachment mass {{value:.4g}} kg at drive grid {d.grid} ({d.name})")
    ts, k = _scaled(pm, AddedSpring, "stinger_spring", ((int(d.grid), c, 0, 0),), ref, STINGER_SHIFTS * shift,
                    f"stinger/shaker axial spring {{value:.4g}} N/m to ground at drive grid {d.grid}, component {c}")
    out["shaker_attachment"] = (Effect(tm, m, family="shaker_attachment"),
                                Effect(ts, k, family="shaker_attachment"))

    if gap:
        pairs = tuple((int(a), int(b)) for a, b in gap)
        xa = fe.xyz[fe.grid_index([a for a, _ in pairs])]
        xb = fe.xyz[fe.grid_index([b for _, b in pairs])]
        comps = {int(np.argmax(np.abs(v))) + 1 for v in xb - xa}
        if len(comps) != 1:
            raise EffectError(f"standard_effects: gap pairs {pairs} do not face each other along one axis")
        c = comps.pop()
        gap_mm = float(np.median(np.linalg.norm(xb - xa, axis=1))) * 1e3
        term, k = _scaled(pm, AddedSpring, "contact_spring", tuple((a, c, b, c) for a, b in pairs), ref,
                          CONTACT_SHIFTS * shift,
                          f"closed {gap_mm:.3g} mm gap: contact spring {{value:.4g}} N/m along component {c} "
                          f"between each of {len(pairs)} facing grid pairs")
        out["contact_spring"] = (Effect(term, k, family="contact_spring"),)

    struct = _structural_grids(fe)
    xyz = fe.xyz[fe.grid_index(struct)]
    g = int(struct[np.argmax(np.linalg.norm(xyz - xyz.mean(axis=0), axis=1))])
    term, k = _scaled(pm, AddedSpring, "ground_spring", ((g, 3, 0, 0),), ref, shift,
                      f"suspension spring {{value:.4g}} N/m to ground in z at grid {g}")
    out["ground_spring"] = (Effect(term, k, family="ground_spring"),)

    biggest = {}
    for card, t in fe.elements.items():
        if card in _FACTOR_CARDS:
            for pid in np.asarray(t.fields["pid"]).tolist():
                biggest[(card, pid)] = biggest.get((card, pid), 0) + 1
    card, pid = max(biggest, key=biggest.get)
    els, centre, h = _cluster(fe, card, pid)
    where = ", ".join(f"{x * 1e3:.0f}" for x in centre)
    term = ElementFactor("cluster_K", els, "K", description=(
        f"stiffness x {CLUSTER_FACTOR} on {len(els)} {card} of property {pid} within "
        f"{CLUSTER_RADIUS_ELEMENTS:g} element sizes ({h * 1e3:.3g} mm) of ({where}) mm"))
    out["element_cluster"] = (Effect(term, CLUSTER_FACTOR, family="element_cluster"),)

    near = fe.xyz[fe.grid_index(list({int(ch.grid) for ch in sensors + drives}))]
    dist = np.min(np.linalg.norm(xyz[:, None, :] - near[None], axis=2), axis=1)
    g = int(struct[np.argmax(dist)])
    term, m = _scaled(pm, AddedMass, "lumped_mass", (g,), ref, shift,
                      f"unmodelled lumped mass {{value:.4g}} kg at grid {g}, "
                      f"{dist.max() * 1e3:.0f} mm from the nearest sensor or drive")
    out["lumped_mass"] = (Effect(term, m, family="lumped_mass"),)
    return out


@dataclass(frozen=True)
class ModeShifts:
    """Reference modes of a deck and the matching modes with effects added (exact eigensolutions).

    Attributes
    ----------
    f_ref_hz : (n,) float
        Reference elastic modes of the deck (in the band, or the first n).
    f_hz : (n,) float
        Frequency of the mode of the extended model that best matches each
        reference mode (largest MAC on the mass-weighted a-set shapes).
    mac : (n,) float
        That MAC.
    """

    f_ref_hz: np.ndarray
    f_hz: np.ndarray
    mac: np.ndarray

    @property
    def relative(self) -> np.ndarray:
        """df/f of each reference mode."""
        return self.f_hz / self.f_ref_hz - 1.0

    def bandwidths(self, zeta: float = 1e-3) -> np.ndarray:
        """|df| in half-power bandwidths 2 zeta f of the reference modes."""
        return np.abs(self.f_hz - self.f_ref_hz) / (2.0 * zeta * self.f_ref_hz)


def mode_shifts(pm, effects, *, band_hz=None, n_modes: int = 10, p=None) -> ModeShifts:
    """Exact frequency shifts of the deck's reference modes when ``effects`` are added.

    Parameters
    ----------
    pm : femodel.ParametricModel
    effects : sequence of Effect (or tuples of them)
    band_hz, n_modes, p
        The reference modes, as :func:`standard_effects`.

    Returns
    -------
    ModeShifts
    """
    effects = tuple(e for item in effects for e in ((item,) if isinstance(item, Effect) else tuple(item)))
    p = np.zeros(pm.n_params) if p is None else np.asarray(p, float)
    ref = _reference_modes(pm, p, band_hz, n_modes)
    from frfcal.synth import modes_up_to

    pe = pm.with_terms([e.term for e in effects])
    q = np.concatenate([p, [e.p for e in effects]])
    # every mode of the extended model up to 1.5 x the top reference mode: the partners shift by less
    modes, _ = modes_up_to(pe.stiffness(q), pe.mass(q), 1.5 * float(ref.f_hz.max()), dofs=pe.aset)
    M = pm.mass(p)
    phi = modes.shapes
    mac = (ref.phi.T @ (M @ phi)) ** 2 / np.outer(np.ones(ref.f_hz.size), np.einsum("ik,ik->k", phi, M @ phi))
    best = np.argmax(mac, axis=1)
    return ModeShifts(ref.f_hz, modes.frequencies_hz[best], mac[np.arange(best.size), best])
