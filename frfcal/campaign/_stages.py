"""The campaign's stages: typed inputs, frozen-dataclass results, kernels from the library layers.

load -> identify -> equalize -> group -> calibrate -> validate -> cross-validate
(-> report, :mod:`frfcal.campaign._report`). Each stage function takes the
campaign and the results of earlier stages and returns its own result; it
does not read what an earlier stage already read, and it writes nothing
(:func:`frfcal.campaign.run_campaign` stores every result, see
docs/architecture.md).
"""

from __future__ import annotations

import difflib
import re
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calibration import (
    ESTIMATED,
    CalibrationError,
    CycleOptions,
    CycleResult,
    FitData,
    FRFModel,
    Grouping,
    Identifiability,
    IdentifiedModes,
    Objective,
    Surrogate,
    Validation,
    CrossValidation,
    basis_residuals,
    build_surrogate,
    calibrate_cycles,
    cross_validate,
    grouping,
    half_bandwidth_frequencies,
    identifiability,
    estimate_std_error,
    log_frequency_weights,
    noise_floor_sd,
    pairwise_sd,
    reduced_modes,
    surrogate_frf,
    validate,
    with_spread,
    expected_from_std_error,
    scatter_sd,
)
from calibration._correct import rebased
from calibration._fit import MIN_STARTS
from calibration._refine import ModalDampingObjective, Refinement, carried_damping, refine
from calibration._surrogate import assembled
from calibration._signal import signal_pairs
from labdata._quantities import quantity_factor, quantity_power
from frfcal.campaign._identify import identify_lines, refit_line, unexplained_line
from frfcal.campaign._schema import Campaign

# ----------------------------------------------------------------------------- load


@dataclass(frozen=True)
class RunLines:
    """Every line of a run on the campaign's channels and drives (the identification's input).

    Attributes
    ----------
    frequency_hz : (n_f,) Hz
    frf : (n_f, n_ch, n_in) complex, the run's quantity
    valid : (n_f,) bool
    std_error : (n_f, n_ch, n_in) or None (the run has none)
    """

    frequency_hz: np.ndarray
    frf: np.ndarray
    valid: np.ndarray
    std_error: np.ndarray | None = None


@dataclass(frozen=True)
class Transducer:
    """A channel or drive as the model sees it: FE grid and unit direction (basic system)."""

    name: str
    grid: int
    direction: tuple


@dataclass(frozen=True)
class Article:
    """One test article's data as the calibration uses it.

    Attributes
    ----------
    name : str
    path : Path, the run file
    freq_hz : (n_f,) raw valid lines in the band [Hz]
    frf : (n_f, n_ch, n_in) raw FRF on ``channels`` x ``drives``
    channels : tuple of str, calibration then hold-out channels
    drives : tuple of str
    identification : identification.Identification or None (before the identify stage)
    ident_channels : tuple of str, output rows of ``identification``
    quantity : str
    std_error : like ``frf`` or None (the run has none)
    noise_estimate : like ``frf`` or None
        Without ``std_error``: the standard errors estimated from the lines
        themselves (:func:`calibration.estimate_std_error`), for the floors
        printed beside every SD ("estimated from adjacent lines"); never used
        as identification or calibration weights.
    pairs : (n_ch, n_in) bool or None: pairs with a signal above the noise (None: all)
    lines : RunLines or None, all lines of the run on ``channels`` x ``drives``
    stored : identification.Identification or None
        The run file's stored identification when ``[identification] use_stored``
        and it covers every sensor and drive of the run.
    stored_channels : tuple of str, output rows of ``stored`` (the run's sensors)
    """

    name: str
    path: Path
    freq_hz: np.ndarray
    frf: np.ndarray
    channels: tuple
    drives: tuple
    identification: object
    ident_channels: tuple
    quantity: str
    std_error: np.ndarray | None = None
    noise_estimate: np.ndarray | None = None
    pairs: np.ndarray | None = None
    lines: RunLines | None = field(default=None, repr=False)
    stored: object | None = field(default=None, repr=False)
    stored_channels: tuple = ()


@dataclass(frozen=True)
class LoadResult:
    """The load stage: every article, and the channel/drive geometry of the first run (for the model)."""

    articles: tuple
    channels: tuple  # of Transducer, campaign channel order
    drives: tuple  # of Transducer


def _same_point(a, b, sign: float = 1.0) -> bool:
    return int(a.grid) == int(b.grid) and np.allclose(np.asarray(a.direction, float),
                                                       sign * np.asarray(b.direction, float), atol=1e-6)


def _named_point(name: str):
    """(grid, unit direction) of a channel name that ends in its point as import-uff names channels,
    ``"acc12 (101+Z)"`` or ``"n101-Y"``; None otherwise."""
    m = re.search(r"(?:\(|(?:^|_)n)(\d+)([+-])([XYZ])\)?\s*$", name)
    if m is None:
        return None
    d = np.zeros(3)
    d["XYZ".index(m.group(3))] = 1.0 if m.group(2) == "+" else -1.0
    return int(m.group(1)), d


def _entity_name(name: str) -> str | None:
    """The UFF entity name of a channel import-uff named ``"acc12 (101+Z)"`` (``"acc12"``); None otherwise."""
    m = re.fullmatch(r"(.+) \(\d+[+-][XYZ]\)", name)
    return m.group(1) if m else None


