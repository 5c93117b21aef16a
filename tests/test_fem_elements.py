"""Co-rotational elements against mechanics references: rigid-motion invariance, objectivity, the
patch test, and cantilever tip deflection against Timoshenko beam theory with mesh refinement."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from knee.foundations.conventions import cardan_to_matrix
from knee.foundations.errors import KneeInputError
from knee.models.fem.assembly import PatternAssembler
from knee.models.fem.elements import CorotationalElements, element_strains
from knee.models.fem.material import elasticity_matrix
from knee.models.fem.meshing import box_hexahedra, hexahedra_to_tetrahedra


def _mesh(kind, n=(3, 2, 2), size=(30.0, 20.0, 20.0), distort=0.0, seed=0):
    X, hexes = box_hexahedra(n, size)
    if distort:
        rng = np.random.default_rng(seed)
        inner = np.all((X > 1e-9) & (X < np.array(size) - 1e-9), axis=1)
        X = X.copy()
        X[inner] += rng.uniform(-distort, distort, (inner.sum(), 3))
    return X, (hexes if kind == "hex" else hexahedra_to_tetrahedra(X, hexes))


@pytest.mark.parametrize("kind", ["hex", "tet"])
@pytest.mark.parametrize("distort", [0.0, 2.0])
def test_rigid_motion_gives_no_corotational_force(kind, distort):
    X, cells = _mesh(kind, distort=distort)
    el = CorotationalElements(X, cells, 1500.0, 0.3)
    Q = cardan_to_matrix(0.8, -0.4, 1.1)
    x = X @ Q.T + np.array([5.0, -7.0, 3.0])
    scale = np.abs(el.K).max() * np.abs(X).max()  # force scale of a unit-strain deformation
    assert np.abs(el.forces(x)).max() < 1e-9 * scale
    assert np.abs(el.forces(x, corotational=False)).max() > 1e-2 * scale  # small strain fails
    np.testing.assert_allclose(el.R, np.broadcast_to(Q, el.R.shape), atol=1e-12)


@pytest.mark.parametrize("kind", ["hex", "tet"])
def test_objectivity_of_deformed_elements(kind):
    X, cells = _mesh(kind, distort=1.5)
    el = CorotationalElements(X, cells, 1.0, 0.3)
    rng = np.random.default_rng(3)
    x = X + rng.normal(0, 0.5, X.shape)
    Q = cardan_to_matrix(-1.2, 0.5, 2.0)
    f0 = el.forces(x)
    f1 = el.forces(x @ Q.T + np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(f1, f0 @ Q.T, atol=1e-10 * np.abs(f0).max())


@pytest.mark.parametrize("kind", ["hex", "tet"])
def test_patch_test(kind):
    """An affine displacement gives the uniform strain exactly, and with the boundary nodes prescribed
    by it, the interior nodes of a distorted patch solve to the same affine field."""
    X, cells = _mesh(kind, n=(3, 3, 3), size=(30.0, 30.0, 30.0), distort=3.0, seed=5)
    A = np.array([[1e-3, 2e-3, -1e-3], [5e-4, -2e-3, 1e-3], [3e-3, 0.0, 1.5e-3]])
    u = X @ A.T + np.array([0.1, -0.2, 0.3])
    eps = element_strains(X, cells, u)
    S = 0.5 * (A + A.T)
    expected = np.array([S[0, 0], S[1, 1], S[2, 2], 2 * S[0, 1], 2 * S[1, 2], 2 * S[0, 2]])
    np.testing.assert_allclose(eps, np.broadcast_to(expected, eps.shape), atol=1e-15)
    el = CorotationalElements(X, cells, 10.0, 0.3)
    K = PatternAssembler(cells, len(X)).assemble(el.K).tocsr()
    inner = np.all((X > 1e-9) & (X < 30 - 1e-9), axis=1)
    free = np.repeat(inner, 3)
    rhs = -K[free][:, ~free] @ u.ravel()[~free]
    u_in = spla.spsolve(K[free][:, free].tocsc(), rhs)
    np.testing.assert_allclose(u_in, u.ravel()[free], atol=1e-12)


def test_assembly_matches_naive_coo_and_forces():
    X, cells = _mesh("hex", distort=1.0)
    el = CorotationalElements(X, cells, 5.0, 0.25)
    K = PatternAssembler(cells, len(X)).assemble(el.K)
    E, n = cells.shape
    dof = (3 * cells[:, :, None] + np.arange(3)).reshape(E, 3 * n)
    naive = sp.coo_matrix((el.K.ravel(), (np.repeat(dof, 3 * n, axis=1).ravel(),
                                          np.tile(dof, (1, 3 * n)).ravel())), shape=K.shape).tocsr()
    assert abs(K - naive).max() < 1e-12
    u = np.random.default_rng(1).normal(size=X.shape)
    np.testing.assert_allclose(K @ u.ravel(), -el.forces(X + u, corotational=False).ravel(), atol=1e-10)
    assert abs(K - K.T).max() < 1e-10  # symmetric


@pytest.mark.parametrize("kind", ["hex", "tet"])
def test_rotated_stiffness_is_the_tangent_of_the_corotational_force(kind):
    """``rotated_stiffness()`` against the rotation written out as a block-diagonal matrix, and against
    the forces: for rotations held fixed, -(f(x + h p) - f(x)) / h = R K R^T p exactly (linear in x)."""
    X, cells = _mesh(kind, distort=1.5)
    el = CorotationalElements(X, cells, 7.0, 0.3)
    rng = np.random.default_rng(4)
    x = X + rng.normal(0, 0.8, X.shape)
    el.forces(x)  # rotations at x
    Kr = el.rotated_stiffness()
    n = cells.shape[1]
    Rb = np.einsum("ab,eij->eaibj", np.eye(n), el.R).reshape(len(cells), 3 * n, 3 * n)
    np.testing.assert_allclose(Kr, Rb @ el.K @ np.swapaxes(Rb, 1, 2), atol=1e-12 * np.abs(el.K).max())
    R_at_x = el.R.copy()
    p = rng.normal(size=X.shape)
    fe0 = el.element_forces(x)
    el.update_rotations = lambda *a, **k: R_at_x  # hold the rotations at x
    fe1 = el.element_forces(x + 1e-3 * p)
    expected = -(fe1 - fe0) / 1e-3
    got = (Kr @ p[cells].reshape(len(cells), 3 * n, 1)).reshape(expected.shape)
    np.testing.assert_allclose(got, expected, atol=1e-7 * np.abs(expected).max())


@pytest.mark.parametrize("kind", ["hex", "tet"])
def test_isotropic_stiffness_blocks_match_b_transpose_d_b(kind):
    """The element stiffness written out in Lame blocks (isotropic D) against the strain-displacement form
    V B^T D B summed over the quadrature points; an anisotropic D takes the B form itself."""
    from knee.models.fem.elements import (
        _b_matrix,
        gradient_stiffness,
        hex_gradients,
        tet_gradients,
    )

    X, cells = _mesh(kind, distort=2.0, seed=7)
    if kind == "hex":
        dN, w = hex_gradients(X[cells])
    else:
        dN, vol = tet_gradients(X[cells])
        dN, w = dN[:, None], np.abs(vol)[:, None]
    B = _b_matrix(dN)
    for D in (elasticity_matrix(5.0, 0.3), elasticity_matrix(1500.0, 0.45)):
        ref = np.einsum("eq,eqki,kl,eqlj->eij", w, B, D, B)
        np.testing.assert_allclose(gradient_stiffness(dN, w, D), ref, atol=1e-12 * np.abs(ref).max())
    D = elasticity_matrix(5.0, 0.3)
    D[3, 3] *= 2.0  # not isotropic: the general path
    ref = np.einsum("eq,eqki,kl,eqlj->eij", w, B, D, B)
    np.testing.assert_allclose(gradient_stiffness(dN, w, D), ref, atol=1e-12 * np.abs(ref).max())


def test_shared_stiffness_products_match_each_elements_own():
    """stiffness_product() multiplies a regular grid's cells group by group (one shared matrix per cell
    shape, times the cell's weight): against each element's own matrix, with weights, a dropped element
    and after a rebase on a deformed pose (every cell its own shape: no groups, the batched product)."""
    from knee.models.fem.elements import shared_stiffness_groups

    X, hexes = box_hexahedra((6, 4, 3), (60.0, 40.0, 30.0))
    X = X.copy()
    X[:, 0] = X[:, 0] ** 1.3  # graded along x: one cell shape per layer
    weights = np.random.default_rng(2).uniform(0.2, 1.0, len(hexes))
    el = CorotationalElements(X, hexes, 3.0, 0.3, weights=weights)
    el.K[5] = 0.0  # a dropped cell
    u = np.random.default_rng(3).normal(size=(len(hexes), 24))
    own = np.einsum("eij,ej->ei", el.K, u)
    groups = shared_stiffness_groups(el.K)
    assert groups is not None and len(groups[2]) == 6 + 1  # six cell shapes along x, and the zero matrix
    np.testing.assert_allclose(el.stiffness_product(u), own, atol=1e-12 * np.abs(own).max())
    moved = X + np.random.default_rng(4).normal(scale=0.5, size=X.shape)
    el.rebase(moved)
    assert shared_stiffness_groups(el.K) is None
    own = np.einsum("eij,ej->ei", el.K, u)
    np.testing.assert_allclose(el.stiffness_product(u), own, atol=1e-12 * np.abs(own).max())
    # a tetrahedral mesh of distinct shapes: no groups either
    Xt, tets = _mesh("tet", distort=2.0)
    assert shared_stiffness_groups(CorotationalElements(Xt, tets, 3.0, 0.3).K) is None


def test_shared_stiffness_groups_refuse_matrices_whose_hashes_collide(monkeypatch):
    """The groups are found by one hash per matrix: where different matrices share a hash (every weight
    zero, so every hash is 0), the check against each matrix refuses the groups (None: the batched
    product), rather than multiplying a cell by another cell's matrix."""
    import knee.models.fem.elements as E

    X, hexes = box_hexahedra((6, 4, 3), (60.0, 40.0, 30.0))
    X = X.copy()
    X[:, 0] = X[:, 0] ** 1.3  # six cell shapes
    K = CorotationalElements(X, hexes, 3.0, 0.3).K
    assert len(E.shared_stiffness_groups(K)[2]) == 6
    monkeypatch.setattr(E, "_group_hash_weights", lambda n: np.zeros(n, np.int64))
    assert E.shared_stiffness_groups(K) is None
    # equal matrices still group: one cell shape, every hash equal and the check passed
    Xu, hu = box_hexahedra((6, 4, 3), (60.0, 40.0, 30.0))
    groups = E.shared_stiffness_groups(CorotationalElements(Xu, hu, 3.0, 0.3).K)
    assert groups is not None and len(groups[2]) == 1


