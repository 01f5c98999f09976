"""PNG plots of identification results (matplotlib object API, imported lazily; no pyplot, no backend switch)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._errors import IdentificationError


def _figure(**kw):
    """A new :class:`matplotlib.figure.Figure` (no pyplot state: the user's backend is left alone)."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - matplotlib is a core dependency
        raise IdentificationError("plotting needs matplotlib (pip install matplotlib)") from exc
    return Figure(**kw)


def plot_stabilization(stab, path, freq_hz=None, H=None, title: str | None = None) -> Path:
    """Stabilization diagram as PNG: poles per order over frequency, data magnitude behind.

    Markers: ``o`` (filled) stable in frequency, damping and shape and
    physical; ``+`` stable in frequency only; ``.`` new or unstable pole; grey
    ``x`` poles labelled other than physical.

    Parameters
    ----------
    stab : Stabilization
    path : str or Path
        PNG file to write.
    freq_hz, H : optional
        Data shown as the sum of magnitudes over channels (log scale, right axis).

    Returns
    -------
    Path of the written file.
    """
    fig = _figure(figsize=(10, 6))
    ax = fig.subplots()
    lo, hi = stab.band_hz
    for idx, (n, poles) in enumerate(zip(stab.orders, stab.poles)):
        f = poles.frequency_hz
        phys = poles.physical
        full = stab.stable(idx)
        fonly = stab.stable_frequency[idx] & phys & ~full
        new = phys & ~full & ~fonly
        other = ~phys & (f >= lo) & (f <= hi)
        ax.plot(f[full], np.full(full.sum(), n), "o", color="tab:green", ms=5)
        ax.plot(f[fonly], np.full(fonly.sum(), n), "+", color="tab:blue", ms=6)
        ax.plot(f[new], np.full(new.sum(), n), ".", color="tab:red", ms=5)
        ax.plot(f[other], np.full(other.sum(), n), "x", color="0.6", ms=4)
    ax.set_xlim(lo, hi)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("model order n")
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], ls="", marker="o", color="tab:green", label="stable f, zeta, MAC"),
        Line2D([], [], ls="", marker="+", color="tab:blue", label="stable f"),
        Line2D([], [], ls="", marker=".", color="tab:red", label="new / unstable"),
        Line2D([], [], ls="", marker="x", color="0.6", label="not physical"),
    ]
    if freq_hz is not None and H is not None:
        f = np.asarray(freq_hz)
        Ha = np.asarray(H)
        sel = (f >= lo) & (f <= hi)
        ax2 = ax.twinx()
        ax2.semilogy(f[sel], np.sum(np.abs(Ha[sel]).reshape(sel.sum(), -1), axis=1), color="0.3", lw=0.8)
        ax2.set_ylabel("sum |H| over channels")
        handles.append(Line2D([], [], color="0.3", label="data"))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=len(handles), fontsize=8)
    ax.set_title(title or "stabilization diagram")
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    return out


def plot_fit(identification, freq_hz, H, path, channels=None, equalized_model=None, title: str | None = None) -> Path:
    """Fit overlay as PNG: data vs identified (and optionally equalized) model, magnitude and phase.

    Parameters
    ----------
    identification : Identification
    freq_hz : (n_f,) Hz; H : (n_f, n_out, n_in) the data
    path : PNG file to write
    channels : list of (out, in) pairs, optional
        Default: up to 4 channels with the best-fitting first.
    equalized_model : StateSpace, optional
        Also drawn (dashed).
    """
    f = np.asarray(freq_hz, dtype=float)
    Ha = np.asarray(H)
    if Ha.ndim != 3 or Ha.shape[0] != f.size:
        raise IdentificationError(f"plot_fit: H must be ({f.size}, n_out, n_in), got {Ha.shape}")
    lo, hi = identification.band_hz
    sel = (f >= lo) & (f <= hi)
    f = f[sel]
    Ha = Ha[sel]
    fm = np.linspace(lo, hi, max(4000, 4 * f.size)) if f.size < 20000 else f
    Hm = identification.model.frf(fm)
    He = equalized_model.frf(fm) if equalized_model is not None else None
    if channels is None:
        dev = np.asarray(identification.fit_deviation)
        order = np.argsort(np.nan_to_num(dev, nan=np.inf).reshape(-1))
        channels = [tuple(int(v) for v in np.unravel_index(k, dev.shape)) for k in order[:4]]
    fig = _figure(figsize=(4.2 * len(channels), 6))
    axes = fig.subplots(2, len(channels), squeeze=False, sharex=True)
    for c, (o, i) in enumerate(channels):
        a, b = axes[0, c], axes[1, c]
        a.semilogy(f, np.abs(Ha[:, o, i]), ".", ms=2, color="0.4", label="data")
        a.semilogy(fm, np.abs(Hm[:, o, i]), color="tab:blue", lw=1, label="identified")
        b.plot(f, np.degrees(np.angle(Ha[:, o, i])), ".", ms=2, color="0.4")
        b.plot(fm, np.degrees(np.angle(Hm[:, o, i])), color="tab:blue", lw=1)
        if He is not None:
            a.semilogy(fm, np.abs(He[:, o, i]), "--", color="tab:orange", lw=1, label="equalized")
            b.plot(fm, np.degrees(np.angle(He[:, o, i])), "--", color="tab:orange", lw=1)
        dev = identification.fit_deviation[o, i]
        a.set_title(f"out {o} / in {i}  SD={dev:.2e}", fontsize=9)
        b.set_xlabel("frequency [Hz]")
        b.set_ylim(-185, 185)
    axes[0, 0].set_ylabel(f"|H| ({identification.quantity})")
    axes[1, 0].set_ylabel("phase [deg]")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title or f"identified model, order {identification.order}")
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    return out
