"""The soft-tissue grid: a sparse rectilinear hexahedral grid enclosing the knee's skin (seed 000, 2.1).

The grid is axis-aligned in the frame it is built in (the femur frame at extension: y is the limb's
long axis). ``n_across`` cells span x and z (default 7 x 7, as in the paper; the association model sizes x by
the knee instead: :func:`knee.models.fem.scene.knee_sized_across`). Along y the spacing is
``element_size``, or, with ``joint_y`` given, graded: ``joint_size`` within ``joint_half_width`` of the
joint line, growing by ``growth`` per cell up to ``element_size`` away from it, so the soft joint space
between femur and tibia spans whole cells (the paper's uniform 7 x 7 x 300 grid does this with
uniformly thin cells: ``n_along=300``).

Each cell is sampled on a 3x3x3 lattice: all samples inside the skin -> an *inside* cell (weight 1),
some -> a *boundary* cell (weight = the inside fraction, scaling its stiffness and mass), none ->
*outside* (dropped) unless the skin surface passes through it. Unused nodes are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from knee.foundations.errors import KneeInputError
from knee.foundations.surfaces import SurfaceQuery, closed_surface

INSIDE, BOUNDARY = 0, 1  # a cell's status (cells outside the skin are dropped)
#: mm: how far the grid's box reaches beyond the skin's on every side (:func:`build_grid`'s ``margin``).
GRID_MARGIN_MM = 1.0
#: The paper's cells across the limb, each way (seed 000's 7 x 7 grid): the model's across the medio-lateral axis
#: (z), and the least along the anteroposterior one (x) (:func:`knee.models.fem.scene.knee_sized_across`).
PAPER_CELLS_ACROSS = 7


@dataclass
class SparseGrid:
    """A sparse rectilinear hexahedral grid.

    Attributes
    ----------
    X : (N, 3) float          rest node positions
    cells : (E, 8) int        kept cells (node order of :mod:`knee.models.fem.elements`)
    weights : (E,) float      inside fraction of each kept cell
    status : (E,) int         INSIDE or BOUNDARY
    axes : tuple of three 1-D float arrays   node coordinates of the full grid along x, y, z
    cell_ijk : (E, 3) int     each kept cell's index in the full grid
    """

    X: np.ndarray
    cells: np.ndarray
    weights: np.ndarray
    status: np.ndarray
    axes: tuple
    cell_ijk: np.ndarray

    @property
    def n_nodes(self) -> int:
        return len(self.X)

    @property
    def shape(self) -> np.ndarray:
        return np.array([len(a) - 1 for a in self.axes])

    @property
    def cell_volumes(self) -> np.ndarray:
        """(E,) full volume of each kept cell (before weighting)."""
        d = [np.diff(a) for a in self.axes]
        i, j, k = self.cell_ijk.T
        return d[0][i] * d[1][j] * d[2][k]

    def cell_lookup(self) -> np.ndarray:
        """(nx, ny, nz) int: kept-cell number of each full-grid cell, -1 where dropped."""
        table = -np.ones(tuple(self.shape), dtype=np.int64)
        table[tuple(self.cell_ijk.T)] = np.arange(len(self.cells))
        return table

    def locate(self, points):
        """Full-grid cell indices (P, 3) (clipped to the grid) and natural coordinates (P, 3) of points;
        natural coordinates are in [-1, 1] inside a cell."""
        p = np.asarray(points, dtype=float)
        ijk = np.empty(p.shape, dtype=np.int64)
        xi = np.empty(p.shape)
        for d, a in enumerate(self.axes):  # three axes, vectorised over points
            i = np.clip(np.searchsorted(a, p[:, d], side="right") - 1, 0, len(a) - 2)
            ijk[:, d] = i
            xi[:, d] = 2.0 * (p[:, d] - a[i]) / (a[i + 1] - a[i]) - 1.0
        return ijk, xi


def graded_axis(lo: float, hi: float, fine: float, coarse: float, centre: float, half_width: float,
                growth: float = 1.3) -> np.ndarray:
    """Node coordinates from lo to hi: spacing ``fine`` within ``half_width`` of ``centre``, growing by
    ``growth`` per cell up to ``coarse`` outside, ending exactly at lo and hi."""
    def side(start, end, direction):
        pts, h, p = [], fine, start
        while (end - p) * direction > 1e-9:
            if abs(p - centre) >= half_width:
                h = min(h * growth, coarse)
            p = p + direction * h
            if (end - p) * direction < 0.5 * h:
                p = end
            pts.append(p)
        return pts
    c = min(max(centre, lo), hi)
    up = side(c, hi, 1.0)
    down = side(c, lo, -1.0)
    return np.array(sorted(set([c] + up + down)))


def across_counts(n_across) -> tuple[int, int]:
    """The cells across x and z of ``n_across``: one count for both, or a pair (x, z)."""
    counts = (n_across, n_across) if np.ndim(n_across) == 0 else tuple(n_across)
    if len(counts) != 2 or any(int(n) != n or n < 1 for n in counts):
        raise KneeInputError(f"n_across must be a whole number of at least 1 or a pair of them (x, z), got {n_across}")
    return int(counts[0]), int(counts[1])


def build_grid(skin, n_across: int | tuple[int, int] = PAPER_CELLS_ACROSS,
               element_size: float | None = 12.0, n_along: int | None = None, margin: float = GRID_MARGIN_MM,
               joint_y: float | None = None, joint_size: float = 3.0, joint_half_width: float = 15.0, growth: float = 1.3,
               offset: float = 0.0) -> SparseGrid:
    """Build the sparse grid around a closed skin mesh (trimesh), see the module docstring. ``n_across``: the
    cells across x and z, one count for both or a pair (x, z). ``offset`` (a fraction of a cell, in [0, 1)): the
    same cells moved by that fraction across x and z (so one more cell spans each) and the joint line's grading
    by that fraction of ``joint_size``: another placement of the same discretisation."""
    nx_, nz_ = across_counts(n_across)
    if not 0.0 <= offset < 1.0:
        raise KneeInputError(f"the grid's offset must be a fraction of a cell in [0, 1), got {offset}")
    skin = closed_surface(skin, "skin")
    lo = np.asarray(skin.bounds[0], float) - margin
    hi = np.asarray(skin.bounds[1], float) + margin
    if offset > 0.0:
        hx, hz = (hi[0] - lo[0]) / nx_, (hi[2] - lo[2]) / nz_
        ax = lo[0] - offset * hx + hx * np.arange(nx_ + 2)
        az = lo[2] - offset * hz + hz * np.arange(nz_ + 2)
        if joint_y is not None:
            joint_y = joint_y + offset * joint_size
    else:
        ax = np.linspace(lo[0], hi[0], nx_ + 1)
        az = np.linspace(lo[2], hi[2], nz_ + 1)
    if n_along is not None:
        if n_along < 1:
            raise KneeInputError(f"n_along must be at least 1, got {n_along}")
        ay = np.linspace(lo[1], hi[1], int(n_along) + 1)
    else:
        if element_size is None or not element_size > 0:
            raise KneeInputError("give a positive element_size or n_along")
        if joint_y is None:
            ay = np.linspace(lo[1], hi[1], max(1, int(np.ceil((hi[1] - lo[1]) / element_size))) + 1)
        else:
            if not (0 < joint_size <= element_size):
                raise KneeInputError("joint_size must be positive and at most element_size")
            ay = graded_axis(lo[1], hi[1], joint_size, element_size, joint_y, joint_half_width, growth)
    axes = (ax, ay, az)
    nx, ny, nz = len(ax) - 1, len(ay) - 1, len(az) - 1
    gx, gy, gz = np.meshgrid(ax, ay, az, indexing="ij")
    X = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])

    def node(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    ijk = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    i, j, k = ijk.T
    cells = np.column_stack([node(i, j, k), node(i + 1, j, k), node(i + 1, j + 1, k), node(i, j + 1, k),
                             node(i, j, k + 1), node(i + 1, j, k + 1), node(i + 1, j + 1, k + 1),
                             node(i, j + 1, k + 1)])
    # 3x3x3 samples per cell
    s = (np.arange(3) + 0.5) / 3.0
    lo_c = np.column_stack([ax[i], ay[j], az[k]])
    size_c = np.column_stack([ax[i + 1] - ax[i], ay[j + 1] - ay[j], az[k + 1] - az[k]])
    offs = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    samples = lo_c[:, None, :] + offs[None, :, :] * size_c[:, None, :]
    inside = SurfaceQuery.of(skin).inside(samples.reshape(-1, 3)).reshape(len(cells), -1)
    frac = inside.mean(axis=1)
    # cells the skin surface passes through are boundary cells even if no sample fell inside
    tmp = SparseGrid(X, cells, frac, np.zeros(len(cells), int), axes, ijk)
    vi, _ = tmp.locate(np.asarray(skin.vertices))
    touched = np.zeros(len(cells), bool)
    touched[(vi[:, 0] * ny + vi[:, 1]) * nz + vi[:, 2]] = True
    frac = np.where(touched & (frac == 0), 1.0 / 27.0, frac)
    keep = frac > 0
    if not keep.any():
        raise KneeInputError("the skin mesh encloses no grid cell")
    kept = cells[keep]
    used, inverse = np.unique(kept, return_inverse=True)
    return SparseGrid(X=X[used], cells=inverse.reshape(kept.shape), weights=frac[keep],
                      status=np.where(frac[keep] >= 1.0, INSIDE, BOUNDARY), axes=axes, cell_ijk=ijk[keep])