def _by_point(channels, names, first: dict, what: str, path, log) -> tuple[list, np.ndarray]:
    """Indices of ``names`` among a run's ``channels``, and the sign of each: by name, else by the point
    (grid and direction) the name has in the campaign's first run.

    Run files imported per article often name one point differently (a UFF entity name that carries the
    transducer's serial number: ``PCB-1234 (101+Z)`` in one file, ``PCB-5678 (101+Z)`` in the next): the
    campaign's names are the first run's, and another run's channel at the same grid and direction is that
    channel (logged). A name that is a channel's UFF entity name alone (``acc12`` for ``acc12 (101+Z)``, as
    import-uff names it) is that channel when exactly one channel carries it (logged). A channel at the same
    grid along the opposite direction (a sensor mounted the other way
    round in one article: ``101-Z``) is that channel with its sign turned (-1: its FRF row, or a drive's
    column, is negated; logged). A name found in the run at another point is used as named, with a warning.
    """
    lookup = {c.name: i for i, c in enumerate(channels)}
    out, signs, missing = [], [], []
    for n in names:
        ref = first.get(n)
        if n in lookup:
            if ref is not None and not _same_point(channels[lookup[n]], ref):
                c = channels[lookup[n]]
                log(f"{Path(path).name}: warning: {what[:-1]} {n!r} is at grid {c.grid}, direction "
                    f"{tuple(c.direction)} here but at grid {ref.grid}, direction {tuple(ref.direction)} in the "
                    "first run; the model uses the first run's point")
            out.append(lookup[n])
            signs.append(1.0)
            continue
        if ref is None:  # the UFF entity name alone, as a lab calls the channel: "acc12" for "acc12 (101+Z)"
            ent = [i for i, c in enumerate(channels) if _entity_name(c.name) == n]
            if len(ent) == 1:
                log(f"{Path(path).name}: {what[:-1]} {n!r} is {channels[ent[0]].name!r} (its entity name)")
                out.append(ent[0])
                signs.append(1.0)
                continue
            if len(ent) > 1:
                missing.append(f"{n} (the entity name of {len(ent)} channels: "
                               + ", ".join(repr(channels[i].name) for i in ent) + "; name one of them)")
                continue
        hits = [] if ref is None else [i for i, c in enumerate(channels) if _same_point(c, ref)]
        flips = [] if ref is None or hits else [i for i, c in enumerate(channels) if _same_point(c, ref, -1.0)]
        if len(hits) == 1:
            log(f"{Path(path).name}: {what[:-1]} {n!r} is {channels[hits[0]].name!r} here (same grid {ref.grid}, "
                f"direction {tuple(ref.direction)})")
            out.append(hits[0])
            signs.append(1.0)
        elif len(flips) == 1:
            log(f"{Path(path).name}: {what[:-1]} {n!r} is {channels[flips[0]].name!r} here (same grid {ref.grid}, "
                f"opposite direction {tuple(channels[flips[0]].direction)}): its FRF is negated")
            out.append(flips[0])
            signs.append(-1.0)
        else:
            there = [c for c in channels if ref is not None and int(c.grid) == int(ref.grid)]
            if ref is None:  # a name not in the first run either: one that names a point ("X (101+Z)") may be a typo
                at = _named_point(n)
                same = [c.name for c in channels if at is not None and int(c.grid) == at[0]
                        and np.allclose(np.asarray(c.direction, float), at[1], atol=1e-6)]
                if same:
                    n = f"{n} (the run's {same[0]!r} is at grid {at[0]} along {tuple(at[1])}: that name?)"
                else:  # a name that differs in case or by a character or two
                    folded = [c for c in lookup if c.casefold() == n.casefold()]
                    close = folded or difflib.get_close_matches(n, list(lookup), n=1, cutoff=0.8)
                    if close:
                        n = f"{n} (did you mean {close[0]!r}?)"
            missing.append(n if ref is None else
                           f"{n} (grid {ref.grid}, direction {tuple(ref.direction)}: "
                           + (f"{len(hits)} channels along it" if hits else "none along it or opposite")
                           + ("" if hits or not there else
                              "; the run has " + ", ".join(f"{c.name!r} along {tuple(c.direction)}" for c in there)
                              + " there") + ")")
    if missing:
        raise CalibrationError(f"{path}: {what} {missing} are not {what} of the run, by name or by point "
                               f"(has {sorted(lookup)})")
    return out, np.array(signs)


def load_stage(camp: Campaign, log=print) -> LoadResult:
    """Read every run file once: select channels, drives and band, find pairs without signal.

    Raises
    ------
    CalibrationError
        Naming the run file: unknown channel or drive, no valid line in the
        band, NaN on a valid line, no pair with signal.

    A run of another FRF quantity than the first (mobility or receptance
    beside accelerance) is converted to the first run's, exactly, and
    logged; a run whose valid lines do not cover the band gets a warning.
    """
    from acquisition.runfile import read_analysis, read_run
    from identification import Identification

    ch = camp.channels
    names = list(ch.calibrate) + list(ch.holdout)
    lo, hi = camp.band.low_hz, camp.band.high_hz
    out, geometry = [], None
    first_sensors, first_drives = {}, {}  # the first run's channels and drives by name: the campaign's
    for entry in camp.run:
        path = camp.resolve(entry.path)
        run = read_run(path)
        rows, row_sign = _by_point(run.sensors, names, first_sensors, "sensors", path, log)
        wanted = list(ch.drives) or list(first_drives)  # none named: every drive of the first run
        cols, col_sign = _by_point(run.drives, wanted, first_drives, "drives", path, log) if wanted else (
            list(range(len(run.drives))), np.ones(len(run.drives)))
        if not first_sensors:
            first_sensors = {n: run.sensors[r] for n, r in zip(names, rows)}
            first_drives = {run.drives[c].name: run.drives[c] for c in cols}
        f = np.asarray(run.frequency_hz, float)
        valid = np.asarray(run.valid, bool)
        inband = (f >= lo) & (f <= hi)
        if not np.any(inband & valid):
            raise CalibrationError(
                f"{path}: band [{lo}, {hi}] Hz has no valid lines (run covers "
                f"{f.min() if f.size else float('nan'):.1f}-{f.max() if f.size else float('nan'):.1f} Hz)"
            )
        fv = f[inband & valid]
        if fv.min() > lo * 1.02 + 1e-9 or fv.max() < hi / 1.02:
            log(f"{path.name}: warning: its valid lines cover {fv.min():.4g}-{fv.max():.4g} Hz of the band "
                f"{lo:g}-{hi:g} Hz; the identified model stands in for the rest (equalized data, grouping): "
                "compare such articles with care, or narrow the band")
        H_all = np.asarray(run.frf)[:, rows][:, :, cols] * row_sign[None, :, None] * col_sign[None, None, :]
        se_all = np.asarray(run.std_error, float)
        se_all = se_all[:, rows][:, :, cols] if se_all.shape == np.asarray(run.frf).shape else None
        quantity = run.quantity
        if out and quantity != out[0].quantity:
            # the campaign's quantity is the first run's: H_to = (i w)^(k_to - k_from) H_from, exact
            to = out[0].quantity
            w = 2 * np.pi * f
            factor = quantity_factor(to, w) / quantity_factor(quantity, w)
            H_all = H_all * factor[:, None, None]
            se_all = None if se_all is None else se_all * np.abs(factor)[:, None, None]
            log(f"{path.name}: {quantity} converted to {to} (the first run's quantity; x (i w)^"
                f"{quantity_power(to) - quantity_power(quantity)})")
            quantity = to
        sel = inband & valid
        H = H_all[sel]
        se = None if se_all is None else se_all[sel]
        se = se if se is not None and np.any(se > 0) and np.all(np.isfinite(se)) else None  # all zero: not measured
        bad = ~np.all(np.isfinite(H), axis=(1, 2))
        if bad.any():
            raise CalibrationError(
                f"{path}: {bad.sum()} valid line(s) hold NaN/inf (first at {f[sel][bad][0]:.3f} Hz): flag them invalid"
            )
        drives = tuple(first_drives)  # the first run's names
        sig = signal_pairs(f[sel], H, se)
        for line in sig.describe(names, drives):
            log(f"{path.name}: {line}: left out of calibration and validation")
        if not sig.usable.any():
            raise CalibrationError(f"{path}: no channel/drive pair carries a signal above the noise in the band")
        stored, stored_channels = None, ()
        if camp.identification.use_stored and "identification" in (run.analyses or ()):
            cand = Identification.from_arrays(*read_analysis(path, "identification"))
            if cand.model.n_out == len(run.sensors) and cand.model.n_in == len(run.drives):
                # its rows in the campaign's names where a channel was matched by point
                alias = {run.sensors[r].name: n for n, r in zip(names, rows)}
                stored, stored_channels = cand, tuple(alias.get(s.name, s.name) for s in run.sensors)
                if quantity != run.quantity or np.any(row_sign < 0) or np.any(col_sign < 0):
                    log(f"{path.name}: its stored identification is not used (its {run.quantity} and channel "
                        "signs are the file's, not the campaign's): identified again")
                    stored, stored_channels = None, ()
        if geometry is None:
            # the campaign's names at the points of the run's channels they matched (by name, entity or point)
            geometry = (tuple(Transducer(n, int(run.sensors[r].grid), tuple(run.sensors[r].direction))
                              for n, r in zip(names, rows)),
                        tuple(Transducer(run.drives[c].name, int(run.drives[c].grid), tuple(run.drives[c].direction))
                              for c in cols))
        out.append(Article(
            name=entry.article or run.article,
            path=path,
            freq_hz=f[sel],
            frf=H,
            channels=tuple(names),
            drives=drives,
            identification=None,
            ident_channels=tuple(names),
            quantity=quantity,
            std_error=se,
            noise_estimate=None if se is not None else estimate_std_error(f[sel], H, what=str(path)).std_error,
            pairs=None if sig.usable.all() else sig.usable,
            lines=RunLines(f, H_all, valid, se_all),
            stored=stored,
            stored_channels=stored_channels,
        ))
    return LoadResult(tuple(out), *geometry)


