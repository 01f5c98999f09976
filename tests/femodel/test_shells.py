"""Shell kernels against real Nastran eigenvalues (femap_exhaust, dakota_cylinder).

The decks are driven through a small, independent reference assembly built in
this file on top of pyNastran (GRID/CD frames, PSHELL/PCOMP of MAT1 plies,
solids, CELAS2, CBUSH K, CONM2, RBE2, SPC/SPC1, WTMASS, COUPMASS, K6ROT): it
exercises only the element kernels, independently of the project's reader and
assembler, so a frequency error here is an element-formulation error.
"""

from __future__ import annotations

import json
from functools import lru_cache

import numpy as np
import pytest
import scipy.sparse as sp

from femodel import shell_mass, shell_stiffness, solid_mass, solid_stiffness
from tests.conftest import reference_path

# --------------------------------------------------------------------------- helpers


def _plane_stress(e, nu):
    return e / (1 - nu * nu) * np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])


def _iso3d(e, nu):
    lam = e * nu / ((1 + nu) * (1 - 2 * nu))
    g = e / (2 * (1 + nu))
    c = np.zeros((6, 6))
    c[:3, :3] = lam
    c[np.arange(3), np.arange(3)] += 2 * g
    c[np.arange(3, 6), np.arange(3, 6)] = g
    return c


def _mat1(mat):
    e, g, nu = mat.e, mat.g, mat.nu
    if e is None or e == 0:
        e = 2 * g * (1 + nu)
    if nu is None:
        nu = e / (2 * g) - 1
    if g is None or g == 0:
        g = e / (2 * (1 + nu))
    return e, g, nu, mat.rho


def _cd_axes(model, nid):
    """(3, 3): rows are the basic directions of a grid's components 1, 2, 3."""
    node = model.nodes[nid]
    cd = node.cd
    if cd == 0:
        return np.eye(3)
    coord = model.coords[cd]
    beta = coord.beta()
    if coord.type.endswith("R"):
        return beta
    loc = beta @ (node.get_position() - coord.origin)
    if coord.type.endswith("C"):
        th = np.arctan2(loc[1], loc[0])
        axes = np.array([[np.cos(th), np.sin(th), 0], [-np.sin(th), np.cos(th), 0], [0, 0, 1]])
    else:
        r = np.linalg.norm(loc)
        th = np.arccos(loc[2] / r)
        ph = np.arctan2(loc[1], loc[0])
        axes = np.array([
            [np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)],
            [np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)],
            [-np.sin(ph), np.cos(ph), 0.0],
        ])
    return axes @ beta


def _shell_section(model, prop):
    """dm, db, ds [model units], mass per area and coupling dmb, for PSHELL or PCOMP (MAT1/MAT8 plies)."""
    if prop.type == "PSHELL":
        t = prop.t
        e1, g1, nu1, rho = _mat1(model.materials[prop.mid1])
        dm = _plane_stress(e1, nu1) * t
        mu = rho * t + prop.nsm
        if prop.mid2:
            e2, _, nu2, _ = _mat1(model.materials[prop.mid2])
            db = _plane_stress(e2, nu2) * prop.twelveIt3 * t ** 3 / 12
        else:
            db = np.zeros((3, 3))
        if prop.mid3:
            _, g3, _, _ = _mat1(model.materials[prop.mid3])
            ds = np.eye(2) * g3 * prop.tst * t
        else:
            ds = np.eye(2) * 1e6 * (db[0, 0] + db[1, 1]) / t ** 2
        return dm, db, ds, mu, np.zeros((3, 3))
    if prop.type == "PCOMP":
        from femodel import laminate_abd, orthotropic_q

        if prop.lam not in (None, "", "BLANK"):
            raise ValueError(f"helper: PCOMP LAM={prop.lam}")
        q, g, rho = [], [], []
        for mid in prop.mids:
            mat = model.materials[mid]
            if mat.type == "MAT1":
                e, gm, nu, r = _mat1(mat)
                # in-plane from E and NU (reproduces Nastran's KELM); G for transverse shear
                q.append(_plane_stress(e, nu))
                g.append([gm, gm])
            elif mat.type == "MAT8":
                q.append(orthotropic_q(mat.e11, mat.e22, mat.nu12, mat.g12))
                g.append([mat.g1z or np.inf, mat.g2z or np.inf])
                r = mat.rho
            else:
                raise ValueError(mat.type)
            rho.append(r)
        t = np.asarray(prop.thicknesses, dtype=float)
        dm, dmb, db, ds = laminate_abd(t, prop.thetas, q, g_ply=g, z0=prop.z0)
        mu = float(np.sum(np.asarray(rho) * t)) + prop.nsm
        return dm, db, ds, mu, dmb
    raise ValueError(prop.type)


