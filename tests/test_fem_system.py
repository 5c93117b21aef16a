"""The solver's matrix assembled on a kept pattern (knee.models.fem.system) and refactorised on it
(knee.models.fem.factor.Refactorizer): the same matrix as summing the sparse matrices directly, whatever
entries come and go between refreshes."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from knee.models.fem.factor import Refactorizer, symmetric_from_lower
from knee.models.fem.system import SystemAssembler


def _sym(n, density, seed):
    B = sp.random(n, n, density=density, random_state=seed, format="csr")
    return (B + B.T).tocsr()


def _reference(d, mats, c, free):
    A = sp.diags(d) + c * sum(mats, sp.csr_matrix((len(d), len(d))))
    P = sp.diags(free)
    return (P @ A @ P + sp.diags(1 - free)).toarray()


def test_assembly_matches_the_direct_sum_as_entries_come_and_go():
    n = 60
    rng = np.random.default_rng(0)
    d = rng.uniform(5, 10, n)
    free = (rng.uniform(size=n) > 0.1).astype(float)
    fixed_part = _sym(n, 0.05, 1)
    sa = SystemAssembler(n)
    versions = []
    for step, seed in enumerate([2, 2, 3, 2, 4]):  # the second matrix's pattern changes between refreshes
        mats = [fixed_part * (1 + step), _sym(n, 0.03, seed)]
        indptr, indices, data = sa.assemble(d, mats, 0.3, free)
        np.testing.assert_allclose(symmetric_from_lower(n, indptr, indices, data).toarray(),
                                   _reference(d, mats, 0.3, free), atol=1e-12)
        versions.append(sa.version)
        held = np.nonzero(free == 0)[0]
        cols = np.repeat(np.arange(n), np.diff(indptr))
        # held DOFs are out of the pattern (not only zeroed): their columns and rows hold the diagonal alone
        assert np.all(np.isin(indices[np.isin(cols, held)], held) & (indices[np.isin(cols, held)] == cols[np.isin(cols, held)]))
        assert not np.any(np.isin(indices, held) & (indices != cols))
    assert versions[1] == versions[0]  # same entries: same pattern
    assert versions[2] > versions[1]   # new entries: the pattern grew
    assert versions[3] == versions[2]  # entries seen before are kept: no change when they return


def test_a_primed_pattern_needs_no_work_at_the_first_assembly():
    """prime() builds the pattern ahead: the first assembly of matrices with the primed patterns (other
    values) changes nothing in it and gives the direct sum; a new entry still grows it."""
    n = 50
    rng = np.random.default_rng(4)
    d = rng.uniform(5, 10, n)
    a, b = _sym(n, 0.05, 1), _sym(n, 0.04, 2)
    sa = SystemAssembler(n)
    sa.prime([a, b])
    keys = sa.keys.copy()
    mats = [3.0 * a, -0.5 * b]
    indptr, indices, data = sa.assemble(d, mats, 0.7)
    assert sa.pattern_seconds == 0.0 and np.array_equal(sa.keys, keys)
    np.testing.assert_allclose(symmetric_from_lower(n, indptr, indices, data).toarray(),
                               _reference(d, mats, 0.7, np.ones(n)), atol=1e-12)
    sa.assemble(d, [a, _sym(n, 0.04, 9)], 0.7)
    assert sa.keys.size > keys.size


def test_reserved_entries_keep_the_pattern_and_an_outgrown_one_is_rebuilt():
    n = 40
    d = np.full(n, 3.0)
    base = _sym(n, 0.05, 1)
    extra = _sym(n, 0.05, 7)
    sa = SystemAssembler(n, reserve=[extra])
    sa.assemble(d, [base], 1.0)
    v = sa.version
    indptr, indices, data = sa.assemble(d, [base, extra], 1.0)  # within the reserve
    assert sa.version == v
    np.testing.assert_allclose(symmetric_from_lower(n, indptr, indices, data).toarray(),
                               _reference(d, [base, extra], 1.0, np.ones(n)), atol=1e-12)
    small = SystemAssembler(n, slack=1.05)
    small.assemble(d, [base], 1.0)
    size = small.keys.size
    for seed in range(10, 16):  # patterns that keep changing: the kept one is rebuilt, not grown forever
        small.assemble(d, [base, _sym(n, 0.05, seed)], 1.0)
    assert small.keys.size <= 1.05 * size + _sym(n, 0.05, 15).nnz


def test_a_few_more_held_dofs_keep_the_pattern_with_their_couplings_zeroed():
    """Nodes held after the pattern was made (left with no element when the reference is rebased) stay in it
    with zero couplings and a unit diagonal: the same matrix as taking them out, on the same pattern (no new
    symbolic analysis). A freed DOF, or many more held, makes the pattern again without the held ones."""
    from knee.models.fem.system import HELD_IN_PATTERN

    n = 300
    rng = np.random.default_rng(5)
    d = rng.uniform(5, 10, n)
    mats = [_sym(n, 0.03, 1)]
    free = np.ones(n)
    free[:10] = 0.0
    sa = SystemAssembler(n)
    ip0, ix0, _ = sa.assemble(d, mats, 0.4, free)
    v = sa.version
    more = free.copy()
    more[10:10 + int(HELD_IN_PATTERN * n)] = 0.0  # as many more as the pattern keeps
    indptr, indices, data = sa.assemble(d, mats, 0.4, more)
    assert sa.version == v and np.array_equal(indptr, ip0) and np.array_equal(indices, ix0)
    np.testing.assert_allclose(symmetric_from_lower(n, indptr, indices, data).toarray(),
                               _reference(d, mats, 0.4, more), atol=1e-12)
    # back to the pattern's own held set: the couplings zeroed a moment ago are back
    indptr, indices, data = sa.assemble(d, mats, 0.4, free)
    assert sa.version == v
    np.testing.assert_allclose(symmetric_from_lower(n, indptr, indices, data).toarray(),
                               _reference(d, mats, 0.4, free), atol=1e-12)
    freed = free.copy()
    freed[0] = 1.0
    sa.assemble(d, mats, 0.4, freed)
    assert sa.version > v
    many = freed.copy()
    many[:int(2 * HELD_IN_PATTERN * n) + 12] = 0.0
    v = sa.version
    indptr, indices, data = sa.assemble(d, mats, 0.4, many)
    assert sa.version > v
    cols = np.repeat(np.arange(n), np.diff(indptr))
    held = np.nonzero(many == 0)[0]
    assert not np.any(np.isin(indices, held) & (indices != cols))  # taken out, not zeroed
    np.testing.assert_allclose(symmetric_from_lower(n, indptr, indices, data).toarray(),
                               _reference(d, mats, 0.4, many), atol=1e-12)


def test_refactorizer_reuses_the_analysis_and_solves_exactly():
    n = 80
    rng = np.random.default_rng(3)
    B = sp.random(n, n, density=0.05, random_state=3)
    sa = SystemAssembler(n)
    rf = Refactorizer()
    for scale in (1.0, 2.0, 0.5):
        indptr, indices, data = sa.assemble(np.full(n, 1.0), [(B @ B.T) * scale], 1.0)
        f = rf.factor(sa.version, n, indptr, indices, data)
        A = symmetric_from_lower(n, indptr, indices, data)
        b = rng.normal(size=n)
        np.testing.assert_allclose(f.solve(b), spla.spsolve(A, b), rtol=1e-9, atol=1e-12)
    if f.backend == "cholmod":
        assert rf.symbolic_analyses == 1
    # not positive definite: LU, and the next positive definite matrix is factorised afresh
    indptr, indices, data = sa.assemble(np.full(n, -1.0), [B @ B.T], 1e-3)
    f = rf.factor(sa.version, n, indptr, indices, data)
    assert f.backend == "superlu"
    A = symmetric_from_lower(n, indptr, indices, data)
    b = rng.normal(size=n)
    np.testing.assert_allclose(A @ f.solve(b), b, atol=1e-8)
    indptr, indices, data = sa.assemble(np.full(n, 1.0), [B @ B.T], 1.0)
    f = rf.factor(sa.version, n, indptr, indices, data)
    A = symmetric_from_lower(n, indptr, indices, data)
    np.testing.assert_allclose(A @ f.solve(b), b, atol=1e-9)


def test_refactorizer_refuses_an_unknown_backend():
    with pytest.raises(ValueError, match="prefer must be one of"):
        Refactorizer("magic")
