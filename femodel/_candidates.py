"""Candidate effects: new term families generated from a deck and the test set-up.

After a calibration some deviation remains; the diagnosis looks for the
effect the model lacks among *candidates*. Each candidate is one added term
(:class:`~femodel.AddedSpring`, :class:`~femodel.AddedMass` or
:class:`~femodel.ElementFactor`) with p = 0 the deck as it is, plus where it
acts (grids, parts, centre, local element size) and a physical description.

Families (registry :data:`CANDIDATE_FAMILIES`, extended with
:func:`register_family`):

========================== =========================================================
family                     generates
========================== =========================================================
``sensor_mass``            one common mass on all sensor grids (AddedMass)
``sensor_masses``          one mass per sensor grid that is not a drive grid (AddedMass)
``shaker_attachment_mass`` a mass at each drive grid (force sensor, stinger end)
``stinger_spring``         a spring to ground at each drive grid along the drive axis
``contact_spring``         springs between facing grids of different parts that no
                           element joins, one candidate per patch of pairs
``ground_spring``          a spring to ground at spread grids, per direction
``lumped_mass``            an unmodelled mass at spread grids and at grids spread
                           away from the sensors and drives (not the sensor grids)
``element_cluster``        stiffness (optionally mass) factor of a sub-region of a
                           property group: cubes of a few element sizes and
                           element-centred balls of 1 and 2 element sizes
========================== =========================================================

Geometry is SI inside (as :class:`~femodel.FEModel`); a candidate's
``center`` and ``size`` are in the deck's length unit. docs/diagnosis.md
("Candidate families") describes the rules, scales and options.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np
import scipy.sparse as sp

from femodel._model import FEModel, ModelError
from femodel._params import ParameterError
from femodel._terms import AddedMass, AddedSpring, ElementFactor

#: Element cards whose property is a "part" (property group) of the structure.
_LINE_CARDS = ("CBAR", "CBEAM", "CROD", "CONROD", "CTUBE")
_SHELL_CARDS = ("CQUAD4", "CTRIA3")
_SOLID_CARDS = ("CTETRA", "CPYRAM", "CPENTA", "CHEXA")
_STRUCTURAL_CARDS = _LINE_CARDS + _SHELL_CARDS + _SOLID_CARDS
#: Grids of the spread sample of the point families on a model too large to have them at every grid
#: (``CandidateOptions.spread_grids`` None).
SPREAD_GRIDS = 40
#: Corner-node count and the factor taking the mean corner-to-centroid distance of a regular solid to its edge.
_SOLID_CORNERS = {"CTETRA": (4, 1.633), "CPYRAM": (5, 1.3), "CPENTA": (6, 1.309), "CHEXA": (8, 1.1547)}
#: Properties an :class:`ElementFactor` can scale and write back (with MAT1 materials).
_FACTOR_PROPERTIES = ("PSHELL", "PBAR", "PBARL", "PBEAM", "PBEAML", "PROD", "PSOLID")
_MID_FIELDS = ("mid", "mid1", "mid2", "mid3")


# ----------------------------------------------------------------------------
# options and results
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class CandidateOptions:
    """How candidates are generated (validated; units in each field).

    Attributes
    ----------
    contact_factor : float
        Contact distance in local element sizes: facing grids closer than
        ``contact_factor`` times the local element size (and than
        ``contact_max_gap_m``) are candidate contact pairs. Default 1.5.
    contact_max_gap_m : float
        Absolute cap on the contact distance, m (default 0.01: an air gap
        of a few mm that closes, whatever the mesh size).
    contact_hops : int
        Pairs whose grids are joined through at most this many elements
        are already connected and skipped: 1 = an element holds both grids,
        2 (default) = also pairs sharing a neighbouring grid (the first rows
        beside a welded junction).
    contact_axis_deg : float
        A gap within this angle (deg) of a displacement axis gets a spring
        on that component only; otherwise on x, y and z. Default 20.
    contact_patch : float
        Largest extent of one contact patch in local element sizes (pairs
        linked within two element sizes form a patch, cut into cells of
        this edge). Default 4.
    contact_fraction : float
        p = 1 of a contact spring is this fraction of the smaller K-diagonal
        entry of the two grids at the sprung component (median over the
        patch). Default 0.1.
    cluster_size : float
        Edge of an element cluster in element sizes of its property group
        (voxel binning of element centroids). Default 3.
    cluster_radii : tuple of float
        Radii, in element sizes of the property group, of the element-centred
        clusters offered besides the cube tiling: around a seed element, the
        elements of its group whose centres lie within radius x the group's
        median element size of the seed's centre. They overlap, so a
        stiffness change of a region of a few element sizes anywhere in the
        group is matched by one candidate, not split over two or three cubes.
        Default (1.0, 2.0) (on a line of elements: 3 and 5 elements); ()
        for the cube tiling alone.
    cluster_seeds : int
        At most this many seed elements per property group and radius
        (farthest-point sampling of the element centres when the group has
        more). Default 60.
    cluster_kinds : tuple of {"K", "M"}
        Which factors the clusters get. Default ("K",): a local stiffness
        change (weld, joint, damage, thickness) is the common unmodelled
        effect; a local mass change is covered by ``lumped_mass``, and
        doubling the clusters with nearly collinear mass twins would halve
        the screening's discrimination.
    factor_bounds : (float, float)
        Bounds on p of an element-cluster factor 1 + p (-1 < lower < 0 <
        upper). Default (-0.9, 3.0).
    ground_components : tuple of int
        Translational components (1..3, in each grid's displacement system)
        of the ground springs. Default (1, 2, 3).
    spread_grids : int or None
        Number of grids, spread evenly over the structure (farthest-point
        sampling: the extremes come first), that get ground springs and
        lumped masses. Default None: every eligible grid when the family's
        candidates at every grid number at most ``max_per_family`` (a small
        model: a mass or spring between sampled grids is then a candidate
        itself, not left to the zoom), else :data:`SPREAD_GRIDS` (40).
    f_ref_hz : float
        p = 1 of a ground or stinger spring is total mass * (2 pi f_ref)^2,
        N/m: the whole structure on that spring alone would bounce at
        f_ref. Default 10 Hz.
    lumped_mass_fraction : float
        p = 1 of a lumped mass as a fraction of the total mass. Default 0.01.
    sensor_mass_fraction : float
        p = 1 of a sensor mass (per grid) as a fraction of the total mass.
        Default 0.001.
    attachment_mass_fraction : float
        p = 1 of a shaker attachment mass as a fraction of the total mass.
        Default 0.002.
    upper : float
        Upper bound on p of added springs and masses (lower bound 0).
        Default 100.
    max_per_family : int
        At most this many candidates per family; more are subsampled
        evenly in space (farthest-point sampling of their centres,
        deterministic). Default 500.
    zoom_rounds : int
        Rounds of the zoom of the point families (:data:`POINT_FAMILIES`:
        ``lumped_mass``, ``ground_spring``) after the linear screening of the
        spread sample: the same family's candidates at the untested grids
        nearer the best candidate than any tested grid
        (:func:`zoom_candidates`), screened linearly, repeated around the new
        best. 0: no zoom. Default 3.
    zoom_top : int
        Best candidates of each point family zoomed per round. Default 3.
    zoom_grids : int
        At most this many new grids per zoomed candidate and round (spread
        over its neighbourhood). Default 12.
    """

    contact_factor: float = 1.5
    contact_max_gap_m: float = 0.01
    contact_hops: int = 2
    contact_axis_deg: float = 20.0
    contact_patch: float = 4.0
    contact_fraction: float = 0.1
    cluster_size: float = 3.0
    cluster_radii: tuple = (1.0, 2.0)
    cluster_seeds: int = 60
    cluster_kinds: tuple = ("K",)
    factor_bounds: tuple = (-0.9, 3.0)
    ground_components: tuple = (1, 2, 3)
    spread_grids: int | None = None
    f_ref_hz: float = 10.0
    lumped_mass_fraction: float = 0.01
    sensor_mass_fraction: float = 0.001
    attachment_mass_fraction: float = 0.002
    upper: float = 100.0
    max_per_family: int = 500
    zoom_rounds: int = 3
    zoom_top: int = 3
    zoom_grids: int = 12

    def __post_init__(self) -> None:
        def bad(name, why):
            raise ParameterError(f"CandidateOptions.{name}: {why}, got {getattr(self, name)!r}")

        for name in ("contact_factor", "contact_max_gap_m", "contact_patch", "contact_fraction", "cluster_size",
                     "f_ref_hz", "lumped_mass_fraction", "sensor_mass_fraction", "attachment_mass_fraction",
                     "upper"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                bad(name, "must be a positive finite number")
        if not 0.0 < float(self.contact_axis_deg) < 90.0:
            bad("contact_axis_deg", "must be in (0, 90) degrees")
        for name, lo in (("contact_hops", 1), ("spread_grids", 1), ("max_per_family", 1), ("cluster_seeds", 1),
                         ("zoom_rounds", 0), ("zoom_top", 1), ("zoom_grids", 1)):
            v = getattr(self, name)
            if v is None and name == "spread_grids":
                continue
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                bad(name, f"must be an integer >= {lo}")
        kinds = tuple(self.cluster_kinds)
        if not kinds or not set(kinds) <= {"K", "M"} or len(set(kinds)) != len(kinds):
            bad("cluster_kinds", "must be a non-empty subset of ('K', 'M')")
        object.__setattr__(self, "cluster_kinds", kinds)
        radii = tuple(self.cluster_radii)
        if not all(not isinstance(r, bool) and isinstance(r, (int, float)) and math.isfinite(r) and r > 0
                   for r in radii) or len(set(radii)) != len(radii):
            bad("cluster_radii", "must be distinct positive finite numbers (element sizes)")
        object.__setattr__(self, "cluster_radii", tuple(float(r) for r in radii))
        fb = tuple(self.factor_bounds)
        if len(fb) != 2 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in fb) \
                or not -1.0 < fb[0] < 0.0 < fb[1]:
            bad("factor_bounds", "must be (lower, upper) with -1 < lower < 0 < upper")
        object.__setattr__(self, "factor_bounds", (float(fb[0]), float(fb[1])))
        comps = tuple(self.ground_components)
        if not comps or not all(isinstance(c, (int, np.integer)) and c in (1, 2, 3) for c in comps) \
                or len(set(comps)) != len(comps):
            bad("ground_components", "must be distinct translational components among 1, 2, 3")
        object.__setattr__(self, "ground_components", tuple(int(c) for c in comps))


@dataclass(frozen=True)
class Candidate:
    """One candidate effect: an added term and where it acts.

    Attributes
    ----------
    family : str
        Registry name (:data:`CANDIDATE_FAMILIES`).
    term : AddedSpring, AddedMass or ElementFactor
        The term (unique name; p = 0 is the deck as it is; ``scale`` so that
        a plausible magnitude is p ~ 1).
    grids : tuple of int
        Grid ids where it acts.
    parts : tuple of str
        Property groups involved, e.g. "PSHELL 12", "PBAR 3" (a grid's parts
        are the properties of its structural elements).
    center : (float, float, float)
        Centroid in basic coordinates, deck length unit.
    size : float
        Local element size, deck length unit ("within two element sizes").
    description : str
        Physical description.
    """

    family: str
    term: AddedSpring | AddedMass | ElementFactor
    grids: tuple
    parts: tuple
    center: tuple
    size: float
    description: str

    def __post_init__(self) -> None:
        what = f"Candidate of family {self.family!r}"
        if not isinstance(self.term, (AddedSpring, AddedMass, ElementFactor)):
            raise ParameterError(f"{what}: term must be an AddedSpring, AddedMass or ElementFactor, "
                                 f"got {type(self.term).__name__}")
        center = tuple(float(x) for x in self.center)
        if len(center) != 3 or not all(math.isfinite(x) for x in center):
            raise ParameterError(f"{what} {self.term.name!r}: center must be 3 finite coordinates, got {self.center!r}")
        if not (math.isfinite(float(self.size)) and float(self.size) >= 0.0):
            raise ParameterError(f"{what} {self.term.name!r}: size must be finite and >= 0, got {self.size!r}")
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "size", float(self.size))
        object.__setattr__(self, "grids", tuple(int(g) for g in self.grids))
        object.__setattr__(self, "parts", tuple(str(q) for q in self.parts))

    @property
    def name(self) -> str:
        return self.term.name

    def to_dict(self) -> dict:
        """JSON-able dict (the term as family, name, scale, unit, bounds and dofs | grids | elements)."""
        t = self.term
        term = {"family": type(t).__name__, "name": t.name, "unit": t.unit, "lower": float(t.lower),
                "upper": float(t.upper)}
        if isinstance(t, AddedSpring):
            term.update(scale=float(t.scale), dofs=[list(d) for d in t.dofs])
        elif isinstance(t, AddedMass):
            term.update(scale=float(t.scale), grids=list(t.grids))
        else:
            term.update(scale=1.0, kind=t.kind, elements=list(t.elements))
        return {"family": self.family, "name": t.name, "grids": list(self.grids), "parts": list(self.parts),
                "center": [float(x) for x in self.center], "size": float(self.size),
                "description": self.description, "term": term}


@dataclass(frozen=True, eq=False)
class CandidateContext:
    """What a family generator sees: the model's geometry, topology, scales and the test set-up.

    Built once by :func:`generate_candidates`; a user family reads it and
    returns :class:`Candidate` objects (make them with :meth:`candidate`).

    Attributes
    ----------
    model : FEModel
        The deck (SI arrays, basic coordinates).
    assembly : Assembly
        Its nominal assembly (g-set terms, constraint transformation T).
    options : CandidateOptions
    sensors : tuple of int
        Measured grid ids (distinct, in the given order).
    drives : tuple of (int, (3,) float)
        Drive grid and unit direction in basic.
    length_m : float
        Metres per deck length unit.
    xyz : (n_grid, 3) float
        Grid positions, basic, m (rows as ``model.grid_ids``).
    element_ids : (n_el,) int
        Every element with grids (all element tables, CONM2 and springs included).
    element_cards : (n_el,) str
        Their cards ("CQUAD4", "CBAR", "CELAS2", ...).
    element_parts : (n_el,) str
        Property label ("PSHELL 12", "PBARL 3", "CONROD") of structural
        elements (bars, beams, rods, shells, solids); "" for the others.
    element_grids : tuple of tuple of int
        Grid ids of each element (ground entries dropped).
    element_centers : (n_el, 3) float
        Centroid of the corner grids, basic, m.
    element_sizes : (n_el,) float
        Length (lines), mean edge (shells), edge of the regular solid with
        the same corner-to-centroid distance (solids), m; 0 for the others.
    factorable : (n_el,) bool
        Elements an :class:`ElementFactor` can scale (structural, property in
        PSHELL/PBAR/PBARL/PROD/PSOLID with MAT1 materials, not already in an
        element-subset term of the parametric model).
    grid_parts : tuple of tuple of str
        Parts of each grid (its structural elements' property labels).
    grid_sizes : (n_grid,) float
        Mean size of each grid's structural elements, m (the median of all
        elements for a grid without any).
    free : (n_grid, 6) bool
        DOF not removed by single-point constraints.
    stiffness_diagonal : (n_grid, 6) float
        Diagonal of the nominal g-set stiffness (N/m, N m/rad; components in
        each grid's displacement system).
    total_mass : float
        Rigid-body mass of the nominal model, kg.
    used_names : frozenset of str
        Parameter names of the parametric model (candidates must not reuse them).
    cd_axes : (n_grid, 3, 3) float or None
        Columns: each grid's displacement axes in basic; None when every
        grid displaces in basic.
    element_incidence : csr_matrix (n_el, n_grid)
        1 where an element holds a grid (rows as ``element_ids``).
    """

    model: FEModel
    assembly: object
    options: CandidateOptions
    sensors: tuple
    drives: tuple
    length_m: float
    xyz: np.ndarray
    element_ids: np.ndarray
    element_cards: np.ndarray
    element_parts: np.ndarray
    element_grids: tuple
    element_centers: np.ndarray
    element_sizes: np.ndarray
    factorable: np.ndarray
    grid_parts: tuple
    grid_sizes: np.ndarray
    free: np.ndarray
    stiffness_diagonal: np.ndarray
    total_mass: float
    used_names: frozenset = field(default_factory=frozenset)
    cd_axes: np.ndarray | None = None
    element_incidence: sp.csr_matrix = field(default=None, repr=False)

    @property
    def grid_ids(self) -> np.ndarray:
        return self.model.grid_ids

    @property
    def connectivity(self) -> dict:
        """{element id: grid ids}."""
        return dict(zip(self.element_ids.tolist(), self.element_grids))

    def grid_index(self, grids) -> np.ndarray:
        """Rows of grid ids (ParameterError naming missing ids)."""
        try:
            return self.model.grid_index(grids, what="candidate grid")
        except ModelError as exc:
            raise ParameterError(str(exc)) from None

    def grid_label(self, grid: int) -> str:
        """"grid 40211 (PSHELL 12)"."""
        parts = self.grid_parts[int(self.grid_index([grid])[0])]
        return f"grid {int(grid)} ({', '.join(parts)})" if parts else f"grid {int(grid)}"

    def deck_length(self, x_m):
        """Metres to the deck's length unit."""
        return np.asarray(x_m, dtype=float) / self.length_m

    def spread(self, points, k: int, away_from=None) -> np.ndarray:
        """Indices of ``k`` of ``points`` (n, 3) spread evenly (farthest-point sampling, deterministic).

        Starts at the point farthest from the centroid, then repeatedly takes
        the point farthest from those taken (ties: the lowest index), so the
        extremes of the structure come first. With ``away_from`` ((m, 3)
        points, m >= 1) those count as taken already: the first index is the
        point farthest from all of them, then the regions farthest from them
        and from each other. Returns all indices when n <= k, else k sorted
        indices.
        """
        pts = np.asarray(points, dtype=float)
        n = pts.shape[0]
        if n <= k:
            return np.arange(n)
        if away_from is not None and len(away_from):
            ref = np.asarray(away_from, dtype=float).reshape(-1, 3)
            dist = np.min(np.linalg.norm(pts[:, None, :] - ref[None], axis=2), axis=1)
            taken = []
            k += 1  # the loop below takes the first point too
        else:
            d = np.linalg.norm(pts - pts.mean(axis=0), axis=1)
            taken = [int(np.argmax(d))]
            dist = np.linalg.norm(pts - pts[taken[0]], axis=1)
            dist[taken[0]] = -1.0
        # a taken point is marked -1 so that it is never taken again: with coincident points (grids of two
        # parts at one place, the x/y/z candidates of one grid) every distance left can be 0, and argmax
        # would return an index already taken
        for _ in range(k - 1):
            i = int(np.argmax(dist))
            taken.append(i)
            np.minimum(dist, np.linalg.norm(pts - pts[i], axis=1), out=dist)
            dist[i] = -1.0
        return np.sort(np.array(taken))

    def candidate(self, family: str, term, grids, description: str, *, parts=None, points=None,
                  size=None) -> Candidate:
        """A :class:`Candidate` with location filled in from the grids.

        ``parts`` default: the union of the grids' parts (sorted); ``points``
        (m, basic) default: the grids' positions (centre = their mean);
        ``size`` (m) default: the mean local element size of the grids.
        """
        grids = tuple(int(g) for g in grids)
        idx = self.grid_index(grids)
        if parts is None:
            parts = sorted({p for i in idx for p in self.grid_parts[i]})
        pts = self.xyz[idx] if points is None else np.atleast_2d(np.asarray(points, dtype=float))
        s = float(np.mean(self.grid_sizes[idx])) if size is None else float(size)
        center = tuple(float(x) for x in self.deck_length(pts.mean(axis=0)))
        return Candidate(family, term, grids, tuple(parts), center, float(self.deck_length(s)), description)

    def mm(self, x_m: float) -> str:
        return f"{1000.0 * float(x_m):.3g} mm"


# ----------------------------------------------------------------------------
# context
# ----------------------------------------------------------------------------


def _property_labels(fe: FEModel) -> dict:
    """{pid: label} over every property table ("PSHELL 12"; PBAR rows carry their source card)."""
    labels = {}
    for name, tab in fe.properties.items():
        cards = tab.fields.get("card")
        for r, pid in enumerate(tab.ids.tolist()):
            labels[int(pid)] = f"{cards[r] if cards is not None else tab.card} {int(pid)}"
    return labels


def _factorable_pids(fe: FEModel) -> set:
    mat1 = set(fe.materials["MAT1"].ids.tolist()) if "MAT1" in fe.materials else set()
    ok = set()
    for name, tab in fe.properties.items():
        if tab.card not in _FACTOR_PROPERTIES:
            continue
        cards = tab.fields.get("card")
        for r, pid in enumerate(tab.ids.tolist()):
            if cards is not None and str(cards[r]) not in _FACTOR_PROPERTIES:
                continue
            mids = [int(tab.fields[f][r]) for f in _MID_FIELDS if f in tab.fields and int(tab.fields[f][r]) > 0]
            if mids and all(m in mat1 for m in mids):
                ok.add(int(pid))
    return ok


def _element_geometry(card: str, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroids (n, 3) and sizes (n,) of elements from their corner positions (n, nc, 3), m."""
    center = corners.mean(axis=1)
    nc = corners.shape[1]
    if card in _LINE_CARDS:
        size = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)
    elif card in _SHELL_CARDS:
        size = np.mean(np.linalg.norm(np.roll(corners, -1, axis=1) - corners, axis=2), axis=1)
    elif card in _SOLID_CORNERS:
        size = _SOLID_CORNERS[card][1] * np.mean(np.linalg.norm(corners - center[:, None], axis=2), axis=1)
    else:
        size = np.zeros(corners.shape[0]) if nc else np.zeros(0)
    return center, size


def candidate_context(model, *, sensors=(), drives=(), options: CandidateOptions | None = None) -> CandidateContext:
    """Build the :class:`CandidateContext` of a model and a test set-up.

    Parameters
    ----------
    model : FEModel or ParametricModel
        A model from :func:`femodel.read_bdf` (assembled here) or a
        parametric model (its nominal assembly is reused; elements already
        in one of its element-subset terms are not factorable again).
    sensors : iterable of int
        Measured grid ids (repeats, e.g. a triaxial sensor, are merged).
    drives : iterable of (int, (3,) float)
        Drive grid ids and force directions in basic.
    options : CandidateOptions, optional

    Returns
    -------
    CandidateContext

    Raises
    ------
    ParameterError
        An unknown sensor or drive grid, a malformed drive direction, or a
        model that is neither an FEModel nor a ParametricModel.
    """
    from femodel._assembly import assemble
    from femodel._pattern import _selection_map
    from femodel._sensors import mass_properties
    from femodel._units import unit_system

    options = CandidateOptions() if options is None else options
    if not isinstance(options, CandidateOptions):
        raise ParameterError(f"options must be a CandidateOptions, got {type(options).__name__}")
    used = frozenset()
    taken_elements: set = set()
    if isinstance(model, FEModel):
        fe = model
        asm = assemble(fe)
    elif hasattr(model, "assembly") and hasattr(model, "with_terms"):
        asm = model.assembly
        fe = asm.model
        used = frozenset(model.names)
        for t in model.terms:
            if isinstance(t, ElementFactor):
                taken_elements.update(t.elements)
    else:
        raise ParameterError(f"generate_candidates: model must be an FEModel or a ParametricModel, "
                             f"got {type(model).__name__}")
    where = f"{fe.path}: " if fe.path else ""
    sensors = tuple(dict.fromkeys(int(g) for g in sensors))
    try:
        if sensors:
            fe.grid_index(sensors, what="sensor grid")
    except ModelError as exc:
        raise ParameterError(str(exc)) from None
    drv = []
    for item in drives:
        try:
            g, d = item
            d = np.asarray(d, dtype=float).reshape(3)
        except (TypeError, ValueError):
            raise ParameterError(f"{where}drives must be (grid, (dx, dy, dz)) pairs, got {item!r}") from None
        n = float(np.linalg.norm(d))
        if not (np.all(np.isfinite(d)) and n > 0):
            raise ParameterError(f"{where}drive at grid {g}: direction {d.tolist()} must be finite and non-zero")
        try:
            fe.grid_index([int(g)], what="drive grid")
        except ModelError as exc:
            raise ParameterError(str(exc)) from None
        drv.append((int(g), tuple(float(x) for x in d / n)))

    labels = _property_labels(fe)
    factor_pids = _factorable_pids(fe)
    n_g = fe.n_grids
    taken = np.fromiter(taken_elements, dtype=np.int64, count=len(taken_elements))
    ids, cards, parts, egrids, centers, sizes, factorable = [], [], [], [], [], [], []
    inc_el, inc_grid = [], []
    offset = 0
    for key, tab in fe.elements.items():
        n = len(tab)
        if n == 0:
            continue
        card = tab.card
        nodes = np.asarray(tab["nodes"], dtype=np.int64).reshape(n, -1)
        held = nodes > 0
        flat = fe.grid_index(nodes[held], what=f"{card} grid")  # row-major: element by element
        local = np.repeat(np.arange(n), held.sum(axis=1))
        inc_el.append(offset + local)
        inc_grid.append(flat)
        nc = _SOLID_CORNERS[card][0] if card in _SOLID_CORNERS else nodes.shape[1]
        if card in _STRUCTURAL_CARDS and np.all(held[:, :nc]):
            corner_rows = fe.grid_index(nodes[:, :nc].ravel(), what=f"{card} grid").reshape(-1, nc)
            c, sz = _element_geometry(card, fe.xyz[corner_rows])
            pids = np.asarray(tab.fields.get("pid", np.full(n, -1)), dtype=np.int64)
            upid, inv = np.unique(pids, return_inverse=True)
            inv = inv.ravel()
            labels_u = [card if card == "CONROD" else labels.get(int(q), f"{card} pid {int(q)}") for q in upid]
            part = np.array(labels_u, dtype=object)[inv]
            fac = np.array([int(q) in factor_pids and card != "CONROD" for q in upid], dtype=bool)[inv]
            fac &= ~np.isin(tab.ids, taken)
        else:
            cnt = held.sum(axis=1)
            c = np.zeros((n, 3))
            np.add.at(c, local, fe.xyz[flat])
            c /= np.maximum(cnt, 1)[:, None]
            sz = np.zeros(n)
            part = np.full(n, "", dtype=object)
            fac = np.zeros(n, dtype=bool)
        ids.append(np.asarray(tab.ids, dtype=np.int64))
        cards.append(np.full(n, card, dtype=object))
        parts.append(part)
        egrids.extend(tuple(g for g in r if g > 0) for r in nodes.tolist())
        centers.append(c)
        sizes.append(sz)
        factorable.append(fac)
        offset += n
    cat = (lambda xs, empty: np.concatenate(xs) if xs else empty)
    element_ids = cat(ids, np.zeros(0, np.int64))
    element_cards = cat(cards, np.zeros(0, object))
    element_parts = cat(parts, np.zeros(0, object))
    element_centers = cat(centers, np.zeros((0, 3)))
    element_sizes = cat(sizes, np.zeros(0))
    factorable_arr = cat(factorable, np.zeros(0, bool))
    inc_el = cat(inc_el, np.zeros(0, np.int64))
    inc_grid = cat(inc_grid, np.zeros(0, np.int64))
    element_incidence = sp.csr_matrix((np.ones(inc_el.size), (inc_el, inc_grid)), shape=(offset, n_g))
    element_incidence.data[:] = 1.0

    # parts and local size per grid, from the structural elements
    structural = element_parts != ""
    grid_parts_sets = [[] for _ in range(n_g)]
    grid_sizes = np.zeros(n_g)
    on = structural[inc_el]
    if np.any(on):
        part_names, part_idx = np.unique(element_parts[structural].astype(str), return_inverse=True)
        pidx = np.full(offset, -1, dtype=np.int64)
        pidx[structural] = part_idx.ravel()
        gr, er = inc_grid[on], inc_el[on]
        for g, q in np.unique(np.column_stack([gr, pidx[er]]), axis=0).tolist():
            grid_parts_sets[g].append(str(part_names[q]))
        cnt = np.bincount(gr, minlength=n_g)
        tot = np.bincount(gr, weights=element_sizes[er], minlength=n_g)
        has = cnt > 0
        grid_sizes[has] = tot[has] / cnt[has]
        grid_sizes[~has] = float(np.median(element_sizes[structural]))
    else:
        positive = element_sizes[element_sizes > 0]
        grid_sizes[:] = float(np.median(positive)) if positive.size else 1.0
    grid_parts = tuple(tuple(sorted(p)) for p in grid_parts_sets)

    amap = _selection_map(asm.T)
    free = (amap != -1).reshape(n_g, 6)
    kdiag = np.asarray(asm.stiffness_g().diagonal(), dtype=float).reshape(n_g, 6)
    try:
        total_mass = float(mass_properties(asm).mass)
    except ModelError as exc:
        raise ParameterError(f"{where}candidates need the structure's mass: {exc}") from None
    return CandidateContext(
        model=fe, assembly=asm, options=options, sensors=sensors, drives=tuple(drv),
        length_m=float(unit_system(fe.units).length_m), xyz=np.asarray(fe.xyz, dtype=float),
        element_ids=element_ids, element_cards=element_cards, element_parts=element_parts,
        element_grids=tuple(egrids), element_centers=element_centers, element_sizes=element_sizes,
        factorable=factorable_arr, grid_parts=grid_parts, grid_sizes=grid_sizes, free=free,
        stiffness_diagonal=kdiag, total_mass=total_mass, used_names=used,
        cd_axes=fe.cd_axes() if np.any(fe.cd != 0) else None, element_incidence=element_incidence)


# ----------------------------------------------------------------------------
# families
# ----------------------------------------------------------------------------


def _slug(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9]", "", label) or "x"


_AXES = "xyz"


def _movable(ctx: CandidateContext, grids) -> tuple:
    """The grids with at least one free translation (a mass on a clamped grid does nothing)."""
    grids = tuple(grids)
    if not grids:
        return ()
    ok = np.any(ctx.free[ctx.grid_index(grids), :3], axis=1)
    return tuple(g for g, k in zip(grids, ok.tolist()) if k)


def sensor_mass_family(ctx: CandidateContext):
    """One common mass on every sensor grid (accelerometers of one type): p = 1 is
    ``sensor_mass_fraction`` of the total mass on each grid. Clamped sensor grids are left out."""
    g = _movable(ctx, ctx.sensors)
    if not g:
        return
    scale = ctx.options.sensor_mass_fraction * ctx.total_mass
    term = AddedMass("sensor_mass", g, scale, 0.0, ctx.options.upper,
                     f"one sensor mass on each of the {len(g)} measured grids")
    yield ctx.candidate("sensor_mass", term, g,
                        f"sensor mass {scale:.3g} kg x p on each of the {len(g)} measured grids "
                        f"({', '.join(str(x) for x in g[:6])}{', ...' if len(g) > 6 else ''})")


def sensor_masses_family(ctx: CandidateContext):
    """One mass per sensor grid (a heavier sensor or cable clamp): p = 1 is
    ``sensor_mass_fraction`` of the total mass. Drive grids are left out: the shaker
    attachment mass there is the same term (one candidate per physical effect)."""
    scale = ctx.options.sensor_mass_fraction * ctx.total_mass
    driven = {g for g, _ in ctx.drives}
    for g in _movable(ctx, [g for g in ctx.sensors if g not in driven]):
        term = AddedMass(f"sensor_mass_g{g}", (g,), scale, 0.0, ctx.options.upper, f"sensor mass at grid {g}")
        yield ctx.candidate("sensor_masses", term, (g,),
                            f"sensor mass {scale:.3g} kg x p at sensor {ctx.grid_label(g)}")


def shaker_attachment_mass_family(ctx: CandidateContext):
    """A mass at each drive grid (force sensor, stinger end, adhesive): p = 1 is
    ``attachment_mass_fraction`` of the total mass."""
    scale = ctx.options.attachment_mass_fraction * ctx.total_mass
    for g in _movable(ctx, dict.fromkeys(g for g, _ in ctx.drives)):
        term = AddedMass(f"shaker_mass_g{g}", (g,), scale, 0.0, ctx.options.upper,
                         f"shaker attachment mass at drive grid {g}")
        yield ctx.candidate("shaker_attachment_mass", term, (g,),
                            f"shaker attachment mass {scale:.3g} kg x p at drive {ctx.grid_label(g)}")


def _ground_scale(ctx: CandidateContext) -> float:
    return ctx.total_mass * (2.0 * np.pi * ctx.options.f_ref_hz) ** 2


def _local_axis(ctx: CandidateContext, row: int, direction) -> tuple[int, float]:
    """Component (1..3, in the grid's displacement system) nearest a basic direction, and |cos| to it."""
    lam = ctx.cd_axes[row] if ctx.cd_axes is not None else np.eye(3)
    local = lam.T @ np.asarray(direction, dtype=float)
    c = int(np.argmax(np.abs(local)))
    return c + 1, float(abs(local[c]) / max(np.linalg.norm(local), 1e-300))


def stinger_spring_family(ctx: CandidateContext):
    """A spring to ground at each drive grid along the drive's dominant axis (stinger and
    shaker suspension): p = 1 is total mass * (2 pi f_ref)^2."""
    scale = _ground_scale(ctx)
    seen = set()
    for g, d in ctx.drives:
        row = int(ctx.grid_index([g])[0])
        c, _ = _local_axis(ctx, row, d)
        if (g, c) in seen or not ctx.free[row, c - 1]:
            continue
        seen.add((g, c))
        term = AddedSpring(f"stinger_g{g}_{_AXES[c - 1]}", ((g, c, 0, 0),), scale, 0.0, ctx.options.upper,
                           f"stinger spring at drive grid {g}, component {c}")
        yield ctx.candidate("stinger_spring", term, (g,),
                            f"stinger/shaker spring to ground {scale:.3g} N/m x p at drive {ctx.grid_label(g)} "
                            f"along {_AXES[c - 1]}")


def _structural_rows(ctx: CandidateContext) -> np.ndarray:
    return np.flatnonzero(np.array([bool(p) for p in ctx.grid_parts]))


def _ground_rows(ctx: CandidateContext, components) -> np.ndarray:
    """Structural grid rows with at least one of ``components`` (1..3) free."""
    rows = _structural_rows(ctx)
    return rows[np.any(ctx.free[rows][:, [c - 1 for c in components]], axis=1)]


def _ground_springs_at(ctx: CandidateContext, row: int, components):
    g = int(ctx.grid_ids[row])
    scale = _ground_scale(ctx)
    for c in components:
        if not ctx.free[row, c - 1]:
            continue
        term = AddedSpring(f"ground_g{g}_{_AXES[c - 1]}", ((g, c, 0, 0),), scale, 0.0, ctx.options.upper,
                           f"spring to ground at grid {g}, component {c}")
        yield ctx.candidate("ground_spring", term, (g,),
                            f"spring to ground {scale:.3g} N/m x p at {ctx.grid_label(g)} along {_AXES[c - 1]}")


def _spread_count(ctx: CandidateContext, n_candidates: int) -> int:
    """Grids a point family spreads its candidates over: ``spread_grids``, or when it is None every grid
    if the family's ``n_candidates`` at every grid fit ``max_per_family``, else :data:`SPREAD_GRIDS`."""
    o = ctx.options
    if o.spread_grids is not None:
        return int(o.spread_grids)
    return max(int(n_candidates), 1) if n_candidates <= o.max_per_family else SPREAD_GRIDS


def ground_spring_family(ctx: CandidateContext):
    """Springs to ground (suspension, fixture) at ``spread_grids`` grids spread over the
    structure (every grid of a small model, see :class:`CandidateOptions`), one candidate per grid
    and free component: p = 1 is total mass * (2 pi f_ref)^2."""
    comps = ctx.options.ground_components
    rows = _ground_rows(ctx, comps)
    n_all = int(np.count_nonzero(ctx.free[rows][:, [c - 1 for c in comps]]))
    rows = rows[ctx.spread(ctx.xyz[rows], _spread_count(ctx, n_all))]
    for r in rows.tolist():
        yield from _ground_springs_at(ctx, r, ctx.options.ground_components)


def _mass_rows(ctx: CandidateContext) -> np.ndarray:
    """Structural grid rows with a free translation that are not sensor grids (``lumped_mass``)."""
    rows = _structural_rows(ctx)
    return rows[np.any(ctx.free[rows, :3], axis=1) & ~np.isin(ctx.grid_ids[rows], list(ctx.sensors))]


def _mass_at(ctx: CandidateContext, row: int) -> Candidate:
    g = int(ctx.grid_ids[row])
    scale = ctx.options.lumped_mass_fraction * ctx.total_mass
    term = AddedMass(f"mass_g{g}", (g,), scale, 0.0, ctx.options.upper, f"lumped mass at grid {g}")
    return ctx.candidate("lumped_mass", term, (g,), f"lumped mass {scale:.3g} kg x p at {ctx.grid_label(g)}")


def lumped_mass_family(ctx: CandidateContext):
    """An unmodelled lumped mass at ``spread_grids`` grids spread over the structure (every grid of a
    small model, see :class:`CandidateOptions`) and, when that is not every grid, at
    ``spread_grids // 4`` grids spread away from the sensors and drives (the grid farthest from
    every one of them first); sensor grids excluded. p = 1 is ``lumped_mass_fraction`` of the
    total mass."""
    rows = _mass_rows(ctx)
    k = _spread_count(ctx, rows.size)
    pick = set(ctx.spread(ctx.xyz[rows], k).tolist())
    measured = list(dict.fromkeys(list(ctx.sensors) + [g for g, _ in ctx.drives]))
    if measured and rows.size > k:
        # and the grids farthest from every sensor and drive, where nothing measured is near a missing mass
        far = ctx.spread(ctx.xyz[rows], max(k // 4, 1),
                         away_from=ctx.xyz[ctx.grid_index(measured)])
        pick |= set(far.tolist())
    rows = rows[np.array(sorted(pick), dtype=int)]
    for r in rows.tolist():
        yield _mass_at(ctx, r)


def element_cluster_family(ctx: CandidateContext):
    """Stiffness (``cluster_kinds``) factors 1 + p of sub-regions of each property group with
    MAT1 material.

    Two kinds of region per group: the cubes of ``cluster_size`` element sizes (element centroids
    binned from the group's lowest corner; disjoint, they cover the group), and element-centred
    balls of ``cluster_radii`` element sizes around up to ``cluster_seeds`` seed elements
    (overlapping: a region of a few element sizes anywhere has a candidate centred on it). An
    element set offered twice (a ball equal to a cube or to a smaller ball) is offered once.
    """
    o = ctx.options
    fac = np.flatnonzero(ctx.factorable)
    parts = ctx.element_parts[fac]

    def offer(part, sel, name, how):
        eids = tuple(int(e) for e in ctx.element_ids[sel])
        listed = ", ".join(str(e) for e in eids[:2]) + (f", ..., {eids[-1]}" if len(eids) > 2 else "")
        grids = sorted({g for e in sel for g in ctx.element_grids[e]})
        size = float(np.median(ctx.element_sizes[sel]))
        c = ctx.deck_length(ctx.element_centers[sel].mean(axis=0))
        for kind in o.cluster_kinds:
            what = "stiffness" if kind == "K" else "mass"
            term = ElementFactor(f"{name}_{kind}", eids, kind, o.factor_bounds[0], o.factor_bounds[1],
                                 f"{what} of {len(eids)} elements of {part}")
            yield ctx.candidate(
                "element_cluster", term, grids,
                f"{what} of {len(eids)} {part} elements ({ctx.element_cards[sel[0]]} {listed}) "
                f"{how} around ({c[0]:.4g}, {c[1]:.4g}, {c[2]:.4g}) (deck length unit), times 1 + p",
                parts=(part,), points=ctx.element_centers[sel], size=size)

    for part in sorted(set(parts.tolist())):
        els = fac[parts == part]
        h = float(np.median(ctx.element_sizes[els]))
        edge = o.cluster_size * h
        pts = ctx.element_centers[els]
        keys = np.floor((pts - pts.min(axis=0)) / edge).astype(np.int64)
        _, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.ravel()
        order = np.argsort(inv, kind="stable")
        cells = np.split(els[order], np.cumsum(np.bincount(inv))[:-1])
        seen = set()
        for n, sel in enumerate(cells):
            seen.add(frozenset(sel.tolist()))
            yield from offer(part, sel, f"cluster_{_slug(part)}_{n + 1}", f"in a cube of {ctx.deck_length(edge):.4g}")
        seeds = ctx.spread(pts, o.cluster_seeds)
        for r in sorted(o.cluster_radii):
            for i in seeds.tolist():
                near = np.linalg.norm(pts - pts[i], axis=1) <= r * h * (1 + 1e-9)
                sel = els[near]
                key = frozenset(sel.tolist())
                if sel.size < 2 or key in seen:
                    continue
                seen.add(key)
                tag = f"{r:g}".replace(".", "p")
                yield from offer(part, np.sort(sel), f"cluster_{_slug(part)}_e{int(ctx.element_ids[els[i]])}_r{tag}",
                                 f"within {ctx.deck_length(r * h):.4g} of element {int(ctx.element_ids[els[i]])}")


def _incidence(ctx: CandidateContext) -> sp.csr_matrix:
    """Grid x connector incidence (elements, RBE2, RBE3, MPC equations), (n_grid, n_conn)."""
    fe = ctx.model
    groups = [(r.gn,) + tuple(r.gm) for r in fe.rbe2]
    groups += [(r.refgrid,) + tuple(g for _, _, gs in r.groups for g in gs) for r in fe.rbe3]
    groups += [tuple(g for g, _, _ in terms) for _, terms in fe.mpc]
    groups = [g for g in groups if g]
    parts = [sp.csr_matrix(ctx.element_incidence.T)]
    if groups:
        rows = fe.grid_index(np.concatenate([np.asarray(g, dtype=np.int64) for g in groups]))
        cols = np.repeat(np.arange(len(groups)), [len(g) for g in groups])
        parts.append(sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(fe.n_grids, len(groups))))
    m = sp.csr_matrix(sp.hstack(parts))
    m.data[:] = 1.0
    return m


def _adjacency(ctx: CandidateContext, inc: sp.csr_matrix) -> sp.csr_matrix:
    """Grid adjacency (n_grid, n_grid): cliques of connectors of up to 27 grids, stars of larger ones."""
    sizes = np.asarray(inc.sum(axis=0)).ravel()
    small = sp.csr_matrix(inc[:, np.flatnonzero(sizes <= 27)])
    adj = small @ small.T
    big = np.flatnonzero(sizes > 27)
    if big.size:
        cols = inc.tocsc()
        r, c = [], []
        for j in big.tolist():
            g = cols.indices[cols.indptr[j]:cols.indptr[j + 1]]
            r += [g[0]] * (g.size - 1) + g[1:].tolist()
            c += g[1:].tolist() + [g[0]] * (g.size - 1)
        adj = adj + sp.csr_matrix((np.ones(len(r)), (r, c)), shape=adj.shape)
    adj = sp.csr_matrix(adj)
    adj.data[:] = 1.0
    return adj


def _part_label(parts) -> str:
    """A grid's part label: its part, or its parts joined by '+' at a junction ("" for none)."""
    return "+".join(sorted(parts))


def contact_pairs(ctx: CandidateContext) -> np.ndarray:
    """Candidate contact pairs: (n_pairs, 2) grid rows (i < j).

    The two grids share no part (a grid of two parts, a junction, may face
    a third part: a sheet at a welded corner), the distance is within
    min(``contact_factor`` x local size, ``contact_max_gap_m``) of either
    grid, each is the other's nearest grid of its part (mutual nearest:
    facing grids, not the diagonals of a fine mesh nor the overhang at the
    edge of an overlap; equal distances all kept), no
    connector (element, RBE2, RBE3, MPC equation) holds both (and no path
    of at most ``contact_hops`` connectors joins them), and both grids'
    displacement systems agree (a scalar spring between equal components
    is then a physical spring).
    """
    from scipy.spatial import cKDTree

    o = ctx.options
    single = np.flatnonzero(np.array([len(p) >= 1 for p in ctx.grid_parts], dtype=bool))
    single = single[np.any(ctx.free[single, :3], axis=1)]
    if single.size < 2:
        return np.zeros((0, 2), np.int64)
    radius = np.minimum(o.contact_max_gap_m, o.contact_factor * ctx.grid_sizes[single])
    tree = cKDTree(ctx.xyz[single])
    found = tree.query_ball_point(ctx.xyz[single], r=radius, return_sorted=False)
    counts = np.fromiter((len(f) for f in found), dtype=np.int64, count=single.size)
    a = np.repeat(np.arange(single.size), counts)
    b = np.fromiter((j for f in found for j in f), dtype=np.int64, count=int(counts.sum()))
    a, b = single[a], single[b]
    part_of = np.full(ctx.grid_ids.size, -1, dtype=np.int64)
    _, inv = np.unique(np.array([_part_label(ctx.grid_parts[i]) for i in single.tolist()], dtype=object),
                       return_inverse=True)
    part_of[single] = inv.ravel()
    keep = part_of[a] != part_of[b]
    # a junction grid (of two parts) may face a third part; grids sharing a part are the same part
    mixed = np.flatnonzero(keep)
    mixed = mixed[[len(ctx.grid_parts[i]) > 1 or len(ctx.grid_parts[j]) > 1
                   for i, j in zip(a[mixed].tolist(), b[mixed].tolist())]]
    keep[mixed] = [not set(ctx.grid_parts[i]) & set(ctx.grid_parts[j])
                   for i, j in zip(a[mixed].tolist(), b[mixed].tolist())]
    # the union over the two grids' radii: a pair found from either side once
    pairs = np.unique(np.column_stack([np.minimum(a[keep], b[keep]), np.maximum(a[keep], b[keep])]), axis=0)
    if pairs.size == 0:
        return np.zeros((0, 2), np.int64)
    d = np.linalg.norm(ctx.xyz[pairs[:, 0]] - ctx.xyz[pairs[:, 1]], axis=1)
    n_parts = int(part_of.max()) + 1

    def nearest(x, y, dist):
        """Where y is (one of) the nearest grids of its part to x, among every (x, y) given."""
        key = x * n_parts + part_of[y]
        order = np.lexsort((dist, key))
        k = key[order]
        first = np.r_[True, k[1:] != k[:-1]]
        best = np.minimum.reduceat(dist[order], np.flatnonzero(first))
        low = np.empty_like(dist)
        low[order] = np.repeat(best, np.diff(np.r_[np.flatnonzero(first), k.size]))
        return dist <= low * (1.0 + 1e-9) + 1e-15

    # a grid's nearest grid of a part is sought among ALL its pairs, whichever end of the (i < j) pair it is:
    # each orientation once (checked over one orientation only, a web grid beyond the edge of a doubler
    # paired with the doubler's edge grid although the edge grid's facing web grid is nearer)
    n_p = len(pairs)
    ok = nearest(np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]], np.r_[d, d])
    pairs, d = pairs[ok[:n_p] & ok[n_p:]], d[ok[:n_p] & ok[n_p:]]
    # a pair behind a nearer one: j lies beyond another grid k that i faces in (about) the same direction
    # (a doubler's edge grid facing the web/skin junction at 2 mm and the skin grid behind it at 7 mm):
    # contact acts on the nearest surface, not through it
    if len(pairs):
        u = (ctx.xyz[pairs[:, 1]] - ctx.xyz[pairs[:, 0]]) / np.maximum(d, 1e-300)[:, None]
        ends = np.r_[pairs[:, 0], pairs[:, 1]]
        dirs = np.vstack([u, -u])
        dd = np.r_[d, d]
        order = np.lexsort((dd, ends))
        cos_tol = math.cos(math.radians(o.contact_axis_deg))
        hidden = np.zeros(2 * len(pairs), bool)
        starts = np.flatnonzero(np.r_[True, ends[order][1:] != ends[order][:-1]])
        for a, b in zip(starts, np.r_[starts[1:], order.size]):
            grp = order[a:b]
            if grp.size < 2:
                continue
            cos = dirs[grp] @ dirs[grp].T  # rows by increasing distance
            near = dd[grp][None, :] < dd[grp][:, None] * (1.0 - 1e-9)
            hidden[grp] = np.any((cos >= cos_tol) & near, axis=1)
        keep = ~(hidden[:len(pairs)] | hidden[len(pairs):])
        pairs, d = pairs[keep], d[keep]
    inc = _incidence(ctx)
    joined = np.asarray(inc[pairs[:, 0]].multiply(inc[pairs[:, 1]]).sum(axis=1)).ravel() > 0
    if o.contact_hops >= 2:
        adj = _adjacency(ctx, inc)
        reach = adj  # grids within hops - 1 connectors of a grid (walks of up to that length)
        step = sp.csr_matrix(adj + sp.identity(adj.shape[0], format="csr"))
        for _ in range(o.contact_hops - 2):
            reach = sp.csr_matrix(reach @ step)
        joined |= np.asarray(adj[pairs[:, 0]].multiply(reach[pairs[:, 1]]).sum(axis=1)).ravel() > 0
    pairs = pairs[~joined]
    if ctx.cd_axes is not None:
        lam = ctx.cd_axes
        same = np.all(np.abs(lam[pairs[:, 0]] - lam[pairs[:, 1]]) < 1e-6, axis=(1, 2))
        pairs = pairs[same]
    return pairs


def contact_spring_family(ctx: CandidateContext):
    """Contact springs between facing grids of different parts that no element joins.

    Pairs (:func:`contact_pairs`) of the same two parts linked within two
    element sizes form a patch, cut into cells of ``contact_patch`` element
    sizes; each patch is one candidate: one common rate on every pair, on
    the gap component when the gap lies within ``contact_axis_deg`` of an
    axis, else on x, y and z. p = 1 is ``contact_fraction`` of the smaller
    K-diagonal entry of the two grids (median over the patch).

    A part pair with several patches gets unions as well: per connected
    stretch cut into several cells, the whole stretch (``..._join<k>``), and,
    when there are several stretches, every pair of the two parts
    (``..._all``). A gap that closes over its whole length is one term with
    one rate (one patch standing in for it is locally stiffer and misplaces
    the stiffness); the screening decides between the whole and a part.
    """
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    o = ctx.options
    pairs = contact_pairs(ctx)
    if pairs.size == 0:
        return
    part_of = [_part_label(p) for p in ctx.grid_parts]
    keyset = {}
    for k, (i, j) in enumerate(pairs.tolist()):
        keyset.setdefault(tuple(sorted((part_of[i], part_of[j]))), []).append(k)
    cos_tol = math.cos(math.radians(o.contact_axis_deg))
    kd = ctx.stiffness_diagonal
    for (pa, pb), members in sorted(keyset.items()):
        pr = pairs[members]
        mid = 0.5 * (ctx.xyz[pr[:, 0]] + ctx.xyz[pr[:, 1]])
        psize = np.maximum(ctx.grid_sizes[pr[:, 0]], ctx.grid_sizes[pr[:, 1]])
        h = float(np.median(psize))
        links = cKDTree(mid).query_pairs(r=2.0 * h, output_type="ndarray")
        graph = sp.csr_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(len(pr), len(pr)))
        _, comp = connected_components(graph, directed=False)
        cell = np.floor((mid - mid.min(axis=0)) / (o.contact_patch * h)).astype(np.int64)
        _, patch = np.unique(np.column_stack([comp, cell]), axis=0, return_inverse=True)
        patch = patch.ravel()
        order = sorted(range(patch.max() + 1), key=lambda q: int(ctx.grid_ids[pr[patch == q]].min()))
        offered = set()
        for n, q in enumerate(order):
            offered.add(frozenset(np.flatnonzero(patch == q).tolist()))
            cand = _contact_candidate(ctx, pr[patch == q], pa, pb, f"contact_{_slug(pa)}_{_slug(pb)}_{n + 1}",
                                      part_of, kd, cos_tol)
            if cand is not None:
                yield cand
        if len(order) < 2:
            continue
        # the cells are tiled from the lowest corner, so a contact region of the patch size that straddles a
        # cell boundary has no candidate of its own (only a cell holding part of it, or the whole stretch):
        # windows (cubes) of the patch size centred on each pair of a stretch cut into several cells, as the element
        # clusters' balls; a window equal to a cell or to another window is offered once
        windows = []
        tree = cKDTree(mid)
        for k in np.unique(comp):
            if np.unique(patch[comp == k]).size < 2:
                continue
            for c in np.flatnonzero(comp == k):
                near = np.array(tree.query_ball_point(mid[c], r=0.5 * o.contact_patch * h * (1 + 1e-9),
                                                      p=np.inf), int)
                key = frozenset(near[comp[near] == k].tolist())
                if len(key) > 1 and key not in offered:
                    offered.add(key)
                    windows.append(np.array(sorted(key)))
        for n, sel in enumerate(windows):
            cand = _contact_candidate(ctx, pr[sel], pa, pb, f"contact_{_slug(pa)}_{_slug(pb)}_w{n + 1}",
                                      part_of, kd, cos_tol)
            if cand is not None:
                yield cand
        # one physical gap cut into several patches: the union of the patches of one connected stretch, and of
        # every patch of the part pair, as one term (one common rate), so the whole gap can be one effect
        unions = []
        for k in np.unique(comp):
            in_comp = np.unique(patch[comp == k])
            if in_comp.size > 1:
                unions.append((f"contact_{_slug(pa)}_{_slug(pb)}_join{len(unions) + 1}", comp == k))
        if np.unique(comp).size > 1 or not unions:
            unions.append((f"contact_{_slug(pa)}_{_slug(pb)}_all", np.ones(len(pr), bool)))
        for name, keep in unions:
            cand = _contact_candidate(ctx, pr[keep], pa, pb, name, part_of, kd, cos_tol)
            if cand is not None:
                yield cand
    yield from _junction_gaps(ctx, pairs, keyset, part_of, kd, cos_tol)


def _junction_gaps(ctx: CandidateContext, pairs, keyset: dict, part_of, kd, cos_tol: float):
    """One physical gap whose facing grids carry different part labels: one candidate per connected stretch.

    A sheet facing a web whose edge row is a junction (web + skin: label
    "PSHELL 2+PSHELL 3") gives two part pairs, (PSHELL 3, PSHELL 21) and
    (PSHELL 2+PSHELL 3, PSHELL 21), for what is one gap; the per-part-pair
    candidates then cover it only in pieces. Part pairs are merged when both
    sides share a part; each connected stretch (midpoints within two element
    sizes) that holds pairs of two or more part pairs is one candidate
    ``contact_<a>_<b>_gap<k>``, a and b the parts the sides share.
    """
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    keys = sorted(keyset)
    sides = [(set(a.split("+")), set(b.split("+"))) for a, b in keys]
    link = np.zeros((len(keys), len(keys)), bool)
    for u, (a1, b1) in enumerate(sides):
        for v, (a2, b2) in enumerate(sides):
            link[u, v] = bool((a1 & a2 and b1 & b2) or (a1 & b2 and b1 & a2))
    n_groups, group = connected_components(sp.csr_matrix(link), directed=False)
    for g in range(n_groups):
        ks = [keys[u] for u in np.flatnonzero(group == g)]
        if len(ks) < 2:
            continue
        a_common, b_common = sides[keys.index(ks[0])]
        for a, b in ks[1:]:
            sa, sb = set(a.split("+")), set(b.split("+"))
            if a_common & sa and b_common & sb:
                a_common, b_common = a_common & sa, b_common & sb
            else:
                a_common, b_common = a_common & sb, b_common & sa
        members = [k for key in ks for k in keyset[key]]
        pr = pairs[members]
        # orient every pair side a -> side b
        on_a = [bool(set(part_of[i].split("+")) & a_common) and not set(part_of[i].split("+")) & b_common
                for i in pr[:, 0].tolist()]
        pr = np.where(np.array(on_a)[:, None], pr, pr[:, ::-1])
        of_key = np.repeat(np.arange(len(ks)), [len(keyset[key]) for key in ks])
        mid = 0.5 * (ctx.xyz[pr[:, 0]] + ctx.xyz[pr[:, 1]])
        h = float(np.median(np.maximum(ctx.grid_sizes[pr[:, 0]], ctx.grid_sizes[pr[:, 1]])))
        links = cKDTree(mid).query_pairs(r=2.0 * h, output_type="ndarray")
        graph = sp.csr_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(len(pr), len(pr)))
        _, comp = connected_components(graph, directed=False)
        pa, pb = "+".join(sorted(a_common)), "+".join(sorted(b_common))
        n = 0
        for k in np.unique(comp):
            if np.unique(of_key[comp == k]).size < 2:
                continue  # within one part pair: its own candidates cover it
            n += 1
            cand = _contact_candidate(ctx, pr[comp == k], pa, pb, f"contact_{_slug(pa)}_{_slug(pb)}_gap{n}",
                                      part_of, kd, cos_tol, oriented=True)
            if cand is not None:
                yield cand


