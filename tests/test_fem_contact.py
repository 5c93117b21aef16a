"""Penalty contact between two embedded point sets (knee.models.fem.fields.MappedPenaltyContact): the forces
against a brute-force nearest-neighbour computation, whatever the candidate list kept between steps; the
tangent's matrix against its matrix-free product; its pattern within the reserve."""

import numpy as np

from knee.models.fem.fields import MappedPenaltyContact
from knee.models.fem.grid import SparseGrid
from knee.models.fem.meshing import box_hexahedra


def _grid(n=(6, 6, 4), size=(60.0, 60.0, 40.0)):
    X, cells = box_hexahedra(n, size)
    axes = tuple(np.linspace(0, s, k + 1) for s, k in zip(size, n))
    ijk = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    return SparseGrid(X, cells, np.ones(len(cells)), np.zeros(len(cells), int), axes, ijk)


def _contact(g, rng, a_spec, b_spec):
    """Contact between two random point layers, (count, z_low, z_high) each, over the grid's x-y extent."""
    a, b = (np.column_stack([rng.uniform(5, 55, n), rng.uniform(5, 55, n), rng.uniform(lo, hi, n)])
            for n, lo, hi in (a_spec, b_spec))
    return MappedPenaltyContact(g, a, b, k=50.0, distance=10.0)


def _brute(c, x):
    pa, pb = c.ma.apply(x), c.mb.apply(x)
    D = np.linalg.norm(pa[:, None, :] - pb[None, :, :], axis=2)
    j = D.argmin(axis=1)
    d = D[np.arange(len(pa)), j]
    on = d < c.reach
    f = np.zeros_like(pa)
    sep = pa[on] - pb[j[on]]
    f_on = (c.k * (c.reach[on] - d[on]) / d[on])[:, None] * sep
    f[on] = f_on
    fb = np.zeros_like(pb)
    np.add.at(fb, j[on], -f_on)
    return c.ma.apply_transpose(f) + c.mb.apply_transpose(fb), int(on.sum())


def test_contact_forces_match_brute_force_over_moves():
    g = _grid()
    rng = np.random.default_rng(0)
    c = _contact(g, rng, (300, 2, 18), (200, 24, 38))
    x = g.X.copy()
    upper = g.X[:, 2] > 20.0
    total_active = 0
    for step in range(12):  # the upper half sinks towards the lower: small moves reuse the candidates
        x = x.copy()
        x[upper, 2] -= 0.6 if step < 10 else 4.0  # then two large moves that force a new list
        x += rng.normal(scale=0.05, size=x.shape)
        f = c.forces(x)
        ref, n_on = _brute(c, x)
        assert c.active == n_on
        total_active += n_on
        np.testing.assert_allclose(f, ref, atol=1e-9 * max(1.0, np.abs(ref).max()))
    assert total_active > 50  # the test saw contact


def test_contact_tangent_matrix_matches_its_product_and_lies_in_the_reserve():
    g = _grid()
    rng = np.random.default_rng(1)
    c = _contact(g, rng, (200, 12, 19), (200, 21, 28))
    x = g.X.copy()
    x[g.X[:, 2] > 20.0, 2] -= 2.0
    c.forces(x)
    assert c.active > 0
    K = c.matrix()
    p = rng.normal(size=x.shape)
    np.testing.assert_allclose((K @ p.ravel()).reshape(-1, 3), c.apply(p), atol=1e-9)
    np.testing.assert_allclose((K - K.T).toarray(), 0.0, atol=1e-9)
    R = c.pattern_reserve()
    used = abs(K) > 0
    assert used.multiply(R > 0).nnz == used.nnz  # every coupling the contact made was reserved


def test_reserve_for_a_planned_motion_holds_every_pair_it_brings():
    """B's layer slides sideways and sinks in three rigid increments (the nodes of its cells moved with it,
    so that its embedded points move rigidly; A's cells share no node with them): every coupling the
    contact makes at each increment lies in the reserve computed for those motions beforehand, which the
    rest reserve alone does not hold (the slide brings B next to cells of A that were far at rest)."""
    g = _grid(n=(8, 4, 4), size=(120.0, 40.0, 40.0))
    rng = np.random.default_rng(2)
    a = np.column_stack([rng.uniform(5, 115, 300), rng.uniform(5, 35, 300), rng.uniform(2, 19, 300)])
    b = np.column_stack([rng.uniform(5, 40, 150), rng.uniform(5, 35, 150), rng.uniform(31, 38, 150)])
    c = MappedPenaltyContact(g, a, b, k=50.0, distance=10.0)
    moves = [np.array([dx, 0.0, dz]) for dx, dz in ((20.0, -4.0), (45.0, -5.0), (70.0, -6.0))]
    poses = np.stack([np.eye(4)] * 3)
    poses[:, :3, 3] = moves
    R = c.pattern_reserve_for_motion(poses) > 0
    b_nodes = np.unique(g.cells[c.mb.cell])
    assert not np.intersect1d(b_nodes, g.cells[c.ma.cell]).size
    used_any = None
    for d in moves:
        x = g.X.copy()
        x[b_nodes] += d
        np.testing.assert_allclose(c.mb.apply(x), b + d, atol=1e-9)  # B's points moved rigidly
        c.forces(x)
        assert c.active > 0
        used = abs(c.matrix()) > 0
        assert used.multiply(R).nnz == used.nnz
        used_any = used if used_any is None else used_any + used
    assert used_any.multiply(c.pattern_reserve() > 0).nnz < used_any.nnz  # the rest reserve would miss some
