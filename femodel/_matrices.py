"""Nastran-written matrices as a model source: DMIG punch, OP4, OP2.

Each reader returns an :class:`ImportedMatrices` with K and M on one common
DOF map.  K and M rows are aligned by (grid, component) key: Nastran omits
massless DOF from a DMIG mass matrix, so a DOF missing from one matrix gets a
zero row and column there.
"""

from __future__ import annotations

import logging
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from femodel._dofs import DofMap
from femodel._model import ModelError


@dataclass(frozen=True)
class ImportedMatrices:
    """Stiffness and mass read from Nastran output, aligned on one DOF map.

    Attributes
    ----------
    K, M : csr_matrix (n, n)
        Symmetric, in the units Nastran wrote (no conversion: the file does
        not say which units the deck used).
    dofs : DofMap
        (grid or scalar-point id, component) of each row; component 0 for
        scalar points (e.g. Craig-Bampton modal coordinates).
    source : str
        File and matrix names they came from.
    massless : DofMap
        DOF present in K but absent from M (zero mass rows).
    """

    K: sp.csr_matrix
    M: sp.csr_matrix
    dofs: DofMap
    source: str
    massless: DofMap

    def without(self, grids) -> "ImportedMatrices":
        """A copy with every DOF of the given grid/scalar-point ids removed (clamped)."""
        drop = np.isin(self.dofs.grid, np.asarray(grids, dtype=np.int64))
        keep = np.flatnonzero(~drop)
        K = self.K[keep][:, keep].tocsr()
        M = self.M[keep][:, keep].tocsr()
        return ImportedMatrices(K, M, self.dofs.subset(keep), self.source + " (constrained)", self.massless)


def _symmetric(a: sp.spmatrix, name: str, form=None) -> sp.csr_matrix:
    a = sp.csr_matrix(a, dtype=float)
    if a.shape[0] != a.shape[1]:
        raise ModelError(f"{name}: matrix is {a.shape}, not square")
    diff = abs(a - a.T)
    scale = abs(a).max() if a.nnz else 1.0
    if diff.nnz == 0 or diff.max() <= 1e-9 * scale:
        return a
    upper = sp.triu(a, 1)
    lower = sp.tril(a, -1)
    if upper.nnz == 0 or lower.nnz == 0:
        # one triangle stored (symmetric form 6)
        return (a + a.T - sp.diags(a.diagonal())).tocsr()
    if form == 6 or diff.max() <= 1e-6 * scale:
        return (0.5 * (a + a.T)).tocsr()
    raise ModelError(f"{name}: matrix is not symmetric (max |A - A^T| = {diff.max():.3g})")


