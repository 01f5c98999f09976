"""Hold-out validation (paper Eq. 2.22-2.24) with FE damping mapped from identified modes.

The calibrated surrogate's modes are paired with the identified modes by MAC
at the measured channels (one-to-one, greedy on the largest MAC, pairs below
``mac_min`` dropped); a paired FE mode takes the identified modal damping,
an unpaired one keeps zeta0. The hold-out FRFs are then synthesized with
that per-mode damping and compared with the *raw* test lines (only lines
flagged valid) by the square deviation SD = gamma^H gamma / N.

The same mapping is applied at the nominal point, so SD(p0) and SD(p*)
differ only by the parameters. With several articles each data item takes
the damping identified on its own article (one IdentifiedModes per item).

The outcome is worded for what it shows: "improved" or "worse" (SD(p*)
against SD(p0)); "below target"/"above target" only when a target SD was
set. A lower SD is not a pass: a model that lacks physics also improves.

Noise floor. When the per-line standard errors ``sigma`` of the raw FRF
estimates are known (run files store them, same unit as the FRF, the rms of
the complex error), the SD that measurement noise alone leaves is estimated
as ``floor = mean E|log10(1 + n/H)|^2`` over the compared values, with
``E|n|^2 = sigma^2`` (:func:`calibration._metric.log_noise_variance`): that is
``(sigma / |H|)^2 / (ln 10)^2`` where ``sigma << |H|``, and grows only
logarithmically where the noise reaches |H| (anti-resonances, a channel near
its noise), where the first-order form blew up.
A calibrated SD near the floor (ratio ~1) leaves nothing for the model to
explain; a ratio of 10 means model error dominates the noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration._errors import CalibrationError
from calibration._fit import FitData
from calibration._metric import log_deviation, log_noise_floor, square_deviation
from calibration._surrogate import Surrogate, modal_frf, reduced_modes
from calibration._damping import IdentifiedModes, mapped_damping, median_damping, pair_modes  # noqa: F401 (re-exported)
from calibration._refine import ModalDampingObjective
from labdata import mac  # noqa: F401 (re-exported)


def _deviation(sur: Surrogate, p, data: FitData, zeta, quantity: str) -> np.ndarray:
    lam, X = reduced_modes(sur, p)
    rows = sur.output_index(data.outputs)
    if data.inputs:
        lookup = {n: i for i, n in enumerate(sur.input_names)}
        missing = [n for n in data.inputs if n not in lookup]
        if missing:
            raise CalibrationError(f"drives {missing} are not inputs of the model {list(sur.input_names)}")
        cols = np.array([lookup[n] for n in data.inputs])
    else:
        cols = np.arange(sur.inputs.shape[1])
    H = modal_frf(lam, sur.outputs[rows] @ X, X.T @ sur.inputs[:, cols], data.freq_hz, zeta, quantity, sur.rigid_hz)
    g = log_deviation(H, data.frf)
    return (g if data.mask is None else g[data.mask]).ravel()


def holdout_sd(sur: Surrogate, p, data: FitData, zeta, quantity: str = "accelerance") -> float:
    """SD (Eq. 2.23) of the surrogate at p with per-mode damping ``zeta`` against ``data``."""
    return square_deviation(_deviation(sur, p, data, zeta, quantity))


def noise_floor_sd(data: FitData, std_error) -> float:
    """SD that the measurement noise alone leaves on ``data`` (see the module docstring).

    Parameters
    ----------
    data : FitData, the raw lines compared (mask = values compared)
    std_error : (n_f, n_out, n_in) float, standard error of each FRF value (same unit)

    Returns
    -------
    float, mean E|log10(1 + n/H)|^2 (E|n|^2 = sigma^2) over the compared values: (sigma/|H|)^2 / (ln 10)^2
    where sigma << |H| (:func:`calibration._metric.log_noise_variance`).
    """
    sig = np.asarray(std_error, float)
    if sig.shape != data.frf.shape:
        raise CalibrationError(
            f"standard errors of {data.article or 'the hold-out data'}: shape {sig.shape} != FRF shape {data.frf.shape}"
        )
    q = log_noise_floor(data.frf, sig)
    q = q if data.mask is None else q[data.mask]
    if not np.all(np.isfinite(q)):
        raise CalibrationError(
            f"standard errors of {data.article or 'the hold-out data'}: NaN/inf or a zero FRF value among the compared lines"
        )
    return float(np.mean(q))


def floor_range_note(low: float, high: float) -> str:
    """How the hold-out line states the floor's range (:func:`floor_range`), printed and in the report."""
    return f"at its floor a model scores {range_text(low, high)} in 90 % of noise draws"