def _contact_candidate(ctx: CandidateContext, sel, pa: str, pb: str, name: str, part_of, kd, cos_tol: float,
                       oriented: bool = False):
    """The contact-spring Candidate of the grid pairs ``sel`` ((k, 2) grid rows) of parts ``pa`` and ``pb``:
    one common rate on every pair (None when no pair has a free, stiff component). ``oriented``: the rows
    are (side a, side b) already."""
    o = ctx.options
    # orient each pair part a -> part b for the description
    if not oriented:
        sel = np.array([(i, j) if part_of[i] == pa else (j, i) for i, j in sel.tolist()])
    gap = ctx.xyz[sel[:, 1]] - ctx.xyz[sel[:, 0]]
    dist = np.linalg.norm(gap, axis=1)
    dofs, rates = [], []
    comps_used = set()
    for (i, j), v, d in zip(sel.tolist(), gap, dist):
        if d > 0:
            c, cos = _local_axis(ctx, i, v / d)
            comps = (c,) if cos >= cos_tol else (1, 2, 3)
        else:
            comps = (1, 2, 3)
        for c in comps:
            if not (ctx.free[i, c - 1] or ctx.free[j, c - 1]):
                continue
            dofs.append((int(ctx.grid_ids[i]), c, int(ctx.grid_ids[j]), c))
            comps_used.add(c)
            kk = [x for x in (kd[i, c - 1], kd[j, c - 1]) if x > 0]
            if kk:
                rates.append(min(kk))
    if not dofs or not rates:
        return None
    scale = o.contact_fraction * float(np.median(rates))
    gi, gj = int(ctx.grid_ids[sel[0, 0]]), int(ctx.grid_ids[sel[0, 1]])
    axes = ",".join(_AXES[c - 1] for c in sorted(comps_used))
    term = AddedSpring(name, tuple(dofs), scale, 0.0, o.upper,
                       f"contact springs between {pa} and {pb}")
    if len(sel) == 1:
        text = (f"contact springs ({axes}) {scale:.3g} N/m x p between {ctx.grid_label(gi)} and "
                f"{ctx.grid_label(gj)}, {ctx.mm(dist[0])} apart")
    else:
        listed = ", ".join(f"{int(ctx.grid_ids[i])}-{int(ctx.grid_ids[j])}" for i, j in sel[:4].tolist())
        text = (f"contact springs ({axes}) {scale:.3g} N/m x p on {len(sel)} grid pairs between {pa} and "
                f"{pb} ({listed}{', ...' if len(sel) > 4 else ''}), "
                f"{ctx.mm(dist.min())} to {ctx.mm(dist.max())} apart")
    grids = tuple(sorted(set(ctx.grid_ids[sel.ravel()].tolist())))
    return ctx.candidate("contact_spring", term, grids, text, parts=(pa, pb),
                        points=np.vstack([ctx.xyz[sel[:, 0]], ctx.xyz[sel[:, 1]]]),
                        size=float(np.median(np.maximum(ctx.grid_sizes[sel[:, 0]],
                                                        ctx.grid_sizes[sel[:, 1]]))))


