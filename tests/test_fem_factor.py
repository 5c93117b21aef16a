"""The implicit solver's factorisations: CHOLMOD's Cholesky and SuperLU's LU give the same solves."""

import numpy as np
import pytest
import scipy.sparse as sp

from knee.models.fem.factor import SparseFactor, cholmod_available


def _spd(n=300, seed=0):
    rng = np.random.default_rng(seed)
    B = sp.random(n, n, density=0.02, random_state=seed)
    return (B @ B.T + sp.eye(n) * 0.5).tocsc(), rng.normal(size=(n, 3))


@pytest.mark.parametrize("prefer", ["cholmod", "superlu"])
def test_factor_solves_one_and_several_right_hand_sides(prefer):
    A, b = _spd()
    f = SparseFactor(A, prefer=prefer)
    assert f.backend == ("cholmod" if prefer == "cholmod" and cholmod_available() else "superlu")
    z = f.solve(b)
    assert z.shape == b.shape
    np.testing.assert_allclose(A @ z, b, atol=1e-9)
    z1 = f.solve(b[:, 0])
    assert z1.shape == (A.shape[0],)
    np.testing.assert_allclose(z1, z[:, 0], atol=1e-12)


def test_cholmod_is_installed_and_used():
    """cvxopt is a dependency of the project: the fast path must be the one that runs."""
    assert cholmod_available()
    A, _ = _spd()
    assert SparseFactor(A).backend == "cholmod"


def test_an_indefinite_matrix_falls_back_to_lu():
    A, b = _spd()
    A = A.tolil()
    A[0, 0] = -5.0  # a negative diagonal entry: not positive definite
    A = A.tocsc()
    f = SparseFactor(A)
    assert f.backend == "superlu"
    np.testing.assert_allclose(A @ f.solve(b), b, atol=1e-8)


def test_unknown_backend_is_refused():
    A, _ = _spd(20)
    with pytest.raises(ValueError, match="prefer must be one of"):
        SparseFactor(A, prefer="magic")
