"""identify_run(): the one identification of a run file, used by ``frfcal identify`` and the campaign."""

from __future__ import annotations

from typing import Literal

import numpy as np

from calibration._errors import CalibrationError


def run_weights(run, rows=None, cols=None):
    """The run's per-line standard errors as identification weights, or None.

    Returns ``std_error[:, rows][:, :, cols]`` when it is finite and > 0 on
    every valid line (entries on invalid lines are set to 1, they are not
    used), else None (the identification then scales each output by its RMS).
    """
    se = np.asarray(run.std_error, dtype=float)
    if se.shape != np.asarray(run.frf).shape:
        return None
    if rows is not None:
        se = se[:, rows]
    if cols is not None:
        se = se[:, :, cols]
    v = np.asarray(run.valid, bool)
    if not v.any():
        return None
    sev = se[v]
    if np.all(np.isfinite(sev)) and np.all(sev > 0):
        return np.where(np.isfinite(se) & (se > 0), se, 1.0)
    return None


def _index(names, available, what, path):
    lookup = {n: i for i, n in enumerate(available)}
    missing = [n for n in names if n not in lookup]
    if missing:
        raise CalibrationError(f"{path}: {what} {missing} are not in the run (has {sorted(lookup)})")
    return [lookup[n] for n in names]


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
    band_hz : (lo, hi), optional
        Identification band [Hz]; clipped to the valid lines by
        :func:`identification.identify` (the effective band is
        ``result.band_hz``). Default: all valid lines.
    order : int, optional
        State dimension; None chooses it automatically
        (:func:`identification.select_order`, record in
        ``result.order_selection``).
    channels, drives : sequence of str, optional
        Sensor and drive names to use, in this order (default: all).
    weights : {"std_error", None}
        ``"std_error"``: the run's per-line standard errors when finite and
        > 0 on every valid line, else output-RMS scaling; None: output-RMS
        scaling. ``result.settings["weights"]`` says which was used.
    block_rows : int, optional
        Block rows of the subspace data matrices (default automatic).

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
    from dataclasses import replace

    from identification import identify

    if weights not in ("std_error", None):
        raise CalibrationError(f"weights must be 'std_error' or None, got {weights!r}")
    path = getattr(run, "path", "run")
    rows = None if channels is None else _index(list(channels), [s.name for s in run.sensors], "channels", path)
    cols = None if drives is None else _index(list(drives), [d.name for d in run.drives], "drives", path)
    H = np.asarray(run.frf)
    if rows is not None:
        H = H[:, rows]
    if cols is not None:
        H = H[:, :, cols]
    w = run_weights(run, rows, cols) if weights == "std_error" else None
    result = identify(
        run.frequency_hz, H, order, band_hz=band_hz, weights=w, quantity=run.quantity, valid=run.valid,
        block_rows=block_rows,
    )
    settings = dict(result.settings, weights="std_error" if w is not None else "output_rms")
    return replace(result, settings=settings)
