"""MAT1/MAT8 materials and PBAR/PBARL/PBEAM/PBEAML/PROD/PSHELL/PCOMP/PSOLID/PELAS/PMASS/PBUSH properties as SI tables."""

from __future__ import annotations

import numpy as np

from femodel._model import ModelError, Table
from femodel._reader_fields import field_float
from femodel._units import UnitSystem

_SHEAR_FACTOR_PBARL = {
    # Shear factors used for PBARL/PBEAML sections (Timoshenko).  ROD 0.9 is
    # confirmed against MSC Nastran (beam_modes reference); the others are the
    # usual textbook values and are not confirmed against Nastran output.
    "ROD": 0.9,
    "BAR": 5.0 / 6.0,
    "TUBE": 0.5,
}


def read_materials(bdf, us: UnitSystem, where: str) -> dict[str, Table]:
    """MAT1 (always present, possibly empty) and MAT8 tables in SI.

    MAT1 fields: E, G (Pa), NU, RHO (kg/m^3), g_follows_e (G was derived
    from E and NU, so a parametric E scales G too).  MAT8 fields: E1, E2,
    G12, G1Z, G2Z (Pa; blank transverse shear moduli are ``inf``), NU12, RHO.

    Raises
    ------
    ModelError
        MAT1 with E and G both blank, E not positive or G negative.
    """
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

    return mats


def _ptube_table(rows, us: UnitSystem, where: str) -> Table:
    """PTUBE: the tube's area A = pi/4 (OD^2 - ID^2) and torsion constant J = pi/32 (OD^4 - ID^4), ID = OD - 2 T
    (T blank: a solid rod), in SI as PROD's fields; a tapered tube (OD2 != OD) is refused."""
    L = us.length_m
    A, J, nsm, mid = [], [], [], []
    for pid, p in rows:
        od, t = field_float(p.OD1, 0.0), p.t
        od2 = p.OD2 if p.OD2 is not None else od
        if not od > 0:
            raise ModelError(f"{where}: PTUBE {pid}: outer diameter {od!r} must be positive")
        if abs(float(od2) - od) > 1e-12 * od:
            raise ModelError(f"{where}: PTUBE {pid}: a tapered tube (OD2 {od2!r} != OD {od!r}) is not supported")
        t = od / 2.0 if t is None or t == 0 else float(t)
        if not 0 < t <= od / 2.0:
            raise ModelError(f"{where}: PTUBE {pid}: wall thickness {t!r} must be in (0, OD/2]")
        di = od - 2.0 * t
        A.append(np.pi / 4.0 * (od**2 - di**2))
        J.append(np.pi / 32.0 * (od**4 - di**4))
        nsm.append(field_float(p.nsm, 0.0))
        mid.append(int(p.mid))
    return Table("PTUBE", np.array([r[0] for r in rows], np.int64),
                 {"mid": np.array(mid, np.int64), "A": np.array(A) * L**2, "J": np.array(J) * L**4,
                  "nsm": np.array(nsm) * us.mass_kg / L})


