"""Figures of a pretest layout: sensors on the mesh, and the autoMAC matrix (matplotlib object API: no pyplot, no backend switch)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pretest._errors import PretestError

__all__ = ["plot_layout", "plot_automac"]

_SHELLS = ("CQUAD4", "CTRIA3", "CQUAD8", "CTRIA6")


def _figure(**kw):
    """A new :class:`matplotlib.figure.Figure` (no pyplot state: the user's backend is left alone)."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise PretestError("figures need matplotlib: pip install matplotlib (a core frfcal dependency)") from None
    return Figure(**kw)


def _edges(model) -> np.ndarray:
    """(n_edges, 2, 3) unique shell edges in basic coordinates (m)."""
    pairs = []
    for card in _SHELLS:
        table = model.elements.get(card)
        if table is None or len(table) == 0:
            continue
        nodes = np.asarray(table["nodes"])
        corner = 3 if card.startswith("CTRIA") else 4
        nodes = nodes[:, :corner]
        for a in range(corner):
            pairs.append(np.stack([nodes[:, a], nodes[:, (a + 1) % corner]], axis=1))
    if not pairs:
        return np.zeros((0, 2, 3))
    e = np.sort(np.concatenate(pairs), axis=1)
    e = np.unique(e, axis=0)
    idx = model.grid_index(e.ravel()).reshape(e.shape)
    return model.xyz[idx]


def plot_layout(model, result, path, *, title: str | None = None) -> Path:
    """Sensors (arrows) and drive points (markers) on the mesh, in 3D and three views.

    Parameters
    ----------
    model : femodel.FEModel
    result : PretestResult
    path : str or Path
        PNG to write.
    """
    from mpl_toolkits.mplot3d.art3d import Line3DCollection
    from matplotlib.collections import LineCollection

    edges = _edges(model)
    s, d = result.sensors, result.drives
    extent = np.ptp(model.xyz, axis=0).max() or 1.0
    arrow = 0.08 * extent
    fig = _figure(figsize=(14, 10))
    ax3 = fig.add_subplot(2, 2, 1, projection="3d")
    if len(edges):
        ax3.add_collection3d(Line3DCollection(edges, colors="0.75", linewidths=0.3))
    else:
        ax3.scatter(*model.xyz.T, s=1, c="0.7")
    ax3.quiver(*s.xyz_m.T, *(arrow * s.directions.T), color="tab:blue", linewidth=1.5)
    ax3.scatter(*s.xyz_m.T, c="tab:blue", s=12)
    if d.n_rows:
        ax3.quiver(*d.xyz_m.T, *(-1.3 * arrow * d.directions.T), color="tab:red", linewidth=2.5)
        ax3.scatter(*d.xyz_m.T, c="tab:red", s=60, marker="*")
    lo, hi = model.xyz.min(axis=0), model.xyz.max(axis=0)
    mid = 0.5 * (lo + hi)
    for setl, c in zip((ax3.set_xlim, ax3.set_ylim, ax3.set_zlim), mid):
        setl(c - 0.5 * extent, c + 0.5 * extent)
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("z (m)")
    ax3.set_title("layout (blue: sensors, red: drive)")
    views = ((0, 1, "top view (x-y)"), (0, 2, "side view (x-z)"), (1, 2, "end view (y-z)"))
    for k, (i, j, name) in enumerate(views):
        ax = fig.add_subplot(2, 2, k + 2)
        if len(edges):
            ax.add_collection(LineCollection(edges[:, :, [i, j]], colors="0.8", linewidths=0.3))
        else:
            ax.scatter(model.xyz[:, i], model.xyz[:, j], s=1, c="0.7")
        ax.quiver(s.xyz_m[:, i], s.xyz_m[:, j], s.directions[:, i], s.directions[:, j], color="tab:blue",
                  angles="xy", scale_units="xy", scale=1.0 / arrow, width=0.004)
        ax.scatter(s.xyz_m[:, i], s.xyz_m[:, j], c="tab:blue", s=10)
        done = set()
        for name_, g, p in zip(result.channel_names, s.group.tolist(), s.xyz_m):
            if g in done:
                continue
            done.add(g)
            label = name_.rstrip("xyz") if len(result.channel_names) > len(set(s.group.tolist())) else name_
            ax.annotate(label.replace("acc", ""), (p[i], p[j]), fontsize=7, color="tab:blue",
                        xytext=(3, 3), textcoords="offset points")
        if d.n_rows:
            ax.scatter(d.xyz_m[:, i], d.xyz_m[:, j], c="tab:red", s=90, marker="*", zorder=5)
            for n, p in zip(result.drive_names, d.xyz_m):
                ax.annotate(n, (p[i], p[j]), fontsize=8, color="tab:red", xytext=(4, -10), textcoords="offset points")
        pad = 0.05 * extent + 1.1 * arrow  # room for the arrows pointing off the mesh
        ax.set_xlim(lo[i] - pad, hi[i] + pad)
        ax.set_ylim(lo[j] - pad, hi[j] + pad)
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[i] + " (m)")
        ax.set_ylabel("xyz"[j] + " (m)")
        ax.set_title(name)
    m = result.metrics
    fig.suptitle(
        title
        or f"{len(set(s.group.tolist()))} sensors / {s.n_rows} channels for {m.n_modes} modes "
        f"({result.target.frequencies_hz[0]:.1f}-{result.target.frequencies_hz[-1]:.1f} Hz): "
        f"max off-diag autoMAC {m.automac_max_offdiag:.3f}, cond(FIM) {m.fim_condition:.3g}"
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path


def plot_automac(result, path) -> Path:
    """The autoMAC matrix of the target modes at the chosen channels.

    Parameters
    ----------
    result : PretestResult
    path : str or Path
        PNG to write.
    """
    am = result.metrics.automac
    n = am.shape[0]
    labels = [f"{k + 1}\n{f:.0f}" if n <= 25 else f"{k + 1}" for k, f in zip(result.target.indices, result.target.frequencies_hz)]
    fig = _figure(figsize=(8, 7))
    ax = fig.subplots()
    im = ax.imshow(am, vmin=0, vmax=1, cmap="viridis", origin="upper")
    for i in range(n):
        for j in range(n):
            if i != j and am[i, j] >= 0.05 and n <= 30:
                ax.text(j, i, f"{am[i, j]:.2f}", ha="center", va="center", fontsize=6,
                        color="w" if am[i, j] < 0.6 else "k")
    ax.set_xticks(range(n))
    ax.set_yticks(range(n))
    ax.set_xticklabels(labels, fontsize=6)
    ax.set_yticklabels([lab.replace("\n", " / ") for lab in labels], fontsize=6)
    ax.set_xlabel("mode number / Hz")
    ax.set_ylabel("mode number / Hz")
    m = result.metrics
    i, j = m.automac_worst_pair
    ax.set_title(
        f"autoMAC at {m.n_channels} channels: max off-diagonal {m.automac_max_offdiag:.3f} "
        f"(modes {result.target.indices[i] + 1} & {result.target.indices[j] + 1})",
        fontsize=9,
    )
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="MAC")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    return path
