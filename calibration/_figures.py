"""Report figures of a calibration: functions on typed results that return matplotlib figures.

Figures are built with the object API (:class:`matplotlib.figure.Figure`):
no pyplot state and no backend switch, so nothing global changes for the
caller. Writing them (``fig.savefig(path)``) is the caller's.
"""

from __future__ import annotations

import numpy as np

from calibration._errors import CalibrationError
from calibration._surrogate import modal_frf, reduced_modes
from calibration._damping import mapped_damping


def _figure(**kw):
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - matplotlib is a core dependency
        raise CalibrationError("figures need matplotlib (pip install matplotlib) or output.figures = false") from exc
    return Figure(**kw)


def model_frf(sur, p, rows, freq_hz, zeta, quantity: str) -> np.ndarray:
    """Surrogate FRF at ``p`` on output ``rows`` with modal damping ``zeta`` (scalar or per reduced mode).

    Returns
    -------
    (n_f, len(rows), n_in) complex, in ``quantity``
    """
    lam, X = reduced_modes(sur, p)
    return modal_frf(lam, sur.outputs[rows] @ X, X.T @ sur.inputs, freq_hz, zeta, quantity, sur.rigid_hz)


def frf_figure(label: str, sur_nominal, sur_calibrated, p, tests, modes, channels, calibrate_channels,
               zeta0: float, mac_min: float, band_hz, quantity: str):
    """FRF overlay of test lines, nominal model and calibrated model, first drive.

    Parameters
    ----------
    label : str
        Member label (title).
    sur_nominal, sur_calibrated : Surrogate
        Bases at the nominal point (evaluated at p = 0, damping ``zeta0``) and
        at the calibrated point (evaluated at ``p``, identified damping mapped
        by MAC from ``modes``).
    p : (n_p,) normalized calibrated parameters
    tests : sequence of FitData
        Raw measured lines of each article; ``outputs`` must hold ``channels``.
        The model is evaluated on the first one's lines.
    modes : IdentifiedModes
        Identified modes of the first article (damping mapping).
    channels : sequence of str
        Channels to draw, one axis each.
    calibrate_channels : collection of str
        Channels used for calibration (the others are labelled hold-out).
    zeta0, mac_min : float
    band_hz : (lo, hi) Hz
    quantity : str

    Returns
    -------
    matplotlib.figure.Figure
    """
    n_p = sur_nominal.n_params
    z1, *_ = mapped_damping(sur_calibrated, p, modes, zeta0, mac_min, band_hz)
    fig = _figure(figsize=(8, 2.2 * len(channels)))
    axes = fig.subplots(len(channels), 1, sharex=True, squeeze=False)
    f = tests[0].freq_hz
    rows = sur_nominal.output_index(channels)
    H0 = model_frf(sur_nominal, np.zeros(n_p), rows, f, zeta0, quantity)
    H1 = model_frf(sur_calibrated, p, sur_calibrated.output_index(channels), f, z1, quantity)
    for k, (ax, name) in enumerate(zip(axes[:, 0], channels)):
        for t in tests:
            ax.semilogy(t.freq_hz, np.abs(t.frf[:, list(t.outputs).index(name), 0]), color="0.7", lw=2.5)
        ax.semilogy(f, np.abs(H0[:, k, 0]), "b--", lw=1, label="nominal (zeta0)")
        ax.semilogy(f, np.abs(H1[:, k, 0]), "r-", lw=1, label="calibrated (mapped damping)")
        ax.set_ylabel(f"{name} ({'cal' if name in calibrate_channels else 'hold-out'})")
    axes[0, 0].plot([], [], color="0.7", lw=2.5, label="test ensemble (raw lines)")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("frequency [Hz]")
    fig.suptitle(f"{label}: |{quantity}| test vs model")
    fig.tight_layout()
    return fig


