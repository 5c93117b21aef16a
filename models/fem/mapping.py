"""The association mapping: points embedded in grid cells with trilinear (natural-coordinate) weights.

``J`` (P x N, sparse) carries grid node positions (or displacements) to the embedded points:
``x_points = J x_grid``; ``J^T`` carries forces on the points back to the grid nodes, and a stiffness
``K_p`` acting on the points enters the grid's equations as ``J^T K_p J`` (seed 000, 2.2). The weights
are fixed at the rest configuration (the embedding does not change).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from knee.models.fem.elements import HEX_CORNERS
from knee.models.fem.grid import SparseGrid


class TrilinearMapping:
    """Embed ``points`` (P, 3), given at rest, in the cells of ``grid``.

    A point in a dropped (outside) cell is attached to the nearest kept cell and extrapolated from it;
    ``outside`` counts those.
    """

    def __init__(self, grid: SparseGrid, points):
        P = np.asarray(points, dtype=float)
        ijk, xi = grid.locate(P)
        lookup = grid.cell_lookup()
        cell = lookup[tuple(ijk.T)]
        missing = cell < 0
        self.outside = int(missing.sum())
        self.outside_mask = missing.copy()
        if missing.any():  # nearest kept cell by cell-centre distance, extrapolating from it
            centres = np.column_stack([0.5 * (a[:-1] + a[1:])[grid.cell_ijk[:, d]] for d, a in enumerate(grid.axes)])
            d2 = ((P[missing, None, :] - centres[None, :, :]) ** 2).sum(-1)
            cell[missing] = d2.argmin(axis=1)
            ijk[missing] = grid.cell_ijk[cell[missing]]
            for d, a in enumerate(grid.axes):
                i = ijk[missing, d]
                xi[missing, d] = 2.0 * (P[missing, d] - a[i]) / (a[i + 1] - a[i]) - 1.0
        w = np.prod(1.0 + xi[:, None, :] * HEX_CORNERS[None, :, :], axis=2) / 8.0  # (P, 8)
        nodes = grid.cells[cell]  # (P, 8)
        self.cell = cell
        self.natural = xi
        self.weights = w
        self.nodes = nodes
        self.J = sp.csr_matrix((w.ravel(), (np.repeat(np.arange(len(P)), 8), nodes.ravel())),
                               shape=(len(P), grid.n_nodes))
        self.J3 = sp.kron(self.J, sp.identity(3, format="csr"), format="csr")  # on flattened xyz
        self.JT = self.J.T.tocsr()

    def apply(self, x_grid) -> np.ndarray:
        """Positions of the embedded points, (P, 3), from grid positions (N, 3)."""
        return self.J @ np.asarray(x_grid, float)

    def apply_transpose(self, forces) -> np.ndarray:
        """Grid forces (N, 3) equivalent to point forces (P, 3) (virtual work)."""
        return self.JT @ np.asarray(forces, float)
