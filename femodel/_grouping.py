"""Parameter bookkeeping of the parametric model: nominal values, exponent rows, grouped terms.

Assembly terms are summed by their exponent row in the parameters (one term
per distinct monomial) and reduced to the independent DOF once; element
subsets are assembled alone for :class:`~femodel.ElementFactor` terms.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from femodel._params import ParameterError, ParameterSet
from femodel._pattern import _canonical, _selection_map, _to_aset
from femodel._shellshear import _shell_shear_corrections, _shell_shear_elements, _shell_shear_series


def _element_terms(model) -> tuple:
    """The K and M g-set terms of a model's elements (what :func:`femodel.assemble` collects)."""
    from femodel import _assembly as A

    col = A._Collector(6 * model.n_grids)
    cd_axes = A._cd_transform(model)
    wt = float(model.wtmass)
    A.add_elements(model, col, cd_axes, wt)
    return col.terms()


def _subset_terms(assembly, params: ParameterSet, factor, amap=None):
    """(a-set matrices, a rows, b rows, ratios) of the K or M terms of an element subset.

    The subset's elements are assembled alone on the full model's grids and
    reduced with the full model's constraint transformation; coefficients
    (including the shell shear series) are those of the same parameters.
    With ``amap`` (:func:`_selection_map` of the assembly's T) the work runs
    on the subset's own grids (:func:`_local_subset_terms`) wherever that
    gives the same matrices.
    """
    if amap is not None:
        local = _local_subset_terms(assembly, params, factor, amap)
        if local is not None:
            (mats, a, b, r), lift = local
            return [lift(m) for m in mats], a, b, r
    sub = factor.submodel(assembly.model)
    sub_asm = replace(assembly, model=sub, terms=_element_terms(sub))
    return _subset_terms_on(sub_asm, params, factor)


def _subset_terms_on(sub_asm, params: ParameterSet, factor, drop_zeros=None):
    """:func:`_subset_terms` on an assembly of the subset's elements (its own T)."""
    source = params.source
    if factor.kind == "M":
        return _grouped_terms(sub_asm, params, "M", source, drop_zeros=drop_zeros)
    prepared = _shell_shear_elements(sub_asm.model, params, _key_index(params))
    series, _ = _shell_shear_series(sub_asm, params, prepared)
    return _with_series(*_grouped_terms(sub_asm, params, "K", source, _shell_shear_corrections(prepared),
                                        drop_zeros=drop_zeros), series)


def _local_subset_terms(assembly, params: ParameterSet, factor, amap):
    """The terms of an element subset assembled on the grids its elements touch, and their lift to the a-set.

    A cluster of a few elements touches a few dozen grids of a model of
    hundreds of thousands: assembling it on the full g-set costs several
    full-size passes (block maps, the a-set map, sparse sums) per subset.
    Here the subset's model keeps only its own grids and its T is the
    selection of their independent DOF. That is the full model's T restricted
    to them, and gives the same matrices entry for entry (the same elements,
    summed in the same order), when every DOF of these grids is independent
    or removed (no rigid-element or MPC dependent DOF) and their independent
    DOF keep the g-set order. Otherwise None (then the full-size path).

    Returns
    -------
    ((mats, a, b, ratio), lift) or None
        ``mats`` on the local independent DOF; ``lift(m)`` places a local
        (n_l, n_l) CSR matrix on the full a-set, (n_a, n_a) canonical CSR.
    """
    fe = assembly.model
    place = _local_place(fe, factor, amap)
    if place is None:
        return None
    sub, g, kept, gcols = place
    local_model = replace(sub, grid_ids=fe.grid_ids[g], xyz=fe.xyz[g], cp=fe.cp[g], cd=fe.cd[g], ps=fe.ps[g],
                          rbe2=(), rbe3=(), mpc=(), spc_grid=np.zeros(0, np.int64),
                          spc_component=np.zeros(0, np.int8))
    local = _selected_assembly(assembly, local_model, kept)
    return (_subset_terms_on(local, params, factor, drop_zeros=_drop_zeros(assembly)),
            _lifter(gcols, int(assembly.T.shape[1])))


