"""Mass properties against Nastran's grid point weight generator (femap_exhaust OP2)."""

from __future__ import annotations

import warnings

import numpy as np

import femodel
from tests.conftest import reference_path


def test_femap_exhaust_mass_properties_match_nastran_gpwg():
    folder = reference_path("nastran", "femap_exhaust")
    model = femodel.read_bdf(folder / "modal_example_from_op2.bdf", units="consistent")
    mp = femodel.mass_properties(femodel.assemble(model))

    from pyNastran.op2.op2 import OP2

    op2 = OP2(debug=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        op2.read_op2(str(folder / "modal_example.op2"))
    gpwg = list(op2.grid_point_weight.values())[0]
    # PARAM,GRDPNT,100000: Nastran reports the CG relative to grid 100000
    ref = model.xyz[model.grid_index(100000)[0]]
    np.testing.assert_allclose(mp.mass, gpwg.mass[0], rtol=1e-6)  # WTMASS applied, shell + NSM mass
    cg_nastran = np.array([gpwg.cg[1, 0], gpwg.cg[0, 1], gpwg.cg[0, 2]])
    np.testing.assert_allclose(mp.cg - ref, cg_nastran, atol=5e-4)  # BDF regenerated from OP2 geometry
    # Nastran's I(S) lists products of inertia as +sum(m x y); our tensor has -sum(m x y)
    flip = np.where(np.eye(3, dtype=bool), 1.0, -1.0)
    np.testing.assert_allclose(mp.inertia * flip, gpwg.IS, rtol=2e-4, atol=1e-4 * np.abs(gpwg.IS).max())