def range_text(low: float, high: float) -> str:
    """``"low-high"`` with 2 significant digits, more (up to 4) where 2 would print both the same."""
    for d in (2, 3, 4):
        a, b = f"{low:.{d}g}", f"{high:.{d}g}"
        if a != b:
            break
    return f"{a}-{b}"


#: At most this many noise values (draws x values) behind :func:`floor_range` (about 1 s).
FLOOR_RANGE_BUDGET = 2e7


def floor_range(h_model, std_error, draws: int = 400, seed: int = 0, levels=(5.0, 95.0)) -> tuple[float, float]:
    """The SD a model at its floor scores under the noise alone: the ``levels`` percentiles over noise draws.

    The floor (:func:`noise_floor_sd`) is the mean of per-value expectations,
    but the SD a correct model realizes is one draw of a heavy-tailed mean: a
    value whose |H| is below its noise (an anti-resonance, a cross-axis pair)
    contributes ``|log10(H / (H + n))|^2`` up to tens of times its expectation,
    and a handful of such values can carry most of it (outside-style frame:
    one line at an anti-resonance, |H| a quarter of its noise, held 83 % of a
    pair's realized floor; the truth then scored 2.1-2.4 x the expected
    floor). So beside the floor this gives the range a correct model falls in:
    complex Gaussian noise of the values' standard errors about the model's
    own values ``h_model`` (its |H|, not the data's, decides how near the noise
    a value is), ``draws`` times (fewer for large data: at most
    :data:`FLOOR_RANGE_BUDGET` values in all, at least 50 draws).

    Parameters
    ----------
    h_model : complex array, the model's FRF values compared (any shape)
    std_error : float array, their standard errors (same shape)

    Returns
    -------
    (low, high) : float, the SDs at ``levels`` (default the 5th and 95th percentiles)
    """
    H = np.asarray(h_model, complex).ravel()
    s = np.asarray(std_error, float).ravel()
    if H.shape != s.shape:
        raise CalibrationError(f"floor_range: {H.size} model values but {s.size} standard errors")
    ok = np.isfinite(H) & np.isfinite(s) & (np.abs(H) > 0)
    H, s = H[ok], s[ok]
    if H.size == 0:
        raise CalibrationError("floor_range: no finite model value with a finite standard error")
    draws = int(max(50, min(draws, FLOOR_RANGE_BUDGET // H.size)))
    rng = np.random.default_rng(seed)
    scale = s / np.sqrt(2.0)
    sds = np.empty(draws)
    for k in range(draws):
        noisy = H + scale * (rng.standard_normal(H.size) + 1j * rng.standard_normal(H.size))
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.abs(np.log10(H / noisy)) ** 2
        sds[k] = float(np.mean(e[np.isfinite(e)]))
    lo, hi = np.percentile(sds, levels)
    return float(lo), float(hi)


@dataclass(frozen=True)
class Validation:
    """Hold-out validation outcome (paper Eq. 2.24).

    sd_nominal, sd_calibrated : SD on the hold-out raw lines at p0 and p*, identified damping
    target : SD target (None if not set)
    improved : SD(p*) < SD(p0) ; below_target : SD(p*) < target (None without target)
    sd_floor : noise-floor estimate of the SD from the lines' standard errors (None without them)
    pairs_nominal, pairs_calibrated : per data item, the MAC pairs used for the damping mapping
    mac_nominal, mac_calibrated : per data item, (m_fe, m_test) MAC matrices
    items : per data item dict (article, sd_nominal, sd_calibrated, sd_floor, n_values)
    damping_source : "identified" (MAC-mapped at both points) or "estimated" (calibrated point:
        the damping the refinement estimated on the calibration channels)
    n_values : number of complex values compared
    floor_range : (low, high) 5-95 % of the SD a model at its floor scores under the noise alone
        (:func:`floor_range`, about the calibrated model's values; None without standard errors)
    """

    sd_nominal: float
    sd_calibrated: float
    target: float | None
    improved: bool
    below_target: bool | None
    pairs_nominal: tuple
    pairs_calibrated: tuple
    mac_nominal: tuple
    mac_calibrated: tuple
    n_values: int
    sd_floor: float | None = None
    items: tuple = ()
    damping_source: str = "identified"
    floor_source: str | None = None
    floor_range: tuple | None = None

    @property
    def floor_ratio(self) -> float | None:
        """SD(p*) / noise floor (None without a floor)."""
        return self.sd_calibrated / self.sd_floor if self.sd_floor else None

    @property
    def verdict(self) -> str:
        """"improved" or "worse", with "below target"/"above target" only when a target was set."""
        v = "improved" if self.improved else "worse"
        if self.below_target is not None:
            v += f", {'below' if self.below_target else 'above'} target {self.target:.4g}"
        return v

    def summary(self) -> str:
        """One line: ``hold-out SD (raw lines, identified damping) a -> b, floor ~c (r x) (verdict)``."""
        txt = f"hold-out SD (raw lines, identified damping) {self.sd_nominal:.4g} -> {self.sd_calibrated:.4g}"
        if self.damping_source != "identified":
            txt += " (calibrated model: damping estimated on the calibration channels)"
        if self.sd_floor:
            src = f" ({self.floor_source})" if self.floor_source and "estimated" in self.floor_source else ""
            txt += f", floor ~{self.sd_floor:.2g}{src} ({self.floor_ratio:.1f}x"
            txt += f"; {floor_range_note(*self.floor_range)})" if self.floor_range else ")"
        return f"{txt} ({self.verdict})"

    def to_dict(self) -> dict:
        return {
            "definition": "SD of the raw hold-out lines; FE damping mapped from the identified modes per article "
                          "(nominal), " + ("the same at the calibrated point" if self.damping_source == "identified"
                                           else "estimated on the calibration channels (calibrated)"),
            "damping_source": self.damping_source,
            "sd_nominal": self.sd_nominal,
            "sd_calibrated": self.sd_calibrated,
            "reduction_percent": 100.0 * (1 - self.sd_calibrated / self.sd_nominal) if self.sd_nominal else None,
            "sd_floor": self.sd_floor,
            "floor_source": self.floor_source if self.sd_floor is not None else None,
            "floor_ratio": self.floor_ratio,
            "floor_range": None if self.floor_range is None else list(self.floor_range),
            "target": self.target,
            "improved": self.improved,
            "below_target": self.below_target,
            "verdict": self.verdict,
            "items": [dict(it) for it in self.items],
            "pairs_nominal": [list(x) for x in self.pairs_nominal],
            "pairs_calibrated": [list(x) for x in self.pairs_calibrated],
            "n_values": self.n_values,
        }


def validate(
    sur_nominal: Surrogate,
    sur_calibrated: Surrogate,
    p_calibrated,
    data,
    modes,
    zeta0: float = 0.01,
    target_sd: float | None = None,
    mac_min: float = 0.6,
    quantity: str = "accelerance",
    band_hz=None,
    std_error=None,
    damping=None,
    floor_source: str | None = None,
    with_floor_range: bool = True,
) -> Validation:
    """Hold-out validation: SD before (nominal) and after calibration against raw data.

    Parameters
    ----------
    sur_nominal : surrogate whose basis is at the nominal point (evaluated at p = 0)
    sur_calibrated : surrogate with a basis at (or near) p_calibrated
    data : FitData or sequence of FitData
        Raw hold-out lines (mask = valid lines), hold-out channels; one item per article.
    modes : IdentifiedModes, sequence of IdentifiedModes/None (one per data item), or None
        Identified modes for the damping mapping of each item (None: uniform zeta0).
        A single IdentifiedModes is used for every item.
    std_error : sequence of (n_f, n_out, n_in) arrays or None, one per data item, optional
        Standard errors of the raw FRF values; with them for every item the
        noise floor of the SD is estimated (:func:`noise_floor_sd`).
        Standard errors estimated from the lines themselves
        (:func:`calibration.estimate_std_error`) are welcome: say so in
        ``floor_source``.
    floor_source : str, optional
        Where ``std_error`` came from, printed beside an estimated floor
        (default "per-line standard errors" when given).
    damping : (zeta, p_ref), optional
        Per-mode damping of the calibrated model for every data item (a
        sequence of (r,) arrays assigned at ``p_ref`` on ``sur_calibrated``,
        e.g. the damping the raw-line refinement estimated on the calibration
        channels); modes are tracked from ``p_ref``. Default: identified
        damping mapped by MAC, as at the nominal point. Modes no identified
        mode pairs with take the median identified damping (zeta0 without
        identified modes).
    with_floor_range : bool
        With standard errors, also the floor's 5-95 % range (:func:`floor_range`,
        400 noise draws about the model's values; off for callers that use the
        SD alone).
    """
    datas = [data] if isinstance(data, FitData) else list(data)
    if modes is None or isinstance(modes, IdentifiedModes):
        modes_per = [modes] * len(datas)
    else:
        modes_per = list(modes)
        if len(modes_per) != len(datas):
            raise CalibrationError(f"validation: {len(modes_per)} sets of identified modes for {len(datas)} data items")
    errs = None if std_error is None else list(std_error)
    if errs is not None and len(errs) != len(datas):
        raise CalibrationError(f"validation: {len(errs)} standard-error arrays for {len(datas)} data items")
    p0 = np.zeros(sur_nominal.n_params)
    sds, pairs, macs, eps = [], [], [], []
    if damping is not None and len(damping[0]) != len(datas):
        raise CalibrationError(f"validation: {len(damping[0])} damping vectors for {len(datas)} data items")
    for stage, (sur, p) in enumerate(((sur_nominal, p0), (sur_calibrated, np.asarray(p_calibrated, float)))):
        e_all, pr_all, M_all = [], [], []
        for k, (d, m) in enumerate(zip(datas, modes_per)):
            if m is not None:
                fallback = median_damping(m, zeta0)
                zeta, pr, M, _ = mapped_damping(sur, p, m, fallback, mac_min, band_hz)
            else:
                lam, _ = reduced_modes(sur, p)
                zeta, pr, M = np.full(lam.size, zeta0), [], np.zeros((0, 0))
            if stage == 1 and damping is not None:
                obj = ModalDampingObjective(sur, [d], [damping[0][k]], damping[1], 0.0, quantity)
                e_all.append(obj.deviation(p)[0])
            else:
                e_all.append(_deviation(sur, p, d, zeta, quantity))
            pr_all.append(tuple(pr))
            M_all.append(M)
        eps.append(e_all)
        sds.append(square_deviation(np.concatenate(e_all)))
        pairs.append(tuple(pr_all))
        macs.append(tuple(M_all))
    floors = [None] * len(datas) if errs is None else [
        None if se is None else noise_floor_sd(d, se) for d, se in zip(datas, errs)]
    n = [e.size for e in eps[0]]
    floor = None
    ranges = [None] * len(datas)
    pooled = None
    if all(fl is not None for fl in floors):
        floor = float(np.dot(floors, n) / sum(n))
        if with_floor_range:
            # the calibrated model's values (data x 10^eps) and their standard errors, in the order of eps
            hm = [(d.frf if d.mask is None else d.frf[d.mask]).ravel() * 10.0 ** e1 for d, e1 in zip(datas, eps[1])]
            sm = [(np.asarray(se, float) if d.mask is None else np.asarray(se, float)[d.mask]).ravel()
                  for d, se in zip(datas, errs)]
            ranges = [floor_range(h, se) for h, se in zip(hm, sm)]
            pooled = ranges[0] if len(datas) == 1 else floor_range(np.concatenate(hm), np.concatenate(sm))
    items = tuple(
        {"article": d.article, "sd_nominal": square_deviation(e0), "sd_calibrated": square_deviation(e1),
         "sd_floor": fl, "sd_floor_range": None if r is None else list(r), "n_values": int(e0.size)}
        for d, e0, e1, fl, r in zip(datas, eps[0], eps[1], floors, ranges)
    )
    sd0, sd1 = sds
    return Validation(
        sd_nominal=sd0,
        sd_calibrated=sd1,
        target=target_sd,
        improved=bool(sd1 < sd0),
        below_target=None if target_sd is None else bool(sd1 < target_sd),
        pairs_nominal=pairs[0],
        pairs_calibrated=pairs[1],
        mac_nominal=macs[0],
        mac_calibrated=macs[1],
        n_values=int(sum(n)),
        sd_floor=floor,
        items=items,
        damping_source="identified" if damping is None else "estimated",
        floor_source=None if floor is None else (floor_source or "per-line standard errors"),
        floor_range=pooled,
    )