def _local_place(fe, factor, amap):
    """(submodel, grid rows, kept local DOF mask, their a-set columns) of an element subset on the grids its
    elements touch; None where the local path does not apply (no grids, a rigid-element or MPC dependent
    DOF, independent DOF out of g-set order). Raises what ``factor.submodel`` and ``grid_index`` raise."""
    sub = factor.submodel(fe)
    grids = [np.asarray(t["nodes"]).ravel() for t in sub.elements.values() if len(t) and "nodes" in t.fields]
    grids = np.unique(np.concatenate(grids)) if grids else np.zeros(0, np.int64)
    grids = grids[grids > 0]
    if grids.size == 0:
        return None
    g = fe.grid_index(grids, what=f"ElementFactor {factor.name!r} grid")
    am = amap[(6 * g[:, None] + np.arange(6)[None, :]).ravel()]
    kept = am >= 0
    gcols = am[kept]
    if np.any(am < -1) or np.any(np.diff(gcols) <= 0):
        return None
    return sub, g, kept, gcols


def _selected_assembly(assembly, local_model, kept):
    """The assembly of a local model whose T selects its ``kept`` DOF (no dependent DOF)."""
    sel = np.flatnonzero(kept)
    n_l = int(sel.size)
    T = sp.csr_matrix((np.ones(n_l), (sel, np.arange(n_l))), shape=(kept.size, n_l))
    return replace(assembly, model=local_model, terms=_element_terms(local_model), T=T, selection=sel,
                   dependent=np.zeros(0, np.int64), dependent_rows=None)


def _drop_zeros(assembly) -> bool:
    """The full assembly's choice (see _grouped_terms): drop exact zeros unless T is a plain selection."""
    return assembly.selection is None or (assembly.dependent is not None and assembly.dependent.size > 0)


def _local_subset_batch(assembly, params: ParameterSet, factors, amap) -> list:
    """:func:`_local_subset_terms` of many element subsets of one kind in ONE assembly pass.

    Each subset keeps its own copy of the grids its elements touch (renumbered
    1, 2, ... subset after subset), so no two subsets share a DOF: the
    assembled matrices are block diagonal, one block per subset, and each
    block holds exactly the entries the subset assembled alone would have
    (the same elements; the coefficients of a block's pieces are those of
    its own pieces). A few hundred element clusters cost one pass over their
    elements instead of a few hundred passes of fixed per-call overhead.

    Returns
    -------
    list
        Per factor ``(pieces, (offset, size), lift)``: ``pieces`` = (mats, a,
        b, ratio) of the combined assembly (the same object for every
        factor), the subset's block in the combined local DOF, and its lift
        to the a-set; None where :func:`_local_subset_terms` would return
        None or the submodel cannot be formed (the caller takes the
        one-by-one path, which also raises the error that names the fault).
    """
    from femodel._model import Table

    fe = assembly.model
    n_a = int(assembly.T.shape[1])
    todo = []  # (index, g, kept, gcols, sub)
    for i, factor in enumerate(factors):
        try:
            place = _local_place(fe, factor, amap)
        except (ParameterError, ValueError):
            continue
        if place is not None:
            sub, g, kept, gcols = place
            todo.append((i, g, kept, gcols, sub))
    out: list = [None] * len(factors)
    if not todo:
        return out
    g_all = np.concatenate([g for _, g, _, _, _ in todo])
    new_ids = np.arange(1, g_all.size + 1, dtype=np.int64)
    tables: dict = {}
    base = 0
    for _, g, _, _, sub in todo:
        old = fe.grid_ids[g]  # increasing (np.unique), so a searchsorted maps a node id to its copy
        for card, tab in sub.elements.items():
            if not len(tab):
                continue
            fields = dict(tab.fields)
            if "nodes" in fields:
                nodes = np.asarray(fields["nodes"])
                pos = np.searchsorted(old, np.where(nodes > 0, nodes, old[0]))
                fields["nodes"] = np.where(nodes > 0, base + pos + 1, nodes).astype(nodes.dtype)
            tables.setdefault(card, []).append((tab.ids, fields))
        base += g.size
    elements = {}
    for card, parts in tables.items():
        keys = parts[0][1].keys()
        elements[card] = Table(card, np.concatenate([ids for ids, _ in parts]),
                               {k: np.concatenate([np.asarray(f[k]) for _, f in parts]) for k in keys})
    local_model = replace(fe, elements=elements, grid_ids=new_ids, xyz=fe.xyz[g_all], cp=fe.cp[g_all],
                          cd=fe.cd[g_all], ps=fe.ps[g_all], rbe2=(), rbe3=(), mpc=(),
                          spc_grid=np.zeros(0, np.int64), spc_component=np.zeros(0, np.int8))
    local = _selected_assembly(assembly, local_model, np.concatenate([k for _, _, k, _, _ in todo]))
    pieces = _subset_terms_on(local, params, factors[todo[0][0]], drop_zeros=_drop_zeros(assembly))
    offset = 0
    for i, _, _, gcols, _ in todo:
        out[i] = (pieces, (offset, int(gcols.size)), _lifter(gcols, n_a))
        offset += int(gcols.size)
    return out


