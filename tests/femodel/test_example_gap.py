"""The air-gap variants of the example decks: facing grids, no joining element, own property, free-free, defaults."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

import femodel
from femodel import example_frame, example_subframe
from femodel._example import DOUBLER_PID
from femodel._example_frame import BUMP_STOP_PID
from frfcal.cli import main

#: sha256 of the decks and parameter files as written before the gap option existed (main at 184e98b)
DEFAULT_SHA256 = {
    ("subframe", 1500, "mm-t-s"): ("1dd9f4460ffb6d9e9bc80e07c7280f5a444ddcd87b21f36b3ff51fdf52259dcd",
                                   "55264791dbce1bd1a3e33f25143a731db6779914fc99a0ca24d99cb016121aa0"),
    ("subframe", 5000, "si"): ("dc1fecf8ff89eaba58aa429d4d32cd8e5f477880f088498f83e5d3b1962b2e5c",
                               "5f692a4bdc2446b10facf37b3d7e847faf15a797b15b34bc0330ba72a61a256c"),
    ("frame", 6, "si"): ("82c69e60bf59b29a45112d8bf9a424ad6bb80c892530aece8651d78b5ec38a13",
                         "2ff252fd1a24802e799da0501a8fcdfe7ea57f5c7ce5872fb8ccf79e3f74242e"),
    ("frame", 5, "mm-t-s"): ("ece3e5144ff376a2b8c60420a92636a1f80030dc1694aa3f547fa34dd8cfeea4",
                             "1d510184d682bd5947a3f2d73397e90fa3f41a38df45e88884ef4ff564089a16"),
}


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("key", sorted(DEFAULT_SHA256))
def test_default_decks_are_byte_identical(tmp_path, key):
    """gap_mm=None (and no argument) writes exactly the decks of before the option."""
    kind, size, units = key
    if kind == "subframe":
        exs = [example_subframe(tmp_path / "a", size, units=units),
               example_subframe(tmp_path / "b", size, units=units, gap_mm=None)]
    else:
        exs = [example_frame(tmp_path / "a", units=units, elements_per_member=size),
               example_frame(tmp_path / "b", units=units, elements_per_member=size, gap_mm=None)]
    for ex in exs:
        assert (_sha(ex.bdf), _sha(ex.params)) == DEFAULT_SHA256[key], \
            f"{ex.bdf}: the default {kind} deck changed; update DEFAULT_SHA256 only if that was intended"
        assert ex.gap_mm is None and ex.gap_pairs == ()


def _element_grids(fe):
    """{card: (n_el, n_nodes) grid ids} for every element card (CELAS2 and CONM2 included)."""
    out = {}
    for card, t in fe.elements.items():
        if len(t):
            out[card] = np.asarray(t.fields["nodes"]).reshape(len(t), -1)
    return out


def _check_gap(ex, gap_mm, own_pid, other_pids):
    pm = femodel.parametric_model(ex.params)
    fe = pm.assembly.model
    pairs = np.array(ex.gap_pairs)
    assert pairs.ndim == 2 and pairs.shape[1] == 2 and len(pairs) >= 2
    xa, xb = fe.xyz[fe.grid_index(pairs[:, 0])], fe.xyz[fe.grid_index(pairs[:, 1])]
    d = xb - xa
    # exactly gap_mm apart (the model is SI, the deck's digits are exact decimals), along one axis
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), gap_mm * 1e-3, rtol=1e-12)
    assert np.all(np.sum(np.abs(d) > 1e-12, axis=1) == 1)
    # no element, spring, mass or rigid element connects a facing pair
    grids = _element_grids(fe)
    for card, nodes in grids.items():
        for a, b in pairs:
            joined = np.any(nodes == a, axis=1) & np.any(nodes == b, axis=1)
            assert not joined.any(), f"{card} joins gap grids {a}, {b}"
    gap_grids = set(pairs.ravel().tolist())
    for r in fe.rbe3:
        assert r.refgrid not in gap_grids and not gap_grids & {g for grp in r.groups for g in grp[2]}
    assert not fe.rbe2 and not fe.mpc  # the examples have none; a new one must be checked here
    # the two sides belong to different property groups: side a only to the new part, side b never to it
    for card, nodes in grids.items():
        if card not in ("CQUAD4", "CBAR"):
            continue
        pid = np.asarray(fe.elements[card].fields["pid"])
        on_a = np.isin(nodes, pairs[:, 0]).any(axis=1)
        on_b = np.isin(nodes, pairs[:, 1]).any(axis=1)
        assert on_a.any() and set(pid[on_a].tolist()) == {own_pid}
        assert own_pid not in pid[on_b] and set(pid[on_b].tolist()) <= set(other_pids)
    # still free-free: six rigid-body modes, then a clear gap
    modes = pm.modes(np.zeros(pm.n_params), 10)
    assert np.sum(np.abs(modes.frequencies_hz) < 1e-2) == 6 and modes.frequencies_hz[6] > 20.0
    return pm


def test_subframe_gap_doubler(tmp_path):
    """A doubler sheet (own PSHELL) 3 mm outside the LHS web, its grids facing web grids, welded only at the top."""
    ex = example_subframe(tmp_path / "g", 3000, gap_mm=3.0)
    base = example_subframe(tmp_path / "b", 3000)
    assert ex.gap_mm == 3.0 and ex.element_size_mm == base.element_size_mm
    assert ex.n_elements > base.n_elements and ex.mass_kg > base.mass_kg
    # the doubler: 200 x 50 mm sheet plus a 200 x 3 mm flange, 2 mm steel
    assert ex.mass_kg - base.mass_kg == pytest.approx(200e-3 * 53e-3 * 2e-3 * 7850, rel=1e-9)
    pm = _check_gap(ex, 3.0, DOUBLER_PID, (2, 3))  # web (and bottom-skin corner)
    fe = pm.assembly.model
    assert DOUBLER_PID in fe.properties["PSHELL"].ids
    # its elements are no larger than the deck's element size
    t = fe.elements["CQUAD4"]
    mine = np.asarray(t.fields["pid"]) == DOUBLER_PID
    nodes = np.asarray(t.fields["nodes"])[mine]
    xyz = fe.xyz[fe.grid_index(nodes.ravel()).reshape(nodes.shape)]
    edges = np.linalg.norm(np.roll(xyz, -1, axis=1) - xyz, axis=2)
    assert edges.max() <= ex.element_size_mm * 1e-3 * 1.5
    # same physics in both unit systems
    si = example_subframe(tmp_path / "si", 3000, units="si", gap_mm=3.0)
    assert si.gap_pairs == ex.gap_pairs and si.mass_kg == pytest.approx(ex.mass_kg, rel=1e-12)


def test_frame_gap_bump_stops(tmp_path):
    """Two bump-stop CBARs (own PBAR) on the cradle end 3 mm under the rail grids; nothing joins tip and rail."""
    ex = example_frame(tmp_path / "g", gap_mm=3.0)
    base = example_frame(tmp_path / "b")
    assert ex.n_elements == base.n_elements + 2 and ex.n_dof == base.n_dof + 12
    pm = _check_gap(ex, 3.0, BUMP_STOP_PID, (1,))
    fe = pm.assembly.model
    # tips are above the cradle side members at the rails' y, gap along +z
    a, b = np.array(ex.gap_pairs).T
    np.testing.assert_allclose(fe.xyz[fe.grid_index(b)] - fe.xyz[fe.grid_index(a)], [[0, 0, 3e-3]] * 2, atol=1e-15)
    np.testing.assert_allclose(np.abs(fe.xyz[fe.grid_index(a), 1]), 0.4)
    mm = example_frame(tmp_path / "mm", units="mm-t-s", gap_mm=3.0)
    assert mm.gap_pairs == ex.gap_pairs and mm.mass_kg == pytest.approx(ex.mass_kg, rel=1e-12)


def test_gap_arguments_are_checked(tmp_path):
    with pytest.raises(ValueError, match="gap_mm"):
        example_subframe(tmp_path, 1500, gap_mm=0.0)
    with pytest.raises(ValueError, match="gap_mm"):
        example_subframe(tmp_path, 1500, gap_mm=12.0)
    with pytest.raises(ValueError, match="gap_mm"):
        example_frame(tmp_path, gap_mm=-1.0)


def test_cli_gap_mm(tmp_path, capsys):
    assert main(["example", "frame", "--gap-mm", "2.5", "--out", str(tmp_path / "f"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["gap_mm"] == 2.5 and len(doc["gap_pairs"]) == 2
    assert main(["example", "subframe", "--dof", "1500", "--gap-mm", "4", "--out", str(tmp_path / "s")]) == 0
    out = capsys.readouterr().out
    assert "air gap 4 mm" in out and "facing grid pairs" in out
    assert "PSHELL        21" in (tmp_path / "s" / "subframe.bdf").read_text()