# ----------------------------------------------------------------------------- model


def build_model(camp: Campaign, load: LoadResult, log=print):
    """ParametricModel + FRFModel with the campaign's channels as outputs and drives as inputs.

    Returns
    -------
    (femodel.ParametricModel, calibration.FRFModel)
    """
    import scipy.sparse as sp

    import femodel

    t0 = time.perf_counter()
    pm = femodel.parametric_model(camp.resolve(camp.model.parameters), camp.resolve(camp.model.bdf),
                                  units=camp.model.units)

    def column(t: Transducer, what: str):
        try:
            return femodel.sensor_matrix(pm.assembly, [t.grid], [t.direction])
        except ValueError as exc:
            raise CalibrationError(f"{what} {t.name!r} (grid {t.grid}, direction {tuple(t.direction)}): {exc}") from None

    C_rows = [column(t, "channel") for t in load.channels]
    B_cols = [column(t, "drive").T for t in load.drives]
    model = FRFModel(
        K=pm.K, M=pm.M,
        inputs=sp.hstack(B_cols).tocsc(),
        outputs=sp.vstack(C_rows).tocsr(),
        input_names=tuple(t.name for t in load.drives),
        output_names=tuple(t.name for t in load.channels),
        parameter_names=tuple(pm.parameters.names),
        parametric=pm,
    )
    log(f"model: {pm.K.shape[0]} DOF, {pm.n_params} parameters ({time.perf_counter() - t0:.1f} s)")
    return pm, model


# ----------------------------------------------------------------------------- identify


@dataclass(frozen=True)
class IdentifyResult:
    """The identify stage: one identification per article (stored or computed) and its output rows."""

    identifications: tuple
    channels: tuple  # per article: tuple of output names of its identification

    def attached(self, articles) -> tuple:
        """``articles`` with their identification attached."""
        return tuple(replace(a, identification=i, ident_channels=c)
                     for a, i, c in zip(articles, self.identifications, self.channels))


def identify_stage(camp: Campaign, articles, log=print) -> IdentifyResult:
    """The run file's stored identification when usable, else subspace identification of the article's lines.

    The identification band is ``[identification] low_hz/high_hz``, by default
    0.8 x band low to 1.25 x band high (clipped to the data); the work is
    :func:`frfcal.campaign.identify_lines`, the same as ``frfcal identify``.
    """
    lo, hi = camp.band.low_hz, camp.band.high_hz
    ilo = camp.identification.low_hz or 0.8 * lo
    ihi = camp.identification.high_hz or 1.25 * hi
    idents, chans = [], []
    for a in articles:
        if camp.identification.use_stored and a.stored is not None:
            idents.append(a.stored)
            chans.append(a.stored_channels)
            log(f"{a.path.name}: using stored identification (order {a.stored.order})")
            continue
        t0 = time.perf_counter()
        ln = a.lines
        ident = identify_lines(ln.frequency_hz, ln.frf, ln.valid, ln.std_error, a.quantity, (ilo, ihi),
                               order=camp.identification.order)
        blo, bhi = ident.band_hz
        how = "set" if ident.order_selection is None else f"automatic: {ident.order_selection.reason}"
        log(f"{a.path.name}: identified order {ident.order} ({how}), {ident.modal.n_modes} modes in "
            f"{blo:.0f}-{bhi:.0f} Hz, weights {ident.settings['weights']} ({time.perf_counter() - t0:.1f} s)")
        log(f"{a.path.name}: {refit_line(ident)}")
        unexplained = unexplained_line(ident)
        if unexplained:
            log(f"{a.path.name}: note: {unexplained}")
        idents.append(ident)
        chans.append(a.channels)
    return IdentifyResult(tuple(idents), tuple(chans))


def identified_modes(article: Article) -> IdentifiedModes:
    """The identified modes of an article (after the identify stage)."""
    m = article.identification.modal
    return IdentifiedModes(m.frequency_hz, m.damping, m.shapes, article.ident_channels)


def pair_mask(article: Article, channels, n_f: int):
    """FitData mask leaving out the pairs without signal (None when every pair has one)."""
    if article.pairs is None:
        return None
    use = article.pairs[[article.channels.index(n) for n in channels]]
    return None if use.all() else np.broadcast_to(use, (n_f, *use.shape)).copy()


def raw_data(article: Article, channels) -> FitData:
    """The article's measured in-band lines on ``channels``."""
    rows = [article.channels.index(n) for n in channels]
    return FitData(article.freq_hz, article.frf[:, rows], tuple(channels), article.drives, article=article.name,
                   mask=pair_mask(article, channels, article.freq_hz.size))