def parameter_figure(label: str, pm, p, sd_nominal: float, sd: float, crossvalidation=None, identifiability=None):
    """Parameter table: nominal and calibrated SI values, change, CV mean and CV, identifiability.

    Parameters
    ----------
    label : str
    pm : femodel.ParametricModel
    p : (n_p,) normalized calibrated parameters
    sd_nominal, sd : float
        Calibration SD before and after (title).
    crossvalidation : CrossValidation, optional
        Adds the CV mean (SI) and CV [%] columns; a CV that is not meaningful
        (pinned parameter) shows "n/a".
    identifiability : Identifiability, optional
        Adds an identifiable column; a non-identifiable row is greyed, the
        first reason shortened into the last column.

    Returns
    -------
    matplotlib.figure.Figure
    """
    names = list(pm.parameters.names)
    nom = pm.physical(np.zeros(pm.n_params))
    cal = pm.physical(p)
    cv, idf = crossvalidation, identifiability
    cells = []
    for j, n in enumerate(names):
        row = [n, f"{nom[n]:.4g}", f"{cal[n]:.4g}", f"{100 * p[j]:+.2f}"]
        if cv is not None:
            cvj = cv.cv(j)
            row += [f"{pm.nominal[j] * (1 + cv.mean_p[j]):.4g}", "n/a" if cvj is None else f"{cvj:.3f}"]
        if idf is not None:
            why = idf.reasons[j].split(";")[0].split(":")[0]
            row += ["yes" if idf.identifiable[j] else f"NO: {why.replace(' exceeds', ' >')}"]
        cells.append(row)
    cols = ["parameter", "nominal (SI)", "calibrated", "change %"] + (["CV mean", "CV %"] if cv is not None else [])
    cols += ["identifiable"] if idf is not None else []
    fig = _figure(figsize=(9 if idf is None else 13, 0.3 * len(names) + 1))
    ax = fig.subplots()
    ax.axis("off")
    tab = ax.table(cellText=cells, colLabels=cols, loc="center")
    tab.auto_set_font_size(False)
    tab.set_fontsize(8)
    tab.auto_set_column_width(list(range(len(cols))))
    if idf is not None:
        for j in np.flatnonzero(~np.asarray(idf.identifiable, bool)):
            for k in range(len(cols)):
                tab[j + 1, k].set_facecolor("0.85")
    ax.set_title(f"{label}: parameters (SD {sd_nominal:.3g} -> {sd:.3g})")
    fig.tight_layout()
    return fig


def crossvalidation_figure(names, p, crossvalidation):
    """Cross-validation parameter scatter (percent) beside the calibrated ``p``, and SD of the two halves.

    Returns
    -------
    matplotlib.figure.Figure
    """
    cv = crossvalidation
    n_p = len(names)
    fig = _figure(figsize=(11, 4))
    a1, a2 = fig.subplots(1, 2)
    for j in range(n_p):
        a1.plot(np.full(cv.p.shape[0], j), 100 * cv.p[:, j], "k.", ms=4)
    a1.plot(range(n_p), 100 * np.asarray(p), "r_", ms=14, label="calibrated")
    a1.set_xticks(range(n_p))
    a1.set_xticklabels(list(names), rotation=70, fontsize=7)
    a1.set_ylabel("p [%]")
    a1.legend(fontsize=8)
    a1.set_title("cross-validation parameter scatter")
    a2.plot(cv.sd_fit, cv.sd_test, "o")
    a2.set_xlabel("SD on calibration half")
    a2.set_ylabel("SD on other half")
    a2.set_title(f"RSE = {cv.rse:.4g}")
    fig.tight_layout()
    return fig


def mac_figure(validation, article: str):
    """MAC of the first article's identified modes against the FE modes, nominal and calibrated.

    Returns
    -------
    matplotlib.figure.Figure or None
        None when the validation holds no MAC matrix.
    """
    val = validation
    if val is None or not val.mac_nominal or not np.asarray(val.mac_nominal[0]).size:
        return None
    fig = _figure(figsize=(10, 4.5))
    axs = fig.subplots(1, 2)
    for ax, M, title in ((axs[0], val.mac_nominal[0], f"MAC nominal ({article})"),
                         (axs[1], val.mac_calibrated[0], f"MAC calibrated ({article})")):
        im = ax.imshow(M, vmin=0, vmax=1, cmap="viridis", origin="lower")
        ax.set_xlabel("identified mode")
        ax.set_ylabel("FE mode (in band)")
        ax.set_title(title)
    fig.colorbar(im, ax=list(axs), shrink=0.8)
    return fig
