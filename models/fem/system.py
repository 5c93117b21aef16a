"""The implicit solver's matrix, assembled for its factorisation on a sparsity pattern kept across refreshes.

The matrix ``diag(m) + c K`` (K: the fields' stiffnesses summed; the rows and columns of held DOFs replaced
by identity) is symmetric, and the Cholesky factorisation reads only its lower triangle in compressed
columns. :class:`SystemAssembler` keeps that triangle's pattern (a sorted array of ``col * n + row`` keys)
and, per field, where its matrix's entries land in it; a refresh then only scatters the fields' values
(``data[pos] += values``) instead of summing sparse matrices, projecting, transposing and converting. The
pattern is rebuilt when a field brings entries it does not hold (contact pairs that were never active
before); it keeps the entries it had, so pairs that come and go do not change it each time, until it has
grown to ``slack`` times its size when last built from scratch. A field can reserve entries up front
(``pattern_reserve()``: the contact's possible pairs), which the pattern always holds. The held DOFs'
rows and columns are left out of the returned pattern. Its ``version`` changes with that pattern, which
tells the factorisation when the symbolic analysis must be redone (:class:`knee.models.fem.factor.Refactorizer`).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp


def _lower_keys(M: sp.csr_matrix, n: int):
    """Keys ``col * n + row`` of the lower-triangle entries of a CSR matrix, and which entries they are."""
    rows = np.repeat(np.arange(M.shape[0], dtype=np.int64), np.diff(M.indptr))
    cols = M.indices.astype(np.int64)
    low = rows >= cols
    return cols[low] * n + rows[low], low


def _sorted_unique(a: np.ndarray) -> np.ndarray:
    """Sorted distinct values (by sorting: several times faster than ``np.unique``'s hashing here)."""
    a = np.sort(a)
    return a[np.concatenate([[True], a[1:] != a[:-1]])] if a.size else a


class SystemAssembler:
    """Lower triangle (CSC) of ``diag(d) + c * sum(matrices)`` on a kept pattern (see the module docstring).

    ``n``: the matrix's size (3 x nodes). ``slack``: how far the kept pattern may grow (relative to its
    size when last built from scratch) before a rebuild drops the entries no longer used."""

    def __init__(self, n: int, slack: float = 1.5, reserve=()):
        self.n = int(n)
        self.slack = float(slack)
        # the diagonal, always present, and the entries fields declare they may use (pattern_reserve())
        self._always = _sorted_unique(np.concatenate([np.arange(self.n, dtype=np.int64) * (self.n + 1)]
                                                     + [_lower_keys(sp.csr_matrix(R), self.n)[0] for R in reserve]))
        self.keys = self._always
        self._base_size = self.keys.size  # the pattern's size when last rebuilt from scratch
        self.version = 0  # of the returned pattern (the kept one less the held DOFs' rows and columns)
        self._pattern_version = 0
        self._held_version = None  # the pattern version the held DOFs' pattern was made for
        self.pattern_seconds = 0.0  # time the last assemble() spent changing the pattern (one-off work)
        self._cache: dict[int, tuple] = {}  # slot -> (indptr, indices, lower mask, positions)
        self._geometry()

    def _geometry(self):
        self.rows = self.keys % self.n
        self.cols = self.keys // self.n
        self.indices = self.rows.astype(np.int32)
        self.diag_pos = np.searchsorted(self.keys, np.arange(self.n, dtype=np.int64) * (self.n + 1))

    def _positions(self, slot: int, M: sp.csr_matrix):
        """(lower mask, positions in the pattern, keys) of M's entries; positions None when the pattern
        lacks some of them."""
        c = self._cache.get(slot)
        if c is not None and c[0].shape == M.indptr.shape and c[1].shape == M.indices.shape \
                and np.array_equal(c[0], M.indptr) and np.array_equal(c[1], M.indices):
            return c[2], c[3], None
        keys, low = _lower_keys(M, self.n)
        pos = np.searchsorted(self.keys, keys)
        if keys.size and not np.array_equal(self.keys[np.minimum(pos, len(self.keys) - 1)], keys):
            return low, None, keys
        self._cache[slot] = (M.indptr.copy(), M.indices.copy(), low, pos)
        return low, pos, None

    def _grow(self, new_keys: np.ndarray) -> None:
        """Add keys to the pattern; the cached positions shift by the number of keys inserted before them."""
        new = _sorted_unique(new_keys)
        new = new[~np.isin(new, self.keys, assume_unique=True)]
        if not new.size:
            return
        shift = np.searchsorted(new, self.keys)  # how many new keys sort before each kept one
        self._cache = {k: (ip, ix, low, pos + shift[pos]) for k, (ip, ix, low, pos) in self._cache.items()}
        self.keys = np.insert(self.keys, np.searchsorted(self.keys, new), new)
        self._pattern_version += 1
        self._geometry()

    def _rebuild(self, mats) -> None:
        """The pattern from scratch: the diagonal, the reserved entries and what the current matrices hold."""
        self.keys = _sorted_unique(np.concatenate([self._always] + [_lower_keys(M, self.n)[0] for M in mats]))
        self._base_size = self.keys.size
        self._pattern_version += 1
        self._cache.clear()
        self._geometry()

    def prime(self, matrices) -> None:
        """Build the pattern from these matrices (with the diagonal and the reserve) and cache where their
        entries land, ahead of the first :meth:`assemble` (matrices of the same patterns then find their
        positions cached)."""
        mats = [sp.csr_matrix(M) for M in matrices]
        for M in mats:
            M.sum_duplicates()
        self._rebuild(mats)
        for i, M in enumerate(mats):
            self._positions(i, M)

    def reserve(self, matrix) -> None:
        """Add the entries of ``matrix`` (n, n; values ignored) to the kept pattern now (one growth, so one
        new symbolic analysis, instead of one each time some of them first carry values); like entries
        grown on demand, they stay until the pattern is next rebuilt from scratch."""
        keys, _ = _lower_keys(sp.csr_matrix(matrix), self.n)
        self._grow(keys)

    def assemble(self, d, matrices, c: float, free=None):
        """``d`` (n,) diagonal, ``matrices`` list of (n, n) sparse, ``c`` their factor; ``free`` (n,) 1/0 per
        DOF (held ones: identity row and column). Returns ``(indptr, indices, data)`` of the lower triangle
        in compressed columns; ``version`` identifies its pattern."""
        mats = [sp.csr_matrix(M) for M in matrices]
        for M in mats:
            M.sum_duplicates()
        t0 = time.perf_counter()
        located = [self._positions(i, M) for i, M in enumerate(mats)]
        missing = [keys for _, pos, keys in located if pos is None]
        if missing:
            self._grow(np.concatenate(missing))
            if self.keys.size > self.slack * self._base_size:
                self._rebuild(mats)
            located = [self._positions(i, M) for i, M in enumerate(mats)]
        self.pattern_seconds = time.perf_counter() - t0 if missing else 0.0
        data = np.zeros(self.keys.size)
        data[self.diag_pos] = d
        for M, (low, pos, _) in zip(mats, located):
            data[pos] += c * M.data[low]  # positions are distinct within one summed matrix
        if free is None:
            free = np.ones(self.n)
        return self._held_out(np.asarray(free, float), data)

    def _held_out(self, free, data):
        """The held DOFs' rows and columns taken out of the pattern (not merely zeroed: CHOLMOD's ordering
        would still see them as couplings), their diagonal set to 1. A few DOFs held beyond those the
        returned pattern was made for (up to :data:`HELD_IN_PATTERN` of the DOFs: nodes left with no element
        when the reference is rebased) stay in it, their couplings zeroed, so that the pattern, and with it
        the factorisation's symbolic analysis, is kept."""
        if self._held_version == self._pattern_version:
            was = self._held_free
            more = (free == 0) & (was > 0)
            if not np.any((free > 0) & (was == 0)) and more.sum() <= HELD_IN_PATTERN * self.n:
                if not np.array_equal(free, self._zero_free):
                    rows, cols = self.rows[self._keep], self.cols[self._keep]
                    self._zeroed = np.nonzero((free[rows] * free[cols] == 0) & (rows != cols))[0]
                    self._zero_free = free.copy()
                out = data[self._keep]
                out[self._zeroed] = 0.0
                out[self._out_diag] = np.where(free > 0, out[self._out_diag], 1.0)
                return self._out[0], self._out[1], out
        keep = (free[self.rows] * free[self.cols] > 0) | (self.rows == self.cols)
        self._keep = np.nonzero(keep)[0]
        cols = self.cols[self._keep]
        self._out = (np.concatenate([[0], np.cumsum(np.bincount(cols, minlength=self.n))]).astype(np.int64),
                     self.indices[self._keep])
        self._out_diag = np.searchsorted(self._keep, self.diag_pos)
        self._held_version = self._pattern_version
        self._held_free = self._zero_free = free.copy()
        self._zeroed = np.zeros(0, np.int64)
        self.version += 1
        out = data[self._keep]
        out[self._out_diag] = np.where(free > 0, out[self._out_diag], 1.0)
        return self._out[0], self._out[1], out


#: The share of the DOFs that may be held beyond those the assembler's returned pattern was made for
#: before the pattern is made again without them (:meth:`SystemAssembler._held_out`).
HELD_IN_PATTERN = 0.02