def ident_frf(article: Article, channels):
    """f -> the article's identified model on ``channels`` x its drives, (n_f, n_ch, n_in)."""
    rows = [article.ident_channels.index(n) for n in channels]
    ident = article.identification
    n_in = ident.model.n_in

    def frf(f):
        H = ident.frf(f)[:, rows]
        return H if n_in == len(article.drives) else H[:, :, :len(article.drives)]
    return frf


#: Relative error floor of the raw-line weights (:func:`fit_data`): a value's log ratio is never trusted
#: beyond 0.1 % of |H|, whatever its standard error says (model error, not noise, rules there).
REL_ERROR_FLOOR = 1e-3


def noise_weights(article: Article, channels) -> np.ndarray | None:
    """Per-value weights of the article's raw lines on ``channels``: 1 / variance of each log ratio,
    ``|H|^2 / (sigma^2 + (REL_ERROR_FLOOR |H|)^2)`` with sigma the run's standard errors or, without them,
    the estimate from the lines (:func:`floor_std_error`); None when neither is there. A value whose standard
    error is zero (not measured there, e.g. one average) takes its pair's median relative error instead of
    the largest weight."""
    se, _ = floor_std_error(article, channels)
    if se is None:
        return None
    rows = [article.channels.index(n) for n in channels]
    a = np.abs(article.frf[:, rows])
    rel = np.asarray(se, float) / np.where(a > 0, a, np.inf)
    measured = rel > 0
    if not measured.all():
        pos = np.where(measured, rel, np.nan)
        any_pair = measured.any(axis=0)
        med = np.full(rel.shape[1:], np.nanmedian(pos) if measured.any() else REL_ERROR_FLOOR)
        med[any_pair] = np.nanmedian(pos[:, any_pair], axis=0)  # per pair where it has measured values
        rel = np.where(measured, rel, med[None])
    w = 1.0 / (rel**2 + REL_ERROR_FLOOR**2)
    return np.where(a > 0, w, 0.0)


def fit_data(article: Article, channels, weights: str = "noise") -> FitData:
    """The raw lines on ``channels`` as the raw-line fits see them: with ``weights = "noise"`` each value
    weighted by 1 / the variance of its log ratio (:func:`noise_weights`; the maximum-likelihood estimate
    under the noise), with ``"uniform"`` every value alike (the paper's Eq. 2.23). Square deviations the
    campaign reports stay unweighted (:func:`raw_data`)."""
    d = raw_data(article, channels)
    w = noise_weights(article, channels) if weights == "noise" else None
    return d if w is None else replace(d, weights=w)


def holdout_scatter(articles, channels) -> float | None:
    """Test-to-test scatter of several articles on ``channels`` (:func:`calibration.scatter_sd`: their
    measured lines against each other less the noise), the part of a pooled model's square deviation that
    one parameter set for all of them cannot remove; None for one article."""
    if len(articles) < 2:
        return None
    raw = [raw_data(a, channels) for a in articles]
    expected = []
    for a, r in zip(articles, raw):
        se, _ = floor_std_error(a, channels)
        if se is None:
            expected = None
            break
        expected.append(expected_from_std_error(r.frf, se))
    return scatter_sd([r.freq_hz for r in raw], [r.frf for r in raw], [ident_frf(a, channels) for a in articles],
                      expected, [r.mask for r in raw])


def raw_std_error(article: Article, channels):
    """The article's standard errors on ``channels`` (None without)."""
    if article.std_error is None:
        return None
    return article.std_error[:, [article.channels.index(n) for n in channels]]


def floor_std_error(article: Article, channels):
    """(standard errors on ``channels``, source) for a floor: the run's own, else the estimate from the lines.

    Source is "per-line standard errors" or :data:`calibration.ESTIMATED`
    ("estimated from adjacent lines"); (None, None) when neither is there.
    """
    rows = [article.channels.index(n) for n in channels]
    if article.std_error is not None:
        return article.std_error[:, rows], "per-line standard errors"
    est = getattr(article, "noise_estimate", None)
    if est is None:
        return None, None
    return est[:, rows], ESTIMATED


def floors_of(articles, channels):
    """(list of standard errors or None, source) of several articles for :func:`calibration.validate`."""
    got = [floor_std_error(a, channels) for a in articles]
    if any(se is None for se, _ in got):
        return None, None
    return [se for se, _ in got], " / ".join(sorted({s for _, s in got}))


# ----------------------------------------------------------------------------- equalize


@dataclass(frozen=True)
class EqualizeResult:
    """The equalize stage: each article's identified model, damping-equalized, on the calibration channels.

    Attributes
    ----------
    freq_hz : (n_f,) half-bandwidth grid at zeta0 [Hz]
    data : tuple of FitData, one per article, equalized to zeta0
    continuation : tuple of (zeta, tuple of FitData per article), the continuation stages
    """

    freq_hz: np.ndarray
    data: tuple
    continuation: tuple = ()

    def member(self, idx):
        """(data, continuation) of the articles ``idx`` in the form :func:`calibration.calibrate_cycles` takes."""
        return ([self.data[i] for i in idx],
                [(z, [d[i] for i in idx]) for z, d in self.continuation])


def equalized_data(article: Article, zeta, freq_hz, outputs) -> FitData:
    """The article's identified model with every physical pole at ``zeta``, on ``freq_hz`` and ``outputs``."""
    from identification import equalized

    H = equalized(article.identification, zeta).frf(freq_hz)
    rows = [article.ident_channels.index(n) for n in outputs]
    return FitData(freq_hz, H[:, rows], tuple(outputs), inputs=article.drives, article=article.name,
                   mask=pair_mask(article, outputs, freq_hz.size))


def equalize_stage(camp: Campaign, articles) -> EqualizeResult:
    """Equalized data at zeta0 and at each continuation damping, on their half-bandwidth grids."""
    c = camp.calibration
    band = (camp.band.low_hz, camp.band.high_hz)
    chans = camp.channels.calibrate
    f = half_bandwidth_frequencies(*band, c.zeta0, c.samples_per_half_bandwidth)
    data = tuple(equalized_data(a, c.zeta0, f, chans) for a in articles)
    cont = []
    for z in c.continuation_zeta:
        fz = half_bandwidth_frequencies(*band, z, c.samples_per_half_bandwidth)
        cont.append((z, tuple(equalized_data(a, z, fz, chans) for a in articles)))
    return EqualizeResult(f, data, tuple(cont))


# ----------------------------------------------------------------------------- group


@dataclass(frozen=True)
class GroupResult:
    """The group stage: the ensemble members (label, article indices), pairwise SD and grouping (or None)."""

    members: tuple  # of (label, tuple of int)
    pairwise_sd: np.ndarray | None = None
    grouping: Grouping | None = None