def _align(kmat, kkeys, mmat, mkeys, source) -> ImportedMatrices:
    """Put K (rows kkeys) and M (rows mkeys) on the union of their keys."""
    allkeys = np.unique(np.concatenate([kkeys, mkeys]))
    n = allkeys.size

    def place(a, keys):
        idx = np.searchsorted(allkeys, keys)
        c = sp.coo_matrix(a)
        return sp.csr_matrix((c.data, (idx[c.row], idx[c.col])), shape=(n, n))

    K = place(kmat, kkeys)
    M = place(mmat, mkeys)
    dofs = DofMap(allkeys // 10, allkeys % 10)
    massless = np.setdiff1d(allkeys, mkeys)
    return ImportedMatrices(K, M, dofs, source, DofMap(massless // 10, massless % 10))


def _quiet_log():
    log = logging.getLogger("femodel.pynastran")
    log.setLevel(logging.ERROR)
    return log


def read_dmig(path, *, stiffness: str = "KAAX", mass: str = "MAAX") -> ImportedMatrices:
    """K and M from DMIG entries of a punch/bulk file (e.g. PARAM,EXTOUT,DMIGPCH).

    Parameters
    ----------
    path : str or Path
    stiffness, mass : str
        DMIG names.

    Raises
    ------
    ModelError
        A missing matrix (the message lists the DMIG names found), an
        unsymmetric or complex matrix.
    """
    from pyNastran.bdf.bdf import BDF

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"DMIG file not found: {path}")
    bdf = BDF(debug=None, log=_quiet_log())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            bdf.read_bdf(str(path), punch=True, xref=False, validate=False)
        except (SyntaxError, RuntimeError, ValueError, KeyError, IndexError, TypeError, AssertionError) as exc:
            raise ModelError(f"{path}: pyNastran could not parse the DMIG file: {exc}") from None
    got = {}
    for name in (stiffness, mass):
        if name not in bdf.dmig:
            raise ModelError(f"{path}: no DMIG {name!r}; found {sorted(bdf.dmig)}")
        d = bdf.dmig[name]
        if d.is_complex:
            raise ModelError(f"{path}: DMIG {name} is complex")
        a, rows, cols = d.get_matrix(is_sparse=True)
        a = sp.coo_matrix(a)
        rk = np.array([rows[i][0] * 10 + rows[i][1] for i in range(a.shape[0])], np.int64)
        ck = np.array([cols[j][0] * 10 + cols[j][1] for j in range(a.shape[1])], np.int64)
        # rows and columns may be listed in different orders: place both on the sorted union
        keys = np.unique(np.concatenate([rk, ck]))
        a = sp.coo_matrix(
            (a.data, (np.searchsorted(keys, rk[a.row]), np.searchsorted(keys, ck[a.col]))), shape=(keys.size, keys.size)
        )
        got[name] = (_symmetric(a, f"{path} DMIG {name}", d.matrix_form), keys)
    (K, kk), (M, mk) = got[stiffness], got[mass]
    return _align(K, kk, M, mk, f"{path} DMIG {stiffness}/{mass}")


_EXTRN_RE = re.compile(r"^EXTRN", re.IGNORECASE)


def read_extrn_dofs(path) -> DofMap:
    """The a-set DOF map from the EXTRN entry of an external-superelement punch/asm file.

    Components "123456" expand to six DOF, "0" (or blank) is a scalar point.
    Rows are sorted by id (Nastran's a-set order).
    """
    lines = Path(path).read_text(errors="replace").splitlines()
    fields: list[str] = []
    active = False
    for line in lines:
        if line.startswith("$"):
            continue
        if _EXTRN_RE.match(line):
            active = True
            body = line[8:72]
        elif active and (line[:1] in (" ", "+", "*") and line.strip()):
            body = line[8:72]
        elif active:
            break
        else:
            continue
        for k in range(0, len(body), 8):
            fields.append(body[k : k + 8].strip())
    if not fields:
        raise ModelError(f"{path}: no EXTRN entry to give the OP4 DOF map")
    grid, comp = [], []
    for k in range(0, len(fields) - 1, 2):
        if not fields[k]:
            continue
        gid = int(fields[k])
        c = fields[k + 1] or "0"
        if c == "0":
            grid.append(gid)
            comp.append(0)
        else:
            for ch in sorted(set(c)):
                grid.append(gid)
                comp.append(int(ch))
    keys = np.sort(np.array(grid, np.int64) * 10 + np.array(comp, np.int64))
    return DofMap(keys // 10, keys % 10)


def read_op4(path, *, stiffness: str = "KAA", mass: str = "MAA", dofs: DofMap | None = None) -> ImportedMatrices:
    """K and M from an OP4 file (ASCII or binary) with pyNastran's OP4 reader.

    Parameters
    ----------
    path : str or Path
    stiffness, mass : str
        Matrix names in the file.
    dofs : DofMap, optional
        Row labels.  Default: the EXTRN entry of a sibling ``.pch`` or
        ``.asm`` file with the same stem; if there is none, rows are labelled
        (1..n, 0).
    """
    from pyNastran.op4.op4 import read_op4 as _read

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"OP4 file not found: {path}")
    try:
        mats = _read(str(path), debug=False, log=_quiet_log())
    except (ValueError, RuntimeError, OSError, IndexError, KeyError, AssertionError) as exc:
        raise ModelError(f"{path}: pyNastran could not read the OP4 file: {exc}") from None
    out = {}
    for name in (stiffness, mass):
        if name not in mats:
            raise ModelError(f"{path}: no matrix {name!r}; found {sorted(mats)}")
        m = mats[name]
        data = m.data if hasattr(m, "data") else m[1]
        if np.iscomplexobj(data):
            raise ModelError(f"{path}: OP4 matrix {name} is complex")
        out[name] = _symmetric(sp.csr_matrix(data), f"{path} OP4 {name}", getattr(m, "form", None))
    K, M = out[stiffness], out[mass]
    if K.shape != M.shape:
        raise ModelError(f"{path}: {stiffness} {K.shape} and {mass} {M.shape} differ in size")
    if dofs is None:
        for ext in (".pch", ".asm"):
            side = path.with_suffix(ext)
            if side.is_file():
                try:
                    dofs = read_extrn_dofs(side)
                    break
                except ModelError:
                    continue
    if dofs is None:
        dofs = DofMap(np.arange(1, K.shape[0] + 1), np.zeros(K.shape[0], np.int8))
    if len(dofs) != K.shape[0]:
        raise ModelError(f"{path}: DOF map has {len(dofs)} rows but {stiffness} is {K.shape[0]}x{K.shape[0]}")
    return ImportedMatrices(K, M, dofs, f"{path} OP4 {stiffness}/{mass}", DofMap(np.zeros(0), np.zeros(0)))


def read_op2_matrices(path, *, stiffness: str = "KAAX", mass: str = "MAAX") -> ImportedMatrices:
    """K and M from matrices in an OP2 file (MATPOOL/DMIG-style, with DOF maps when present).

    Rows are aligned by (grid, component) when the OP2 matrix carries
    ``row_nid``/``row_dof``; otherwise both must have the same size and rows
    are labelled (1..n, 0).
    """
    from pyNastran.op2.op2 import OP2

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"OP2 file not found: {path}")
    op2 = OP2(debug=None, log=_quiet_log())
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            op2.read_op2(str(path), build_dataframe=False)
    except Exception as exc:  # pyNastran raises many unrelated types on bad files
        raise ModelError(f"{path}: pyNastran could not read the OP2 file: {type(exc).__name__}: {exc}") from None
    mats = dict(op2.matrices)
    got = {}
    for name in (stiffness, mass):
        if name not in mats:
            raise ModelError(f"{path}: no matrix {name!r} in the OP2; found {sorted(mats)}")
        m = mats[name]
        a = _symmetric(sp.csr_matrix(m.data), f"{path} OP2 {name}", getattr(m, "form", None))
        rn = getattr(m, "row_nid", None)
        rd = getattr(m, "row_dof", None)
        if rn is not None and rd is not None and len(rn) == a.shape[0]:
            keys = np.asarray(rn, np.int64) * 10 + np.asarray(rd, np.int64)
        else:
            keys = None
        got[name] = (a, keys)
    (K, kk), (M, mk) = got[stiffness], got[mass]
    if kk is not None and mk is not None:
        return _align(K, kk, M, mk, f"{path} OP2 {stiffness}/{mass}")
    if K.shape != M.shape:
        raise ModelError(f"{path}: {stiffness} {K.shape} and {mass} {M.shape} differ and carry no DOF maps")
    n = K.shape[0]
    return ImportedMatrices(K, M, DofMap(np.arange(1, n + 1), np.zeros(n)), f"{path} OP2 {stiffness}/{mass}", DofMap(np.zeros(0), np.zeros(0)))


def read_matrices(path, *, stiffness: str | None = None, mass: str | None = None) -> ImportedMatrices:
    """Dispatch on the file suffix: .op4 -> OP4, .op2 -> OP2, otherwise DMIG punch/bulk."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".op4":
        return read_op4(path, stiffness=stiffness or "KAA", mass=mass or "MAA")
    if suffix == ".op2":
        return read_op2_matrices(path, stiffness=stiffness or "KAAX", mass=mass or "MAAX")
    return read_dmig(path, stiffness=stiffness or "KAAX", mass=mass or "MAAX")
