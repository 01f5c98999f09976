"""Solid kernels against real Nastran eigenvalues (nx_sine_solids).

Uses the independent reference assembly of ``test_shells`` (pyNastran cards
-> our kernels) so that a frequency error is an element error.
"""

from __future__ import annotations

import numpy as np

from femodel import solid_mass, solid_stiffness
from tests.conftest import reference_path
from tests.femodel.test_shells import MiniModel, _error_table, reference_frequencies


def test_nx_sine_solids_modes_1_to_8_within_2_percent():
    ref, data = reference_frequencies("nx_sine_solids")
    mm = MiniModel(reference_path("nastran", "nx_sine_solids", "nx_sine.bdf"))
    assert {("CTETRA", 4), ("CPYRAM", 5), ("CPENTA", 6), ("CHEXA", 8)} <= set(mm.counts)
    use = np.array(data["use_modes"]) - 1
    ours = mm.modes(len(use))
    table = _error_table(ours, ref, use)
    print(table)
    err = ours[use] / ref[use] - 1
    assert np.all(np.abs(err) < 0.02), table


def _nastran_element_matrices():
    """Per-element KELM/MELM of solid_shell_bar (NX, SOL 101 DMAP output) with the deck."""
    from pyNastran.bdf.bdf import read_bdf
    from pyNastran.op2.op2 import OP2

    folder = reference_path("nastran", "solid_shell_bar")
    op2 = OP2(debug=None, log=None)
    op2.read_op2(str(folder / "static_solid_shell_bar_kelm.op2"), skip_undefined_matrices=False)
    bdf = read_bdf(str(folder / "static_solid_shell_bar_kelm.bdf"), debug=None)
    kdict = op2.matdicts["KDICT"]
    order = [(name, int(e)) for name, eids in zip(kdict.element_names, kdict.eids) for e in eids]
    return bdf, order, op2.matrices["KELM"].data, op2.matrices["MELM"].data


def _unpack_upper(col, n):
    """Row-wise packed upper triangle -> symmetric (n, n)."""
    k = np.zeros((n, n))
    iu = np.triu_indices(n)
    k[iu] = col[: iu[0].size]
    return k + np.triu(k, 1).T


def test_solid_element_matrices_against_nastran_kelm():
    """Element-level check against Nastran's own element matrices (KELM/MELM).

    Eigenvalues are compared (independent of DOF order and frame).  CTETRA is
    identical; CHEXA agrees on 13 of its 18 deformation modes and Nastran's
    brick is softer on the other 5 (ratios 0.46-0.88: its default HEXA adds
    more than our incompatible modes); lumped masses are identical.
    """
    from tests.femodel.test_shells import _iso3d

    bdf, order, kelm, melm = _nastran_element_matrices()
    mat = bdf.materials[1]
    c = _iso3d(mat.e, mat.nu)
    seen = set()
    for col, (name, eid) in enumerate(order):
        if name not in ("CTETRA", "CHEXA", "CPENTA"):
            continue
        elem = bdf.elements[eid]
        xyz = np.array([bdf.nodes[g].get_position() for g in elem.node_ids])
        n = 3 * len(xyz)
        kn = _unpack_upper(kelm[:, col], n)
        ours = solid_stiffness(xyz[None], c[None])[0]
        wn, wo = np.linalg.eigvalsh(kn), np.linalg.eigvalsh(ours)
        assert np.all(np.abs(wn[:6]) < 1e-6 * wn[-1])  # Nastran's matrix unpacked right: 6 rigid modes
        ratio = wn[6:] / wo[6:]
        mn = np.sort(np.diag(_unpack_upper(melm[:, col], n)))
        mo = np.sort(np.diag(solid_mass(xyz[None], [mat.rho], False)[0]))
        np.testing.assert_allclose(mo, mn, rtol=1e-6)
        if name == "CTETRA":
            np.testing.assert_allclose(ratio, 1.0, rtol=1e-5)
        elif name == "CHEXA":
            assert np.sum(np.abs(ratio - 1) < 1e-4) == 13, ratio
            assert np.all(ratio > 0.45) and np.all(ratio < 1 + 1e-4), ratio
        else:  # CPENTA: a different wedge formulation in Nastran; recorded, loosely bounded
            assert np.all((ratio > 0.5) & (ratio < 1.2)), ratio
        seen.add(name)
    assert seen == {"CTETRA", "CHEXA", "CPENTA"}
