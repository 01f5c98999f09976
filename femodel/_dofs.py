"""Degree-of-freedom maps: (grid, component) keys for matrix rows."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from femodel._model import ModelError


@dataclass(frozen=True)
class DofMap:
    """Row labels of a DOF set.

    Parameters
    ----------
    grid : (n,) int64
        Grid (or scalar point) id of each DOF.
    component : (n,) int8
        Component 1..6 (T1 T2 T3 R1 R2 R3, in the grid's CD system); 0 for
        scalar points and modal coordinates.
    """

    grid: np.ndarray
    component: np.ndarray

    def __post_init__(self) -> None:
        g = np.asarray(self.grid, dtype=np.int64).ravel()
        c = np.asarray(self.component, dtype=np.int8).ravel()
        if g.shape != c.shape:
            raise ModelError(f"DofMap: grid {g.shape} and component {c.shape} differ in length")
        object.__setattr__(self, "grid", g)
        object.__setattr__(self, "component", c)

    def __len__(self) -> int:
        return int(self.grid.shape[0])

    @classmethod
    def for_grids(cls, grids, n_comp: int = 6) -> "DofMap":
        """Six (or ``n_comp``) components per grid, grid-major."""
        grids = np.asarray(grids, dtype=np.int64)
        return cls(np.repeat(grids, n_comp), np.tile(np.arange(1, n_comp + 1, dtype=np.int8), grids.size))

    @property
    def keys(self) -> np.ndarray:
        """(n,) int64 sortable keys grid*10 + component."""
        return self.grid * 10 + self.component

    def indices(self, grid, component) -> np.ndarray:
        """Row index of each (grid, component) pair; ModelError naming the missing ones."""
        g = np.atleast_1d(np.asarray(grid, dtype=np.int64))
        c = np.atleast_1d(np.asarray(component, dtype=np.int64))
        g, c = np.broadcast_arrays(g, c)
        want = g * 10 + c
        keys = self.keys
        order = np.argsort(keys, kind="stable")
        pos = np.searchsorted(keys, want, sorter=order)
        pos = np.clip(pos, 0, max(len(self) - 1, 0))
        idx = order[pos] if len(self) else pos
        bad = np.ones(want.shape, bool) if len(self) == 0 else keys[idx] != want
        if np.any(bad):
            miss = [(int(a), int(b)) for a, b in zip(g[bad][:10], c[bad][:10])]
            raise ModelError(f"DOF (grid, component) {miss} not in this DOF set")
        return idx

    def index(self, grid: int, component: int) -> int:
        """Row index of one (grid, component)."""
        return int(self.indices(grid, component)[0])

    def subset(self, rows) -> "DofMap":
        """The DofMap of the selected rows."""
        rows = np.asarray(rows)
        return DofMap(self.grid[rows], self.component[rows])

    def labels(self) -> list[str]:
        """Human-readable labels like "101-T3"."""
        names = ["S", "T1", "T2", "T3", "R1", "R2", "R3"]
        return [f"{g}-{names[c]}" for g, c in zip(self.grid.tolist(), self.component.tolist())]
