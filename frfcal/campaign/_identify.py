"""The one identification of measured lines, used by ``frfcal identify`` and the campaign.

:func:`identify_lines` works on the lines of a selection of channels and
drives (the campaign keeps them from its load stage); :func:`identify_run`
selects them from a run file (``acquisition.runfile.Run``) and calls it.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Literal

import numpy as np

from calibration import CalibrationError
from calibration._metric import true_runs


def line_weights(std_error, frf, valid):
    """Per-line standard errors as identification weights, or None.

    Parameters
    ----------
    std_error, frf : (n_f, n_out, n_in) arrays
        Standard errors (same unit as the FRF) and the FRF they belong to.
    valid : (n_f,) bool

    Returns
    -------
    (n_f, n_out, n_in) ndarray or None
        ``std_error`` when it is finite and > 0 on every valid line (entries
        on invalid lines are set to 1, they are not used), else None (the
        identification then scales each output by its RMS).
    """
    se = np.asarray(std_error, dtype=float)
    if se.shape != np.asarray(frf).shape:
        return None
    v = np.asarray(valid, bool)
    if not v.any():
        return None
    sev = se[v]
    if np.all(np.isfinite(sev)) and np.all(sev > 0):
        return np.where(np.isfinite(se) & (se > 0), se, 1.0)
    return None


def run_std_error(run):
    """The run's per-line standard errors as an array like its FRFs, or None (the run has none)."""
    se = np.asarray(run.std_error, dtype=float)
    return se if se.shape == np.asarray(run.frf).shape else None


def run_weights(run, rows=None, cols=None):
    """The run's per-line standard errors (``[:, rows][:, :, cols]``) as weights, or None (see :func:`line_weights`)."""
    se, H = run_std_error(run), np.asarray(run.frf)
    if se is None:
        return None
    if rows is not None:
        se, H = se[:, rows], H[:, rows]
    if cols is not None:
        se, H = se[:, :, cols], H[:, :, cols]
    return line_weights(se, H, run.valid)


def _index(names, available, what, path):
    lookup = {n: i for i, n in enumerate(available)}
    missing = [n for n in names if n not in lookup]
    if missing:
        raise CalibrationError(f"{path}: {what} {missing} are not in the run (has {sorted(lookup)})")
    return [lookup[n] for n in names]


def identify_lines(
    frequency_hz,
    frf,
    valid,
    std_error,
    quantity: str,
    band_hz=None,
    *,
    order: int | None = None,
    weights: Literal["std_error"] | None = "std_error",
    block_rows: int | None = None,
):
    """Subspace identification of measured FRF lines (valid lines only), then the modal refit.

    The refit (``identification.identify(..., modal_refit=True)``) refines
    the physical poles and stands the out-of-band modes in by residual poles
    outside the band; ``result.settings["modal_refit"]`` records it.

    Parameters
    ----------
    frequency_hz : (n_f,) Hz
    frf : (n_f, n_out, n_in) complex, in ``quantity``
    valid : (n_f,) bool
    std_error : (n_f, n_out, n_in) or None
        Standard error of every value (same unit as ``frf``).
    quantity : str
        FRF quantity ("accelerance", ...).
    band_hz : (lo, hi), optional
        Identification band [Hz]; clipped to the valid lines by
        :func:`identification.identify` (the effective band is
        ``result.band_hz``). Default: all valid lines.
    order : int, optional
        State dimension; None chooses it automatically
        (:func:`identification.select_order`, record in
        ``result.order_selection``).
    weights : {"std_error", "relative", None}
        ``"std_error"``: the standard errors when finite and > 0 on every
        valid line, else standard errors estimated from the lines themselves
        (:func:`estimated_weights`); ``"relative"``: every value weighted by
        1 / (|H| + 1e-3 x its channel pair's RMS); None: output-RMS scaling.
        ``result.settings["weights"]`` says which was used (``"std_error"``,
        ``"estimated"``, ``"relative"`` or ``"output_rms"``).
    block_rows : int, optional
        Block rows of the subspace data matrices (default automatic).

    Returns
    -------
    identification.Identification
    """
    from identification import identify

    w, used = identification_weights(frequency_hz, frf, valid, std_error, weights)
    result = identify(frequency_hz, frf, order, band_hz=band_hz, weights=w, quantity=quantity, valid=valid,
                      block_rows=block_rows, modal_refit=True)
    settings = dict(result.settings, weights=used)
    if used in ("std_error", "estimated"):  # weights that are the noise: the residual can be read in sigma
        settings["unexplained"] = unexplained_residual(frequency_hz, frf, valid, w, result)
    return replace(result, settings=settings)


