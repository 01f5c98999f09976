"""Mode-shape figures: the deformed mesh of a few modes, coloured by displacement."""

from __future__ import annotations

from pathlib import Path

import numpy as np

_SURFACE_CARDS = ("CQUAD4", "CTRIA3")
_LINE_CARDS = ("CBAR", "CBEAM", "CROD", "CONROD")


def grid_translations(assembly, shapes) -> np.ndarray:
    """Translations of every grid in basic coordinates.

    Parameters
    ----------
    assembly : femodel.Assembly
    shapes : (n_a, n_modes) array
        Shapes on the independent DOF.

    Returns
    -------
    (n_grid, 3, n_modes) array
    """
    from femodel import sensor_matrix

    grids = assembly.model.grid_ids
    n = grids.shape[0]
    out = np.empty((n, 3, shapes.shape[1]))
    for axis in range(3):
        direction = np.zeros((n, 3))
        direction[:, axis] = 1.0
        out[:, axis, :] = sensor_matrix(assembly, grids, direction) @ shapes
    return out


def _edges(model) -> np.ndarray:
    """(n_edges, 2) grid-row index pairs of shell and line elements (unique)."""
    pairs = []
    for card in _SURFACE_CARDS + _LINE_CARDS:
        table = model.elements.get(card)
        if table is None or len(table["nodes"]) == 0:
            continue
        nodes = np.asarray(table["nodes"])
        nn = 2 if card in _LINE_CARDS else nodes.shape[1]
        nodes = nodes[:, :nn]
        for a in range(nn):
            b = (a + 1) % nn
            if nn == 2 and a == 1:
                break
            pairs.append(np.stack([nodes[:, a], nodes[:, b]], axis=1))
    if not pairs:
        return np.zeros((0, 2), dtype=int)
    ids = np.sort(np.concatenate(pairs), axis=1)
    ids = np.unique(ids, axis=0)
    return model.grid_index(ids.ravel(), what="element node").reshape(-1, 2)


def plot_mode_shapes(assembly, modes, path, *, which=None, max_modes: int = 6, title: str = "") -> Path:
    """Write a PNG of deformed mode shapes.

    Parameters
    ----------
    assembly : femodel.Assembly
    modes : femodel.Modes
        Shapes on ``assembly``'s independent DOF.
    path : str or Path
        PNG file to write.
    which : sequence of int, optional
        Mode indices (0-based) to draw; default the first ``max_modes``
        elastic modes.
    """
    import matplotlib
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Line3DCollection  # also registers the 3d projection

    model = assembly.model
    if which is None:
        which = list(range(modes.n_rigid, min(modes.n_modes, modes.n_rigid + max_modes)))
    which = list(which)
    if not which:
        raise ValueError("plot_mode_shapes: no elastic modes to draw")
    u = grid_translations(assembly, modes.shapes[:, which])
    xyz = model.xyz
    extent = float(np.ptp(xyz, axis=0).max()) or 1.0
    edges = _edges(model)
    ncol = min(3, len(which))
    nrow = int(np.ceil(len(which) / ncol))
    fig = Figure(figsize=(5.2 * ncol, 4.4 * nrow))  # object API: the user's backend is left alone
    cmap = matplotlib.colormaps["viridis"]
    for k, mode in enumerate(which):
        ax = fig.add_subplot(nrow, ncol, k + 1, projection="3d")
        disp = u[:, :, k]
        mag = np.linalg.norm(disp, axis=1)
        scale = 0.08 * extent / (mag.max() or 1.0)
        deformed = xyz + scale * disp
        if len(edges):
            seg = deformed[edges]
            colour = cmap(0.5 * (mag[edges[:, 0]] + mag[edges[:, 1]]) / (mag.max() or 1.0))
            ax.add_collection3d(Line3DCollection(xyz[edges], colors="0.85", linewidths=0.3))
            ax.add_collection3d(Line3DCollection(seg, colors=colour, linewidths=0.7))
        else:
            ax.scatter(*deformed.T, c=mag, s=2, cmap=cmap)
        lo, hi = deformed.min(axis=0), deformed.max(axis=0)
        mid, half = 0.5 * (lo + hi), 0.5 * float((hi - lo).max())
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=28, azim=-60)
        ax.set_axis_off()
        ax.set_title(f"mode {mode + 1}: {modes.frequencies_hz[mode]:.1f} Hz", fontsize=11)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path