def _diagonal_block(m, offset: int, size: int) -> sp.csr_matrix:
    """Rows and columns offset .. offset + size of a block-diagonal CSR matrix (no entries outside the block
    in those rows), as a (size, size) CSR matrix."""
    m = sp.csr_matrix(m)
    lo, hi = m.indptr[offset], m.indptr[offset + size]
    return sp.csr_matrix((m.data[lo:hi], m.indices[lo:hi] - offset, m.indptr[offset:offset + size + 1] - lo),
                         shape=(size, size))


def _lifter(gcols: np.ndarray, n_a: int):
    """``lift(m)``: a local (n_l, n_l) matrix on the local independent DOF ``gcols`` (increasing) placed on the
    full a-set, (n_a, n_a) canonical CSR."""

    def lift(m) -> sp.csr_matrix:
        m = sp.csr_matrix(m)
        # global row j starts where local row #{gcols < j} does: each local offset repeated over the global
        # rows up to its own (gcols increasing); a cumulative sum over all n_a rows costs 10x more per subset
        indptr = np.repeat(m.indptr, np.diff(np.r_[-1, gcols, n_a]))
        return sp.csr_matrix((m.data, gcols[m.indices].astype(m.indices.dtype), indptr), shape=(n_a, n_a))

    return lift


def _factor_key(key) -> tuple[str, int, str]:
    """Normalize an assembly factor key to the parameter-file spelling."""
    card, cid, fld = key
    if card == "PELAS" and fld == "K1":
        fld = "K"
    return (card, int(cid), fld)


