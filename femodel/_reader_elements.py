"""Element cards (bars and beams, rods, springs, bushings, shells, solids, CONM1/CONM2, CMASS1/CMASS2, RBE2/RBE3) as SI tables."""

from __future__ import annotations

import numpy as np

from femodel._model import RBE2, RBE3, ModelError, Table
from femodel._reader_fields import component_mask, component_string, field_float
from femodel._reader_grids import GridSet
from femodel._units import UnitSystem


def read_elements(bdf, grids: GridSet, props: dict[str, Table], us: UnitSystem,
                  ignored: dict[str, int]) -> tuple[dict[str, Table], dict[str, int]]:
    """Element tables keyed by card name, and the elements dropped with their unsupported property.

    Parameters
    ----------
    bdf : pyNastran BDF
    grids : GridSet
    props : dict
        Output of :func:`femodel._reader_properties.read_properties` (CELAS1
        takes its rate from the PELAS table).
    us : UnitSystem
    ignored : dict
        Unsupported card types being ignored; elements whose property is of
        one of them are dropped.

    Returns
    -------
    elements : dict str -> Table
        Tables in the order assembly has always seen them: CBAR, CBEAM, CROD,
        CONROD, CELAS1, CELAS2, CBUSH, CQUAD4, CTRIA3, solids, CONM2, then
        CONM1, CMASS1, CMASS2.
    dropped : dict str -> int
        "CQUAD4 with PCOMPG"-style keys and counts of the dropped elements.

    Raises
    ------
    ModelError
        Undefined grids, coordinate systems or PELAS; unsupported options
        (OFFT in element system, TFLAG=1, CBUSH spring offsets, partial
        midside nodes); bad component codes; CBUSH without orientation.
    """
    # properties of unsupported types (PCOMPG, ...): their elements are dropped
    # (only reachable with allow_unsupported=True; otherwise the card list failed)
    bad_pids = {int(pid): p.type for pid, p in bdf.properties.items() if p.type in ignored}
    dropped: dict[str, int] = {}
    by_type: dict[str, list] = {}
    for eid, e in sorted(bdf.elements.items()):
        pid = getattr(e, "pid", None)
        if isinstance(pid, (int, np.integer)) and int(pid) in bad_pids:
            key = f"{e.type} with {bad_pids[int(pid)]}"
            dropped[key] = dropped.get(key, 0) + 1
            continue
        by_type.setdefault(e.type, []).append((eid, e))
    pelas = props.get("PELAS")
    pelas_k = {} if pelas is None else dict(zip(pelas.ids.tolist(), pelas["k_deck"].tolist()))
    L = us.length_m
    elements: dict[str, Table] = {}
    elements.update(_bar_elements(by_type, grids, L))
    elements.update(_rod_elements(by_type, grids, us))
    elements.update(_spring_elements(by_type, grids, pelas_k, us))
    elements.update(_bush_elements(by_type, grids))
    elements.update(_shell_elements(by_type, grids, L))
    elements.update(_solid_elements(by_type, grids))
    elements.update(_mass_elements(bdf, grids, us))
    pmass = props.get("PMASS")
    pmass_m = {} if pmass is None else dict(zip(pmass.ids.tolist(), pmass["m_deck"].tolist()))
    elements.update(_scalar_mass_elements(bdf, grids, pmass_m, us))
    return elements, dropped


def _bar_elements(by_type: dict, grids: GridSet, L: float) -> dict[str, Table]:
    """CBAR/CBEAM: orientation "v" and offsets "wa"/"wb" in basic (m), pin flags (n, 12)."""
    elements = {}
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
            grids.require(card, eid, (ga, gb, e.g0))
            nodes[i] = ga, gb
            pid[i] = int(e.pid)
            try:
                pins[i] = [component_mask(e.pa), component_mask(e.pb)]
            except ValueError:
                raise ModelError(f"{grids.where}: {card} {eid}: bad pin flags PA={e.pa!r} PB={e.pb!r}") from None
            offt = getattr(e, "offt", None) or "GGG"
            if not isinstance(offt, str):
                offt = "GGG"
            if "O" in offt[1:]:
                raise ModelError(f"{grids.where}: {card} {eid}: OFFT {offt} (offsets in element system) is not supported")
            if e.g0 not in (None, 0):
                v[i] = grids.position(e.g0) - grids.position(ga)
            else:
                x = np.asarray(e.x, dtype=float)
                v[i] = x if offt[0] == "B" else grids.cd_rotation(ga) @ x
            w_a = np.asarray(e.wa if e.wa is not None else np.zeros(3), float) * L
            w_b = np.asarray(e.wb if e.wb is not None else np.zeros(3), float) * L
            wa[i] = w_a if offt[1] == "B" else grids.cd_rotation(ga) @ w_a
            wb[i] = w_b if offt[2] == "B" else grids.cd_rotation(gb) @ w_b
        elements[card] = Table(
            card,
            np.array([r[0] for r in rows], np.int64),
            {"pid": pid, "nodes": nodes, "v": v, "wa": wa, "wb": wb, "pins": pins.reshape(n, 12)},
        )

    return elements


