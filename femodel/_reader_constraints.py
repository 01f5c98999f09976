"""SPC/SPC1/SPCADD and MPC/MPCADD sets selected by case control, and the PARAMs that act on K and M."""

from __future__ import annotations

import numpy as np

from femodel._model import ModelError
from femodel._reader_fields import component_string
from femodel._reader_grids import GridSet


def read_spcs(bdf, grids: GridSet) -> tuple[np.ndarray, np.ndarray]:
    """Single-point constraints of the case-control SPC set, or of every set when none is selected.

    Returns
    -------
    grid : (k,) int64
    component : (k,) int8
        One row per constrained component (in the grid's CD system).

    Raises
    ------
    ModelError
        Selected set not in the bulk data, undefined grids, non-zero
        enforced displacements, unsupported constraint cards.
    """
    where = grids.where
    spc_id = _case_control_set(bdf, "SPC", where)
    if spc_id is not None:
        adds = getattr(bdf, "spcadds", {}) or {}
        sids = _expand_sets(adds, spc_id)
        if spc_id not in adds and spc_id not in bdf.spcs:
            raise ModelError(f"{where}: case control SPC = {spc_id} but no SPC/SPC1 set {spc_id} in the bulk data")
    else:
        sids = sorted(bdf.spcs)
    sg, sc_ = [], []
    for sid in sids:
        for spc in bdf.spcs.get(sid, []):
            if spc.type == "SPC1":
                comps = component_string(spc.components)
                for g in spc.nodes:
                    grids.require("SPC1", sid, [g])
                    for ch in comps:
                        sg.append(int(g))
                        sc_.append(int(ch))
            elif spc.type == "SPC":
                for g, c, enforced in zip(spc.nodes, spc.components, spc.enforced):
                    grids.require("SPC", sid, [g])
                    if enforced not in (None, 0, 0.0):
                        raise ModelError(f"{where}: SPC {sid}: enforced displacement {enforced} at GRID {g} (only zero is supported)")
                    for ch in component_string(c):
                        sg.append(int(g))
                        sc_.append(int(ch))
            else:
                raise ModelError(f"{where}: constraint {spc.type} {sid} is not supported")
    return np.array(sg, np.int64), np.array(sc_, np.int8)


def read_mpcs(bdf, grids: GridSet) -> tuple:
    """Multipoint constraints of the case-control MPC set only (as Nastran); () when none is selected.

    Returns
    -------
    tuple of (sid, ((grid, component, coefficient), ...))
        The first term's DOF is the dependent one.

    Raises
    ------
    ModelError
        Undefined grids, components other than one of 1..6, a zero first
        coefficient, MPC-type cards other than MPC.
    """
    where = grids.where
    mpc_id = _case_control_set(bdf, "MPC", where)
    if mpc_id is None:
        return ()
    mpcs = []
    for sid in _expand_sets(getattr(bdf, "mpcadds", {}) or {}, mpc_id):
        for card in bdf.mpcs.get(sid, []):
            if card.type != "MPC":
                raise ModelError(f"{where}: {card.type} {sid} is not supported")
            terms = []
            for g, c, a in zip(card.nodes, card.components, card.coefficients):
                grids.require("MPC", sid, [g])
                cc_ = component_string(c)
                if len(cc_) != 1:
                    raise ModelError(f"{where}: MPC {sid}: component {c!r} of GRID {g} must be one of 1..6")
                terms.append((int(g), int(cc_), float(a)))
            if not terms or terms[0][2] == 0.0:
                raise ModelError(f"{where}: MPC {sid}: the first (dependent) coefficient must be non-zero")
            mpcs.append((int(sid), tuple(terms)))
    return tuple(mpcs)


def read_params(bdf) -> tuple[float, bool, float]:
    """PARAM,WTMASS (default 1.0), PARAM,COUPMASS > 0 (default off) and PARAM,K6ROT (default 100.0)."""

    def param(name, default):
        p = bdf.params.get(name)
        if p is None:
            return default
        return p.values[0]

    wtmass = float(param("WTMASS", 1.0))
    coupmass = int(param("COUPMASS", -1) or -1) > 0
    k6rot = float(param("K6ROT", 100.0))
    return wtmass, coupmass, k6rot


def _case_control_set(bdf, name: str, where: str) -> int | None:
    """Set id of ``SPC = n`` / ``MPC = n``: the first subcase that names one (the global one if only it does)."""
    cc = getattr(bdf, "case_control_deck", None)
    if cc is None:
        return None
    set_id = None
    for sc_id in sorted(cc.subcases):
        sc = cc.subcases[sc_id]
        val = sc.params.get(name) if hasattr(sc, "params") else None
        if val is not None:
            try:
                set_id = int(val[0])
            except (TypeError, ValueError):
                raise ModelError(f"{where}: case control {name} = {val[0]!r} is not a set id") from None
            if sc_id != 0:
                break
    return set_id


def _expand_sets(adds: dict, sid: int) -> list[int]:
    """SPCADD/MPCADD set ``sid`` expanded (recursively) into the member set ids; [sid] for a plain set."""
    if sid in adds:
        return [x for card in adds[sid] for s in card.sets for x in _expand_sets(adds, int(s))]
    return [sid]