# ----------------------------------------------------------------------------
# registry and entry point
# ----------------------------------------------------------------------------

#: Registered families: name -> generator(ctx: CandidateContext) -> iterable of Candidate.
CANDIDATE_FAMILIES: dict[str, Callable[[CandidateContext], Iterable[Candidate]]] = {
    "sensor_mass": sensor_mass_family,
    "sensor_masses": sensor_masses_family,
    "shaker_attachment_mass": shaker_attachment_mass_family,
    "stinger_spring": stinger_spring_family,
    "contact_spring": contact_spring_family,
    "ground_spring": ground_spring_family,
    "lumped_mass": lumped_mass_family,
    "element_cluster": element_cluster_family,
}

_FAMILY_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


@dataclass(frozen=True)
class PointFamily:
    """How to re-create a point family's candidate at another grid (the zoom, :func:`zoom_candidates`).

    Attributes
    ----------
    rows : callable
        ``rows(ctx, like) -> int array``: the grid rows (of ``ctx.grid_ids``) where the family places a
        candidate of ``like``'s kind (e.g. the grids whose component is free for a ground spring).
    at : callable
        ``at(ctx, like, row) -> Candidate or None``: that candidate at grid row ``row``.
    key : callable
        ``key(like) -> hashable``: candidates of the family with equal keys are one kind at different
        grids (a ground spring's component); default: one kind.
    """

    rows: Callable
    at: Callable
    key: Callable = lambda like: None


