"""Read Nastran bulk data through pyNastran and convert it to :class:`FEModel` arrays.

pyNastran's ``BDF`` object is used only inside :func:`read_bdf`; everything
returned is our own arrays in SI and basic coordinates.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

from femodel._model import FEModel, ModelError
from femodel._reader_constraints import read_mpcs, read_params, read_spcs
from femodel._reader_elements import read_elements, read_rigid_elements
from femodel._reader_grids import read_grids
from femodel._reader_properties import read_materials, read_properties
from femodel._units import UnitSystem, unit_system

#: Cards that define the structure and are converted.
SUPPORTED_CARDS = frozenset(
    """GRID GRDSET CORD2R CORD2C CORD2S CORD1R CORD1C CORD1S
    CQUAD4 CTRIA3 PSHELL CBAR CBEAM PBAR PBARL PBEAM PBEAML CROD CONROD PROD CTUBE PTUBE
    CHEXA CPENTA CTETRA CPYRAM PSOLID CONM1 CONM2 CMASS1 CMASS2 PMASS CELAS1 CELAS2 PELAS CBUSH PBUSH
    RBE2 RBE3 SPC SPC1 SPCADD MPC MPCADD MAT1 MAT8 PCOMP PARAM""".split()
)

#: Cards with no effect on K and M (solution control, loads, output, thermal
#: material, test-analysis sets); read and ignored without complaint.
NEUTRAL_CARDS = frozenset(
    """ENDDATA EIGRL EIGR EIGC EIGB MDLPRM USET USET1 SUPORT SUPORT1 MAT4 MAT5
    TEMP TEMPD FORCE FORCE1 FORCE2 MOMENT MOMENT1 MOMENT2 PLOAD PLOAD1 PLOAD2 PLOAD4
    LOAD GRAV DLOAD RLOAD1 RLOAD2 TLOAD1 TLOAD2 DAREA DPHASE DELAY TABLED1 TABLED2
    TABLED3 TABLED4 TABDMP1 FREQ FREQ1 FREQ2 FREQ3 FREQ4 FREQ5 TSTEP NLPARM PLOTEL
    PLOTEL3 PLOTEL4 DESVAR DVPREL1 DVPREL2 DRESP1 DRESP2 DOPTPRM DCONSTR SET1 SET3
    MONPNT1 SPCD AECOMP AELIST AERO AEROS AESTAT AESURF AESURFS CAERO1 CAERO2 CAERO3
    CAERO4 CAERO5 PAERO1 PAERO2 PAERO3 PAERO4 PAERO5 SPLINE1 SPLINE2 SPLINE3 SPLINE4
    SPLINE5 GUST MKAERO1 MKAERO2 TRIM FLUTTER FLFACT""".split()
)


def read_bdf(path, *, units: str = "si", allow_unsupported: bool = False) -> FEModel:
    """Read a Nastran bulk data deck into an :class:`FEModel` (SI, basic coordinates).

    Parameters
    ----------
    path : str or Path
        The deck (executive/case control optional; INCLUDE followed by pyNastran).
    units : str
        Unit system the deck is written in: "si", "mm-t-s", "in-lbf-s" or
        "consistent" (no conversion).
    allow_unsupported : bool
        If False (default), a deck with cards outside the supported set raises
        one ModelError listing every unsupported card type and count.  If
        True, those cards are ignored with a warning and recorded in
        ``FEModel.ignored_cards``.

    Returns
    -------
    FEModel

    Raises
    ------
    ModelError
        Unsupported cards, malformed cards (naming card and id), references to
        undefined grids/properties/materials.
    OSError
        If the file cannot be read.
    """
    from pyNastran.bdf.bdf import BDF

    us = unit_system(units)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Nastran deck not found: {path}")
    log = logging.getLogger("femodel.pynastran")
    log.setLevel(logging.ERROR)
    bdf = BDF(debug=None, log=log)
    import contextlib
    import io as _io

    try:
        # pyNastran prints its parse errors (duplicate cards, ...) on stdout as well as raising them: that
        # text would corrupt the one JSON object of `--json` (it is in the ModelError below)
        with warnings.catch_warnings(), contextlib.redirect_stdout(_io.StringIO()):
            warnings.simplefilter("ignore")
            mode = _deck_kind(path)
            if mode == "bulk-with-begin":
                read_bulk_with_begin(bdf, path)
            else:
                bdf.read_bdf(str(path), xref=False, validate=False, punch=(mode == "bulk"))
    except (SyntaxError, RuntimeError, ValueError, KeyError, IndexError, TypeError, AssertionError) as exc:
        msg = " ".join(str(exc).split())   # one line: pyNastran's messages span several
        raise ModelError(f"{path}: pyNastran could not parse the deck: {msg}") from None

    counts = card_counts(dict(bdf.card_count), getattr(bdf, "reject_cards", []) or [])
    unsupported = {k: v for k, v in counts.items() if k not in SUPPORTED_CARDS and k not in NEUTRAL_CARDS}
    if unsupported:
        listing = ", ".join(f"{k} x{v}" for k, v in sorted(unsupported.items()))
        if not allow_unsupported:
            raise ModelError(
                f"{path}: unsupported card types: {listing} "
                "(pass allow_unsupported=True / --allow-unsupported to ignore them)"
            )
        warnings.warn(f"{path}: ignoring unsupported cards: {listing}", stacklevel=2)

    return _convert(bdf, path, us, unsupported)


def read_bulk_with_begin(bdf, path: Path) -> None:
    """Bulk data with a BEGIN BULK line but no executive/case control into ``bdf`` (pyNastran wants either
    both or neither, so it is fed without the line; INCLUDEs relative to the deck's folder)."""
    import io

    text = "".join(line for line in open(path, errors="replace") if not line.strip().upper().startswith("BEGIN"))
    bdf.include_dir = str(path.parent)
    bdf.read_bdf(io.StringIO(text), xref=False, validate=False, punch=True)


def _deck_kind(path: Path) -> str:
    """"full" (CEND before BEGIN BULK), "bulk-with-begin" or "bulk" (no control sections)."""
    with open(path, errors="replace") as f:
        for line in f:
            word = line.strip().upper()
            if word.startswith("CEND"):
                return "full"
            if word.startswith("BEGIN") and "BULK" in word:
                return "bulk-with-begin"
    return "bulk"


def card_counts(card_count: dict[str, int], rejected) -> dict[str, int]:
    """Cards per type: pyNastran's ``card_count`` completed by the cards it rejected.

    pyNastran counts a card when it reads it, rejected or not; a rejected card
    (one it holds as raw fields in ``reject_cards``) that its count missed is
    counted here, once, so that every unsupported type is listed with the
    number of its cards and never with zero.

    Parameters
    ----------
    card_count : dict str -> int
        ``BDF.card_count``.
    rejected : sequence
        ``BDF.reject_cards``: card objects whose first field is the card name.
    """
    counts = dict(card_count)
    n_rejected: dict[str, int] = {}
    for rej in rejected:
        name = str(rej[0]).strip().rstrip("*").upper() if rej else "?"
        n_rejected[name] = n_rejected.get(name, 0) + 1
    for name, n in n_rejected.items():
        counts[name] = max(counts.get(name, 0), n)
    return counts


def _convert(bdf, path: Path, us: UnitSystem, ignored: dict) -> FEModel:
    """The parsed deck as an :class:`FEModel`: one converter per card family, in dependency order."""
    where = str(path)
    grids = read_grids(bdf, us.length_m, where)
    mats = read_materials(bdf, us, where)
    props = read_properties(bdf, mats, us, where)
    elements, dropped = read_elements(bdf, grids, props, us, ignored)
    rbe2, rbe3 = read_rigid_elements(bdf, grids, ignored)
    spc_grid, spc_component = read_spcs(bdf, grids)
    mpcs = read_mpcs(bdf, grids)
    wtmass, coupmass, k6rot = read_params(bdf)
    ignored_cards = dict(ignored)
    for key, n in dropped.items():
        ignored_cards[key] = ignored_cards.get(key, 0) + n
    return FEModel(
        path=where,
        units=us.name,
        grid_ids=grids.ids,
        xyz=grids.xyz,
        cp=grids.cp,
        cd=grids.cd,
        ps=grids.ps,
        coords=grids.coords,
        elements=elements,
        properties=props,
        materials=mats,
        rbe2=rbe2,
        rbe3=rbe3,
        mpc=mpcs,
        spc_grid=spc_grid,
        spc_component=spc_component,
        wtmass=wtmass,
        coupmass=coupmass,
        k6rot=k6rot,
        ignored_cards=ignored_cards,
    )
