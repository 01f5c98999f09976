"""Read Nastran bulk data through pyNastran and convert it to :class:`FEModel` arrays.

pyNastran's ``BDF`` object is used only inside :func:`read_bdf`; everything
returned is our own arrays in SI and basic coordinates.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np

from femodel._coords import resolve_coords
from femodel._model import FEModel, ModelError, RBE2, RBE3, Table
from femodel._units import UnitSystem, unit_system

#: Cards that define the structure and are converted.
SUPPORTED_CARDS = frozenset(
    """GRID GRDSET CORD2R CORD2C CORD2S CORD1R CORD1C CORD1S
    CQUAD4 CTRIA3 PSHELL CBAR CBEAM PBAR PBARL PBEAM PBEAML CROD CONROD PROD
    CHEXA CPENTA CTETRA CPYRAM PSOLID CONM2 CELAS1 CELAS2 PELAS CBUSH PBUSH
    RBE2 RBE3 SPC SPC1 SPCADD MPC MPCADD MAT1 MAT8 PCOMP PARAM""".split()
)

#: Cards with no effect on K and M (solution control, loads, output, thermal
#: material, test-analysis sets); read and ignored without complaint.
NEUTRAL_CARDS = frozenset(
    """ENDDATA EIGRL EIGR EIGC EIGB MDLPRM USET USET1 SUPORT SUPORT1 MAT4 MAT5
    TEMP TEMPD FORCE FORCE1 FORCE2 MOMENT MOMENT1 MOMENT2 PLOAD PLOAD1 PLOAD2 PLOAD4
    LOAD GRAV DLOAD RLOAD1 RLOAD2 TLOAD1 TLOAD2 DAREA DPHASE DELAY TABLED1 TABLED2
    TABLED3 TABLED4 TABDMP1 FREQ FREQ1 FREQ2 FREQ3 FREQ4 FREQ5 TSTEP NLPARM PLOTEL
    PLOTEL3 PLOTEL4 DESVAR DVPREL1 DVPREL2 DRESP1 DRESP2 DOPTPRM DCONSTR SET1 SET3
    MONPNT1 SPCD AECOMP AELIST AERO AEROS AESTAT AESURF AESURFS CAERO1 CAERO2 CAERO3
    CAERO4 CAERO5 PAERO1 PAERO2 PAERO3 PAERO4 PAERO5 SPLINE1 SPLINE2 SPLINE3 SPLINE4
    SPLINE5 GUST MKAERO1 MKAERO2 TRIM FLUTTER FLFACT""".split()
)

_SHEAR_FACTOR_PBARL = {
    # Shear factors used for PBARL/PBEAML sections (Timoshenko).  ROD 0.9 is
    # confirmed against MSC Nastran (beam_modes reference); the others are the
    # usual textbook values and are not confirmed against Nastran output.
    "ROD": 0.9,
    "BAR": 5.0 / 6.0,
    "TUBE": 0.5,
}


def _f(value, default=np.nan) -> float:
    return default if value is None else float(value)


def _comp_mask(code) -> np.ndarray:
    mask = np.zeros(6, bool)
    if code in (None, "", 0, "0"):
        return mask
    for ch in str(int(code)) if not isinstance(code, str) else code.strip():
        if ch not in "123456":
            raise ValueError(f"bad component code {code!r}")
        mask[int(ch) - 1] = True
    return mask


def _comps(code) -> str:
    """Normalized component string ('123456' subset), '' for blank/0."""
    m = _comp_mask(code)
    return "".join(str(i + 1) for i in np.flatnonzero(m))


def read_bdf(path, *, units: str = "si", allow_unsupported: bool = False) -> FEModel:
    """Read a Nastran bulk data deck into an :class:`FEModel` (SI, basic coordinates).

    Parameters
    ----------
    path : str or Path
        The deck (executive/case control optional; INCLUDE followed by pyNastran).
    units : str
        Unit system the deck is written in: "si", "mm-t-s", "in-lbf-s" or
        "consistent" (no conversion).
    allow_unsupported : bool
        If False (default), a deck with cards outside the supported set raises
        one ModelError listing every unsupported card type and count.  If
        True, those cards are ignored with a warning and recorded in
        ``FEModel.ignored_cards``.

    Returns
    -------
    FEModel

    Raises
    ------
    ModelError
        Unsupported cards, malformed cards (naming card and id), references to
        undefined grids/properties/materials.
    OSError
        If the file cannot be read.
    """
    from pyNastran.bdf.bdf import BDF

    us = unit_system(units)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Nastran deck not found: {path}")
    log = logging.getLogger("femodel.pynastran")
    log.setLevel(logging.ERROR)
    bdf = BDF(debug=None, log=log)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mode = _deck_kind(path)
            if mode == "bulk-with-begin":
                # bulk data with a BEGIN BULK line but no executive/case control:
                # pyNastran wants either both or neither, so feed it without the line
                import io

                text = "".join(
                    line for line in open(path, errors="replace") if not line.strip().upper().startswith("BEGIN")
                )
                bdf.include_dir = str(path.parent)
                bdf.read_bdf(io.StringIO(text), xref=False, validate=False, punch=True)
            else:
                bdf.read_bdf(str(path), xref=False, validate=False, punch=(mode == "bulk"))
    except (SyntaxError, RuntimeError, ValueError, KeyError, IndexError, TypeError, AssertionError) as exc:
        raise ModelError(f"{path}: pyNastran could not parse the deck: {exc}") from None

    counts = dict(bdf.card_count)
    for rej in getattr(bdf, "reject_cards", []) or []:
        name = str(rej[0]).strip().rstrip("*").upper() if rej else "?"
        counts[name] = counts.get(name, 0) + 0
    unsupported = {k: v for k, v in counts.items() if k not in SUPPORTED_CARDS and k not in NEUTRAL_CARDS}
    if unsupported:
        listing = ", ".join(f"{k} x{v}" for k, v in sorted(unsupported.items()))
        if not allow_unsupported:
            raise ModelError(
                f"{path}: unsupported card types: {listing} "
                "(pass allow_unsupported=True / --allow-unsupported to ignore them)"
            )
        warnings.warn(f"{path}: ignoring unsupported cards: {listing}", stacklevel=2)

    return _convert(bdf, path, us, unsupported)


def _shells_fast(rows, nn, nids, nodes, tn, zoffs, theta, mcid, L) -> bool:
    """Fill the CQUAD4/CTRIA3 arrays at once; False (nothing filled) if any element needs a closer look.

    Gives exactly what the element-by-element loop of :func:`_convert` gives
    for well-formed elements (every grid given and defined, TFLAG 0).
    """
    elems = [e for _, e in rows]
    node_lists = [e.nodes for e in elems]
    if any(len(ns) != nn or None in ns for ns in node_lists):
        return False
    if any(getattr(e, "tflag", 0) not in (0, None) for e in elems):
        return False
    arr = np.array(node_lists, dtype=np.int64)
    pos = np.searchsorted(nids, arr)
    if np.any(pos >= nids.size) or np.any(nids[np.minimum(pos, nids.size - 1)] != arr):
        return False
    nodes[:] = arr
    names = [f"T{j + 1}" for j in range(nn)]
    tn[:] = [[np.nan if x is None or x == -1.0 else float(x) * L for x in (getattr(e, a, None) for a in names)]
             for e in elems]
    zoffs[:] = [_f(getattr(e, "zoffset", 0.0), 0.0) * L for e in elems]
    for i, e in enumerate(elems):
        tm = getattr(e, "theta_mcid", 0.0)
        if isinstance(tm, (int, np.integer)) and not isinstance(tm, bool):
            mcid[i] = int(tm)
        else:
            theta[i] = _f(tm, 0.0)
    return True


def _deck_kind(path: Path) -> str:
    """"full" (CEND before BEGIN BULK), "bulk-with-begin" or "bulk" (no control sections)."""
    with open(path, errors="replace") as f:
        for line in f:
            word = line.strip().upper()
            if word.startswith("CEND"):
                return "full"
            if word.startswith("BEGIN") and "BULK" in word:
                return "bulk-with-begin"
    return "bulk"


def _convert(bdf, path: Path, us: UnitSystem, ignored: dict) -> FEModel:
    L = us.length_m
    where = str(path)

    # ---------------- grids and coordinate systems
    nids = np.array(sorted(bdf.nodes), dtype=np.int64)
    if nids.size == 0:
        raise ModelError(f"{where}: no GRID cards")
    grdset = getattr(bdf, "grdset", None)
    gs_cp = int(grdset.cp or 0) if grdset is not None else 0
    gs_cd = int(grdset.cd or 0) if grdset is not None else 0
    gs_ps = _comps(grdset.ps) if grdset is not None and grdset.ps else ""
    grids = [bdf.nodes[nid] for nid in nids.tolist()]
    raw = np.zeros((nids.size, 3))
    raw[:] = [g.xyz for g in grids]
    cp = np.array([gs_cp if g.cp in (None, 0) and gs_cp else int(g.cp or 0) for g in grids], np.int64)
    cd = np.array([int((g.cd if g.cd not in (None, 0) else (gs_cd if g.cd is None or g.cd == 0 else 0)) or 0)
                   for g in grids], np.int64)
    codes = [g.ps if g.ps not in (None, "", 0) else gs_ps for g in grids]
    masks = {}  # PS code -> mask (most grids share a code)
    for i, code in enumerate(codes):
        key = (type(code), code)
        if key not in masks:
            try:
                masks[key] = _comp_mask(code)
            except ValueError:
                raise ModelError(f"{where}: GRID {int(nids[i])}: bad PS component code {grids[i].ps!r}") from None
    ps = np.zeros((nids.size, 6), bool)
    ps[:] = [masks[(type(code), code)] for code in codes]
    raw *= L
    xyz = np.full_like(raw, np.nan)
    xyz[cp == 0] = raw[cp == 0]
    row_of = {int(n): i for i, n in enumerate(nids.tolist())}

    defs = {}
    for cid, c in bdf.coords.items():
        if cid == 0:
            continue
        kind = c.type[-1]
        if c.type.startswith("CORD2"):
            pts = np.array([c.e1, c.e2, c.e3], dtype=float)
            if kind == "R" or True:
                # lengths convert; angles (cylindrical/spherical RID) do not
                pts = pts.copy()
            defs[int(cid)] = {"kind": kind, "type": 2, "rid": int(c.rid or 0), "points": pts, "raw": True}
        elif c.type.startswith("CORD1"):
            defs[int(cid)] = {"kind": kind, "type": 1, "grids": (int(c.g1), int(c.g2), int(c.g3))}
        else:
            raise ModelError(f"{where}: coordinate system {c.type} {cid} is not supported")
    # scale CORD2 points: coordinates in a rectangular RID are all lengths;
    # for cylindrical/spherical RIDs only the radius (and z) are lengths.
    rid_kind = {cid: d["kind"] for cid, d in defs.items()}
    rid_kind[0] = "R"
    for cid, d in defs.items():
        if d["type"] != 2:
            continue
        rk = rid_kind.get(d["rid"], "R")
        pts = d["points"]
        if rk == "R":
            pts *= L
        elif rk == "C":
            pts[:, [0, 2]] *= L
        else:
            pts[:, 0] *= L

    def grid_basic(gid):
        i = row_of.get(int(gid))
        if i is None:
            raise ModelError(f"{where}: coordinate system references undefined GRID {gid}")
        return None if np.isnan(xyz[i, 0]) else xyz[i]

    coords = None
    for _ in range(4):
        coords = resolve_coords(defs, grid_basic)
        missing = [c for c in np.unique(cp) if c not in coords]
        if missing:
            raise ModelError(f"{where}: GRID CP references undefined coordinate systems {missing}")
        for c in np.unique(cp):
            if c == 0:
                continue
            sel = cp == c
            loc = raw[sel].copy()
            k = coords[int(c)].kind
            if k == "C":
                loc[:, 1] /= L
            elif k == "S":
                loc[:, 1:] /= L
            xyz[sel] = coords[int(c)].to_basic(loc)
        break
    bad_cd = sorted(set(np.unique(cd).tolist()) - set(coords))
    if bad_cd:
        raise ModelError(f"{where}: GRID CD references undefined coordinate systems {bad_cd}")

    model_grids = set(row_of)

    def need_grids(card, eid, ids):
        for g in ids:
            if g is not None and int(g) not in model_grids:
                raise ModelError(f"{where}: {card} {eid} references undefined GRID {g}")

    # ---------------- materials
    mats = {}
    mids, E, G, NU, RHO, gfe = [], [], [], [], [], []
    for mid, m in sorted(bdf.materials.items()):
        if m.type != "MAT1":
            continue
        e, g, nu = m.e, m.g, m.nu
        if e is None and g is None:
            raise ModelError(f"{where}: MAT1 {mid}: E and G both blank")
        # pyNastran fills blank fields (G = E/2/(1+NU) when G is blank, NU = E/(2G)-1
        # when NU is blank); recover which one was derived to know whether G
        # follows E (a parametric E then scales G too).
        if e is not None and g is None:
            nu = 0.0 if nu is None else nu
            g = e / 2.0 / (1 + nu)
        elif e is None:
            nu = 0.0 if nu is None else nu
            e = 2 * (1 + nu) * g
        elif nu is None:
            nu = e / (2 * g) - 1.0 if g else 0.0
        if g and nu == e / (2 * g) - 1.0:
            follows = False
        else:
            follows = g == e / 2.0 / (1 + nu)
        if not e > 0 or g < 0:
            raise ModelError(f"{where}: MAT1 {mid}: E={e} must be positive and G={g} non-negative")
        mids.append(mid)
        E.append(e * us.stress_pa)
        G.append(g * us.stress_pa)
        NU.append(nu)
        RHO.append((m.rho or 0.0) * us.density_kg_m3)
        gfe.append(follows)
    mats["MAT1"] = Table(
        "MAT1",
        np.array(mids, np.int64),
        {"E": np.array(E), "G": np.array(G), "NU": np.array(NU), "RHO": np.array(RHO), "g_follows_e": np.array(gfe, bool)},
    )

    rows8 = [(mid, m) for mid, m in sorted(bdf.materials.items()) if m.type == "MAT8"]
    if rows8:
        def g8(v):
            return np.inf if v in (None, 0, 0.0) else float(v) * us.stress_pa

        mats["MAT8"] = Table(
            "MAT8",
            np.array([r[0] for r in rows8], np.int64),
            {
                "E1": np.array([float(m.e11) for _, m in rows8]) * us.stress_pa,
                "E2": np.array([float(m.e22) for _, m in rows8]) * us.stress_pa,
                "NU12": np.array([float(m.nu12 or 0.0) for _, m in rows8]),
                "G12": np.array([float(m.g12 or 0.0) for _, m in rows8]) * us.stress_pa,
                "G1Z": np.array([g8(m.g1z) for _, m in rows8]),
                "G2Z": np.array([g8(m.g2z) for _, m in rows8]),
                "RHO": np.array([float(m.rho or 0.0) for _, m in rows8]) * us.density_kg_m3,
            },
        )

    # ---------------- properties
    props = {}
    props_by_type: dict[str, list] = {}
    for pid, p in sorted(bdf.properties.items()):
        props_by_type.setdefault(p.type, []).append((pid, p))
    props.update(_bar_properties(props_by_type, us, where))
    if "PROD" in props_by_type:
        rows = props_by_type["PROD"]
        props["PROD"] = Table(
            "PROD",
            np.array([r[0] for r in rows], np.int64),
            {
                "mid": np.array([r[1].mid for r in rows], np.int64),
                "A": np.array([_f(r[1].A, 0.0) for r in rows]) * L**2,
                "J": np.array([_f(r[1].j, 0.0) for r in rows]) * L**4,
                "nsm": np.array([_f(r[1].nsm, 0.0) for r in rows]) * us.mass_kg / L,
            },
        )
    if "PSHELL" in props_by_type:
        rows = props_by_type["PSHELL"]

        def mid_or0(x):
            return int(x) if x not in (None, 0) else 0

        t = np.array([_f(r[1].t) for r in rows])
        props["PSHELL"] = Table(
            "PSHELL",
            np.array([r[0] for r in rows], np.int64),
            {
                "mid1": np.array([mid_or0(r[1].mid1) for r in rows], np.int64),
                "t": t * L,
                "mid2": np.array([mid_or0(r[1].mid2) for r in rows], np.int64),
                "bending_ratio": np.array([_f(r[1].twelveIt3, 1.0) for r in rows]),
                "mid3": np.array([mid_or0(r[1].mid3) for r in rows], np.int64),
                "ts_t": np.array([_f(r[1].tst, 0.833333) for r in rows]),
                "nsm": np.array([_f(r[1].nsm, 0.0) for r in rows]) * us.mass_kg / L**2,
                "z1": np.array([_f(r[1].z1) for r in rows]) * L,
                "z2": np.array([_f(r[1].z2) for r in rows]) * L,
            },
        )
    if "PCOMP" in props_by_type:
        props["PCOMP"] = _pcomp_table(props_by_type["PCOMP"], mats, us, where)
    if "PSOLID" in props_by_type:
        rows = props_by_type["PSOLID"]
        props["PSOLID"] = Table(
            "PSOLID",
            np.array([r[0] for r in rows], np.int64),
            {
                "mid": np.array([r[1].mid for r in rows], np.int64),
                "cordm": np.array([int(r[1].cordm or 0) for r in rows], np.int64),
            },
        )
    pelas_k = {}
    if "PELAS" in props_by_type:
        rows = props_by_type["PELAS"]
        pelas_k = {int(pid): _f(p.k, 0.0) for pid, p in rows}
        props["PELAS"] = Table(
            "PELAS",
            np.array([r[0] for r in rows], np.int64),
            {"k_deck": np.array([_f(r[1].k, 0.0) for r in rows]), "ge": np.array([_f(r[1].ge, 0.0) for r in rows])},
        )
    if "PBUSH" in props_by_type:
        rows = props_by_type["PBUSH"]
        kk = np.zeros((len(rows), 6))
        for i, (pid, p) in enumerate(rows):
            if "K" in (p.vars or []):
                vals = [np.nan if v is None else float(v) for v in (list(p.Ki) + [None] * 6)[:6]]
                kk[i] = vals
            else:
                raise ModelError(f"{where}: PBUSH {pid} has no K line (only K is supported)")
        kk = np.nan_to_num(kk, nan=0.0)
        kk[:, :3] *= us.force_n / L
        kk[:, 3:] *= us.force_n * L
        props["PBUSH"] = Table("PBUSH", np.array([r[0] for r in rows], np.int64), {"k": kk})

    # ---------------- elements
    # properties of unsupported types (PCOMP, ...): their elements are dropped
    # (only reachable with allow_unsupported=True; otherwise the card list failed)
    bad_pids = {int(pid): p.type for pid, p in bdf.properties.items() if p.type in ignored}
    by_type: dict[str, list] = {}
    for eid, e in sorted(bdf.elements.items()):
        pid = getattr(e, "pid", None)
        if isinstance(pid, (int, np.integer)) and int(pid) in bad_pids:
            key = f"{e.type} with {bad_pids[int(pid)]}"
            ignored[key] = ignored.get(key, 0) + 1
            continue
        by_type.setdefault(e.type, []).append((eid, e))
    elements: dict[str, Table] = {}
    cd_axes_cache = {}

    def cd_rot(gid):
        i = row_of[int(gid)]
        c = int(cd[i])
        if c == 0:
            return np.eye(3)
        if (i, c) not in cd_axes_cache:
            cd_axes_cache[(i, c)] = coords[c].local_axes(xyz[i : i + 1])[0]
        return cd_axes_cache[(i, c)]

    for card in ("CBAR", "CBEAM"):
        rows = by_type.get(card, [])
        if not rows:
            continue
        n = len(rows)
        nodes = np.zeros((n, 2), np.int64)
        v = np.zeros((n, 3))
        wa = np.zeros((n, 3))
        wb = np.zeros((n, 3))
        pid = np.zeros(n, np.int64)
        pins = np.zeros((n, 2, 6), bool)
        for i, (eid, e) in enumerate(rows):
            ga, gb = int(e.ga), int(e.gb)
            need_grids(card, eid, (ga, gb, e.g0))
            nodes[i] = ga, gb
            pid[i] = int(e.pid)
            try:
                pins[i] = [_comp_mask(e.pa), _comp_mask(e.pb)]
            except ValueError:
                raise ModelError(f"{where}: {card} {eid}: bad pin flags PA={e.pa!r} PB={e.pb!r}") from None
            offt = (getattr(e, "offt", None) or "GGG") if card == "CBAR" else (getattr(e, "offt", None) or "GGG")
            if not isinstance(offt, str):
                offt = "GGG"
            if "O" in offt[1:]:
                raise ModelError(f"{where}: {card} {eid}: OFFT {offt} (offsets in element system) is not supported")
            if e.g0 not in (None, 0):
                v[i] = xyz[row_of[int(e.g0)]] - xyz[row_of[ga]]
            else:
                x = np.asarray(e.x, dtype=float)
                v[i] = x if offt[0] == "B" else cd_rot(ga) @ x
            w_a = np.asarray(e.wa if e.wa is not None else np.zeros(3), float) * L
            w_b = np.asarray(e.wb if e.wb is not None else np.zeros(3), float) * L
            wa[i] = w_a if offt[1] == "B" else cd_rot(ga) @ w_a
            wb[i] = w_b if offt[2] == "B" else cd_rot(gb) @ w_b
        elements[card] = Table(
            card,
            np.array([r[0] for r in rows], np.int64),
            {"pid": pid, "nodes": nodes, "v": v, "wa": wa, "wb": wb, "pins": pins.reshape(n, 12)},
        )

    if "CROD" in by_type:
        rows = by_type["CROD"]
        for eid, e in rows:
            need_grids("CROD", eid, e.nodes)
        elements["CROD"] = Table(
            "CROD",
            np.array([r[0] for r in rows], np.int64),
            {"pid": np.array([int(e.pid) for _, e in rows], np.int64), "nodes": np.array([e.nodes for _, e in rows], np.int64)},
        )
    if "CONROD" in by_type:
        rows = by_type["CONROD"]
        for eid, e in rows:
            need_grids("CONROD", eid, e.nodes)
        elements["CONROD"] = Table(
            "CONROD",
            np.array([r[0] for r in rows], np.int64),
            {
                "pid": np.full(len(rows), -1, np.int64),
                "nodes": np.array([e.nodes for _, e in rows], np.int64),
                "mid": np.array([int(e.mid) for _, e in rows], np.int64),
                "A": np.array([_f(e.A, 0.0) for _, e in rows]) * L**2,
                "J": np.array([_f(e.j, 0.0) for _, e in rows]) * L**4,
                "nsm": np.array([_f(e.nsm, 0.0) for _, e in rows]) * us.mass_kg / L,
            },
        )
    for card in ("CELAS1", "CELAS2"):
        rows = by_type.get(card, [])
        if not rows:
            continue
        n = len(rows)
        nodes = np.zeros((n, 2), np.int64)
        c12 = np.zeros((n, 2), np.int8)
        k = np.zeros(n)
        pid = np.full(n, -1, np.int64)
        for i, (eid, e) in enumerate(rows):
            g = [0 if x is None else int(x) for x in e.nodes]
            need_grids(card, eid, [x for x in g if x])
            c = [int(e.c1 or 0), int(e.c2 or 0)]
            for j in range(2):
                if g[j] and not 1 <= c[j] <= 6:
                    raise ModelError(f"{where}: {card} {eid}: component C{j + 1}={c[j]} must be 1..6 for a GRID")
            nodes[i] = g
            c12[i] = c
            if card == "CELAS1":
                pid[i] = int(e.pid)
                if pid[i] not in pelas_k:
                    raise ModelError(f"{where}: CELAS1 {eid} references undefined PELAS {pid[i]}")
                kd = pelas_k[pid[i]]
            else:
                kd = _f(e.k, 0.0)
            rot = [cc >= 4 for cc, gg in zip(c, g) if gg]
            if all(rot):
                fac = us.force_n * L
            elif not any(rot):
                fac = us.force_n / L
            else:
                fac = us.force_n
            k[i] = kd * fac
        elements[card] = Table(card, np.array([r[0] for r in rows], np.int64), {"pid": pid, "nodes": nodes, "components": c12, "k": k})

    if "CBUSH" in by_type:
        rows = by_type["CBUSH"]
        n = len(rows)
        nodes = np.zeros((n, 2), np.int64)
        axes = np.zeros((n, 3, 3))
        s = np.zeros(n)
        pid = np.zeros(n, np.int64)
        for i, (eid, e) in enumerate(rows):
            ga = int(e.nodes[0])
            gb = 0 if e.nodes[1] in (None, 0) else int(e.nodes[1])
            need_grids("CBUSH", eid, [ga] + ([gb] if gb else []))
            nodes[i] = ga, gb
            pid[i] = int(e.pid)
            s[i] = 0.5 if e.s is None else float(e.s)
            if getattr(e, "ocid", -1) not in (None, -1) or any(x is not None for x in (getattr(e, "si", None) or [])):
                raise ModelError(f"{where}: CBUSH {eid}: OCID/S1-S3 spring offsets are not supported")
            xa = xyz[row_of[ga]]
            xb = xyz[row_of[gb]] if gb else xa
            if e.cid is not None and int(e.cid) >= 0:
                cid = int(e.cid)
                if cid not in coords:
                    raise ModelError(f"{where}: CBUSH {eid} references undefined coordinate system {cid}")
                axes[i] = coords[cid].local_axes(xa[None])[0].T
            else:
                ex = xb - xa
                if np.linalg.norm(ex) <= 1e-12 * max(1.0, np.linalg.norm(xa)):
                    raise ModelError(f"{where}: CBUSH {eid}: coincident grids need a CID")
                ex = ex / np.linalg.norm(ex)
                if e.g0 not in (None, 0):
                    vv = xyz[row_of[int(e.g0)]] - xa
                elif e.x is not None and e.x[0] is not None:
                    vv = cd_rot(ga) @ np.asarray(e.x, float)
                else:
                    raise ModelError(f"{where}: CBUSH {eid}: no orientation (X/G0 or CID)")
                ez = np.cross(ex, vv)
                if np.linalg.norm(ez) == 0:
                    raise ModelError(f"{where}: CBUSH {eid}: orientation vector is parallel to the axis")
                ez /= np.linalg.norm(ez)
                axes[i] = np.vstack([ex, np.cross(ez, ex), ez])
        elements["CBUSH"] = Table("CBUSH", np.array([r[0] for r in rows], np.int64), {"pid": pid, "nodes": nodes, "axes": axes, "s": s})

    for card, nn in (("CQUAD4", 4), ("CTRIA3", 3)):
        rows = by_type.get(card, [])
        if not rows:
            continue
        nodes = np.zeros((len(rows), nn), np.int64)
        tn = np.full((len(rows), nn), np.nan)
        zoffs = np.zeros(len(rows))
        theta = np.zeros(len(rows))
        mcid = np.full(len(rows), -1, np.int64)
        if _shells_fast(rows, nn, nids, nodes, tn, zoffs, theta, mcid, L):
            rows_left = []
        else:  # something to report: element by element, in id order
            rows_left = rows
        for i, (eid, e) in enumerate(rows_left):
            need_grids(card, eid, e.nodes)
            if any(x is None for x in e.nodes):
                raise ModelError(f"{where}: {card} {eid}: missing grid")
            nodes[i] = e.nodes
            if getattr(e, "tflag", 0) not in (0, None):
                raise ModelError(f"{where}: {card} {eid}: TFLAG=1 (relative thicknesses) is not supported")
            tt = [getattr(e, f"T{j + 1}", None) for j in range(nn)]
            tn[i] = [np.nan if x is None or x == -1.0 else float(x) * L for x in tt]
            zoffs[i] = _f(getattr(e, "zoffset", 0.0), 0.0) * L
            tm = getattr(e, "theta_mcid", 0.0)
            if isinstance(tm, (int, np.integer)) and not isinstance(tm, bool):
                mcid[i] = int(tm)
            else:
                theta[i] = _f(tm, 0.0)
        elements[card] = Table(
            card,
            np.array([r[0] for r in rows], np.int64),
            {
                "pid": np.array([int(e.pid) for _, e in rows], np.int64),
                "nodes": nodes,
                "t": tn,
                "zoffs": zoffs,
                "theta": theta,
                "mcid": mcid,
            },
        )

    for card in ("CTETRA", "CPYRAM", "CPENTA", "CHEXA"):
        rows = by_type.get(card, [])
        if not rows:
            continue
        groups: dict[int, list] = {}
        for eid, e in rows:
            ns = list(e.nodes)
            while ns and ns[-1] is None:
                ns.pop()
            if any(x is None for x in ns):
                raise ModelError(f"{where}: {card} {eid}: partial midside nodes are not supported")
            need_grids(card, eid, ns)
            groups.setdefault(len(ns), []).append((eid, e, ns))
        for nn, grp in sorted(groups.items()):
            name = f"{card}{nn}" if len(groups) > 1 or nn not in (4, 5, 6, 8) else card
            elements[name] = Table(
                card,
                np.array([g[0] for g in grp], np.int64),
                {"pid": np.array([int(g[1].pid) for g in grp], np.int64), "nodes": np.array([g[2] for g in grp], np.int64)},
            )

    if bdf.masses:
        rows = [(eid, m) for eid, m in sorted(bdf.masses.items()) if m.type == "CONM2"]
        n = len(rows)
        grid = np.zeros(n, np.int64)
        mass = np.zeros(n)
        off = np.zeros((n, 3))
        inertia = np.zeros((n, 3, 3))
        for i, (eid, m) in enumerate(rows):
            need_grids("CONM2", eid, [m.nid])
            grid[i] = int(m.nid)
            mass[i] = _f(m.mass, 0.0) * us.mass_kg
            cid = int(m.cid if m.cid is not None else 0)
            xg = xyz[row_of[grid[i]]]
            X = np.asarray(m.X, float) * L
            if cid == -1:
                off[i] = X - xg
                R = np.eye(3)
            else:
                if cid not in coords:
                    raise ModelError(f"{where}: CONM2 {eid} references undefined coordinate system {cid}")
                R = coords[cid].local_axes(xg[None])[0]
                off[i] = R @ X
            I11, I21, I22, I31, I32, I33 = [float(x) for x in m.I]
            J = np.array([[I11, -I21, -I31], [-I21, I22, -I32], [-I31, -I32, I33]]) * us.mass_kg * L**2
            inertia[i] = R @ J @ R.T
        elements["CONM2"] = Table(
            "CONM2",
            np.array([r[0] for r in rows], np.int64),
            {"pid": np.full(n, -1, np.int64), "nodes": grid[:, None], "mass": mass, "offset": off, "inertia": inertia},
        )

    # ---------------- rigid elements
    rbe2, rbe3 = [], []
    for eid, r in sorted(bdf.rigid_elements.items()):
        if r.type == "RBE2":
            gm = tuple(int(g) for g in r.Gmi)
            need_grids("RBE2", eid, (r.gn,) + gm)
            try:
                comps = _comps(r.cm)
            except ValueError:
                raise ModelError(f"{where}: RBE2 {eid}: bad CM {r.cm!r}") from None
            rbe2.append(RBE2(int(eid), int(r.gn), comps, gm))
        elif r.type == "RBE3":
            if r.Gmi:
                raise ModelError(f"{where}: RBE3 {eid}: UM (extra dependent DOF) is not supported")
            groups = []
            for w, c, gs in zip(r.weights, r.comps, r.Gijs):
                gs = tuple(int(g) for g in gs)
                need_grids("RBE3", eid, gs)
                groups.append((float(w), _comps(c), gs))
            need_grids("RBE3", eid, (r.refgrid,))
            rbe3.append(RBE3(int(eid), int(r.refgrid), _comps(r.refc), tuple(groups)))
        elif r.type not in ignored:
            raise ModelError(f"{where}: rigid element {r.type} {eid} is not supported")

    # ---------------- SPCs (the case-control set if given, else all)
    spc_id = None
    cc = getattr(bdf, "case_control_deck", None)
    if cc is not None:
        for sc_id in sorted(cc.subcases):
            sc = cc.subcases[sc_id]
            val = sc.params.get("SPC") if hasattr(sc, "params") else None
            if val is not None:
                try:
                    spc_id = int(val[0])
                except (TypeError, ValueError):
                    raise ModelError(f"{where}: case control SPC = {val[0]!r} is not a set id") from None
                if sc_id != 0:
                    break
    if spc_id is not None:
        sids = _expand_spcadd(bdf, spc_id)
        missing = [s for s in sids if s not in bdf.spcs]
        if missing and spc_id not in getattr(bdf, "spcadds", {}) and spc_id not in bdf.spcs:
            raise ModelError(f"{where}: case control SPC = {spc_id} but no SPC/SPC1 set {spc_id} in the bulk data")
    else:
        sids = sorted(bdf.spcs)
    sg, sc_ = [], []
    for sid in sids:
        for spc in bdf.spcs.get(sid, []):
            if spc.type == "SPC1":
                comps = _comps(spc.components)
                for g in spc.nodes:
                    need_grids("SPC1", sid, [g])
                    for ch in comps:
                        sg.append(int(g))
                        sc_.append(int(ch))
            elif spc.type == "SPC":
                for g, c, enforced in zip(spc.nodes, spc.components, spc.enforced):
                    need_grids("SPC", sid, [g])
                    if enforced not in (None, 0, 0.0):
                        raise ModelError(f"{where}: SPC {sid}: enforced displacement {enforced} at GRID {g} (only zero is supported)")
                    for ch in _comps(c):
                        sg.append(int(g))
                        sc_.append(int(ch))
            else:
                raise ModelError(f"{where}: constraint {spc.type} {sid} is not supported")

    # ---------------- MPCs (only the case-control MPC set, as Nastran)
    mpc_id = None
    if cc is not None:
        for sc_id in sorted(cc.subcases):
            val = cc.subcases[sc_id].params.get("MPC") if hasattr(cc.subcases[sc_id], "params") else None
            if val is not None:
                try:
                    mpc_id = int(val[0])
                except (TypeError, ValueError):
                    raise ModelError(f"{where}: case control MPC = {val[0]!r} is not a set id") from None
                if sc_id != 0:
                    break
    mpcs = []
    if mpc_id is not None:
        adds = getattr(bdf, "mpcadds", {}) or {}

        def expand(sid):
            if sid in adds:
                return [x for card in adds[sid] for s_ in card.sets for x in expand(int(s_))]
            return [sid]

        for sid in expand(mpc_id):
            for card in bdf.mpcs.get(sid, []):
                if card.type != "MPC":
                    raise ModelError(f"{where}: {card.type} {sid} is not supported")
                terms = []
                for g, c, a in zip(card.nodes, card.components, card.coefficients):
                    need_grids("MPC", sid, [g])
                    cc_ = _comps(c)
                    if len(cc_) != 1:
                        raise ModelError(f"{where}: MPC {sid}: component {c!r} of GRID {g} must be one of 1..6")
                    terms.append((int(g), int(cc_), float(a)))
                if not terms or terms[0][2] == 0.0:
                    raise ModelError(f"{where}: MPC {sid}: the first (dependent) coefficient must be non-zero")
                mpcs.append((int(sid), tuple(terms)))

    # ---------------- params
    def param(name, default):
        p = bdf.params.get(name)
        if p is None:
            return default
        return p.values[0]

    wtmass = float(param("WTMASS", 1.0))
    coupmass = int(param("COUPMASS", -1) or -1) > 0
    k6rot = float(param("K6ROT", 100.0))

    return FEModel(
        path=where,
        units=us.name,
        grid_ids=nids,
        xyz=xyz,
        cp=cp,
        cd=cd,
        ps=ps,
        coords=coords,
        elements=elements,
        properties=props,
        materials=mats,
        rbe2=tuple(rbe2),
        rbe3=tuple(rbe3),
        mpc=tuple(mpcs),
        spc_grid=np.array(sg, np.int64),
        spc_component=np.array(sc_, np.int8),
        wtmass=wtmass,
        coupmass=coupmass,
        k6rot=k6rot,
        ignored_cards=dict(ignored),
    )


def _pcomp_table(rows, mats, us: UnitSystem, where: str) -> Table:
    """PCOMP laminates resolved to shell constitutive matrices (classical lamination), SI.

    Fields: dm, dmb, db (n, 3, 3) in the material axes of THETA = 0, ds (n, 2, 2)
    (``inf`` where every ply is shear-rigid), mu (n,) kg/m^2, t (n,) m.
    """
    from femodel._elements_shell import laminate_abd, orthotropic_q

    L = us.length_m
    m1 = mats.get("MAT1")
    m8 = mats.get("MAT8")
    n = len(rows)
    dm, dmb, db = (np.zeros((n, 3, 3)) for _ in range(3))
    ds = np.zeros((n, 2, 2))
    mu = np.zeros(n)
    tt = np.zeros(n)
    for i, (pid, p) in enumerate(rows):
        try:
            t = np.array(p.get_thicknesses(), float) * L
            th = np.array(p.get_thetas(), float)
            mids = [int(x) for x in p.get_material_ids()]
        except (AttributeError, TypeError, ValueError, IndexError) as exc:
            raise ModelError(f"{where}: PCOMP {pid}: cannot read the plies ({exc})") from None
        q = np.zeros((t.size, 3, 3))
        g = np.zeros((t.size, 2))
        rho = np.zeros(t.size)
        for k, mid in enumerate(mids):
            if m8 is not None and mid in set(m8.ids.tolist()):
                r = m8.rows([mid])[0]
                q[k] = orthotropic_q(m8["E1"][r], m8["E2"][r], m8["NU12"][r], m8["G12"][r])
                g[k] = m8["G1Z"][r], m8["G2Z"][r]
                rho[k] = m8["RHO"][r]
            elif m1 is not None and mid in set(m1.ids.tolist()):
                r = m1.rows([mid])[0]
                e, nu = m1["E"][r], m1["NU"][r]
                q[k] = e / (1 - nu**2) * np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])
                g[k] = m1["G"][r], m1["G"][r]
                rho[k] = m1["RHO"][r]
            else:
                raise ModelError(f"{where}: PCOMP {pid} ply {k + 1} references undefined MAT1/MAT8 {mid}")
        z0 = None if p.z0 is None else float(p.z0) * L
        try:
            dm[i], dmb[i], db[i], ds[i] = laminate_abd(t, th, q, g, z0)
        except ValueError as exc:
            raise ModelError(f"{where}: PCOMP {pid}: {exc}") from None
        mu[i] = float(np.sum(rho * t)) + _f(p.nsm, 0.0) * us.mass_kg / L**2
        tt[i] = t.sum()
    return Table(
        "PCOMP",
        np.array([r[0] for r in rows], np.int64),
        {"dm": dm, "dmb": dmb, "db": db, "ds": ds, "mu": mu, "t": tt},
    )


def _expand_spcadd(bdf, sid: int) -> list[int]:
    adds = getattr(bdf, "spcadds", {}) or {}
    if sid in adds:
        out = []
        for card in adds[sid]:
            for s in card.sets:
                out.extend(_expand_spcadd(bdf, int(s)))
        return out
    return [sid]


def _bar_properties(props_by_type: dict, us: UnitSystem, where: str) -> dict:
    """PBAR/PBARL/PBEAM/PBEAML resolved to one "PBAR"-like section table (SI)."""
    L = us.length_m
    rows = []
    for card in ("PBAR", "PBARL", "PBEAM", "PBEAML"):
        for pid, p in props_by_type.get(card, []):
            try:
                if card == "PBAR":
                    A, I1, I2, I12, J, nsm = p.A, p.i1, p.i2, p.i12, p.j, p.nsm
                    k1 = np.nan if p.k1 in (None, 1e8) or p.k1 <= 0 else float(p.k1)
                    k2 = np.nan if p.k2 in (None, 1e8) or p.k2 <= 0 else float(p.k2)
                elif card == "PBEAM":
                    A, I1, I2, I12, J, nsm = (float(np.mean([x[0], x[-1]])) for x in (p.A, p.i1, p.i2, p.i12, p.j, p.nsm))
                    k1 = np.nan if p.k1 in (None,) or p.k1 <= 0 else float(p.k1)
                    k2 = np.nan if p.k2 in (None,) or p.k2 <= 0 else float(p.k2)
                else:
                    btype = p.beam_type
                    if card == "PBEAML":
                        from pyNastran.bdf.cards.properties.bars import PBARL

                        # a tapered PBEAML uses the mean of its stations' section
                        # properties (an approximation; Nastran integrates along the beam)
                        secs = [PBARL(pid, p.mid, btype, list(d)) for d in p.dim]
                        vals = np.array([[_section(x, btype, k) for k in range(5)] for x in secs], float)
                        A, I1, I2, I12, J = vals.mean(axis=0)
                        nsm = float(np.mean(p.nsm))
                        sec = secs[0]
                    else:
                        sec = p
                        A, I1, I2, I12, J = (_section(sec, btype, k) for k in range(5))
                        nsm = p.nsm
                    kf = _shear_factor(btype, p.dim if card == "PBARL" else p.dim[0], A)
                    k1 = k2 = kf
            except ModelError:
                raise
            except (NotImplementedError, AttributeError, TypeError, ValueError, IndexError) as exc:
                raise ModelError(f"{where}: {card} {pid}: cannot evaluate section ({exc})") from None
            if I12 not in (None, 0, 0.0):
                raise ModelError(f"{where}: {card} {pid}: I12 != 0 (unsymmetric section) is not supported")
            rows.append((pid, card, int(p.mid), A or 0.0, I1 or 0.0, I2 or 0.0, J or 0.0, nsm or 0.0, k1, k2))
    if not rows:
        return {}
    arr = list(zip(*rows))
    return {
        "PBAR": Table(
            "PBAR",
            np.array(arr[0], np.int64),
            {
                "card": np.array(arr[1]),
                "mid": np.array(arr[2], np.int64),
                "A": np.array(arr[3], float) * L**2,
                "I1": np.array(arr[4], float) * L**4,
                "I2": np.array(arr[5], float) * L**4,
                "J": np.array(arr[6], float) * L**4,
                "nsm": np.array(arr[7], float) * us.mass_kg / L,
                "k1": np.array(arr[8], float),
                "k2": np.array(arr[9], float),
            },
        )
    }


def _section(sec, btype: str, k: int) -> float:
    """A, I1, I2, I12, J (k = 0..4) of a PBARL-type section; T2 computed here (pyNastran lacks it)."""
    if btype == "T2":
        # DIM1 flange width, DIM2 total height, DIM3 flange thickness, DIM4 web thickness
        b, h, tf, tw = (float(x) for x in sec.dim[:4])
        hw = h - tf
        a_f, a_w = b * tf, tw * hw
        area = a_f + a_w
        yf, yw = hw + 0.5 * tf, 0.5 * hw  # centroid heights from the web foot
        yc = (a_f * yf + a_w * yw) / area
        i_strong = b * tf**3 / 12 + a_f * (yf - yc) ** 2 + tw * hw**3 / 12 + a_w * (yw - yc) ** 2
        i_weak = tf * b**3 / 12 + hw * tw**3 / 12
        j = (b * tf**3 + hw * tw**3) / 3.0
        return (area, i_strong, i_weak, 0.0, j)[k]
    return [sec.Area, sec.I11, sec.I22, sec.I12, sec.J][k]()


def _shear_factor(btype: str, dim, area: float) -> float:
    if btype in _SHEAR_FACTOR_PBARL:
        return _SHEAR_FACTOR_PBARL[btype]
    if btype == "BOX":
        # web shear area / total area
        w, h, t1, t2 = (float(x) for x in dim[:4])
        return float(2 * t2 * (h - 2 * t1) / area) if area > 0 else np.nan
    if btype == "T2":
        b, h, tf, tw = (float(x) for x in dim[:4])
        return float(tw * (h - tf) / area) if area > 0 else np.nan
    if btype == "I":
        d1, d2, d3, d4, d5, d6 = (float(x) for x in dim[:6])
        return float(d4 * (d1 - d5 - d6) / area) if area > 0 else np.nan
    return np.nan