def group_stage(camp: Campaign, articles, equalize: EqualizeResult, log=print) -> GroupResult:
    """Members of the ensemble: all articles, each, or groups of articles by their pairwise SD."""
    mode = camp.calibration.ensemble
    if len(articles) == 1:
        return GroupResult((("all", tuple(range(len(articles)))),))
    if mode == "article":
        return GroupResult(tuple((a.name, (i,)) for i, a in enumerate(articles)))
    # the pairs without signal (left out of calibration and validation) are left out here too: an identified
    # model's FRF at a noise-only pair is arbitrary and would swamp the articles' differences
    masks = None
    if any(d.mask is not None for d in equalize.data):
        masks = [np.ones(d.frf.shape, bool) if d.mask is None else d.mask for d in equalize.data]
    D = pairwise_sd([d.frf for d in equalize.data], masks)
    floors = []
    for a in articles:
        se = raw_std_error(a, camp.channels.calibrate)
        floors.append(None if se is None else noise_floor_sd(raw_data(a, camp.channels.calibrate), se))
    grp = grouping(D, camp.calibration.n_groups, None if any(x is None for x in floors) else floors)
    labels = grp.labels
    groups = [tuple(i for i in range(len(articles)) if labels[i] == g) for g in range(labels.max() + 1)]
    if mode == "all":  # one member; the grouping is said (and kept for the report and the diagnosis's verdict)
        if len(groups) > 1:
            log(f"grouping: the articles fall into {len(groups)} groups ({split_words(articles, groups)}); "
                "[calibration] ensemble = \"all\" fits one parameter set to all of them, so what differs between "
                "the groups (an effect on some articles only) stays in the residual: ensemble = \"group\" "
                "calibrates and diagnoses each group")
            log("grouping: " + grp.describe([a.name for a in articles]))
        return GroupResult((("all", tuple(range(len(articles)))),), D, grp)
    log("groups: " + split_words(articles, groups))
    log("grouping: " + grp.describe([a.name for a in articles]))
    return GroupResult(tuple((f"group{g + 1}", idx) for g, idx in enumerate(groups)), D, grp)


def split_words(articles, groups) -> str:
    """"A1, A2; A3, A4": the articles of each group (tuples of article indices)."""
    return "; ".join(", ".join(articles[i].name for i in g) for g in groups)


# ----------------------------------------------------------------------------- calibrate


@dataclass(frozen=True)
class MemberCalibration:
    """One ensemble member's calibration.

    Attributes
    ----------
    label : str
    articles : tuple of int, indices into the load stage's articles
    cycle : CycleResult
        The equalized stage (multi-start, re-basis cycles). Its ``basis`` is
        None after a resume (not stored).
    refinement : Refinement or None
        The raw-line refinement with its re-basis cycles (None with
        ``[calibration] refine = false``).
    p : (n_p,) the reported normalized parameters (refined when refined)
    surrogate : Surrogate at ``p``'s basis point
    identifiability : Identifiability at ``p``
    time_s : float, wall time of this member's calibration
    basis : (n, r) ndarray or None
        The full-order basis of ``surrogate`` (for diagnosis and model
        extension, :func:`calibration.extended_surrogate`). Not stored: None
        after a resume.
    """

    label: str
    articles: tuple
    cycle: CycleResult
    refinement: Refinement | None
    p: np.ndarray
    surrogate: Surrogate
    identifiability: Identifiability
    time_s: float = 0.0
    basis: np.ndarray | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class CalibrateResult:
    """The calibrate stage: the nominal surrogate and every member's calibration; ``level``: per article the
    model's FRF level over the data's at the nominal parameters (:func:`level_check`; empty when it is off)."""

    surrogate: Surrogate
    members: tuple  # of MemberCalibration
    basis_s: float = 0.0
    level: dict = field(default_factory=dict)


def raw_rebasis_tol(c, cycle: int | None) -> float:
    """The basis-check tolerance before raw-line re-basis ``cycle`` (0-based; None: the check at the reported
    point once the cycles ran out): the first re-basis follows the refinement's large step and is gated only by
    ``refine_basis_tol``; later ones by it, else by ``basis_tol`` (0: no check, the p-move trigger alone)."""
    return c.refine_basis_tol if cycle == 0 else (c.refine_basis_tol or c.basis_tol)


def raw_basis_check(model, sur, basis, ref, band, tol: float):
    """(BasisCheck, zeta_min): the Ritz-residual check of ``basis`` at the raw-line refinement ``ref``'s point,
    against Ritz frequency errors of ``tol`` x the half-power bandwidth of its least damped estimated mode."""
    zeta_min = max(min(float(np.min(z)) for z in ref.zeta), 1e-5)
    return basis_residuals(model, sur, basis, ref.p, band, 4 * tol * zeta_min), zeta_min