def _rod_elements(by_type: dict, grids: GridSet, us: UnitSystem) -> dict[str, Table]:
    """CROD (PROD property) and CONROD (section on the element card)."""
    L = us.length_m
    elements = {}
    for card in ("CROD", "CTUBE"):  # CTUBE: a rod of its PTUBE's tube section
        rows = by_type.get(card, [])
        if not rows:
            continue
        for eid, e in rows:
            grids.require(card, eid, e.nodes)
        elements[card] = Table(
            card,
            np.array([r[0] for r in rows], np.int64),
            {"pid": np.array([int(e.pid) for _, e in rows], np.int64), "nodes": np.array([e.nodes for _, e in rows], np.int64)},
        )
    if "CONROD" in by_type:
        rows = by_type["CONROD"]
        for eid, e in rows:
            grids.require("CONROD", eid, e.nodes)
        elements["CONROD"] = Table(
            "CONROD",
            np.array([r[0] for r in rows], np.int64),
            {
                "pid": np.full(len(rows), -1, np.int64),
                "nodes": np.array([e.nodes for _, e in rows], np.int64),
                "mid": np.array([int(e.mid) for _, e in rows], np.int64),
                "A": np.array([field_float(e.A, 0.0) for _, e in rows]) * L**2,
                "J": np.array([field_float(e.j, 0.0) for _, e in rows]) * L**4,
                "nsm": np.array([field_float(e.nsm, 0.0) for _, e in rows]) * us.mass_kg / L,
            },
        )
    return elements


def _scalar_table(card: str, rows: list, grids: GridSet, by_pid: dict, pcard: str, own, field: str,
                  factor) -> Table:
    """CELAS/CMASS rows as a table: the two grids (0: ground), their components (1..6, in CD), the
    property id (-1 on the element's own value) and ``field``: the deck value (``by_pid[pid]``, or
    ``own(e)``) times ``factor(rot)``, ``rot`` the rotational flags of the components held."""
    n = len(rows)
    nodes = np.zeros((n, 2), np.int64)
    c12 = np.zeros((n, 2), np.int8)
    val = np.zeros(n)
    pid = np.full(n, -1, np.int64)
    for i, (eid, e) in enumerate(rows):
        g = [0 if x is None else int(x) for x in e.nodes]
        if not any(g):
            raise ModelError(f"{grids.where}: {card} {eid} names no grid")
        grids.require(card, eid, [x for x in g if x])
        c = [int(e.c1 or 0), int(e.c2 or 0)]
        for j in range(2):
            if g[j] and not 1 <= c[j] <= 6:
                raise ModelError(f"{grids.where}: {card} {eid}: component C{j + 1}={c[j]} must be 1..6 for a GRID")
        nodes[i] = g
        c12[i] = c
        if pcard:
            pid[i] = int(e.pid)
            if pid[i] not in by_pid:
                raise ModelError(f"{grids.where}: {card} {eid} references undefined {pcard} {pid[i]}")
            vd = by_pid[pid[i]]
        else:
            vd = own(e)
        val[i] = vd * factor([cc >= 4 for cc, gg in zip(c, g) if gg])
    return Table(card, np.array([r[0] for r in rows], np.int64), {"pid": pid, "nodes": nodes, "components": c12,
                                                                   field: val})