def _cantilever(kind, n, L=100.0, h=10.0, E=1000.0, nu=0.3, P=1.0, hex_element="trilinear", distort=0.0):
    X, cells = _mesh(kind, n=n, size=(L, h, h), distort=distort, seed=2)
    el = CorotationalElements(X, cells, E, nu, hex_element=hex_element)
    K = PatternAssembler(cells, len(X)).assemble(el.K)
    clamped, tip = X[:, 0] < 1e-9, X[:, 0] > L - 1e-9
    f = np.zeros(X.shape)
    f[tip, 1] = -P / tip.sum()
    free = ~np.repeat(clamped, 3)
    u = np.zeros(3 * len(X))
    u[free] = spla.spsolve(K[free][:, free].tocsc(), f.ravel()[free])
    deflection = -u.reshape(-1, 3)[tip, 1].mean()
    I, G, A = h ** 4 / 12, E / (2 * (1 + nu)), h * h
    kappa = 10 * (1 + nu) / (12 + 11 * nu)  # Cowper's shear coefficient for a rectangle
    timoshenko = P * L ** 3 / (3 * E * I) + P * L / (kappa * G * A)
    return deflection / timoshenko


@pytest.mark.parametrize("kind, meshes", [
    ("hex", [(10, 2, 2), (20, 4, 2), (40, 8, 2)]),
    ("tet", [(20, 4, 2), (40, 8, 2), (80, 16, 4)]),
])
def test_cantilever_converges_to_timoshenko(kind, meshes):
    ratios = [_cantilever(kind, n) for n in meshes]
    # linear elements are too stiff (locking) on coarse meshes and converge from below
    assert all(r < 1.0 for r in ratios)
    assert all(b > a for a, b in zip(ratios, ratios[1:])), ratios
    assert abs(ratios[-1] - 1.0) < 0.05, ratios