def _bar_section(model, prop):
    """A, I1, I2, J, E, G, mass per length of a PBAR or a PBARL T2 (thin-walled J)."""
    e, g, _, rho = _mat1(prop.mid_ref)
    if prop.type == "PBAR":
        return prop.A, prop.i1, prop.i2, prop.j, e, g, rho * prop.A + prop.nsm
    if prop.type == "PBARL" and prop.beam_type == "T2":
        # flange width, height, flange and web thickness; the height runs along the element y
        # axis (plane 1): with it bwb's frequencies agree, with the height along z modes 3-13
        # come out up to 11 % soft
        b, h, tf, tw = prop.dim
        hw = h - tf
        area = b * tf + hw * tw
        yc = (b * tf * tf / 2 + hw * tw * (tf + hw / 2)) / area
        i1 = b * tf ** 3 / 12 + b * tf * (tf / 2 - yc) ** 2 + tw * hw ** 3 / 12 + hw * tw * (tf + hw / 2 - yc) ** 2
        i2 = tf * b ** 3 / 12 + hw * tw ** 3 / 12
        j = (b * tf ** 3 + hw * tw ** 3) / 3
        return area, i1, i2, j, e, g, rho * area + prop.nsm
    raise ValueError(f"helper: {prop.type} {getattr(prop, 'beam_type', '')}")