def _spring_component(like: Candidate) -> int:
    return int(like.term.dofs[0][1])


#: Point families: their candidates act at one grid, and the screening's zoom re-creates them at the grids near
#: the best ones (:func:`zoom_candidates`). Extended with ``register_family(..., point=PointFamily(...))``.
POINT_FAMILIES: dict[str, PointFamily] = {
    "lumped_mass": PointFamily(rows=lambda ctx, like: _mass_rows(ctx), at=lambda ctx, like, row: _mass_at(ctx, row)),
    "ground_spring": PointFamily(
        rows=lambda ctx, like: _ground_rows(ctx, (_spring_component(like),)),
        at=lambda ctx, like, row: next(iter(_ground_springs_at(ctx, row, (_spring_component(like),))), None),
        key=_spring_component),
}


#: Region families: their candidates are alternatives of one region (a contact gap's cells, the windows
#: straddling their boundaries and the unions of them), so the screening gives the candidates of one region one
#: nonlinear-check slot and checks the enclosing and overlapping alternatives of the member that takes it with it
#: (``calibration.screen(regions=...)``, :func:`candidate_regions`). Family -> ``key(candidate)``: the region's
#: label (hashable) or None (a region of its own). Extended with ``register_family(..., region=key)``.
REGION_FAMILIES: dict = {
    "contact_spring": lambda c: c.parts,  # the part pair: its stretches, cells, windows and unions
}