def _refined(camp: Campaign, model, arts, cyc, band, lower, upper, log, label):
    """Refine the equalized optimum on the raw lines, then re-basis the raw-line stage: once after the
    refinement's step, again (up to ``refine_cycles``) while p moves and the last basis fails its check at p.

    Returns (Refinement of the last cycle with every stage of all cycles, p, surrogate, its basis).
    """
    c = camp.calibration
    raw = [fit_data(a, camp.channels.calibrate, c.refine_weights) for a in arts]
    idents = [(a.identification, a.ident_channels) for a in arts]
    modes = [identified_modes(a) for a in arts]
    opts = dict(quantity=arts[0].quantity, mac_min=camp.validation.mac_min, band_hz=band,
                max_nfev=c.max_evaluations)
    t0 = time.perf_counter()
    ref = refine(cyc.surrogate, cyc.p, raw, idents, modes, lower, upper, c.zeta0, floors=c.refine_floors, **opts)
    start = ref.sd_raw_start  # at the equalized optimum: the re-basis cycles below start from the refined point
    stages = list(ref.stages)
    log(f"[{label}] raw-line SD (identified damping) {ref.sd_raw_start:.4g} -> {ref.sd_raw:.4g} "
        f"after {len(ref.stages)} refinement stage(s), max |dp| {np.max(np.abs(ref.p - cyc.p)):.3g} "
        f"({time.perf_counter() - t0:.1f} s)")
    sur, basis = cyc.surrogate, cyc.basis
    checks = []
    for k in range(c.refine_cycles):
        tol = raw_rebasis_tol(c, k)  # a later re-basis only where the last basis fails at the new point
        if tol and basis is not None:
            chk, zeta_min = raw_basis_check(model, sur, basis, ref, band, tol)
            checks.append({**chk.to_dict(), "cycle": k + 1})
            log(f"[{label}] raw-line re-basis {k + 1}: basis at the refined point (damping down to "
                f"{100 * zeta_min:.3g} %): {chk.describe()}" + (": kept" if chk.adequate else ""))
            if chk.adequate:
                break
        t0 = time.perf_counter()
        old_sur, old_basis = sur, basis
        # the first re-basis follows the refinement's large step from the equalized basis (rebasis); the later
        # ones follow smaller steps (refine_rebasis); "compressed" (both defaults) corrects the basis with the
        # first build's factorization and cuts it back to a cold build's size
        kind = c.rebasis if k == 0 else c.refine_rebasis
        sur, basis, corr = rebased(model, sur, basis, ref.p, band, c.basis_factor, c.enrich, kind)
        if corr is not None:
            log(f"[{label}] raw-line re-basis {k + 1}: basis corrected at the refined point: {corr.describe()}")
        carry = {}
        if old_basis is not None:  # start where the last raw stage ended (its damping, carried to the new modes)
            zeta, fit = carried_damping(old_sur, old_basis, ref.zeta, ref.fit_modes, ref.p_zeta, sur, basis,
                                        ref.p, assembled(model, ref.p)[1])
            carry = dict(zeta=zeta, fit_modes=fit)
        if c.rebasis_hold:
            carry["hold"] = c.rebasis_hold
        nxt = refine(sur, ref.p, raw, idents, modes, lower, upper, c.zeta0, floors=(0.0,), **carry, **opts)
        dp = float(np.max(np.abs(nxt.p - ref.p)))
        stages.extend(nxt.stages)
        ref = nxt
        log(f"[{label}] raw-line re-basis {k + 1}: SD {ref.sd_raw:.4g}, max |dp| {dp:.2e} "
            f"({time.perf_counter() - t0:.1f} s)")
        if dp < c.cycle_tol:
            break
    else:
        tol = raw_rebasis_tol(c, None)
        if tol and c.refine_cycles and basis is not None:
            # the cycles ran out: say how well the final basis holds the reported point (a diagnostic only)
            chk, _ = raw_basis_check(model, sur, basis, ref, band, tol)
            checks.append({**chk.to_dict(), "final": True})
            log(f"[{label}] raw-line re-basis cycles used up; final basis at the final point: {chk.describe()}")
    for line in ref.describe_unpaired([a.name for a in arts]):
        log(f"[{label}] note: {line}")
    return replace(ref, stages=tuple(stages), basis_checks=tuple(checks), sd_raw_start=start), ref.p, sur, basis


def _identifiability(camp: Campaign, cyc, data, ref, p, sur, arts, lower, upper, names):
    """Identifiability at the reported point, from the objective that produced it.

    After the refinement that is the raw-line objective (identified damping as
    estimated, each article's lines); else the equalized one. The residual is
    stacked frequency-major per data set, so adjacent lines are n_out x n_in
    values apart (the stride of the correlated-residual inflation).
    """
    if ref is None:
        obj = Objective(cyc.surrogate, data, camp.calibration.zeta0, arts[0].quantity)
        stride = data[0].frf.shape[1] * data[0].frf.shape[2]
    else:
        raw = [fit_data(a, camp.channels.calibrate, camp.calibration.refine_weights) for a in arts]
        obj = ModalDampingObjective(sur, raw, ref.zeta, ref.p_zeta, 0.0, arts[0].quantity)
        stride = raw[0].frf.shape[1] * raw[0].frf.shape[2]
    return identifiability(obj.jacobian(p), obj.residual(p), p, lower, upper, names, stride=stride)


#: A channel whose FRF level (model over data) is off its article's by more than this factor is named in the
#: level check's log: the smallest unit slip, g against m/s^2, is 9.81x; physics the model lacks changes a
#: channel's level less (the demo's closed gap: 4.2x on the channel beside it).
CHANNEL_FACTOR = 8.0


def _unit_hint(factor: float, units: str) -> str:
    """The unit systems whose deck, read as ``units``, makes the model's FRFs ``factor`` x the data's."""
    from femodel import UNIT_SYSTEMS, unit_system

    read = unit_system(units)
    per = read.force_n / read.length_m  # an FRF of length over force: SI value per deck number read as ``units``
    fits = [name for name, u in UNIT_SYSTEMS.items() if name not in (read.name, "consistent")
            and abs(np.log10(factor * per * u.length_m / u.force_n)) < 0.15]
    if fits:
        return (f"that is what a deck in {' or '.join(repr(f) for f in fits)} read as {units!r} gives: set "
                f"[model] units (or \"units\" in the parameter file) to the deck's unit system")
    return (f"no unit system of the deck explains it (read as {units!r}); check the data files' units "
            f"(accelerations in g labelled m/s^2 are 9.81 x off) and the channels' grids; a model that does lack "
            f"that much may raise [calibration] level_factor")


def _weighted_median(x, w) -> float:
    """The value below which half the weight ``w`` of ``x`` lies."""
    order = np.argsort(x)
    c = np.cumsum(np.asarray(w, float)[order])
    return float(np.asarray(x)[order][np.searchsorted(c, 0.5 * c[-1])])


