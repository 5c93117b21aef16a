"""Global sparse matrices with a fixed sparsity pattern, filled without Python loops.

The pattern (CSR) is built once from the element connectivity; every later fill maps the element
matrices' entries to the CSR data array with a precomputed index and ``np.bincount``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


class PatternAssembler:
    """Assemble element matrices (E, 3n, 3n) on cells (E, n) into an (3N, 3N) CSR matrix."""

    def __init__(self, cells: np.ndarray, n_nodes: int):
        cells = np.asarray(cells, dtype=np.int64)
        E, n = cells.shape
        dof = (3 * cells[:, :, None] + np.arange(3)[None, None, :]).reshape(E, 3 * n)
        rows = np.repeat(dof[:, :, None], 3 * n, axis=2).ravel()
        cols = np.repeat(dof[:, None, :], 3 * n, axis=1).ravel()
        size = 3 * n_nodes
        key = rows * size + cols
        uniq, self._map = np.unique(key, return_inverse=True)
        r, c = uniq // size, uniq % size
        self.shape = (size, size)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=size))])
        self.indices = c.astype(np.int32)
        self.nnz = uniq.size

    def assemble(self, element_matrices: np.ndarray) -> sp.csr_matrix:
        data = np.bincount(self._map, weights=np.asarray(element_matrices).ravel(), minlength=self.nnz)
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)