def candidate_regions(candidates) -> list:
    """Per candidate None or ``(label, places)`` (``calibration.screen``'s ``regions``): for a family of
    :data:`REGION_FAMILIES`, the label ``(family, key(candidate))`` and its grids as the places it acts on."""
    out = []
    for c in candidates:
        key = REGION_FAMILIES.get(c.family)
        label = None if key is None else key(c)
        out.append(None if label is None else ((c.family, label), frozenset(int(g) for g in c.grids)))
    return out


def point_coverage(ctx: CandidateContext, candidates) -> dict:
    """How much of each point family's eligible grids ``candidates`` cover.

    Returns ``{(family, kind): (grids with a candidate, eligible grids)}`` for every point family
    (:data:`POINT_FAMILIES`) and kind (a ground spring's component) among ``candidates``: fewer than
    eligible means a spread sample (``CandidateOptions.spread_grids``), which an effect between the
    sampled grids can slip through when the zoom does not reach it.
    """
    out, like = {}, {}
    for c in candidates:
        pf = POINT_FAMILIES.get(c.family)
        if pf is None or len(c.grids) != 1:
            continue
        key = (c.family, pf.key(c))
        like.setdefault(key, c)
        out.setdefault(key, set()).add(int(c.grids[0]))
    return {k: (len(g), int(len(POINT_FAMILIES[k[0]].rows(ctx, like[k])))) for k, g in out.items()}