def test_incompatible_hexahedra_bend_without_locking():
    """Wilson's incompatible modes (Taylor's correction): one layer of coarse hexahedra gives the cantilever's
    deflection within a few per cent of Timoshenko's where the 2x2x2 Gauss hexahedra give a fraction of it
    (shear locking), distorted cells too; and the element still passes the patch test and gives no force
    under a rigid motion. Catches a condensation with the wrong sign or without Taylor's correction (which
    fails the distorted patch)."""
    coarse = (10, 1, 1)
    assert _cantilever("hex", coarse) < 0.8
    assert _cantilever("hex", coarse, hex_element="incompatible") == pytest.approx(1.0, abs=0.05)
    assert _cantilever("hex", (10, 2, 2), hex_element="incompatible", distort=1.0) == pytest.approx(1.0, abs=0.08)
    X, cells = _mesh("hex", n=(3, 3, 3), size=(30.0, 30.0, 30.0), distort=3.0, seed=5)
    el = CorotationalElements(X, cells, 10.0, 0.3, hex_element="incompatible")
    A = np.array([[1e-3, 2e-3, -1e-3], [5e-4, -2e-3, 1e-3], [3e-3, 0.0, 1.5e-3]])
    u = X @ A.T + np.array([0.1, -0.2, 0.3])
    K = PatternAssembler(cells, len(X)).assemble(el.K).tocsr()
    inner = np.all((X > 1e-9) & (X < 30 - 1e-9), axis=1)
    free = np.repeat(inner, 3)
    u_in = spla.spsolve(K[free][:, free].tocsc(), -K[free][:, ~free] @ u.ravel()[~free])
    np.testing.assert_allclose(u_in, u.ravel()[free], atol=1e-12)
    Q = cardan_to_matrix(0.8, -0.4, 1.1)
    assert np.abs(el.forces(X @ Q.T + 5.0)).max() < 1e-9 * np.abs(el.K).max() * 30.0
    with pytest.raises(KneeInputError, match="hexahedra's element"):
        CorotationalElements(X, cells, 10.0, 0.3, hex_element="quadratic")


