"""Structured meshes: boxes of hexahedra, and their conforming split into tetrahedra."""

from __future__ import annotations

import numpy as np

# the six tetrahedra of a hexahedron along its diagonal 0-6 (Kuhn split; conforming on a regular grid)
_KUHN = np.array([[0, 1, 2, 6], [0, 1, 5, 6], [0, 3, 2, 6], [0, 3, 7, 6], [0, 4, 5, 6], [0, 4, 7, 6]])


def box_hexahedra(n, size, origin=(0.0, 0.0, 0.0)):
    """A box split into ``n = (nx, ny, nz)`` hexahedra.

    Returns
    -------
    X : ((nx+1)(ny+1)(nz+1), 3) float and cells : (nx ny nz, 8) int (node order of
    :mod:`knee.models.fem.elements`).
    """
    nx, ny, nz = (int(v) for v in n)
    axes = [np.linspace(o, o + s, k + 1) for o, s, k in zip(origin, size, (nx, ny, nz))]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    X = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])

    def node(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    cells = np.column_stack([node(i, j, k), node(i + 1, j, k), node(i + 1, j + 1, k), node(i, j + 1, k),
                             node(i, j, k + 1), node(i + 1, j, k + 1), node(i + 1, j + 1, k + 1),
                             node(i, j + 1, k + 1)])
    return X, cells


def hexahedra_to_tetrahedra(X, cells):
    """Split each hexahedron into six positively oriented tetrahedra, (6E, 4)."""
    tets = np.asarray(cells)[:, _KUHN].reshape(-1, 4)
    p = np.asarray(X)[tets]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    neg = vol < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
    return tets