def zoom_candidates(ctx: CandidateContext, screened, best: Candidate, n: int | None = None) -> tuple:
    """The candidates of ``best``'s point family at the grids nearer ``best`` than any grid already screened.

    The spread sample of a point family (``spread_grids`` grids) misses an effect at a grid between the
    sampled ones: its nearest sampled candidate ranks high but explains it only in part. The zoom offers the
    same family's candidate (same kind: a ground spring's component) at the untested grids of ``best``'s
    neighbourhood: the grids whose nearest screened grid of that family and kind is ``best``'s (its Voronoi
    cell among the screened grids; Euclidean distance in basic coordinates, so any deck unit and mesh). A
    repeated zoom around the new best halves the spacing each round until the neighbourhood holds no
    untested grid.

    Parameters
    ----------
    ctx : CandidateContext
    screened : iterable of Candidate
        The candidates screened so far (every family may be given; only ``best``'s family and kind count).
    best : Candidate
        A candidate of a point family (:data:`POINT_FAMILIES`) acting at one grid.
    n : int, optional
        At most this many new candidates, spread evenly over the neighbourhood (farthest-point sampling away
        from ``best``'s grid); default ``ctx.options.zoom_grids``.

    Returns
    -------
    tuple of Candidate
        New candidates (none of ``screened``), in grid-row order; empty when ``best`` acts at several grids
        or its neighbourhood is screened already.

    Raises
    ------
    ParameterError
        ``best`` is not of a point family.
    """
    from scipy.spatial import cKDTree

    pf = POINT_FAMILIES.get(best.family)
    if pf is None:
        raise ParameterError(f"zoom_candidates: family {best.family!r} of {best.name!r} is not a point family "
                             f"(known: {', '.join(POINT_FAMILIES)})")
    n = ctx.options.zoom_grids if n is None else int(n)
    if len(best.grids) != 1 or n < 1:
        return ()
    kind = pf.key(best)
    tested = {best.grids[0]}
    tested |= {c.grids[0] for c in screened
               if c.family == best.family and len(c.grids) == 1 and pf.key(c) == kind}
    trows = ctx.grid_index(sorted(tested))
    rows = np.asarray(pf.rows(ctx, best), dtype=int)
    rows = rows[~np.isin(rows, trows)]
    if not rows.size:
        return ()
    b = ctx.xyz[int(ctx.grid_index([best.grids[0]])[0])]
    d_near, _ = cKDTree(ctx.xyz[trows]).query(ctx.xyz[rows])
    d_best = np.linalg.norm(ctx.xyz[rows] - b, axis=1)
    cell = rows[d_best <= d_near * (1.0 + 1e-9)]  # ties (equidistant grids) belong to every tied cell
    if not cell.size:
        return ()
    cell = cell[ctx.spread(ctx.xyz[cell], n, away_from=b[None, :])]
    out = []
    for r in cell.tolist():
        c = pf.at(ctx, best, int(r))
        if c is not None and c.name not in ctx.used_names:
            if not isinstance(c, Candidate) or c.family != best.family:
                raise ParameterError(f"point family {best.family!r} made {c!r:.120}, not a Candidate of its family")
            out.append(c)
    return tuple(out)