def _spring_elements(by_type: dict, grids: GridSet, pelas_k: dict, us: UnitSystem) -> dict[str, Table]:
    """CELAS1/CELAS2: rate "k" in SI for the pair of components it joins (N/m, N m/rad or N/rad)."""
    L, F = us.length_m, us.force_n

    def factor(rot):
        return F * L if all(rot) else F / L if not any(rot) else F

    elements = {}
    for card in ("CELAS1", "CELAS2"):
        rows = by_type.get(card, [])
        if rows:
            elements[card] = _scalar_table(card, rows, grids, pelas_k, "PELAS" if card == "CELAS1" else "",
                                           lambda e: field_float(e.k, 0.0), "k", factor)
    return elements


def _bush_elements(by_type: dict, grids: GridSet) -> dict[str, Table]:
    """CBUSH: element axes (n, 3, 3) rows in basic, spring location "s"."""
    elements = {}
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
            grids.require("CBUSH", eid, [ga] + ([gb] if gb else []))
            nodes[i] = ga, gb
            pid[i] = int(e.pid)
            s[i] = 0.5 if e.s is None else float(e.s)
            if getattr(e, "ocid", -1) not in (None, -1) or any(x is not None for x in (getattr(e, "si", None) or [])):
                raise ModelError(f"{grids.where}: CBUSH {eid}: OCID/S1-S3 spring offsets are not supported")
            xa = grids.position(ga)
            xb = grids.position(gb) if gb else xa
            if e.cid is not None and int(e.cid) >= 0:
                cid = int(e.cid)
                if cid not in grids.coords:
                    raise ModelError(f"{grids.where}: CBUSH {eid} references undefined coordinate system {cid}")
                axes[i] = grids.coords[cid].local_axes(xa[None])[0].T
            else:
                ex = xb - xa
                if np.linalg.norm(ex) <= 1e-12 * max(1.0, np.linalg.norm(xa)):
                    raise ModelError(f"{grids.where}: CBUSH {eid}: coincident grids need a CID")
                ex = ex / np.linalg.norm(ex)
                if e.g0 not in (None, 0):
                    vv = grids.position(e.g0) - xa
                elif e.x is not None and e.x[0] is not None:
                    vv = grids.cd_rotation(ga) @ np.asarray(e.x, float)
                else:
                    raise ModelError(f"{grids.where}: CBUSH {eid}: no orientation (X/G0 or CID)")
                ez = np.cross(ex, vv)
                if np.linalg.norm(ez) == 0:
                    raise ModelError(f"{grids.where}: CBUSH {eid}: orientation vector is parallel to the axis")
                ez /= np.linalg.norm(ez)
                axes[i] = np.vstack([ex, np.cross(ez, ex), ez])
        elements["CBUSH"] = Table("CBUSH", np.array([r[0] for r in rows], np.int64), {"pid": pid, "nodes": nodes, "axes": axes, "s": s})
    return elements


def _shell_elements(by_type: dict, grids: GridSet, L: float) -> dict[str, Table]:
    """CQUAD4/CTRIA3: corner thicknesses "t" (NaN = from the property), offsets, THETA or MCID."""
    elements = {}
    for card, nn in (("CQUAD4", 4), ("CTRIA3", 3)):
        rows = by_type.get(card, [])
        if not rows:
            continue
        nodes = np.zeros((len(rows), nn), np.int64)
        tn = np.full((len(rows), nn), np.nan)
        zoffs = np.zeros(len(rows))
        theta = np.zeros(len(rows))
        mcid = np.full(len(rows), -1, np.int64)
        if _shells_fast(rows, nn, grids.ids, nodes, tn, zoffs, theta, mcid, L):
            rows_left = []
        else:  # something to report: element by element, in id order
            rows_left = rows
        for i, (eid, e) in enumerate(rows_left):
            grids.require(card, eid, e.nodes)
            if any(x is None for x in e.nodes):
                raise ModelError(f"{grids.where}: {card} {eid}: missing grid")
            nodes[i] = e.nodes
            if getattr(e, "tflag", 0) not in (0, None):
                raise ModelError(f"{grids.where}: {card} {eid}: TFLAG=1 (relative thicknesses) is not supported")
            tt = [getattr(e, f"T{j + 1}", None) for j in range(nn)]
            tn[i] = [np.nan if x is None or x == -1.0 else float(x) * L for x in tt]
            zoffs[i] = field_float(getattr(e, "zoffset", 0.0), 0.0) * L
            tm = getattr(e, "theta_mcid", 0.0)
            if isinstance(tm, (int, np.integer)) and not isinstance(tm, bool):
                mcid[i] = int(tm)
            else:
                theta[i] = field_float(tm, 0.0)
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

    return elements


