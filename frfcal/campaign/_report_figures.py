"""Figures of the campaign report (docs/report.md): layout, sweep quality, level comparison, FRF overlays.

Functions on typed results and arrays that return :class:`matplotlib.figure.Figure`
objects (object API: no pyplot state, no backend switch). The HTML page
(:mod:`frfcal.campaign._html`) embeds them; writing files is the caller's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: SI unit of each FRF quantity (labdata.FRF_QUANTITIES)
_UNITS = {"accelerance": "m/s^2/N", "mobility": "m/s/N", "receptance": "m/N"}


def _figure(**kw):
    from matplotlib.figure import Figure

    return Figure(**kw)


# ----------------------------------------------------------------------------- layout


def layout_figure(model, channels, drives, title: str = ""):
    """3-D view and top view of the FE mesh with the sensors (arrows) and drive points (stars).

    Parameters
    ----------
    model : femodel.FEModel
        Grids (``xyz`` in m, basic system) and elements of the deck.
    channels, drives : sequences of Transducer
        Name, FE grid and unit direction (basic system) of every response
        channel and drive (the load stage's geometry).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.collections import LineCollection
    from mpl_toolkits.mplot3d.art3d import Line3DCollection  # also registers the 3d projection

    from frfcal._modeplot import _edges

    xyz = np.asarray(model.xyz, float)
    edges = _edges(model)
    extent = float(np.ptp(xyz, axis=0).max()) or 1.0
    arrow = 0.08 * extent

    def place(ts):
        if not ts:
            return np.zeros((0, 3)), np.zeros((0, 3))
        idx = model.grid_index([t.grid for t in ts], what="channel grid")
        d = np.array([t.direction for t in ts], float)
        return xyz[idx], d / np.linalg.norm(d, axis=1, keepdims=True)

    sx, sd = place(list(channels))
    dx, dd = place(list(drives))
    fig = _figure(figsize=(13, 5.5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    if len(edges):
        ax3.add_collection3d(Line3DCollection(xyz[edges], colors="0.6", linewidths=0.5))
    else:
        ax3.scatter(*xyz.T, s=1, c="0.6")
    if len(sx):
        ax3.quiver(*sx.T, *(arrow * sd.T), color="tab:blue", linewidth=1.2)
        ax3.scatter(*sx.T, c="tab:blue", s=10)
    if len(dx):
        ax3.quiver(*dx.T, *(-1.5 * arrow * dd.T), color="tab:red", linewidth=2.5)
        ax3.scatter(*dx.T, c="tab:red", s=80, marker="*")
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    mid = 0.5 * (lo + hi)
    ax3.set_xlim(mid[0] - 0.5 * extent, mid[0] + 0.5 * extent)
    ax3.set_ylim(mid[1] - 0.5 * extent, mid[1] + 0.5 * extent)
    ax3.set_zlim(mid[2] - 0.5 * extent, mid[2] + 0.5 * extent)
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("z (m)")
    ax3.set_title("3-D view (blue: sensors, red: shaker)")
    ax = fig.add_subplot(1, 2, 2)
    if len(edges):
        ax.add_collection(LineCollection(xyz[edges][:, :, :2], colors="0.7", linewidths=0.5))
    ax.scatter(sx[:, 0], sx[:, 1], c="tab:blue", s=12)
    for t, p in zip(channels, sx):
        ax.annotate(t.name, (p[0], p[1]), fontsize=6, color="tab:blue", xytext=(2, 2), textcoords="offset points")
    if len(dx):
        ax.scatter(dx[:, 0], dx[:, 1], c="tab:red", s=120, marker="*", zorder=5)
        for t, p in zip(drives, dx):
            ax.annotate(t.name, (p[0], p[1]), fontsize=8, color="tab:red", xytext=(4, -10),
                        textcoords="offset points")
    pad = 0.05 * extent
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("top view (x-y)")
    fig.suptitle(title or f"{len(channels)} response channels, {len(drives)} drive(s)")
    fig.tight_layout()
    return fig


# ----------------------------------------------------------------------------- sweep quality


@dataclass(frozen=True)
class SweepQuality:
    """Per-line quality of one run file (valid and flagged lines).

    Attributes
    ----------
    run : str, the run file
    article : str
    frequency_hz : (n_f,) Hz
    valid : (n_f,) bool, lines without a quality flag
    rel_std_error : (n_f,) or None
        Median over sensor/drive pairs of std_error / |H| (dimensionless);
        None when the run holds no standard errors.
    coherence : (n_f,) or None
        Coherence proxy 1 / (1 + n_blocks (std_error/|H|)^2) of the median
        pair: the ordinary coherence of a block average whose scatter is
        output noise (std_error is the standard error of the mean of n_blocks).
    thd_response, thd_drive : (n_f,) or None
        Largest THD over response channels, over drive channels (fraction);
        None when the run holds no THD (all zero).
    force_n : (n_f, n_in) achieved force amplitude, N peak (None: not recorded)
    level_n : float or None, target force of the plan, N peak
    force_tolerance : float or None, allowed relative force deviation
    thd_limit : float or None, THD flag limit of the plan (fraction)
    std_error_limit : float or None, relative standard error flag limit
    """

    run: str
    article: str
    frequency_hz: np.ndarray
    valid: np.ndarray
    rel_std_error: np.ndarray | None
    coherence: np.ndarray | None
    thd_response: np.ndarray | None
    thd_drive: np.ndarray | None
    force_n: np.ndarray | None
    level_n: float | None
    force_tolerance: float | None
    thd_limit: float | None
    std_error_limit: float | None

    def summary(self) -> dict:
        """One table row: lines, flagged, median/max relative std error, min coherence, max THD, force hold."""
        v = self.valid
        row = {"run": Path(self.run).name, "article": self.article, "lines": int(v.size), "flagged": int((~v).sum()),
               "band_hz": f"{self.frequency_hz.min():.4g}-{self.frequency_hz.max():.4g}" if v.size else ""}
        if self.rel_std_error is not None and v.any():
            row["median rel. std error %"] = 100 * float(np.nanmedian(self.rel_std_error[v]))
            row["max rel. std error %"] = 100 * float(np.nanmax(self.rel_std_error[v]))
            row["min coherence"] = float(np.nanmin(self.coherence[v]))
        if self.thd_response is not None and v.any():
            row["max THD response %"] = 100 * float(np.nanmax(self.thd_response[v]))
        if self.thd_drive is not None and v.any():
            row["max THD drive %"] = 100 * float(np.nanmax(self.thd_drive[v]))
        if self.force_n is not None and self.level_n and v.any():
            dev = np.abs(self.force_n[v] / self.level_n - 1)
            row["target force N"] = self.level_n
            row["max force deviation %"] = 100 * float(np.nanmax(dev))
            if self.force_tolerance:
                row["lines within tolerance %"] = 100 * float(np.mean(np.all(dev <= self.force_tolerance, axis=1)))
        return row


def sweep_quality(run) -> SweepQuality | None:
    """Quality arrays of a run file (``acquisition.runfile.Run``); None for an imported file without any.

    A UFF58 import (``plan["source"] == "uff58"``) carries no acquisition
    quality; a synthetic run carries standard errors only.
    """
    plan = dict(run.plan or {})
    if plan.get("source") == "uff58":
        return None
    f = np.asarray(run.frequency_hz, float)
    H = np.asarray(run.frf)
    se = np.asarray(run.std_error, float)
    n_out = len(run.sensors)
    rel = coh = None
    if se.shape == H.shape and np.any(se > 0):
        with np.errstate(divide="ignore", invalid="ignore"):
            r = se / np.abs(H)
        rel = np.nanmedian(r.reshape(f.size, -1), axis=1)
        nb = np.asarray(run.n_blocks, float)
        nb = np.where(nb > 0, nb, 1.0)
        coh = 1.0 / (1.0 + nb * rel ** 2)
    thd = np.asarray(run.thd, float)
    thd_r = thd_d = None
    if thd.ndim == 2 and thd.shape[0] == f.size and np.any(np.nan_to_num(thd) > 0):
        thd_r = np.nanmax(thd[:, :n_out], axis=1) if n_out else None
        thd_d = np.nanmax(thd[:, n_out:], axis=1) if thd.shape[1] > n_out else None
    force = np.asarray(run.force_n, float)
    force = force if force.ndim == 2 and force.shape[0] == f.size and np.any(np.isfinite(force)) else None
    fspec, mspec = plan.get("force") or {}, plan.get("measure") or {}
    level = plan.get("level_n")
    return SweepQuality(str(run.path), run.article, f, np.asarray(run.valid, bool), rel, coh, thd_r, thd_d, force,
                        None if level is None else float(level), fspec.get("tolerance"), mspec.get("thd_limit"),
                        mspec.get("std_error_limit"))


def sweep_quality_figure(q: SweepQuality):
    """Per-line standard error and coherence proxy, THD, and achieved force against the target.

    Returns
    -------
    matplotlib.figure.Figure
    """
    panels = ["se"] + (["thd"] if q.thd_response is not None or q.thd_drive is not None else []) \
        + (["force"] if q.force_n is not None else [])
    fig = _figure(figsize=(10, 2.3 * len(panels) + 0.6))
    axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    f, v = q.frequency_hz, q.valid
    for ax, what in zip(axes, panels):
        if what == "se":
            if q.rel_std_error is None:
                ax.text(0.5, 0.5, "no standard errors in this run", ha="center", transform=ax.transAxes)
            else:
                ax.semilogy(f[v], 100 * q.rel_std_error[v], ".", ms=2, color="tab:blue", label="valid lines")
                ax.semilogy(f[~v], 100 * q.rel_std_error[~v], "x", ms=4, color="tab:red", label="flagged")
                if q.std_error_limit:
                    ax.axhline(100 * q.std_error_limit, color="tab:red", lw=0.8, ls="--", label="flag limit")
                ax.set_ylabel("rel. std error %\n(median pair)")
                tw = ax.twinx()
                tw.plot(f, q.coherence, color="0.4", lw=0.6)
                tw.set_ylim(min(0.9, float(np.nanmin(q.coherence)) - 0.01), 1.001)
                tw.set_ylabel("coherence proxy", color="0.4")
                ax.legend(fontsize=7, loc="upper left")
        elif what == "thd":
            if q.thd_response is not None:
                ax.semilogy(f, 100 * np.maximum(q.thd_response, 1e-6), ".", ms=2, label="max response channel")
            if q.thd_drive is not None:
                ax.semilogy(f, 100 * np.maximum(q.thd_drive, 1e-6), ".", ms=2, label="max drive channel")
            if q.thd_limit:
                ax.axhline(100 * q.thd_limit, color="tab:red", lw=0.8, ls="--", label="flag limit")
            ax.set_ylabel("THD %")
            ax.legend(fontsize=7, loc="upper left")
        else:
            for j in range(q.force_n.shape[1]):
                ax.plot(f, q.force_n[:, j], ".", ms=2, label=f"drive {j + 1}")
            if q.level_n:
                ax.axhline(q.level_n, color="k", lw=0.8, label="target")
                if q.force_tolerance:
                    ax.axhspan(q.level_n * (1 - q.force_tolerance), q.level_n * (1 + q.force_tolerance),
                               color="tab:green", alpha=0.15, label="tolerance")
            ax.set_ylabel("force N peak")
            ax.legend(fontsize=7, loc="upper left")
    axes[-1].set_xlabel("frequency [Hz]")
    fig.suptitle(f"{q.article}: sweep quality ({int(v.sum())} valid / {v.size} lines)")
    fig.tight_layout()
    return fig


def level_figure(article: str, levels):
    """The same article at several force levels: sum |H| per level and its ratio to the lowest level.

    Parameters
    ----------
    article : str
    levels : sequence of (level_n, frequency_hz (n_f,), H (n_f, n_out, n_in), valid (n_f,))
        Sorted by level; at least two.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = _figure(figsize=(10, 5))
    a1, a2 = fig.subplots(2, 1, sharex=True)
    ref_level, f0, H0, v0 = levels[0]
    s0 = np.sum(np.abs(H0[v0]).reshape(int(v0.sum()), -1), axis=1)
    for level, f, H, v in levels:
        s = np.sum(np.abs(H[v]).reshape(int(v.sum()), -1), axis=1)
        a1.semilogy(f[v], s, lw=0.8, label=f"{level:g} N")
        if level != ref_level:
            common, i0, i1 = np.intersect1d(np.round(f0[v0], 9), np.round(f[v], 9), return_indices=True)
            if common.size:
                a2.plot(common, s[i1] / s0[i0], ".", ms=2, label=f"{level:g} N / {ref_level:g} N")
    a2.axhline(1.0, color="k", lw=0.6)
    a1.set_ylabel("sum |H| over pairs")
    a2.set_ylabel("ratio to lowest level")
    a2.set_xlabel("frequency [Hz]")
    a1.legend(fontsize=7)
    a2.legend(fontsize=7)
    fig.suptitle(f"{article}: level comparison (a linear article gives ratio 1 within the noise)")
    fig.tight_layout()
    return fig


# ----------------------------------------------------------------------------- FRF overlays


@dataclass(frozen=True)
class Overlay:
    """Test lines and the models on them, first drive, for the FRF overlay of one ensemble member.

    Attributes
    ----------
    channels : tuple of str
    tests : tuple of FitData, raw lines of each article on ``channels``
    std_error : (n_f, n_ch, n_in) or None, standard errors of ``tests[0]``
    floor_source : str, where ``std_error`` came from ("per-line standard errors" or estimated)
    models : tuple of (name, (n_f, n_ch, n_in) complex)
        "nominal", "calibrated" (and "extended") on ``tests[0]``'s lines.
    """

    channels: tuple
    tests: tuple
    std_error: np.ndarray | None
    models: tuple
    floor_source: str = "per-line standard errors"

    def deviation(self) -> dict:
        """Per line of ``tests[0]``: RMS over channels of |H_model / H_test - 1| for every model, and the
        floor RMS(std_error / |H_test|) ("floor", None without standard errors); first drive; (n_f,) each."""
        t = self.tests[0]
        rows = [list(t.outputs).index(n) for n in self.channels]
        Ht = t.frf[:, rows, 0]
        if t.mask is not None:  # pairs without signal above the noise (calibration._signal) are left out
            Ht = np.where(t.mask[:, rows, 0], Ht, np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = {name: np.sqrt(np.nanmean(np.abs(H[:, :, 0] / Ht - 1) ** 2, axis=1)) for name, H in self.models}
            out["floor"] = (None if self.std_error is None
                            else np.sqrt(np.nanmean((self.std_error[:, :, 0] / np.abs(Ht)) ** 2, axis=1)))
        return out


def overlay(sur_nominal, sur_calibrated, p, tests, std_errors, modes, channels, zeta0: float, mac_min: float,
            band_hz, quantity: str, extended=None, floor_source: str = "per-line standard errors") -> Overlay:
    """The nominal, calibrated (and extended) models on the first article's lines.

    Parameters
    ----------
    sur_nominal, sur_calibrated : Surrogate
        Evaluated at p = 0 with damping ``zeta0`` and at ``p`` with the
        identified damping mapped by MAC.
    p : (n_p,) normalized calibrated parameters
    tests : sequence of FitData
        Raw lines of each article on ``channels`` (the models are evaluated on
        the first one's lines).
    std_errors : sequence of (n_f, n_ch, n_in) arrays or None
        Standard errors of ``tests`` (same unit as the FRF).
    modes : IdentifiedModes of the first article (damping mapping)
    channels : sequence of str
    zeta0, mac_min : float
    band_hz : (lo, hi) Hz
    quantity : str
    extended : (Surrogate, p) or None
        The extended model of the diagnosis at its parameters.
    floor_source : str, where ``std_errors`` came from (legend)

    Returns
    -------
    Overlay
    """
    from calibration import mapped_damping, model_frf

    f = tests[0].freq_hz
    z1, *_ = mapped_damping(sur_calibrated, p, modes, zeta0, mac_min, band_hz)
    models = [("nominal", model_frf(sur_nominal, np.zeros(sur_nominal.n_params), sur_nominal.output_index(channels),
                                    f, zeta0, quantity)),
              ("calibrated", model_frf(sur_calibrated, p, sur_calibrated.output_index(channels), f, z1, quantity))]
    if extended is not None:
        sur_e, p_e = extended
        ze, *_ = mapped_damping(sur_e, p_e, modes, zeta0, mac_min, band_hz)
        models.append(("extended", model_frf(sur_e, p_e, sur_e.output_index(channels), f, ze, quantity)))
    se0 = None if not std_errors or std_errors[0] is None else std_errors[0]
    return Overlay(tuple(channels), tuple(tests), se0, tuple(models), floor_source)


_STYLE = {"nominal": "b--", "calibrated": "r-", "extended": "g-"}


def frf_overlay_figure(label: str, ov: Overlay, calibrate_channels, zeta0: float, band_hz, quantity: str):
    """Test / nominal / calibrated (/ extended) |FRF| per channel with the test's noise band, and below the
    relative deviation of each model from the test against the floor (:meth:`Overlay.deviation`).

    Parameters
    ----------
    label : str, member label (title)
    ov : Overlay
    calibrate_channels : collection of str (others are labelled hold-out)
    zeta0 : float, damping of the nominal model (legend)
    band_hz : (lo, hi) Hz
    quantity : str

    Returns
    -------
    matplotlib.figure.Figure
    """
    channels, t0, se0 = ov.channels, ov.tests[0], ov.std_error
    fig = _figure(figsize=(9, 2.3 * (len(channels) + 1) + 0.6))
    all_axes = fig.subplots(len(channels) + 1, 1, sharex=True, squeeze=False)[:, 0]
    axes, dev_ax = all_axes[:-1], all_axes[-1]
    f = t0.freq_hz
    for k, (ax, name) in enumerate(zip(axes, channels)):
        row = list(t0.outputs).index(name)
        if se0 is not None:
            a = np.abs(t0.frf[:, row, 0])
            s = se0[:, row, 0]
            ax.fill_between(f, np.maximum(a - 2 * s, 1e-3 * a), a + 2 * s, color="gold", alpha=0.5, lw=0)
        for t in ov.tests:
            ax.semilogy(t.freq_hz, np.abs(t.frf[:, list(t.outputs).index(name), 0]), color="0.6", lw=1.8)
        for mname, H in ov.models:
            ax.semilogy(f, np.abs(H[:, k, 0]), _STYLE[mname], lw=0.9)
        ax.set_ylabel(f"{name}\n({'cal' if name in calibrate_channels else 'hold-out'})", fontsize=8)
        ax.set_xlim(band_hz)
    dev = ov.deviation()
    for mname, _ in ov.models:
        dev_ax.semilogy(f, dev[mname], _STYLE[mname], lw=0.8, label=mname)
    if dev["floor"] is not None:
        dev_ax.fill_between(f, 1e-4, dev["floor"], color="gold", alpha=0.6, lw=0, label="floor (std error / |H|)" if "estimated" not in ov.floor_source
                            else "floor (estimated from adjacent lines)")
    dev_ax.set_ylabel("rel. deviation\n(RMS over channels)", fontsize=8)
    dev_ax.legend(fontsize=7, loc="upper right", ncol=4)
    a0 = axes[0]
    a0.plot([], [], color="0.6", lw=1.8, label="test (raw lines)")
    if se0 is not None:
        a0.fill_between([], [], [], color="gold", alpha=0.5, label="test +- 2 std error (floor)"
                        + ("" if "estimated" not in ov.floor_source else ", estimated"))
    labels = {"nominal": f"nominal (zeta0 {100 * zeta0:g} %)", "calibrated": "calibrated",
              "extended": "extended (diagnosis)"}
    for mname, _ in ov.models:
        a0.plot([], [], _STYLE[mname], label=labels[mname])
    a0.legend(fontsize=7, loc="upper right", ncol=2)
    dev_ax.set_xlabel("frequency [Hz]")
    fig.suptitle(f"{label}: |{quantity}| test vs model, first drive ({quantity_unit(quantity)})")
    fig.tight_layout()
    return fig


def quantity_unit(quantity: str) -> str:
    """SI unit of an FRF quantity (accelerance m/s^2/N, mobility m/s/N, receptance m/N)."""
    return _UNITS.get(quantity, "SI")


def pairwise_sd_figure(names, D):
    """The article-to-article SD matrix as an image (dimensionless log-ratio SD).

    Returns
    -------
    matplotlib.figure.Figure
    """
    n = len(names)
    fig = _figure(figsize=(2.5 + 0.6 * n, 2.0 + 0.5 * n))
    ax = fig.subplots()
    im = ax.imshow(D, cmap="magma_r", origin="upper")
    ax.set_xticks(range(n))
    ax.set_yticks(range(n))
    ax.set_xticklabels(names, rotation=60, fontsize=7)
    ax.set_yticklabels(names, fontsize=7)
    fig.colorbar(im, ax=ax, label="pairwise SD")
    ax.set_title("article-to-article SD", fontsize=9)
    fig.tight_layout()
    return fig
