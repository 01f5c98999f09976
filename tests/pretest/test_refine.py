"""AutoMAC refinement: never worse, det floor kept, constraints kept."""

from __future__ import annotations

import numpy as np
import pytest

from pretest import automac, effective_independence, fim_logdet, refine_automac
from tests.pretest._problems import plate_modes


def _maxoff(p):
    a = automac(p)
    return (a - np.diag(np.diag(a))).max()


@pytest.mark.parametrize("decades", [0.3, 1.0, 3.0])
def test_refinement_lowers_automac_within_det_budget(decades):
    phi, xyz, _ = plate_modes(nx=15, ny=11, n_modes=10, noise=0.01)
    efi = effective_independence(phi, 10)
    ref = refine_automac(phi, efi.groups, max_det_loss_decades=decades)
    assert ref.automac_before == pytest.approx(_maxoff(phi[efi.rows]))
    assert ref.automac_after == pytest.approx(_maxoff(phi[ref.rows]))
    assert ref.automac_after <= ref.automac_before
    assert ref.n_swaps > 0 and ref.automac_after < ref.automac_before - 0.01
    assert ref.log10_det_after >= ref.log10_det_before - decades - 1e-9
    assert ref.log10_det_after == pytest.approx(fim_logdet(phi[ref.rows]) / np.log(10))
    assert ref.groups.size == 10


def test_refinement_keeps_constraints_and_bundles():
    phi, xyz, _ = plate_modes(nx=13, ny=9, n_modes=9, noise=0.02)
    rng = np.random.default_rng(4)
    phi3 = np.vstack([phi, 0.4 * rng.standard_normal(phi.shape), 0.2 * rng.standard_normal(phi.shape)])
    labels = np.tile(np.arange(phi.shape[0]), 3)
    pos = np.tile(xyz, (3, 1))
    include, exclude, dmin = [3], [50, 51, 52], 0.12
    efi = effective_independence(phi3, 5, group_labels=labels, include=include, exclude=exclude,
                                 positions=pos, min_distance=dmin)
    ref = refine_automac(phi3, efi.groups, group_labels=labels, include=include, exclude=exclude,
                         positions=pos, min_distance=dmin, max_det_loss_decades=2.0)
    assert 3 in ref.groups and not set(exclude) & set(ref.groups.tolist())
    _, counts = np.unique(labels[ref.rows], return_counts=True)
    assert np.all(counts == 3)
    p = xyz[ref.groups]
    d = np.linalg.norm(p[:, None] - p[None], axis=-1) + 1e9 * np.eye(len(p))
    assert d.min() >= dmin
    assert ref.automac_after <= ref.automac_before
