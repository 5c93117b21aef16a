"""The soft-tissue grid: a sparse regular hexahedral grid enclosing the knee's skin (seed 000, 2.1).

The grid is axis-aligned in the frame it is built in (the femur frame at extension: y is the limb's
long axis). ``n_across`` cells span x and z (default 7 x 7, as in the paper); the number along y is set by
``element_size`` (mm) unless given. Each cell is sampled on a 3x3x3 lattice: all samples inside the skin
-> an *inside* cell (weight 1), some -> a *boundary* cell (weight = the inside fraction, scaling its
stiffness and mass), none -> *outside* (dropped). Nodes not used by a kept cell are dropped too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.fem.geometry import SurfaceQuery
from models.fem.meshing import box_hexahedra
from toolkit.errors import KneeInputError

INSIDE, BOUNDARY, OUTSIDE = 0, 1, 2


@dataclass
class SparseGrid:
    """A sparse hexahedral grid.

    Attributes
    ----------
    X : (N, 3) float          rest node positions
    cells : (E, 8) int        kept cells (node order of :mod:`models.fem.elements`)
    weights : (E,) float      inside fraction of each kept cell
    status : (E,) int         INSIDE or BOUNDARY
    origin, spacing : (3,) float and shape : (3,) int   the full regular grid the cells come from
    cell_ijk : (E, 3) int     each kept cell's index in the full grid
    """

    X: np.ndarray
    cells: np.ndarray
    weights: np.ndarray
    status: np.ndarray
    origin: np.ndarray
    spacing: np.ndarray
    shape: np.ndarray
    cell_ijk: np.ndarray

    @property
    def n_nodes(self) -> int:
        return len(self.X)

    def cell_lookup(self) -> np.ndarray:
        """(nx, ny, nz) int: kept-cell number of each full-grid cell, -1 where dropped."""
        table = -np.ones(tuple(self.shape), dtype=np.int64)
        table[tuple(self.cell_ijk.T)] = np.arange(len(self.cells))
        return table


def build_grid(skin, n_across: int = 7, element_size: float | None = 12.0, n_along: int | None = None,
               margin: float = 1.0) -> SparseGrid:
    """Build the sparse grid around a closed skin mesh (trimesh), see the module docstring."""
    if n_across < 1:
        raise KneeInputError(f"n_across must be at least 1, got {n_across}")
    lo, hi = np.asarray(skin.bounds[0], float) - margin, np.asarray(skin.bounds[1], float) + margin
    size = hi - lo
    if n_along is None:
        if element_size is None or not element_size > 0:
            raise KneeInputError("give a positive element_size or n_along")
        n_along = max(1, int(np.ceil(size[1] / element_size)))
    shape = np.array([n_across, n_along, n_across])
    X, cells = box_hexahedra(shape, size, lo)
    spacing = size / shape
    # 3x3x3 samples per cell
    s = (np.arange(3) + 0.5) / 3.0
    offs = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3) * spacing
    corner = X[cells[:, 0]]
    samples = corner[:, None, :] + offs[None, :, :]
    inside = SurfaceQuery.of(skin).inside(samples.reshape(-1, 3)).reshape(len(cells), -1)
    frac = inside.mean(axis=1)
    # cells the skin surface passes through are boundary cells even if no sample fell inside
    vi = np.clip(np.floor((np.asarray(skin.vertices) - lo) / spacing).astype(np.int64), 0, shape - 1)
    touched = np.zeros(len(cells), bool)
    touched[(vi[:, 0] * shape[1] + vi[:, 1]) * shape[2] + vi[:, 2]] = True
    frac = np.where(touched & (frac == 0), 1.0 / 27.0, frac)
    keep = frac > 0
    if not keep.any():
        raise KneeInputError("the skin mesh encloses no grid cell")
    ijk_all = np.stack(np.meshgrid(*[np.arange(k) for k in shape], indexing="ij"), -1).reshape(-1, 3)
    kept = cells[keep]
    used, inverse = np.unique(kept, return_inverse=True)
    return SparseGrid(X=X[used], cells=inverse.reshape(kept.shape), weights=frac[keep],
                      status=np.where(frac[keep] >= 1.0, INSIDE, BOUNDARY), origin=lo, spacing=spacing,
                      shape=shape, cell_ijk=ijk_all[keep])