def candidate_pairs(candidate: Candidate) -> tuple:
    """The (grid a, grid b) pairs of a ``contact_spring`` candidate, in its order (one per pair, whatever
    the components)."""
    if candidate.family != "contact_spring":
        raise ParameterError(f"candidate_pairs: {candidate.name!r} is of family {candidate.family!r}, "
                             "not contact_spring")
    return tuple(dict.fromkeys((int(a), int(b)) for a, _, b, _ in candidate.term.dofs))


def contact_on_pairs(ctx: CandidateContext, like: Candidate, pairs, name: str) -> Candidate | None:
    """A ``contact_spring`` candidate between ``like``'s parts on the grid pairs ``pairs`` ((grid a, grid b),
    side a first, as :func:`candidate_pairs` gives them): one common rate, its scale from those pairs' stiffness
    (as the family's own candidates). None when no pair has a free, stiff component."""
    pairs = [(int(a), int(b)) for a, b in pairs]
    if not pairs:
        raise ParameterError(f"contact_on_pairs: no grid pairs for {name!r}")
    if name in ctx.used_names:
        raise ParameterError(f"contact_on_pairs: term name {name!r} is already used")
    sel = np.column_stack([ctx.grid_index([a for a, _ in pairs]), ctx.grid_index([b for _, b in pairs])])
    cos_tol = math.cos(math.radians(ctx.options.contact_axis_deg))
    return _contact_candidate(ctx, sel, like.parts[0], like.parts[-1], name, None, ctx.stiffness_diagonal, cos_tol,
                              oriented=True)