def level_check(camp: Campaign, sur: Surrogate, articles, units: str = "si", log=print) -> dict:
    """The model's FRF level at the nominal parameters against each article's lines (calibration and hold-out
    channels).

    Per channel-drive pair, the median over the lines of log10 |H_model| / |H_data|, each line weighted by
    the log-frequency interval it stands for (a grid dense at the resonances, where the model at
    ``[calibration] zeta0`` and the lightly damped data differ most, does not pull it; resonance offsets move
    single lines, not the median); per article the median over its pairs. An article off by more than
    ``[calibration] level_factor`` is refused with the factor and its likely cause (:func:`_unit_hint`); a
    channel off the article's level by more than :data:`CHANNEL_FACTOR` is named in the log (its units, its
    grid or its direction). Offsets within the bounds change levels by tens of percents, never by a factor of
    4; beyond it the cause is an input error, usually the deck's unit system (an mm-t-s deck read as SI is
    1000 x the data; g labelled m/s^2 9.81 x). ``level_factor = 0``: no check.

    Returns {article: factor} (model over data).
    """
    limit = float(camp.calibration.level_factor)
    if limit <= 0:
        return {}
    chans = list(camp.channels.calibrate) + list(camp.channels.holdout)
    rows = [sur.output_names.index(n) for n in chans]
    p0 = np.zeros(sur.n_params)
    modes = reduced_modes(sur, p0)
    out, bad = {}, []
    for a in articles:
        d = raw_data(a, chans)
        if d.freq_hz.size == 0:
            continue
        cols = [sur.input_names.index(n) for n in a.drives]
        H = surrogate_frf(sur, p0, d.freq_hz, camp.calibration.zeta0, a.quantity, outputs=rows,
                          modes=modes)[:, :, cols]
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.log10(np.abs(H)) - np.log10(np.abs(d.frf))
        ok = np.isfinite(r) if d.mask is None else np.isfinite(r) & d.mask
        w = log_frequency_weights(d.freq_hz)
        pair = np.full(r.shape[1:], np.nan)
        for i, j in zip(*np.nonzero(ok.any(axis=0))):
            pair[i, j] = _weighted_median(r[ok[:, i, j], i, j], w[ok[:, i, j]])
        if not np.isfinite(pair).any():
            continue
        level = float(np.nanmedian(pair))
        out[a.name] = 10.0**level
        if abs(level) > np.log10(limit):
            bad.append((a.name, 10.0**level, int(ok.any(axis=(1, 2)).sum()), int(np.isfinite(pair).sum())))
            continue
        for i, name in enumerate(chans):
            if np.isfinite(pair[i]).any() and abs(np.nanmedian(pair[i]) - level) > np.log10(CHANNEL_FACTOR):
                log(f"{a.name}: channel {name!r}: the model's FRFs are {10.0 ** np.nanmedian(pair[i]):.3g} x the "
                    f"data's where the other channels' are {10.0 ** level:.3g} x: check its units, grid and "
                    f"direction (or physics the model lacks near it)")
    if bad:
        name, factor, n_lines, n_pairs = bad[0]
        others = "".join(f"; {n}: {f:.3g} x" for n, f, _, _ in bad[1:])
        raise CalibrationError(
            f"{name}: at the nominal parameters the model's FRFs are {factor:.3g} x the measured ones (the median "
            f"over {n_lines} lines and {n_pairs} channel-drive pairs of the calibration and hold-out channels"
            f"{others}); no parameter within its bounds closes more than a factor {limit:g} "
            f"([calibration] level_factor): {_unit_hint(factor, units)}")
    if out:
        log("level check: model over data at the nominal parameters (median) "
            + ", ".join(f"{n} {f:.3g}" for n, f in out.items()))
    return out


def calibrate_stage(camp: Campaign, model, articles, equalize: EqualizeResult, groups: GroupResult, executor,
                    log=print) -> CalibrateResult:
    """Nominal surrogate, then per member: equalized multi-start with re-basis cycles, raw-line refinement,
    identifiability at the result.

    ``executor`` runs the multi-start (start it before: its workers then
    import while the basis is built); ``articles`` carry their identification.
    """
    c = camp.calibration
    band = (camp.band.low_hz, camp.band.high_hz)
    pm = model.parametric
    lower, upper = pm.lower, pm.upper
    t = time.perf_counter()
    sur0, T0 = build_surrogate(model, np.zeros(pm.n_params), band, c.basis_factor, enrich=c.enrich)
    basis_s = time.perf_counter() - t
    log(f"surrogate: {sur0.size} ({len(sur0.basis_frequencies_hz)} modes, {sur0.n_static} static and moment, "
        f"{sur0.n_enrich} enrichment) in {basis_s:.1f} s")
    level = level_check(camp, sur0, articles, pm.units, log)
    opts = CycleOptions(n_starts=c.starts, seed=c.seed, quantity=articles[0].quantity, max_cycles=c.max_cycles,
                        adaptive_starts=c.adaptive_starts,
                        tol=c.cycle_tol, basis_factor=c.basis_factor, enrich=c.enrich, max_nfev=c.max_evaluations,
                        basis_tol=c.basis_tol or None, rebasis=c.rebasis)
    members = []
    for label, idx in groups.members:
        arts = [articles[i] for i in idx]
        data, cont = equalize.member(idx)
        t = time.perf_counter()
        log(f"[{label}] calibrating on {len(arts)} article(s), {len(equalize.freq_hz)} frequencies x "
            f"{len(camp.channels.calibrate)} channels, "
            f"{'up to ' if c.adaptive_starts and c.starts + 1 > MIN_STARTS else ''}{c.starts + 1} starts")
        cyc = calibrate_cycles(model, data, band, lower, upper, c.zeta0, options=replace(opts, quantity=arts[0].quantity),
                               executor=executor, surrogate=sur0, basis=T0, continuation=cont, log=log)
        log(f"[{label}] calibration SD (equalized test model, zeta0={100 * c.zeta0:g} %) "
            f"{cyc.calibration.sd_nominal:.4g} -> {cyc.sd:.4g} ({time.perf_counter() - t:.1f} s)")
        ref, p_final, sur_final, basis_final = None, cyc.p, cyc.surrogate, cyc.basis
        if c.refine:
            ref, p_final, sur_final, basis_final = _refined(camp, model, arts, cyc, band, lower, upper, log, label)
        t_cal = time.perf_counter() - t
        idf = _identifiability(camp, cyc, data, ref, p_final, sur_final, arts, lower, upper, pm.parameters.names)
        log(f"[{label}] identifiability at the calibrated point:\n{idf.table()}")
        members.append(MemberCalibration(label, tuple(idx), cyc, ref, p_final, sur_final, idf, t_cal, basis_final))
    return CalibrateResult(sur0, tuple(members), basis_s, level)


# ----------------------------------------------------------------------------- validate


@dataclass(frozen=True)
class MemberValidation:
    """One member's hold-out validation (None without hold-out channels) and per-article estimates.

    ``articles``: with several refined articles, each article's own raw-line
    estimate started from the member's (dicts: article, p,
    sd_raw_calibration, sd_holdout); else empty. ``scatter``: with several
    articles, their test-to-test scatter on the hold-out channels
    (:func:`holdout_scatter`), which one parameter set for all cannot remove;
    None with one.
    """

    label: str
    validation: Validation | None
    articles: tuple = ()
    time_s: float = 0.0
    scatter: float | None = None

    @property
    def floor_with_scatter_ratio(self) -> float | None:
        """Calibrated hold-out SD over noise floor + test-to-test scatter (None without both)."""
        v = self.validation
        if v is None or self.scatter is None or not v.sd_floor:
            return None
        return v.sd_calibrated / (v.sd_floor + self.scatter)


@dataclass(frozen=True)
class ValidationResult:
    members: tuple  # of MemberValidation