class MiniModel:
    """Basic-frame 6-DOF-per-grid assembly used to validate the kernels."""

    def __init__(self, path, shell_mass_fn=None):
        from pyNastran.bdf.bdf import read_bdf

        model = read_bdf(str(path), xref=True, debug=None)
        self.model = model
        nids = sorted(model.nodes)
        self.index = {nid: i for i, nid in enumerate(nids)}
        self.xyz = np.array([model.nodes[n].get_position() for n in nids])
        ndof = 6 * len(nids)
        self.ndof = ndof
        params = model.params
        self.wtmass = params["WTMASS"].values[0] if "WTMASS" in params else 1.0
        self.coupled = "COUPMASS" in params and params["COUPMASS"].values[0] > 0
        self.k6rot = params["K6ROT"].values[0] if "K6ROT" in params else 100.0
        rows, cols, kv, mv = [], [], [], []

        def add(dofs, k=None, m=None):
            r = np.repeat(dofs, dofs.shape[1], axis=1).reshape(dofs.shape[0], -1)
            c = np.tile(dofs, (1, dofs.shape[1]))
            rows.append(r.ravel())
            cols.append(c.ravel())
            size = r.size
            kv.append(np.zeros(size) if k is None else k.reshape(-1))
            mv.append(np.zeros(size) if m is None else m.reshape(-1))

        groups = {}
        for eid, elem in model.elements.items():
            groups.setdefault((elem.type, len(elem.node_ids)), []).append(elem)
        self.counts = {k: len(v) for k, v in groups.items()}
        for (etype, nn), elems in groups.items():
            if etype in ("CQUAD4", "CTRIA3"):
                sec = [_shell_section(model, e.pid_ref) for e in elems]
                for e in elems:
                    if getattr(e, "zoffset", 0.0) not in (0.0, None):
                        raise ValueError("ZOFFS not handled by the helper")
                xyz = np.array([[self.xyz[self.index[n]] for n in e.node_ids] for e in elems])
                dm = np.array([s[0] for s in sec])
                db = np.array([s[1] for s in sec])
                ds = np.array([s[2] for s in sec])
                mu = np.array([s[3] for s in sec]) * self.wtmass
                dmb = np.array([sc[4] for sc in sec])
                dmb = dmb if np.any(dmb != 0) else None
                ks = shell_stiffness(xyz, dm, db, ds, self.k6rot, dmb=dmb)
                k = sum(ks.values())
                m = shell_mass(xyz, mu, self.coupled)
                dofs = np.array([[6 * self.index[n] + d for n in e.node_ids for d in range(6)] for e in elems])
                add(dofs, k, m)
            elif etype in ("CTETRA", "CPYRAM", "CPENTA", "CHEXA"):
                mats = [_mat1(e.pid_ref.mid_ref) for e in elems]
                xyz = np.array([[self.xyz[self.index[n]] for n in e.node_ids] for e in elems])
                c = np.array([_iso3d(mt[0], mt[2]) for mt in mats])
                rho = np.array([mt[3] for mt in mats]) * self.wtmass
                k = solid_stiffness(xyz, c)
                m = solid_mass(xyz, rho, self.coupled)
                dofs = np.array([[6 * self.index[n] + d for n in e.node_ids for d in range(3)] for e in elems])
                add(dofs, k, m)
            elif etype == "CBAR":
                from femodel._elements_line import beam_matrices

                secs = [_bar_section(model, e.pid_ref) for e in elems]
                for e in elems:
                    if e.offt != "GGG" or e.g0 or any(model.nodes[g].cd for g in e.node_ids):
                        raise ValueError("helper: CBAR with OFFT != GGG, G0 or CD")
                xa = np.array([self.xyz[self.index[e.ga]] for e in elems])
                xb = np.array([self.xyz[self.index[e.gb]] for e in elems])
                v = np.array([e.x for e in elems], dtype=float)
                wa = np.array([e.wa for e in elems], dtype=float)
                wb = np.array([e.wb for e in elems], dtype=float)
                a_, i1, i2, j_, e_, g_, mu_ = (np.array(col, dtype=float) for col in zip(*secs))
                nan = np.full(len(elems), np.nan)
                out = beam_matrices(xa, xb, v, wa, wb, a_, i1, i2, j_, e_, g_, nan, nan,
                                    coupled=self.coupled, torsion_inertia=False)
                k = e_[:, None, None] * out["stiffness_E"] + g_[:, None, None] * out["stiffness_G"]
                m = (mu_ * self.wtmass)[:, None, None] * out["mass_unit"]
                dofs = np.array([[6 * self.index[n] + d for n in (e.ga, e.gb) for d in range(6)] for e in elems])
                add(dofs, k, m)
            elif etype == "CELAS2":
                for e in elems:
                    ends = [(n, c) for n, c in zip(e.node_ids, (e.c1, e.c2)) if n]
                    vecs = []
                    for n, comp in ends:
                        axes = _cd_axes(model, n)
                        v = np.zeros(ndof)
                        base = 6 * self.index[n] + (3 if comp > 3 else 0)
                        v[base:base + 3] = axes[(comp - 1) % 3]
                        vecs.append(v)
                    b = vecs[0] - (vecs[1] if len(vecs) > 1 else 0)
                    nz = np.flatnonzero(b)
                    add(nz[None], e.k * np.outer(b[nz], b[nz])[None])
            elif etype == "CBUSH":
                for e in elems:
                    kdiag = np.array(e.pid_ref.Ki, dtype=float)
                    if not np.allclose(kdiag, kdiag[0]):
                        raise ValueError("helper handles isotropic CBUSH only")
                    ga, gb = e.node_ids[0], e.node_ids[1]
                    for a in range(6):
                        if gb:
                            dofs = np.array([[6 * self.index[ga] + a, 6 * self.index[gb] + a]])
                            add(dofs, kdiag[a] * np.array([[1.0, -1], [-1, 1]])[None])
                        else:
                            add(np.array([[6 * self.index[ga] + a]]), np.array([[[kdiag[a]]]]))
            else:
                raise ValueError(f"helper does not handle {etype}")
        for mass in model.masses.values():
            if mass.type != "CONM2":
                raise ValueError(mass.type)
            i = self.index[mass.nid]
            m6 = np.zeros((6, 6))
            off = np.asarray(mass.X, dtype=float)
            if mass.cid not in (0, -1) or np.any(np.asarray(mass.I) != 0):
                raise ValueError("helper handles CONM2 with CID 0 and no inertia only")
            mval = mass.mass
            s = np.array([[0, -off[2], off[1]], [off[2], 0, -off[0]], [-off[1], off[0], 0]])
            m6[:3, :3] = mval * np.eye(3)
            m6[:3, 3:] = -mval * s
            m6[3:, :3] = mval * s
            m6[3:, 3:] = -mval * s @ s
            add(np.arange(6 * i, 6 * i + 6)[None], None, (m6 * self.wtmass)[None])
        r = np.concatenate(rows)
        c = np.concatenate(cols)
        self.k = sp.csr_matrix((np.concatenate(kv), (r, c)), shape=(ndof, ndof))
        self.m = sp.csr_matrix((np.concatenate(mv), (r, c)), shape=(ndof, ndof))
        self.transform = self._constraints()

    def _constraints(self):
        """Sparse T (ndof x n_free): RBE2 rigid links eliminated, SPCs removed."""
        model = self.model
        ndof = self.ndof
        dep = {}
        for rb in model.rigid_elements.values():
            if rb.type != "RBE2":
                raise ValueError(rb.type)
            gi = self.index[rb.Gn()]
            comps = [int(ch) for ch in str(rb.cm)]
            for n in rb.Gmi_node_ids:
                gd = self.index[n]
                d = self.xyz[gd] - self.xyz[gi]
                row = np.zeros((6, 6))
                row[:3, :3] = np.eye(3)
                row[3:, 3:] = np.eye(3)
                row[:3, 3:] = -np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]])
                for comp in comps:
                    # component in basic directions (grid CD frames of the helper decks are handled
                    # only for all-six-component RBE2, which is frame independent)
                    if len(comps) != 6 and model.nodes[n].cd != 0:
                        raise ValueError("helper: partial RBE2 on a grid with CD")
                    dep[6 * gd + comp - 1] = {6 * gi + j: row[comp - 1, j] for j in range(6) if row[comp - 1, j]}
        for mpcs in model.mpcs.values():
            for card in mpcs:
                (n0, c0, a0), rest = (card.nodes[0], card.components[0], card.coefficients[0]), \
                    list(zip(card.nodes[1:], card.components[1:], card.coefficients[1:]))
                if model.nodes[n0].cd or len(str(c0)) != 1:
                    raise ValueError("helper: MPC on a CD grid or with several components")
                terms = {}
                for n, cc, aa in rest:
                    if model.nodes[n].cd:
                        raise ValueError("helper: MPC on a CD grid")
                    terms[6 * self.index[n] + int(cc) - 1] = -aa / a0
                dep[6 * self.index[n0] + int(c0) - 1] = terms
        spc = set()  # every SPC/SPC1 set of the deck (the helper decks have one), components 1-6
        for spcs in model.spcs.values():
            for card in spcs:
                comps = [card.components] * len(card.nodes) if card.type == "SPC1" else card.components
                for n, cc in zip(card.nodes, comps):
                    spc.update(6 * self.index[n] + int(ch) - 1 for ch in str(cc))
        # chained rigid elements / MPCs: substitute dependent DOF until only independent ones remain
        for _ in range(50):
            changed = False
            for d, terms in dep.items():
                if any(k in dep for k in terms):
                    new = {}
                    for k, val in terms.items():
                        for kk, vv in (dep[k].items() if k in dep else [(k, 1.0)]):
                            new[kk] = new.get(kk, 0.0) + val * vv
                    dep[d] = new
                    changed = True
            if not changed:
                break
        else:
            raise ValueError("helper: circular rigid elements")
        free = [i for i in range(ndof) if i not in dep and i not in spc]
        col = {d: j for j, d in enumerate(free)}
        tr, tc, tv = [], [], []
        for d in free:
            tr.append(d)
            tc.append(col[d])
            tv.append(1.0)
        for d, terms in dep.items():
            for ind, val in terms.items():
                if ind in spc:
                    continue
                tr.append(d)
                tc.append(col[ind])
                tv.append(val)
        return sp.csr_matrix((tv, (tr, tc)), shape=(ndof, len(free)))

    def modes(self, n_modes, **kwargs):
        """Lowest natural frequencies [Hz] (AUTOSPC: DOF without stiffness dropped)."""
        import femodel

        t = self.transform
        k = (t.T @ self.k @ t).tocsc()
        m = (t.T @ self.m @ t).tocsc()
        kd = np.abs(k.diagonal())
        keep = np.flatnonzero(kd > 1e-9 * kd.max())
        k = k[keep][:, keep]
        m = m[keep][:, keep]
        return femodel.normal_modes(k, m, n_modes, **kwargs).frequencies_hz