def _shells_fast(rows, nn, nids, nodes, tn, zoffs, theta, mcid, L) -> bool:
    """Fill the CQUAD4/CTRIA3 arrays at once; False (nothing filled) if any element needs a closer look.

    Gives exactly what the element-by-element loop of :func:`_shell_elements` gives
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
    zoffs[:] = [field_float(getattr(e, "zoffset", 0.0), 0.0) * L for e in elems]
    for i, e in enumerate(elems):
        tm = getattr(e, "theta_mcid", 0.0)
        if isinstance(tm, (int, np.integer)) and not isinstance(tm, bool):
            mcid[i] = int(tm)
        else:
            theta[i] = field_float(tm, 0.0)
    return True



def _solid_elements(by_type: dict, grids: GridSet) -> dict[str, Table]:
    """CTETRA/CPYRAM/CPENTA/CHEXA, split by node count when midside nodes are present."""
    elements = {}
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
                raise ModelError(f"{grids.where}: {card} {eid}: partial midside nodes are not supported")
            grids.require(card, eid, ns)
            groups.setdefault(len(ns), []).append((eid, e, ns))
        for nn, grp in sorted(groups.items()):
            name = f"{card}{nn}" if len(groups) > 1 or nn not in (4, 5, 6, 8) else card
            elements[name] = Table(
                card,
                np.array([g[0] for g in grp], np.int64),
                {"pid": np.array([int(g[1].pid) for g in grp], np.int64), "nodes": np.array([g[2] for g in grp], np.int64)},
            )
    return elements


def _mass_elements(bdf, grids: GridSet, us: UnitSystem) -> dict[str, Table]:
    """CONM2: mass (kg), offset (m) and inertia about the offset point (kg m^2), in basic;
    CONM1: the 6 x 6 mass matrix "mass6" in basic at the grid (SI)."""
    L = us.length_m
    elements = {}
    rows = [(eid, m) for eid, m in sorted(bdf.masses.items()) if m.type == "CONM2"]
    if rows:
        n = len(rows)
        grid = np.zeros(n, np.int64)
        mass = np.zeros(n)
        off = np.zeros((n, 3))
        inertia = np.zeros((n, 3, 3))
        for i, (eid, m) in enumerate(rows):
            grids.require("CONM2", eid, [m.nid])
            grid[i] = int(m.nid)
            mass[i] = field_float(m.mass, 0.0) * us.mass_kg
            cid = int(m.cid if m.cid is not None else 0)
            xg = grids.position(grid[i])
            X = np.asarray(m.X, float) * L
            if cid == -1:
                off[i] = X - xg
                R = np.eye(3)
            else:
                if cid not in grids.coords:
                    raise ModelError(f"{grids.where}: CONM2 {eid} references undefined coordinate system {cid}")
                R = grids.coords[cid].local_axes(xg[None])[0]
                off[i] = R @ X
            I11, I21, I22, I31, I32, I33 = [float(x) for x in m.I]
            J = np.array([[I11, -I21, -I31], [-I21, I22, -I32], [-I31, -I32, I33]]) * us.mass_kg * L**2
            inertia[i] = R @ J @ R.T
        elements["CONM2"] = Table(
            "CONM2",
            np.array([r[0] for r in rows], np.int64),
            {"pid": np.full(n, -1, np.int64), "nodes": grid[:, None], "mass": mass, "offset": off, "inertia": inertia},
        )
    rows = [(eid, m) for eid, m in sorted(bdf.masses.items()) if m.type == "CONM1"]
    if rows:
        # the 6 x 6 matrix in the CID system (default basic) at the grid; to basic, SI by block:
        # translation mass, translation-rotation mass x length, rotation mass x length^2
        unit = np.full((6, 6), us.mass_kg * L)
        unit[:3, :3] = us.mass_kg
        unit[3:, 3:] = us.mass_kg * L**2
        n = len(rows)
        grid = np.zeros(n, np.int64)
        m6 = np.zeros((n, 6, 6))
        for i, (eid, m) in enumerate(rows):
            grids.require("CONM1", eid, [m.nid])
            grid[i] = int(m.nid)
            mm = np.asarray(m.mass_matrix, float)
            if mm.shape != (6, 6) or not np.all(np.isfinite(mm)):
                raise ModelError(f"{grids.where}: CONM1 {eid}: mass matrix is not a finite 6 x 6 matrix")
            mm = np.tril(mm) + np.tril(mm, -1).T  # Mij are the lower triangle (i >= j)
            cid = int(m.cid or 0)
            if cid not in grids.coords and cid != 0:
                raise ModelError(f"{grids.where}: CONM1 {eid} references undefined coordinate system {cid}")
            R = np.eye(3) if cid == 0 else grids.coords[cid].local_axes(grids.position(grid[i])[None])[0]
            Rb = np.zeros((6, 6))
            Rb[:3, :3] = Rb[3:, 3:] = R
            m6[i] = Rb @ (mm * unit) @ Rb.T
            if np.any(np.linalg.eigvalsh(m6[i]) < -1e-9 * max(1.0, float(np.abs(m6[i]).max()))):
                raise ModelError(f"{grids.where}: CONM1 {eid}: mass matrix is not positive semi-definite")
        elements["CONM1"] = Table("CONM1", np.array([r[0] for r in rows], np.int64),
                                  {"pid": np.full(n, -1, np.int64), "nodes": grid[:, None], "mass6": m6})

    return elements


def _scalar_mass_elements(bdf, grids: GridSet, pmass_m: dict, us: UnitSystem) -> dict[str, Table]:
    """CMASS1/CMASS2: scalar mass "m" in SI for the pair of components it joins (kg, kg m^2 or kg m).

    As CELAS1/CELAS2: components in the grid's displacement system (CD); a
    blank second grid is a mass to ground (only the first DOF's diagonal).
    """
    L, Mu = us.length_m, us.mass_kg

    def factor(rot):
        return Mu * (L**2 if all(rot) else 1.0 if not any(rot) else L)

    elements = {}
    for card in ("CMASS1", "CMASS2"):
        rows = [(eid, e) for eid, e in sorted(bdf.masses.items()) if e.type == card]
        if rows:
            elements[card] = _scalar_table(card, rows, grids, pmass_m, "PMASS" if card == "CMASS1" else "",
                                           lambda e: field_float(e.mass, 0.0), "m", factor)
    return elements


def read_rigid_elements(bdf, grids: GridSet, ignored: dict[str, int]) -> tuple[tuple[RBE2, ...], tuple[RBE3, ...]]:
    """RBE2 and RBE3 elements; other rigid types raise unless ``ignored`` names them.

    Raises
    ------
    ModelError
        Undefined grids, bad CM codes, RBE3 with UM, unsupported rigid types.
    """
    rbe2, rbe3 = [], []
    for eid, r in sorted(bdf.rigid_elements.items()):
        if r.type == "RBE2":
            gm = tuple(int(g) for g in r.Gmi)
            grids.require("RBE2", eid, (r.gn,) + gm)
            try:
                comps = component_string(r.cm)
            except ValueError:
                raise ModelError(f"{grids.where}: RBE2 {eid}: bad CM {r.cm!r}") from None
            rbe2.append(RBE2(int(eid), int(r.gn), comps, gm))
        elif r.type == "RBE3":
            if r.Gmi:
                raise ModelError(f"{grids.where}: RBE3 {eid}: UM (extra dependent DOF) is not supported")
            groups = []
            for w, c, gs in zip(r.weights, r.comps, r.Gijs):
                gs = tuple(int(g) for g in gs)
                grids.require("RBE3", eid, gs)
                groups.append((float(w), component_string(c), gs))
            grids.require("RBE3", eid, (r.refgrid,))
            rbe3.append(RBE3(int(eid), int(r.refgrid), component_string(r.refc), tuple(groups)))
        elif r.type not in ignored:
            raise ModelError(f"{grids.where}: rigid element {r.type} {eid} is not supported")

    return tuple(rbe2), tuple(rbe3)