def _nominal_from_model(params: ParameterSet, fe, source) -> list[np.ndarray]:
    """SI nominal values from the FE model's tables (WTMASS applied to masses)."""
    where = f"{source}: " if source else ""
    wt = float(fe.wtmass)

    def table(group, name, prm, key):
        tab = group.get(name)
        if tab is None or len(tab) == 0 or key[1] not in set(tab.ids.tolist()):
            raise ParameterError(f"{where}parameter {prm.name!r}: card {key[0]} {key[1]} (field {key[2]}) is not in the deck")
        return tab, int(np.flatnonzero(tab.ids == key[1])[0])

    out = []
    for prm in params.parameters:
        vals = []
        for key in prm.keys:
            card, cid, fld = key
            if card == "MAT1":
                tab, r = table(fe.materials, "MAT1", prm, key)
                v = tab["E"][r] if fld == "E" else tab["RHO"][r] * wt
            elif card == "PSHELL":
                tab, r = table(fe.properties, "PSHELL", prm, key)
                v = tab["t"][r]
            elif card == "CONM2":
                tab, r = table(fe.elements, "CONM2", prm, key)
                v = tab["mass"][r] * wt
            elif card == "PBUSH":
                tab, r = table(fe.properties, "PBUSH", prm, key)
                v = tab["k"][r, int(fld[1]) - 1]
            elif card == "CELAS2":
                tab, r = table(fe.elements, "CELAS2", prm, key)
                v = tab["k"][r]
            elif card == "PBAR":
                tab, r = table(fe.properties, "PBAR", prm, key)
                if tab["card"][r] != "PBAR":
                    raise ParameterError(f"{where}parameter {prm.name!r}: property {cid} is a {tab['card'][r]}; "
                                         f"{fld} is a parameter of PBAR sections only (a {tab['card'][r]} section's "
                                         "A, I and J are not monomials of its fields)")
                from femodel._assembly import _shear_flexible

                if _shear_flexible(tab["k1"][r]) or _shear_flexible(tab["k2"][r]):
                    raise ParameterError(f"{where}parameter {prm.name!r}: PBAR {cid} has shear factors K1/K2: its "
                                         f"bending stiffness is not a monomial of {fld} (Timoshenko); leave K1, K2 "
                                         "blank (Nastran's default, no shear flexibility) to calibrate its section")
                v = tab[fld][r]
            elif card == "PROD":
                tab, r = table(fe.properties, "PROD", prm, key)
                v = tab[fld][r]
            elif card == "CMASS2":
                tab, r = table(fe.elements, "CMASS2", prm, key)
                v = tab["m"][r] * wt
            elif card in ("PMASS", "PELAS"):
                table(fe.properties, card, prm, key)
                el_card, f = ("CMASS1", "m") if card == "PMASS" else ("CELAS1", "k")
                el = fe.elements.get(el_card)
                vs = np.array([]) if el is None else el[f][el["pid"] == cid]
                if vs.size == 0:
                    raise ParameterError(f"{where}parameter {prm.name!r}: {card} {cid} is used by no {el_card}")
                if not np.allclose(vs, vs[0], rtol=1e-12, atol=0.0):
                    raise ParameterError(
                        f"{where}parameter {prm.name!r}: {card} {cid} {el_card} elements join translational and "
                        "rotational components; its SI value is ambiguous"
                    )
                v = vs[0] * (wt if card == "PMASS" else 1.0)
            else:  # pragma: no cover - guarded by SUPPORTED_FIELDS
                raise ParameterError(f"{where}parameter {prm.name!r}: unsupported card {card}")
            v = float(v)
            if not (np.isfinite(v) and v > 0.0):
                raise ParameterError(
                    f"{where}parameter {prm.name!r}: {card} {cid} field {fld} is {v!r} (SI); a scaled "
                    "parameter needs a positive nominal value"
                )
            vals.append(v)
        out.append(np.array(vals))
    return out


def _key_index(params: ParameterSet) -> dict:
    key_index = params.key_to_index()
    # a MAT1 E parameter also moves G (G follows E, or is scaled with it on write-back)
    for (card, cid, fld), j in list(key_index.items()):
        if card == "MAT1" and fld == "E":
            key_index.setdefault(("MAT1", cid, "G"), j)
    return key_index