def reference_frequencies(folder):
    data = json.loads(reference_path("nastran", folder, "reference_modes.json").read_text())
    return np.array(data["frequencies_hz"]), data


@lru_cache(maxsize=None)
def _exhaust_model():
    return MiniModel(reference_path("nastran", "femap_exhaust", "modal_example_from_op2.bdf"))


def _error_table(ours, ref, modes):
    lines = ["| mode | Nastran Hz | ours Hz | error % |", "|---:|---:|---:|---:|"]
    for i in modes:
        lines.append(f"| {i + 1} | {ref[i]:.4f} | {ours[i]:.4f} | {100 * (ours[i] / ref[i] - 1):+.3f} |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- tests
# The issue asks for 2 % (aiming at 0.5 %); the formulation reaches 1 % on every
# mode of both decks, which is what is asserted.  Per-mode tables: docs/validation.md.


def _product_modes(folder, deck, units, n, **kwargs):
    import femodel

    model = femodel.read_bdf(reference_path("nastran", folder, deck), units=units)
    return femodel.solve_modes(model, n, **kwargs)


def test_femap_exhaust_modes_2_to_10_within_1_percent():
    ref, _ = reference_frequencies("femap_exhaust")
    modes = _product_modes("femap_exhaust", "modal_example_from_op2.bdf", "in-lbf-s", 10)
    ours = modes.frequencies_hz
    table = _error_table(ours, ref, range(10))
    print(table)
    assert modes.n_rigid == 0
    err = ours[1:10] / ref[1:10] - 1
    assert np.all(np.abs(err) < 0.01), table
    # mode 1 is the drilling (K6ROT) mechanism: reproduced too
    assert abs(ours[0] / ref[0] - 1) < 0.01, table


def test_dakota_cylinder_coupled_mass_free_free():
    ref, _ = reference_frequencies("dakota_cylinder")
    modes = _product_modes("dakota_cylinder", "modal.bdf", "in-lbf-s", 20)
    ours = modes.frequencies_hz
    table = _error_table(ours, ref, range(6, 20))
    print(table)
    assert modes.n_rigid == 6
    err = ours[6:20] / ref[6:20] - 1
    assert np.all(np.abs(err) < 0.01), table


def test_independent_assembly_agrees_with_product_path_on_dakota():
    """The kernel-only helper assembly (pyNastran cards, own RBE2/CONM2) and the
    project's reader/assembler give the same elastic frequencies."""
    mm = MiniModel(reference_path("nastran", "dakota_cylinder", "modal.bdf"))
    assert mm.coupled
    # dense eigensolutions on both sides: the comparison is of the assemblies, not of a sparse
    # solver (the SciPy-only SuperLU path, without row exchanges, is 1.2e-7 off in mode 9 of this
    # in-lbf-s deck; dense, CHOLMOD and cholespy agree to 1e-9)
    ours = mm.modes(20, solver="dense")
    product = _product_modes("dakota_cylinder", "modal.bdf", "in-lbf-s", 20, solver="dense").frequencies_hz
    np.testing.assert_allclose(ours[6:], product[6:], rtol=1e-7)


@pytest.mark.slow
def test_femap_exhaust_frequencies_do_not_hinge_on_k6rot():
    """Our drilling term penalizes theta_z minus the membrane rotation, so it stays a
    small penalty: K6ROT 10 -> 100 moves every mode, mode 1 included, by < 0.1 %
    (MYSTRAN, whose drilling spring is not tied to the membrane rotation, moves
    mode 1 from 8.2 to 18.3 Hz).  Our mode-1 agreement is not a K6ROT artefact."""
    import femodel
    from dataclasses import replace

    model = femodel.read_bdf(reference_path("nastran", "femap_exhaust", "modal_example_from_op2.bdf"),
                             units="in-lbf-s")
    assert model.k6rot == 10.0
    base = femodel.solve_modes(model, 10).frequencies_hz
    stiff = femodel.solve_modes(replace(model, k6rot=100.0), 10).frequencies_hz
    assert np.all(stiff >= base * (1 - 1e-9))
    assert np.all(np.abs(stiff / base - 1) < 1e-3)


def test_shell_element_matrices_against_nastran_kelm(capsys):
    """CQUAD4/CTRIA3 against NX's element matrices (solid_shell_bar KELM).

    Asserted: the membrane-dominated stiffest modes of the PCOMP (isotropic
    plies) quads agree to 1e-3 — our QM6 membrane is Nastran's.  Printed: the
    full eigenvalue ratios (docs/validation.md discusses the bending, thick-plate
    shear and drilling differences).
    """
    from tests.femodel.test_solids import _nastran_element_matrices, _unpack_upper

    bdf, order, kelm, _ = _nastran_element_matrices()
    checked = 0
    for col, (name, eid) in enumerate(order):
        if name not in ("CQUAD4", "CTRIA3"):
            continue
        elem = bdf.elements[eid]
        xyz = np.array([bdf.nodes[g].get_position() for g in elem.node_ids])
        dm, db, ds, _, _ = _shell_section(bdf, elem.pid_ref)
        k6rot = bdf.params["K6ROT"].values[0] if "K6ROT" in bdf.params else 100.0
        ours = sum(shell_stiffness(xyz[None], dm[None], db[None], ds[None], k6rot).values())[0]
        kn = _unpack_upper(kelm[:, col], ours.shape[0])
        wn, wo = np.linalg.eigvalsh(kn), np.linalg.eigvalsh(ours)
        assert np.all(np.abs(wn[:6]) < 1e-6 * wn[-1])
        print(name, eid, elem.pid_ref.type, np.round(wn[6:] / wo[6:], 3))
        if name == "CQUAD4" and elem.pid_ref.type == "PCOMP":
            np.testing.assert_allclose(wn[-6:], wo[-6:], rtol=1e-3)
            checked += 1
    assert checked == 2


BWB_MEDIAN_ERR, BWB_MAX_ERR = 0.01, 0.04  # observed 0.3 % and 3.5 % (mode 3), docs/validation.md


@pytest.mark.slow
def test_bwb_half_model_sandwich_laminates(capsys):
    """bwb (MSC, 60,810 DOF): CQUAD4/CTRIA3 on PCOMP sandwich laminates (MAT8 faces,
    MAT1 honeycomb core), CBAR PBARL T2 spar caps with offsets, chained RBE2, MPC,
    symmetry SPCs; lower-pedigree reference (eigenvalue table pasted in the deck).

    Runs through the kernel-only helper (the reader has no PCOMP yet), with the
    laminate input from ``femodel.laminate_abd``.  Asserted: the two zero-frequency
    modes of the half model and the per-mode bounds recorded in docs/validation.md.
    """
    ref, _ = reference_frequencies("bwb")
    mm = MiniModel(reference_path("nastran", "bwb", "bwb_freq.bdf"))
    assert mm.counts[("CQUAD4", 4)] == 9236
    ours = mm.modes(20)
    table = _error_table(ours, ref, range(2, 20))
    print(table)
    assert np.all(np.abs(ours[:2]) < 1e-3 * ref[2])
    err = np.abs(ours[2:20] / ref[2:20] - 1)
    assert np.median(err) < BWB_MEDIAN_ERR and err.max() < BWB_MAX_ERR, table
