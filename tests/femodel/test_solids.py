"""Solid kernels against real Nastran eigenvalues (nx_sine_solids).

Uses the independent reference assembly of ``test_shells`` (pyNastran cards
-> our kernels) so that a frequency error is an element error.
"""

from __future__ import annotations

import numpy as np

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