def read_properties(bdf, mats: dict[str, Table], us: UnitSystem, where: str) -> dict[str, Table]:
    """Property tables in SI, keyed by card ("PBAR" holds every bar/beam section type).

    Parameters
    ----------
    bdf : pyNastran BDF
    mats : dict
        Output of :func:`read_materials` (PCOMP plies are resolved against it).
    us : UnitSystem
    where : str
        Deck path for messages.

    Raises
    ------
    ModelError
        Sections that cannot be evaluated, unsymmetric sections, PBUSH without
        a K line, PCOMP plies referencing undefined materials.
    """
    L = us.length_m
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
                "A": np.array([field_float(r[1].A, 0.0) for r in rows]) * L**2,
                "J": np.array([field_float(r[1].j, 0.0) for r in rows]) * L**4,
                "nsm": np.array([field_float(r[1].nsm, 0.0) for r in rows]) * us.mass_kg / L,
            },
        )
    if "PTUBE" in props_by_type:
        props["PTUBE"] = _ptube_table(props_by_type["PTUBE"], us, where)
    if "PSHELL" in props_by_type:
        rows = props_by_type["PSHELL"]

        def mid_or0(x):
            return int(x) if x not in (None, 0) else 0

        t = np.array([field_float(r[1].t) for r in rows])
        props["PSHELL"] = Table(
            "PSHELL",
            np.array([r[0] for r in rows], np.int64),
            {
                "mid1": np.array([mid_or0(r[1].mid1) for r in rows], np.int64),
                "t": t * L,
                "mid2": np.array([mid_or0(r[1].mid2) for r in rows], np.int64),
                "bending_ratio": np.array([field_float(r[1].twelveIt3, 1.0) for r in rows]),
                "mid3": np.array([mid_or0(r[1].mid3) for r in rows], np.int64),
                "ts_t": np.array([field_float(r[1].tst, 0.833333) for r in rows]),
                "nsm": np.array([field_float(r[1].nsm, 0.0) for r in rows]) * us.mass_kg / L**2,
                "z1": np.array([field_float(r[1].z1) for r in rows]) * L,
                "z2": np.array([field_float(r[1].z2) for r in rows]) * L,
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
    if "PELAS" in props_by_type:
        rows = props_by_type["PELAS"]
        props["PELAS"] = Table(
            "PELAS",
            np.array([r[0] for r in rows], np.int64),
            {"k_deck": np.array([field_float(r[1].k, 0.0) for r in rows]), "ge": np.array([field_float(r[1].ge, 0.0) for r in rows])},
        )
    if getattr(bdf, "properties_mass", None):
        rows = sorted((pid, p) for pid, p in bdf.properties_mass.items() if p.type == "PMASS")
        if rows:  # the scalar mass of CMASS1, in deck units (the components it joins fix its SI unit)
            props["PMASS"] = Table("PMASS", np.array([r[0] for r in rows], np.int64),
                                   {"m_deck": np.array([field_float(r[1].mass, 0.0) for r in rows])})
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

    return props


def _pcomp_table(rows, mats, us: UnitSystem, where: str) -> Table:
    """PCOMP laminates resolved to shell constitutive matrices (classical lamination), SI.

    Fields: dm, dmb, db (n, 3, 3) in the material axes of THETA = 0, ds (n, 2, 2)
    (``inf`` where every ply is shear-rigid), mu (n,) kg/m^2, t (n,) m, mids (n, most plies)
    the plies' material ids (-1 past a laminate's last ply).
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
    ply_mids = []
    for i, (pid, p) in enumerate(rows):
        try:
            t = np.array(p.get_thicknesses(), float) * L
            th = np.array(p.get_thetas(), float)
            mids = [int(x) for x in p.get_material_ids()]
        except (AttributeError, TypeError, ValueError, IndexError) as exc:
            raise ModelError(f"{where}: PCOMP {pid}: cannot read the plies ({exc})") from None
        ply_mids.append(mids)
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
        mu[i] = float(np.sum(rho * t)) + field_float(p.nsm, 0.0) * us.mass_kg / L**2
        tt[i] = t.sum()
    mid_table = np.full((n, max((len(m) for m in ply_mids), default=0)), -1, np.int64)
    for i, m in enumerate(ply_mids):
        mid_table[i, :len(m)] = m
    return Table(
        "PCOMP",
        np.array([r[0] for r in rows], np.int64),
        {"dm": dm, "dmb": dmb, "db": db, "ds": ds, "mu": mu, "t": tt, "mids": mid_table},
    )


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
    """A, I1, I2, I12, J (k = 0..4) of a PBARL-type section.

    I1 is the moment for bending in plane 1 (about the element z axis, DIM
    "height" along y), as Nastran's beam library draws the sections. Computed
    here: T2, I and TUBE2 (pyNastran 1.4 has no I1/I2 for them), and the
    torsion constant J of BAR and BOX, for which pyNastran returns 0 (BAR) or
    the polar moment I1 + I2 (BOX: 38 % too stiff for a 40 x 30 x 2.5 box).
    The formulas are the standard ones (Roark for the rectangle, Bredt for the
    closed thin-walled box, sum of b t^3 / 3 over the walls of an open section);
    the BAR and BOX ones are those of Nastran's beam library. ROD and TUBE take
    pyNastran's (exact for circular sections); other types that pyNastran cannot
    evaluate are refused by the caller, naming the property.
    """
    dim = [float(x) for x in sec.dim] if btype in ("BAR", "BOX", "I", "T2", "TUBE2") else None
    if btype == "BAR":
        w, h = dim[:2]  # DIM1 along z, DIM2 along y: I1 = DIM1 DIM2^3 / 12
        a, b = max(w, h), min(w, h)
        j = a * b**3 * (1.0 / 3.0 - 0.21 * (b / a) * (1.0 - b**4 / (12.0 * a**4)))
        return (w * h, w * h**3 / 12.0, h * w**3 / 12.0, 0.0, j)[k]
    if btype == "BOX":
        w, h, t1, t2 = dim[:4]  # width, height, top/bottom wall, side walls
        if not (w > 2 * t2 and h > 2 * t1 and t1 > 0 and t2 > 0):
            raise ModelError(f"BOX dimensions {dim[:4]}: need DIM1 > 2 DIM4, DIM2 > 2 DIM3, walls > 0")
        wi, hi = w - 2 * t2, h - 2 * t1
        j = 2 * t1 * t2 * (w - t2) ** 2 * (h - t1) ** 2 / (w * t2 + h * t1 - t2**2 - t1**2)
        return (w * h - wi * hi, (w * h**3 - wi * hi**3) / 12.0, (h * w**3 - hi * wi**3) / 12.0, 0.0, j)[k]
    if btype == "TUBE2":
        ro, t = dim[:2]
        ri = ro - t
        if not 0 <= ri < ro:
            raise ModelError(f"TUBE2 dimensions {dim[:2]}: need 0 < DIM2 <= DIM1")
        i = np.pi * (ro**4 - ri**4) / 4.0
        return (np.pi * (ro**2 - ri**2), i, i, 0.0, 2.0 * i)[k]
    if btype == "I":
        # DIM1 total height, DIM2/DIM3 bottom/top flange width, DIM4 web, DIM5/DIM6 bottom/top flange thickness
        h, b1, b2, tw, t1, t2 = dim[:6]
        hw = h - t1 - t2
        if not (hw > 0 and min(b1, b2, tw, t1, t2) > 0):
            raise ModelError(f"I dimensions {dim[:6]}: need DIM1 > DIM5 + DIM6 and all dimensions > 0")
        parts = [(b1 * t1, 0.5 * t1, b1 * t1**3 / 12.0, t1 * b1**3 / 12.0),
                 (tw * hw, t1 + 0.5 * hw, tw * hw**3 / 12.0, hw * tw**3 / 12.0),
                 (b2 * t2, h - 0.5 * t2, b2 * t2**3 / 12.0, t2 * b2**3 / 12.0)]
        area = sum(a for a, *_ in parts)
        yc = sum(a * y for a, y, *_ in parts) / area  # centroid height (the flanges may differ)
        i1 = sum(i + a * (y - yc) ** 2 for a, y, i, _ in parts)
        i2 = sum(i for *_, i in parts)
        j = (b1 * t1**3 + b2 * t2**3 + (h - 0.5 * (t1 + t2)) * tw**3) / 3.0  # wall centre lines
        return (area, i1, i2, 0.0, j)[k]
    if btype == "T2":
        # DIM1 flange width, DIM2 total height, DIM3 flange thickness, DIM4 web thickness
        b, h, tf, tw = dim[:4]
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