def _per_article(camp: Campaign, sur0, sur, arts, p, band, lower, upper, log, label) -> tuple:
    """Each article's own raw-line estimate, started from the ensemble's, and its hold-out SD.

    One parameter set cannot fit several articles to their noise floor: the
    articles differ (test-to-test scatter), and at 0.1 % damping a 0.3 %
    stiffness difference already moves a resonance by most of a half-power
    bandwidth. The ensemble estimate stays the member's result; these per-article
    estimates show the scatter (their spread) and whether each article's data
    are explained to their floor.
    """
    c = camp.calibration
    out = []
    for a in arts:
        modes = identified_modes(a)
        r = refine(sur, p, [fit_data(a, camp.channels.calibrate, c.refine_weights)],
                   [(a.identification, a.ident_channels)], [modes], lower, upper, c.zeta0, floors=(0.0,),
                   quantity=a.quantity, mac_min=camp.validation.mac_min, band_hz=band, max_nfev=c.max_evaluations)
        row = {"article": a.name, "p": r.p.tolist(), "sd_raw_calibration": r.sd_raw, "sd_holdout": None}
        if camp.channels.holdout:
            errs, src = floors_of([a], camp.channels.holdout)
            v = validate(sur0, sur, r.p, [raw_data(a, camp.channels.holdout)], modes, c.zeta0, None,
                         camp.validation.mac_min, a.quantity, band, std_error=errs, floor_source=src,
                         with_floor_range=False)
            row["sd_holdout"] = v.sd_calibrated
            row["sd_holdout_floor"] = v.sd_floor
        out.append(row)
        log(f"[{label}] article {a.name}: own estimate, raw-line SD {r.sd_raw:.4g}"
            + ("" if row["sd_holdout"] is None else f", hold-out SD {row['sd_holdout']:.4g}")
            + ("" if row.get("sd_holdout_floor") is None else f" (floor ~{row['sd_holdout_floor']:.2g})"))
    P = np.array([r["p"] for r in out])
    spread = (1 + P).std(axis=0, ddof=1) / (1 + P).mean(axis=0)
    log(f"[{label}] article-to-article spread of the estimates: median {100 * np.median(spread):.3g} %, "
        f"largest {100 * spread.max():.3g} %")
    return tuple(out)


def validate_stage(camp: Campaign, articles, cal: CalibrateResult, bounds, log=print) -> ValidationResult:
    """Hold-out validation of every member (raw hold-out lines, damping as the refinement estimated it),
    and each article's own estimate when a refined member has several articles.

    ``bounds`` is (lower, upper) of the normalized parameters.
    """
    c = camp.calibration
    band = (camp.band.low_hz, camp.band.high_hz)
    lower, upper = bounds
    out = []
    for m in cal.members:
        arts = [articles[i] for i in m.articles]
        ref = m.refinement
        t = time.perf_counter()
        val, scatter = None, None
        if camp.channels.holdout:
            raw = [raw_data(a, camp.channels.holdout) for a in arts]
            errs, src = floors_of(arts, camp.channels.holdout)
            val = validate(cal.surrogate, m.surrogate, m.p, raw, [identified_modes(a) for a in arts], c.zeta0,
                           camp.validation.target_sd, camp.validation.mac_min, arts[0].quantity, band,
                           std_error=errs, damping=None if ref is None else (ref.zeta, ref.p_zeta),
                           floor_source=src)
            log(f"[{m.label}] {val.summary()}")
            scatter = holdout_scatter(arts, camp.channels.holdout)
        rows = ()
        if ref is not None and len(arts) > 1:
            rows = _per_article(camp, cal.surrogate, m.surrogate, arts, m.p, band, lower, upper, log, m.label)
        mv = MemberValidation(m.label, val, rows, time.perf_counter() - t, scatter)
        if mv.floor_with_scatter_ratio is not None:
            log(f"[{m.label}] hold-out floor of one parameter set for {len(arts)} articles: noise "
                f"{val.sd_floor:.2g} + their test-to-test scatter {scatter:.2g} (measured lines against each "
                f"other): {mv.floor_with_scatter_ratio:.2g}x")
        out.append(mv)
    return ValidationResult(tuple(out))


# ----------------------------------------------------------------------------- cross-validate


@dataclass(frozen=True)
class MemberCrossValidation:
    """One member's cross-validation; ``identifiability`` is the calibrate stage's verdict checked against
    the refits' spread (:func:`calibration.with_spread`), None without refits."""

    label: str
    crossvalidation: CrossValidation | None
    time_s: float = 0.0
    identifiability: Identifiability | None = None


@dataclass(frozen=True)
class CrossValidationResult:
    members: tuple  # of MemberCrossValidation


def crossvalidate_stage(camp: Campaign, articles, equalize: EqualizeResult, cal: CalibrateResult, bounds,
                        parameter_names, executor, log=print) -> CrossValidationResult:
    """Monte Carlo half/half recalibration of what each member calibrated last.

    After the refinement: the raw calibration lines with the identified
    damping as estimated; else the equalized data.
    """
    c, xv = camp.calibration, camp.crossvalidation
    lower, upper = bounds
    out = []
    for m in cal.members:
        arts = [articles[i] for i in m.articles]
        t = time.perf_counter()
        cv = None
        if xv.realizations:
            ref = m.refinement
            if ref is None:
                data, _ = equalize.member(m.articles)
                cv = cross_validate(m.cycle.surrogate, data, m.cycle.p, lower, upper, c.zeta0, xv.realizations,
                                    xv.seed, executor, arts[0].quantity, xv.max_evaluations)
            else:
                cv = cross_validate(m.surrogate, [fit_data(a, camp.channels.calibrate, c.refine_weights)
                                                  for a in arts], m.p,
                                    lower, upper, c.zeta0, xv.realizations, xv.seed, executor, arts[0].quantity,
                                    xv.max_evaluations, damping=(ref.zeta, ref.p_zeta))
            log(f"[{m.label}] cross-validation RSE {cv.rse:.4g} ({cv.p.shape[0]} realizations)")
            for j in np.flatnonzero(cv.n_at_bound):
                log(f"[{m.label}] CV of {parameter_names[j]}: not meaningful, {cv.cv_reason[j]}")
        idf = None
        if cv is not None and m.identifiability is not None:
            idf = with_spread(m.identifiability, cv.p)
            before, after = np.asarray(m.identifiability.identifiable), np.asarray(idf.identifiable)
            for j in np.flatnonzero(before & ~after):
                log(f"[{m.label}] {parameter_names[j]} NOT identifiable after all: {idf.reasons[j]}")
            for j in np.flatnonzero(~before & after):
                log(f"[{m.label}] {parameter_names[j]} identifiable after all: its {cv.p.shape[0]} refits agree to "
                    f"{100 * idf.spread[j]:.2g} % (within 1 % of its range) though it takes part in a weak "
                    "combination")
            if idf.n_identifiable != m.identifiability.n_identifiable:
                log(f"[{m.label}] {idf.n_identifiable} of {len(parameter_names)} parameters identifiable "
                    "(checked against the cross-validation refits)")
        out.append(MemberCrossValidation(m.label, cv, time.perf_counter() - t, idf))
    return CrossValidationResult(tuple(out))
