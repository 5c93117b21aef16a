"""Sparse factorisations of the implicit solver's matrix (the preconditioner it keeps across steps).

The matrix ``M/h + K`` (fixed DOFs replaced by identity rows) is symmetric positive definite, so a
supernodal Cholesky factorisation (CHOLMOD, from SuiteSparse, through cvxopt) fits it: on the default
model's matrix (6,000-11,000 unknowns, 3 M factor entries) it factorises about 5x faster than SciPy's
SuperLU LU and solves 2-3x faster (scripts/bench_fem.py, BENCHMARKS.md). SuperLU (symmetric mode,
minimum-degree ordering of A + A^T) remains the fallback: when cvxopt is not installed, or when the
matrix is not numerically positive definite (CHOLMOD refuses it).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

try:  # optional: a supernodal Cholesky; SuperLU otherwise
    import cvxopt
    import cvxopt.cholmod as _cholmod
except ImportError:  # pragma: no cover - depends on the installation
    cvxopt = _cholmod = None
else:
    _cholmod.options["supernodal"] = 2  # always supernodal (BLAS-3 kernels)

#: The factorisations tried in order; "cholmod" is skipped when cvxopt is missing.
BACKENDS = ("cholmod", "superlu")


def cholmod_available() -> bool:
    return _cholmod is not None


class SparseFactor:
    """A factorisation of a symmetric positive definite sparse matrix ``A`` (n, n), solving ``A z = b`` for
    ``b`` (n,) or (n, k). ``backend``: "cholmod" (supernodal Cholesky) or "superlu" (LU); ``prefer``
    picks the first to try ("superlu" forces it)."""

    def __init__(self, A, prefer: str = "cholmod"):
        if prefer not in BACKENDS:
            raise ValueError(f"prefer must be one of {', '.join(BACKENDS)}, got {prefer!r}")
        A = sp.csc_matrix(A)
        self.n = A.shape[0]
        self.backend = None
        if prefer == "cholmod" and _cholmod is not None:
            try:
                self._factor_cholmod(A)
                self.backend = "cholmod"
            except ArithmeticError:  # not positive definite to working precision
                self.backend = None
        if self.backend is None:
            self._lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True})
            self.backend = "superlu"

    def _factor_cholmod(self, A):
        low = sp.tril(A, format="csc")
        S = _cholmod_matrix(self.n, low.indptr, low.indices, low.data)
        F = _cholmod.symbolic(S)
        _cholmod.numeric(S, F)
        self._F = F

    @classmethod
    def _of_cholmod(cls, n: int, F) -> "SparseFactor":
        """A factor wrapping CHOLMOD's ``F`` (made elsewhere, e.g. by :class:`Refactorizer`)."""
        f = cls.__new__(cls)
        f.n, f.backend, f._F = n, "cholmod", F
        return f

    def solve(self, b) -> np.ndarray:
        b = np.asarray(b, float)
        if self.backend == "superlu":
            return self._lu.solve(np.asfortranarray(b) if b.ndim == 2 else b)
        B = cvxopt.matrix(b.reshape(self.n, -1))
        _cholmod.solve(self._F, B)
        out = np.array(B)
        return out.ravel() if b.ndim == 1 else out


class Refactorizer:
    """Factorisations of a sequence of matrices given by their lower triangles on patterns identified by a
    version number (:class:`knee.models.fem.system.SystemAssembler`): while the version stays the same, CHOLMOD's
    sparse matrix is only given new values and its symbolic analysis (ordering, supernodes) is reused, so
    a refresh costs the numeric factorisation alone.

    CHOLMOD refactorises in place: a factor returned by :meth:`factor` is valid until the next call. A
    matrix CHOLMOD refuses (not positive definite) is factorised by SuperLU, and the kept analysis dropped.
    """

    def __init__(self, prefer: str = "cholmod"):
        if prefer not in BACKENDS:
            raise ValueError(f"prefer must be one of {', '.join(BACKENDS)}, got {prefer!r}")
        self.prefer = prefer
        self._version = None
        self._S = self._F = None
        self.symbolic_analyses = 0
        self.analysis_seconds = 0.0  # time the last factor() spent on a new pattern's analysis

    def factor(self, version, n: int, indptr, indices, data) -> "SparseFactor":
        if self.prefer == "cholmod" and _cholmod is not None:
            self.analysis_seconds = 0.0
            if version != self._version or self._S is None:
                t0 = time.perf_counter()
                self._S = _cholmod_matrix(n, indptr, indices, data)
                self._F = _cholmod.symbolic(self._S)
                self._version = version
                self.symbolic_analyses += 1
                self.analysis_seconds = time.perf_counter() - t0
            else:
                self._S.V = cvxopt.matrix(np.asarray(data, float))
            try:
                _cholmod.numeric(self._S, self._F)
                return SparseFactor._of_cholmod(n, self._F)
            except ArithmeticError:  # not positive definite: LU below, and a fresh analysis next time
                self._version = self._S = self._F = None
        return SparseFactor(symmetric_from_lower(n, indptr, indices, data), prefer="superlu")


def _cholmod_matrix(n: int, indptr, indices, data):
    """cvxopt's sparse matrix of a lower triangle given in compressed columns (what CHOLMOD reads)."""
    cols = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr))
    return cvxopt.spmatrix(cvxopt.matrix(np.asarray(data, float)), cvxopt.matrix(np.asarray(indices, np.int64)),
                           cvxopt.matrix(cols), size=(n, n))


def symmetric_from_lower(n: int, indptr, indices, data) -> sp.csc_matrix:
    """The whole symmetric (n, n) matrix from its lower triangle in compressed columns."""
    L = sp.csc_matrix((np.asarray(data, float), indices, indptr), shape=(n, n))
    return (L + sp.triu(L.T, k=1)).tocsc()
