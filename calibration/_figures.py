"""Report figures of a calibration (matplotlib, imported lazily; Agg backend)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration._errors import CalibrationError
from calibration._surrogate import modal_frf, reduced_modes
from calibration._validation import mapped_damping


def _plt():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - matplotlib is a core dependency
        raise CalibrationError("figures need matplotlib (pip install matplotlib) or output.figures = false") from exc
    return plt


def _save(plt, fig, path: Path, tight: bool = True) -> Path:
    """Write ``fig`` to ``path`` (PNG, 90 dpi) and close it."""
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _model_frf(sur, p, rows, f, zeta, quantity):
    lam, X = reduced_modes(sur, p)
    return modal_frf(lam, sur.outputs[rows] @ X, X.T @ sur.inputs, f, zeta, quantity, sur.rigid_hz)


def member_figures(outdir: Path, label, pm, model, sur0, arts, cyc, val, cv, camp, identifiability=None) -> list[Path]:
    """FRF overlays, parameter table, CV scatter, MAC before/after. Returns the written PNG paths.

    With ``identifiability`` the parameter table marks each parameter
    identifiable or not (a non-identifiable row is greyed, the reason
    shortened into the last column); a CV that is not meaningful (pinned
    parameter) shows "n/a".
    """
    plt = _plt()
    outdir = Path(outdir)
    written = []
    c = camp.calibration
    band = (camp.band.low_hz, camp.band.high_hz)
    from calibration._pipeline import identified_modes

    modes = identified_modes(arts[0])
    z0, *_ = mapped_damping(sur0, np.zeros(pm.n_params), modes, c.zeta0, camp.validation.mac_min, band)
    z1, *_ = mapped_damping(cyc.surrogate, cyc.p, modes, c.zeta0, camp.validation.mac_min, band)
    # FRF overlays: up to 3 calibration + 3 hold-out channels, first drive
    chans = list(camp.channels.calibrate[:3]) + list(camp.channels.holdout[:3])
    fig, axes = plt.subplots(len(chans), 1, figsize=(8, 2.2 * len(chans)), sharex=True, squeeze=False)
    f = arts[0].freq_hz
    rows = sur0.output_index(chans)
    H0 = _model_frf(sur0, np.zeros(pm.n_params), rows, f, c.zeta0, arts[0].quantity)
    H1 = _model_frf(cyc.surrogate, cyc.p, rows, f, z1, arts[0].quantity)
    for k, (ax, name) in enumerate(zip(axes[:, 0], chans)):
        for a in arts:
            ax.semilogy(a.freq_hz, np.abs(a.frf[:, a.channels.index(name), 0]), color="0.7", lw=2.5)
        ax.semilogy(f, np.abs(H0[:, k, 0]), "b--", lw=1, label="nominal (zeta0)")
        ax.semilogy(f, np.abs(H1[:, k, 0]), "r-", lw=1, label="calibrated (mapped damping)")
        kind = "cal" if name in camp.channels.calibrate else "hold-out"
        ax.set_ylabel(f"{name} ({kind})")
    axes[0, 0].plot([], [], color="0.7", lw=2.5, label="test ensemble (raw lines)")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("frequency [Hz]")
    fig.suptitle(f"{label}: |{arts[0].quantity}| test vs model")
    written.append(_save(plt, fig, outdir / f"frf_{label}.png"))

    # parameter table
    names = list(pm.parameters.names)
    nom = pm.physical(np.zeros(pm.n_params))
    cal = pm.physical(cyc.p)
    cells = []
    for j, n in enumerate(names):
        row = [n, f"{nom[n]:.4g}", f"{cal[n]:.4g}", f"{100 * cyc.p[j]:+.2f}"]
        if cv is not None:
            cvj = cv.cv(j)
            row += [f"{pm.nominal[j] * (1 + cv.mean_p[j]):.4g}", "n/a" if cvj is None else f"{cvj:.3f}"]
        if identifiability is not None:
            why = identifiability.reasons[j].split(";")[0].split(":")[0]  # first reason, short
            row += ["yes" if identifiability.identifiable[j] else f"NO: {why.replace(' exceeds', ' >')}"]
        cells.append(row)
    cols = ["parameter", "nominal (SI)", "calibrated", "change %"] + (["CV mean", "CV %"] if cv is not None else [])
    cols += ["identifiable"] if identifiability is not None else []
    fig, ax = plt.subplots(figsize=(9 if identifiability is None else 13, 0.3 * len(names) + 1))
    ax.axis("off")
    tab = ax.table(cellText=cells, colLabels=cols, loc="center")
    tab.auto_set_font_size(False)
    tab.set_fontsize(8)
    tab.auto_set_column_width(list(range(len(cols))))
    if identifiability is not None:
        for j in np.flatnonzero(~identifiability.identifiable):
            for k in range(len(cols)):
                tab[j + 1, k].set_facecolor("0.85")
    ax.set_title(f"{label}: parameters (SD {cyc.calibration.sd_nominal:.3g} -> {cyc.sd:.3g})")
    written.append(_save(plt, fig, outdir / f"parameters_{label}.png"))

    if cv is not None:
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
        for j in range(pm.n_params):
            a1.plot(np.full(cv.p.shape[0], j), 100 * cv.p[:, j], "k.", ms=4)
        a1.plot(range(pm.n_params), 100 * cyc.p, "r_", ms=14, label="calibrated")
        a1.set_xticks(range(pm.n_params))
        a1.set_xticklabels(names, rotation=70, fontsize=7)
        a1.set_ylabel("p [%]")
        a1.legend(fontsize=8)
        a1.set_title("cross-validation parameter scatter")
        a2.plot(cv.sd_fit, cv.sd_test, "o")
        a2.set_xlabel("SD on calibration half")
        a2.set_ylabel("SD on other half")
        a2.set_title(f"RSE = {cv.rse:.4g}")
        written.append(_save(plt, fig, outdir / f"crossvalidation_{label}.png"))

    if val is not None and val.mac_nominal and val.mac_nominal[0].size:
        # MAC of the first article's identified modes (each article is mapped with its own)
        fig, axs = plt.subplots(1, 2, figsize=(10, 4.5))
        for ax, M, title in ((axs[0], val.mac_nominal[0], f"MAC nominal ({arts[0].name})"),
                             (axs[1], val.mac_calibrated[0], f"MAC calibrated ({arts[0].name})")):
            im = ax.imshow(M, vmin=0, vmax=1, cmap="viridis", origin="lower")
            ax.set_xlabel("identified mode")
            ax.set_ylabel("FE mode (in band)")
            ax.set_title(title)
        fig.colorbar(im, ax=axs, shrink=0.8)
        written.append(_save(plt, fig, outdir / f"mac_{label}.png", tight=False))
    return written