def _grouped_terms(assembly, params: ParameterSet, kind: str, source, extra=(), series=(), drop_zeros=None):
    """Sum g-set terms of one kind by exponent row; reduce each sum by T once.

    ``extra`` holds (exponent row, g-set matrix) additions to the monomial
    groups; ``series`` holds (a row, b row, ratio, g-set matrix) series terms.
    ``drop_zeros`` overrides the assembly's own choice of removing exact zeros
    (a subset assembled on its own grids takes the full model's).
    """
    key_index = _key_index(params)
    groups: dict[tuple, object] = {}
    for term in assembly.terms:
        if term.kind != kind:
            continue
        e = np.zeros(len(params), dtype=np.int64)
        for key, expo in term.factors:
            j = key_index.get(_factor_key(key))
            if j is not None:
                e[j] += int(expo)
        row = tuple(e.tolist())
        groups[row] = term.matrix if row not in groups else groups[row] + term.matrix
    for erow, m in extra:
        row = tuple(int(x) for x in erow)
        groups[row] = m if row not in groups else groups[row] + m
    if not groups:
        groups[tuple([0] * len(params))] = sp.csr_matrix((assembly.T.shape[0],) * 2)
    rows = sorted(groups)
    amap = _selection_map(assembly.T)
    # assembly.reduce sums with the dependent-DOF products, which drops exact zeros; keep that pattern
    if drop_zeros is None:
        drop_zeros = assembly.selection is None or (assembly.dependent is not None and assembly.dependent.size > 0)
    mats = [_to_aset(assembly, amap, _canonical(groups[r]), drop_zeros) for r in rows]
    a = np.array(rows, dtype=float).reshape(len(rows), len(params))
    b = a.copy()
    ratio = np.zeros(len(rows))
    return _with_series(mats, a, b, ratio, series)


def _with_series(mats, a, b, ratio, series):
    """Append (a row, b row, ratio, a-set matrix) series terms to grouped terms."""
    if series:  # already on the a-set
        mats = list(mats) + [m for _, _, _, m in series]
        a = np.vstack([a, np.array([s_[0] for s_ in series])])
        b = np.vstack([b, np.array([s_[1] for s_ in series])])
        ratio = np.concatenate([ratio, [s_[2] for s_ in series]])
    return mats, a, b, ratio


def _check_pcomp_materials(params: ParameterSet, fe, source) -> None:
    """A MAT1 parameter cannot be a ply material of a PCOMP laminate that shell elements use.

    A laminate enters the model as a constant term (no card-field monomial describes it), while the
    write-back changes the MAT1 card its plies read: the calibrated model and the deck written from it would
    differ. Refused with the laminates named, instead of a deck that silently disagrees with the model."""
    pcomp = fe.properties.get("PCOMP")
    if pcomp is None or len(pcomp) == 0 or "mids" not in pcomp.fields:
        return
    used = [np.asarray(fe.elements[c]["pid"]) for c in ("CQUAD4", "CTRIA3") if c in fe.elements and len(fe.elements[c])]
    if not used:
        return
    live = np.isin(pcomp.ids, np.concatenate(used))
    where = f"{source}: " if source else ""
    for prm in params.parameters:
        if prm.card != "MAT1":
            continue
        hit = live & np.any(np.isin(pcomp["mids"], prm.ids), axis=1)
        if np.any(hit):
            raise ParameterError(
                f"{where}parameter {prm.name!r} (MAT1 {list(prm.ids)} {prm.field}): the material is a ply of PCOMP "
                f"{pcomp.ids[hit][:5].tolist()}, used by shell elements. A laminate is a constant term of the model "
                "(its stiffness is not a monomial of card fields), but the write-back would change it through this "
                "MAT1: give the plies their own MAT1 (or a MAT8), or leave this material out of the parameters"
            )


def _check_element_thickness(params: ParameterSet, fe, source) -> None:
    """A PSHELL T parameter cannot move elements that give their own T1..T4."""
    where = f"{source}: " if source else ""
    for prm in params.parameters:
        if prm.card != "PSHELL":
            continue
        for card in ("CQUAD4", "CTRIA3"):
            tab = fe.elements.get(card)
            if tab is None or len(tab) == 0 or "t" not in tab.fields:
                continue
            own = np.isin(tab["pid"], prm.ids) & np.any(~np.isnan(tab["t"]), axis=1)
            if np.any(own):
                raise ParameterError(
                    f"{where}parameter {prm.name!r}: {card} {tab.ids[own][:5].tolist()} give their own corner "
                    f"thicknesses T1..T4, which PSHELL {list(prm.ids)} T does not scale"
                )