def register_family(name: str, generator, *, replace: bool = False, point: PointFamily | None = None,
                    region=None) -> None:
    """Add a candidate family to :data:`CANDIDATE_FAMILIES`.

    Parameters
    ----------
    name : str
        Lower-case identifier (``[a-z][a-z0-9_]*``); the family of every
        candidate the generator yields.
    generator : callable
        ``generator(ctx: CandidateContext) -> iterable of Candidate``; build
        candidates with :meth:`CandidateContext.candidate`, give each term a
        name no other candidate uses.
    replace : bool
        Allow replacing a registered family of that name.
    point : PointFamily, optional
        The family acts at single grids and can be re-created at any grid:
        registered in :data:`POINT_FAMILIES`, the screening zooms it
        (:func:`zoom_candidates`).
    region : callable, optional
        ``region(candidate) -> hashable or None``: candidates with one label
        are alternatives of one region (registered in
        :data:`REGION_FAMILIES`; the screening checks them together,
        :func:`candidate_regions`).

    Raises
    ------
    ParameterError
        A bad name, a non-callable generator, or a taken name without
        ``replace``.
    """
    if not isinstance(name, str) or not _FAMILY_NAME.match(name):
        raise ParameterError(f"register_family: name {name!r} must match [a-z][a-z0-9_]*")
    if not callable(generator):
        raise ParameterError(f"register_family {name!r}: generator must be callable, got {type(generator).__name__}")
    if name in CANDIDATE_FAMILIES and not replace:
        raise ParameterError(f"register_family: family {name!r} is already registered (pass replace=True)")
    if point is not None and not isinstance(point, PointFamily):
        raise ParameterError(f"register_family {name!r}: point must be a PointFamily, got {type(point).__name__}")
    if region is not None and not callable(region):
        raise ParameterError(f"register_family {name!r}: region must be callable, got {type(region).__name__}")
    CANDIDATE_FAMILIES[name] = generator
    if point is not None:
        POINT_FAMILIES[name] = point
    elif replace:
        POINT_FAMILIES.pop(name, None)
    if region is not None:
        REGION_FAMILIES[name] = region
    elif replace:
        REGION_FAMILIES.pop(name, None)


def generate_candidates(model, *, sensors=(), drives=(), families=None,
                        options: CandidateOptions | None = None,
                        context: CandidateContext | None = None) -> tuple[Candidate, ...]:
    """Candidate effects of a model and a test set-up, family by family.

    Parameters
    ----------
    model : FEModel or ParametricModel
        The deck (:func:`femodel.read_bdf`) or a parametric model (its
        assembly is reused; candidate names avoid its parameter names).
    sensors : iterable of int
        Measured grid ids.
    drives : iterable of (int, (3,) float)
        Drive grids and force directions (basic).
    families : iterable of str, optional
        Registered family names (default: all of :data:`CANDIDATE_FAMILIES`,
        in registry order).
    options : CandidateOptions, optional
    context : CandidateContext, optional
        A context of ``model`` built by :func:`candidate_context` (reused,
        e.g. for :func:`zoom_candidates` afterwards; ``sensors``, ``drives``
        and ``options`` are then its own and must not be given).

    Returns
    -------
    tuple of Candidate
        Grouped by family in the order asked; at most
        ``options.max_per_family`` per family (spread evenly in space).

    Raises
    ------
    ParameterError
        An unknown family (the message lists the known ones), unknown
        sensor/drive grids, a generator yielding something else than a
        Candidate of its family, or a repeated term name.
    """
    names = list(CANDIDATE_FAMILIES) if families is None else list(families)
    unknown = [f for f in names if f not in CANDIDATE_FAMILIES]
    if unknown:
        raise ParameterError(f"unknown candidate families {unknown}; known: {', '.join(CANDIDATE_FAMILIES)}")
    if context is None:
        ctx = candidate_context(model, sensors=sensors, drives=drives, options=options)
    elif tuple(sensors) or tuple(drives) or options is not None:
        raise ParameterError("generate_candidates: give sensors, drives and options to candidate_context, "
                             "not beside context")
    else:
        ctx = context
    out: list[Candidate] = []
    seen = set(ctx.used_names)
    for fam in dict.fromkeys(names):
        got = list(CANDIDATE_FAMILIES[fam](ctx) or ())
        for c in got:
            if not isinstance(c, Candidate) or c.family != fam:
                raise ParameterError(f"candidate family {fam!r} yielded {c!r:.120}, not a Candidate of family {fam!r}")
        if len(got) > ctx.options.max_per_family:
            centers = np.array([c.center for c in got], dtype=float)
            got = [got[i] for i in ctx.spread(centers, ctx.options.max_per_family)]
        for c in got:
            if c.term.name in seen:
                raise ParameterError(f"candidate family {fam!r}: term name {c.term.name!r} is already used")
            seen.add(c.term.name)
        out.extend(got)
    return tuple(out)



# ----------------------------------------------------------------------------
# compound effects: several terms that are one physical effect
# ----------------------------------------------------------------------------

#: Compound effects: name -> member families. Candidates of the member families acting on the same grids are
#: one physical effect with one parameter per member (a shaker attachment is its force-gauge/armature mass
#: and its stinger's axial stiffness at the drive grid). The diagnosis recalibrates and judges them together
#: (the per-parameter penalty counts every member) besides each member alone: a member whose own signature is
#: too weak for the data to confirm (the stinger, a quarter of the mass's frequency shift) is not left to the
#: other member to absorb.
COMPOUND_EFFECTS: dict[str, tuple[str, ...]] = {
    "shaker_attachment": ("shaker_attachment_mass", "stinger_spring"),
}


def compound_candidates(candidates) -> list[tuple[str, tuple[Candidate, ...]]]:
    """The compound effects (:data:`COMPOUND_EFFECTS`) among ``candidates``.

    Returns
    -------
    list of (name, members): ``name`` = "<compound>_g<grid>_..." , ``members`` one Candidate per member
    family (in the compound's order) with the same grids; only complete sets are returned.
    """
    out = []
    for compound, families in COMPOUND_EFFECTS.items():
        by_grids: dict = {}
        for c in candidates:
            if c.family in families:
                by_grids.setdefault(tuple(sorted(c.grids)), {}).setdefault(c.family, c)
        for grids, members in by_grids.items():
            if all(f in members for f in families):
                out.append((f"{compound}_g" + "_".join(str(g) for g in grids),
                            tuple(members[f] for f in families)))
    return out