def unexplained_residual(frequency_hz, frf, valid, sigma, result, threshold: float = 100.0, max_windows: int = 5):
    """Where the identified model leaves a residual far above the noise, away from its physical poles.

    A mode the identification did not find (weakly excited, seen in few pairs, or without a peak of its own
    beside stronger neighbours) leaves its whole contribution in the residual, a bump many standard errors
    high over a few half-power bandwidths. Per line, the mean over pairs of ``|H_model - H|^2 / sigma^2``
    (about 1 for a model at the noise) is taken on the valid lines of the band, leaving out the lines within
    three half-power bandwidths (at least 0.1 %) of every physical pole (there the pole's own small errors
    dominate); runs of at least two adjacent lines above ``threshold`` (10 sigma rms over the pairs) are
    the windows, the largest first. Such a window is a mode the model missed or a misfit of its own there
    (on an outside-style frame: the two missed modes at 30-57 sigma, misfits beside identified modes at
    10-23 sigma); it says where the identified model does not explain the data, not which.

    Returns
    -------
    list of dict
        ``frequency_hz`` (the line of largest residual), ``window_hz`` (first and last line of the run),
        ``residual_sigma`` (the rms over pairs there, in standard errors), ``lines``; at most ``max_windows``.
    """
    f = np.asarray(frequency_hz, float)
    lo, hi = result.band_hz
    sel = np.asarray(valid, bool) & (f >= lo) & (f <= hi)
    if sel.sum() < 2:
        return []
    idx = np.flatnonzero(sel)
    idx = idx[np.argsort(f[idx], kind="stable")]  # adjacent in frequency, whatever order the run holds
    fs = f[idx]
    s = np.asarray(sigma, float)[idx]
    e2 = np.abs(result.model.frf(fs) - np.asarray(frf)[idx]) ** 2 / np.where(s > 0, s, np.inf) ** 2
    r = e2.reshape(fs.size, -1).mean(axis=1)
    near = np.zeros(fs.size, bool)
    for fk, zk in zip(result.modal.frequency_hz, result.modal.damping):
        near |= np.abs(fs - fk) <= max(6.0 * zk * fk, 1e-3 * fk)
    out = []
    for k, j in true_runs((r > threshold) & ~near):
        if j > k:
            m = k + int(np.argmax(r[k:j + 1]))
            out.append({"frequency_hz": float(fs[m]), "window_hz": [float(fs[k]), float(fs[j])],
                        "residual_sigma": float(np.sqrt(r[m])), "lines": int(j - k + 1)})
    out.sort(key=lambda d: -d["residual_sigma"])
    return out[:max_windows]


def unexplained_line(result) -> str | None:
    """The windows of :func:`unexplained_residual` in one line, or None (none, or weights not the noise)."""
    got = result.settings.get("unexplained")
    if not got:
        return None
    return ("residual far above the noise away from the identified modes (a mode the model missed, or its "
            "misfit there): " + ", ".join(f"{u['frequency_hz']:.1f} Hz ({u['residual_sigma']:.0f} sigma rms over "
                                          f"the pairs, {u['lines']} lines)" for u in got))


def identification_weights(frequency_hz, frf, valid, std_error, weights):
    """The weights :func:`identify_lines` identifies with, and their name (its ``weights`` argument).

    Returns
    -------
    (weights (n_f, n_out, n_in) or None, "std_error" | "estimated" | "relative" | "output_rms")
    """
    if weights not in ("std_error", "relative", None):
        raise CalibrationError(f"weights must be 'std_error', 'relative' or None, got {weights!r}")
    if weights == "relative":
        return relative_weights(frf, valid), "relative"
    if weights is None:
        return None, "output_rms"
    w = None if std_error is None else line_weights(std_error, frf, valid)
    return (w, "std_error") if w is not None else estimated_weights(frequency_hz, frf, valid)