def test_material_validation():
    D = elasticity_matrix(1.0, 0.0)
    np.testing.assert_allclose(np.diag(D), [1, 1, 1, 0.5, 0.5, 0.5])
    with pytest.raises(KneeInputError, match="Poisson"):
        elasticity_matrix(1.0, 0.5)
    with pytest.raises(KneeInputError, match="Young"):
        elasticity_matrix(-1.0, 0.3)
    X, cells = _mesh("tet")
    with pytest.raises(KneeInputError, match="cells"):
        CorotationalElements(X, cells[:, :3], 1.0, 0.3)


def test_closed_form_determinants_and_inverted_hexahedra():
    from knee.models.fem.elements import HEX_CORNERS, _hex_jacobians, det3, hex_inverted

    rng = np.random.default_rng(4)
    J = rng.normal(size=(50, 8, 3, 3))
    assert np.allclose(det3(J), np.linalg.det(J), rtol=1e-12, atol=1e-12)
    # the Jacobians against an independent per-Gauss-point sum over the nodes
    cube = (HEX_CORNERS + 1.0) / 2.0
    Xe = cube[None] * [2.0, 3.0, 5.0] + rng.normal(scale=0.1, size=(7, 8, 3))
    dxi, Jh = _hex_jacobians(Xe)
    ref = np.stack([[sum(np.outer(dxi[q, a], Xe[e, a]) for a in range(8)) for q in range(8)] for e in range(7)])
    assert np.allclose(Jh, ref, atol=1e-12)
    # a scaled cube is fine; mirrored it is inside out
    assert not hex_inverted(Xe).any()
    assert hex_inverted(Xe * [-1.0, 1.0, 1.0]).all()