def estimated_weights(frequency_hz, frf, valid):
    """Standard errors estimated from the lines themselves, and the name of what was used.

    :func:`calibration.estimate_std_error` fits ``sigma^2 = a^2 |H|^2 + b^2``
    per channel pair from local differences of log H: errors in proportion
    to the response above a floor, each pair at its own level. A pair that
    carries no signal (a vertical sensor under a lateral drive) gets
    ``sigma ~ |H|`` and weighs no more than its noise; relative weights alone
    gave such a pair 100x the weight of a measured one and left every mode
    of an outside frame "negligible". Pairs the estimate cannot judge take
    the median relative level of the others; when the lines cannot be judged
    at all (too few, not ascending) the weights are :func:`relative_weights`.

    Returns
    -------
    (weights (n_f, n_out, n_in), "estimated" or "relative")
    """
    from calibration import estimate_std_error

    f = np.asarray(frequency_hz, float)
    H = np.asarray(frf)
    v = np.asarray(valid, bool)
    try:
        est = estimate_std_error(f[v], H[v])
    except CalibrationError:
        return relative_weights(frf, valid), "relative"
    a, b = est.relative, est.absolute
    ok = np.isfinite(a) & np.isfinite(b) & (a + b > 0)
    if not ok.any():
        return relative_weights(frf, valid), "relative"
    if not ok.all():  # a pair the estimate could not judge: the others' median relative level, and a floor
        a = np.where(ok, a, np.median(a[ok]))
        rms = np.sqrt(np.mean(np.abs(H[v]) ** 2, axis=0))
        b = np.where(ok, b, 1e-3 * a * rms)
    sigma = np.sqrt((a[None] * np.abs(H)) ** 2 + b[None] ** 2)
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, 1.0)
    return sigma, "estimated"


def relative_weights(frf, valid, floor: float = 1e-3):
    """Standard errors proportional to the FRF: ``|H| + floor x RMS`` of each channel pair over the valid lines.

    Without measured standard errors this is the noise model of a swept
    measurement (an error in proportion to the response, above a floor);
    the log-FRF metric of the calibration weights its lines the same way.
    Scaling every value by one constant does not change an identification.
    """
    H = np.asarray(frf)
    v = np.asarray(valid, bool)
    rms = np.sqrt(np.mean(np.abs(H[v]) ** 2, axis=0))
    rms = np.where(rms > 0, rms, 1.0)
    return np.abs(H) + floor * rms[None]


def identify_run(
    run,
    band_hz=None,
    *,
    order: int | None = None,
    channels=None,
    drives=None,
    weights: Literal["std_error"] | None = "std_error",
    block_rows: int | None = None,
):
    """Subspace identification of a run file's FRFs (valid lines only).

    Parameters
    ----------
    run : acquisition.runfile.Run
        As returned by ``read_run``.
    band_hz, order, weights, block_rows
        As :func:`identify_lines`.
    channels, drives : sequence of str, optional
        Sensor and drive names to use, in this order (default: all).

    Returns
    -------
    identification.Identification
        Outputs in the order of ``channels``, inputs in the order of ``drives``.

    Raises
    ------
    CalibrationError
        A channel or drive name that is not in the run (names the file).
    identification.IdentificationError
        Bad band, too few lines, etc.
    """
    path = getattr(run, "path", "run")
    rows = None if channels is None else _index(list(channels), [s.name for s in run.sensors], "channels", path)
    cols = None if drives is None else _index(list(drives), [d.name for d in run.drives], "drives", path)
    H, se = np.asarray(run.frf), run_std_error(run)
    if rows is not None:
        H = H[:, rows]
        se = None if se is None else se[:, rows]
    if cols is not None:
        H = H[:, :, cols]
        se = None if se is None else se[:, :, cols]
    return identify_lines(run.frequency_hz, H, run.valid, se, run.quantity, band_hz, order=order,
                          weights=weights, block_rows=block_rows)


def refit_line(result) -> str:
    """What the modal refit did, in one line."""
    r = result.settings.get("modal_refit")
    if not r:
        return "modal refit: not run"
    if not r.get("used"):
        why = r.get("reason") or f"weighted residual {r['ssr']:.4g} not below the subspace model's {r['ssr_subspace']:.4g}"
        return f"modal refit: not used ({why})"
    return (f"modal refit: physical poles moved up to {100 * r['max_pole_shift_rel']:.2g} %, "
            f"{len(r['residual_poles_hz'])} residual poles outside the band (rank {r['residual_rank']}), "
            f"weighted residual {r['ssr_subspace']:.4g} -> {r['ssr']:.4g}")
