"""Co-rotational linear hexahedra and tetrahedra, vectorised over elements.

Shapes: ``X`` rest node positions ``(N, 3)``, ``x`` current positions ``(N, 3)``, ``cells`` node indices
``(E, 8)`` (hexahedra) or ``(E, 4)`` (tetrahedra); element matrices ``(E, 3n, 3n)`` with the DOFs of a
node contiguous (node a's x, y, z at 3a, 3a+1, 3a+2). Units mm, MPa, N.

Co-rotational force of an element (seed 000, eq. 1): ``f = R K (R^T x - X)``, where K is the linear
stiffness of the rest shape and R the element's rotation from rest to now. The tangent used by the
implicit solver is ``R K R^T``. Because K annihilates rigid translations, a rigid motion of the element
(x = Q X + t) gives R = Q and zero force, to rounding.

Rotations:

* tetrahedron, QR (Nesme et al. 2005, as SOFA's "large" method): a frame from the edges (p1 - p0) and
  (p2 - p0) by Gram-Schmidt, ``R = F(x) F(X)^T``;
* hexahedron, from the mean element edges (as SOFA's hexahedron "large" method): the mean of the four
  edges along the first local direction and of the four along the second, Gram-Schmidt, then
  ``R = F(x) F(X)^T``.

Hexahedron stiffness: trilinear with 2x2x2 Gauss points (:func:`hex_stiffness`, the paper's), or with
Wilson's incompatible bending modes condensed out (:func:`hex_stiffness_incompatible`), chosen by name
(:data:`HEX_ELEMENTS`).

Hexahedron node order (local coordinates in {-1, 1}^3):
0 (-,-,-), 1 (+,-,-), 2 (+,+,-), 3 (-,+,-), 4 (-,-,+), 5 (+,-,+), 6 (+,+,+), 7 (-,+,+).
"""

from __future__ import annotations

import functools

import numpy as np

from knee.foundations.errors import KneeInputError
from knee.models.fem.material import elasticity_matrix

HEX_CORNERS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                        [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)
_HEX_EDGES_1 = np.array([[0, 1], [3, 2], [4, 5], [7, 6]])  # along the first local direction
_HEX_EDGES_2 = np.array([[0, 3], [1, 2], [4, 7], [5, 6]])  # along the second
_GAUSS = HEX_CORNERS / np.sqrt(3.0)  # 2x2x2 points, weights 1


def _b_matrix(dN: np.ndarray) -> np.ndarray:
    """Strain-displacement matrices from shape-function gradients ``dN`` (..., n, 3) -> (..., 6, 3n)."""
    n = dN.shape[-2]
    B = np.zeros(dN.shape[:-2] + (6, 3 * n))
    dx, dy, dz = dN[..., 0], dN[..., 1], dN[..., 2]
    B[..., 0, 0::3] = dx
    B[..., 1, 1::3] = dy
    B[..., 2, 2::3] = dz
    B[..., 3, 0::3] = dy
    B[..., 3, 1::3] = dx
    B[..., 4, 1::3] = dz
    B[..., 4, 2::3] = dy
    B[..., 5, 0::3] = dz
    B[..., 5, 2::3] = dx
    return B


def tet_gradients(Xe: np.ndarray):
    """Shape-function gradients and volumes of linear tetrahedra.

    Parameters
    ----------
    Xe : (E, 4, 3) float

    Returns
    -------
    dN : (E, 4, 3) float and volume : (E,) float (positive for positively oriented tetrahedra)
    """
    Dm = np.swapaxes(Xe[:, 1:] - Xe[:, :1], 1, 2)  # columns = edges
    vol = np.linalg.det(Dm) / 6.0
    if np.any(np.abs(vol) < 1e-12):
        raise KneeInputError("degenerate tetrahedron (zero volume) in the mesh")
    Dinv = np.linalg.inv(Dm)  # rows = gradients of barycentric coordinates 1..3
    dN = np.empty(Xe.shape)
    dN[:, 1:] = Dinv
    dN[:, 0] = -Dinv.sum(axis=1)
    return dN, vol


def tet_stiffness(X: np.ndarray, cells: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Linear stiffness of tetrahedra, (E, 12, 12): ``V B^T D B``."""
    dN, vol = tet_gradients(X[cells])
    return gradient_stiffness(dN[:, None], np.abs(vol)[:, None], D)


def _hex_jacobians(Xe: np.ndarray):
    """Natural-coordinate derivatives dxi (8 gauss, 8 nodes, 3) and the Jacobians (E, 8, 3, 3) of
    trilinear hexahedra at the 2x2x2 Gauss points."""
    g = _GAUSS
    c = HEX_CORNERS
    # dN/dxi at Gauss point q for node a: c_a,k/8 * prod_{j != k} (1 + c_a,j xi_q,j)
    t = 1.0 + c[None, :, :] * g[:, None, :]  # (q, a, 3)
    dxi = np.empty((8, 8, 3))
    dxi[..., 0] = c[None, :, 0] * t[..., 1] * t[..., 2] / 8
    dxi[..., 1] = c[None, :, 1] * t[..., 0] * t[..., 2] / 8
    dxi[..., 2] = c[None, :, 2] * t[..., 0] * t[..., 1] / 8
    # J[e, q, k, j] = d x_j / d xi_k = sum_a dxi[q, a, k] Xe[e, a, j]: one matrix product (E 3, 8) (8, 24)
    T = np.tensordot(np.asarray(Xe, float), dxi.transpose(0, 2, 1).reshape(24, 8), axes=([1], [1]))
    return dxi, T.reshape(len(Xe), 3, 8, 3).transpose(0, 2, 3, 1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products along the last axis of (..., 3) arrays (np.cross without its axis handling)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def nearest_rotations(M: np.ndarray, tol: float = 1e-12, max_iterations: int = 12) -> np.ndarray:
    """(K, 3, 3) -> (K, 3, 3): the rotation nearest each matrix (its polar factor), by the scaled Newton
    iteration X <- (g X + X^-T / g) / 2, g = |det X|^(-1/3), with X^-T = cofactor(X) / det X written out
    entry by entry (each entry one contiguous vector over the K matrices): several times cheaper than an
    SVD per matrix for many near-rotations (e.g. sums of neighbouring elements' rotations), converging
    quadratically (three or four iterations). Matrices with det <= 0 (or not converged: a last change
    above 1e-9) go to the SVD, a reflection's smallest singular direction flipped."""
    M = np.asarray(M, float)
    d0 = det3(M)
    ok = d0 > 1e-12 * np.einsum("kij,kij->k", M, M) ** 1.5
    X = np.ascontiguousarray(M[ok].reshape(-1, 9).T)  # (9, k): the entries row by row, each over the k
    change = np.zeros(X.shape[1])
    for _ in range(max_iterations):
        a0, a1, a2, b0, b1, b2, c0, c1, c2 = X
        C = np.array([b1 * c2 - b2 * c1, b2 * c0 - b0 * c2, b0 * c1 - b1 * c0,
                      c1 * a2 - c2 * a1, c2 * a0 - c0 * a2, c0 * a1 - c1 * a0,
                      a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])  # cofactors
        d = a0 * C[0] + a1 * C[1] + a2 * C[2]
        g = np.cbrt(np.abs(d))
        Xn = 0.5 * (X / g + C * (g / d))
        change = np.abs(Xn - X).max(axis=0) if X.size else change
        X = Xn
        if not X.size or change.max() < tol:
            break
    out = np.empty_like(M)
    out[ok] = X.T.reshape(-1, 3, 3)
    bad = np.concatenate([np.nonzero(~ok)[0], np.nonzero(ok)[0][change > 1e-9]])
    if bad.size:
        U, _, Vt = np.linalg.svd(M[bad])
        flip = np.linalg.det(U @ Vt) < 0
        U[flip, :, 2] *= -1.0
        out[bad] = U @ Vt
    return out


def det3(J: np.ndarray) -> np.ndarray:
    """Determinants of stacked 3x3 matrices (..., 3, 3) (rows a, b, c: a . (b x c)); a closed form, much
    cheaper than an LU per matrix for many small ones."""
    return np.einsum("...i,...i->...", J[..., 0, :], _cross(J[..., 1, :], J[..., 2, :]))


def hex_inverted(Xe: np.ndarray) -> np.ndarray:
    """(E,) bool: hexahedra (E, 8, 3) with a non-positive Jacobian at any Gauss point."""
    return np.any(det3(_hex_jacobians(Xe)[1]) <= 0, axis=1)


def hex_gradients(Xe: np.ndarray):
    """Shape-function gradients at the 2x2x2 Gauss points of trilinear hexahedra.

    Parameters
    ----------
    Xe : (E, 8, 3) float

    Returns
    -------
    dN : (E, 8 gauss, 8 nodes, 3) float and detJ : (E, 8) float
    """
    dxi, J = _hex_jacobians(Xe)
    detJ = det3(J)
    if np.any(detJ <= 0):
        raise KneeInputError("inverted or degenerate hexahedron (non-positive Jacobian) in the grid")
    # dN[e, q, a, j] = sum_k dxi[q, a, k] inv(J)[e, q, j, k]: a batched product (einsum's loop is ~5x slower)
    dN = dxi[None] @ np.swapaxes(np.linalg.inv(J), 2, 3)
    return dN, detJ


def _isotropic_lame(D: np.ndarray):
    """(lambda, mu) when D is isotropic (Voigt, engineering shear), else None."""
    lam, mu = D[0, 1], D[3, 3]
    ref = np.zeros((6, 6))
    ref[:3, :3] = lam
    ref[[0, 1, 2], [0, 1, 2]] += 2 * mu
    ref[[3, 4, 5], [3, 4, 5]] = mu
    return (lam, mu) if np.allclose(D, ref, rtol=1e-12, atol=1e-12 * np.abs(D).max()) else None


def gradient_stiffness(dN: np.ndarray, w: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Stiffness ``sum_q w_q B_q^T D B_q`` (E, 3n, 3n) from shape-function gradients ``dN`` (E, q, n, 3) and
    quadrature weights ``w`` (E, q). For an isotropic D the blocks are written out,
    ``K_ab = sum_q w_q (lambda g_a g_b^T + mu g_b g_a^T + mu (g_a . g_b) I)`` with g = grad N at q, from one
    batched product of the gradients (several times cheaper than forming B); the B^T D B product otherwise."""
    E, q, n, _ = dN.shape
    lame = _isotropic_lame(D)
    if lame is None:
        B = _b_matrix(dN)  # (E, q, 6, 3n)
        DB = D @ B * w[:, :, None, None]
        return (np.swapaxes(B, 2, 3) @ DB).sum(axis=1)
    lam, mu = lame
    G = dN.reshape(E, q, 3 * n)                               # rows (a, i): dN_a / dx_i at each point
    M = (np.swapaxes(G * w[:, :, None], 1, 2) @ G).reshape(E, n, 3, n, 3)  # sum_q w g_a,i g_b,j
    K = lam * M + mu * np.swapaxes(M, 2, 4)                   # [a, i, b, j]: lam M_aibj + mu M_ajbi
    trace = np.einsum("eakbk->eab", M)
    K += mu * trace[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
    return K.reshape(E, 3 * n, 3 * n)


def hex_stiffness(X: np.ndarray, cells: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Linear stiffness of trilinear hexahedra by 2x2x2 Gauss quadrature, (E, 24, 24)."""
    dN, detJ = hex_gradients(X[cells])
    return gradient_stiffness(dN, detJ, D)


def hex_stiffness_incompatible(X: np.ndarray, cells: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Linear stiffness (E, 24, 24) of hexahedra with Wilson's three incompatible modes (1 - xi_k^2 in each
    displacement component) condensed out, their gradients taken with the Jacobian at the centre (Taylor's
    correction, so that the element passes the patch test when distorted): a trilinear hexahedron bends
    without the spurious shear of the 2x2x2 Gauss stiffness (:func:`hex_stiffness`), which makes coarse
    cells too stiff in bending, and a rectangular one represents pure bending exactly. Rigid motions and
    uniform strains give the same forces as :func:`hex_stiffness`."""
    Xe = np.asarray(X, float)[cells]
    dN, detJ = hex_gradients(Xe)                       # (E, 8, 8, 3), (E, 8)
    J0 = np.einsum("ak,eaj->ekj", HEX_CORNERS / 8.0, Xe)  # the Jacobian at the centre: d x_j / d xi_k
    det0 = det3(J0)
    # d(1 - xi_k^2)/d xi = -2 xi_k e_k at the Gauss points, mapped by J0 and scaled by det J0 / det J
    dP = np.zeros((8, 3, 3))
    dP[:, [0, 1, 2], [0, 1, 2]] = -2.0 * _GAUSS
    dPx = dP[None] @ np.swapaxes(np.linalg.inv(J0), 1, 2)[:, None]  # (E, 8, 3 modes, 3)
    dPx = dPx * (det0[:, None] / detJ)[:, :, None, None]
    K = gradient_stiffness(np.concatenate([dN, dPx], axis=2), detJ, D)  # (E, 33, 33)
    Kuu, Kua, Kaa = K[:, :24, :24], K[:, :24, 24:], K[:, 24:, 24:]
    Kc = Kuu - Kua @ np.linalg.solve(Kaa, np.swapaxes(Kua, 1, 2))
    return 0.5 * (Kc + np.swapaxes(Kc, 1, 2))


#: The hexahedra's stiffness by name (:class:`CorotationalElements`' ``hex_element``).
HEX_ELEMENTS = {"trilinear": hex_stiffness, "incompatible": hex_stiffness_incompatible}


def _frames(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Orthonormal frames (E, 3, 3), columns (x, y, z), from directions a and b by Gram-Schmidt."""
    x = a / np.sqrt(np.einsum("ij,ij->i", a, a))[:, None]
    z = _cross(x, b)
    z /= np.sqrt(np.einsum("ij,ij->i", z, z))[:, None]
    y = _cross(z, x)
    return np.stack([x, y, z], axis=2)


def tet_frames(xe: np.ndarray) -> np.ndarray:
    """QR frames of tetrahedra (E, 4, 3) -> (E, 3, 3)."""
    return _frames(xe[:, 1] - xe[:, 0], xe[:, 2] - xe[:, 0])


# the mean edge vectors along the first and second local directions as combinations of the 8 nodes
_HEX_MEAN_EDGES = np.zeros((2, 8))
for _row, _edges in enumerate((_HEX_EDGES_1, _HEX_EDGES_2)):
    np.add.at(_HEX_MEAN_EDGES[_row], _edges[:, 1], 0.25)
    np.add.at(_HEX_MEAN_EDGES[_row], _edges[:, 0], -0.25)


def hex_frames(xe: np.ndarray) -> np.ndarray:
    """Mean-edge frames of hexahedra (E, 8, 3) -> (E, 3, 3)."""
    e = _HEX_MEAN_EDGES @ xe  # (E, 2, 3)
    return _frames(e[:, 0], e[:, 1])


@functools.lru_cache(maxsize=4)
def _group_hash_weights(n: int) -> np.ndarray:
    """:func:`shared_stiffness_groups`' hash weights: ``n`` odd 62-bit integers, one per entry of an element
    matrix, the same every call."""
    return np.random.default_rng(20261128).integers(1, 2 ** 62, size=n, dtype=np.int64) | 1


def shared_stiffness_groups(K: np.ndarray, max_groups: float = 0.125):
    """Groups of element matrices ``K`` (E, m, m) that are one shared symmetric matrix times a positive
    factor each, as ``(order, bounds, shared, scale)``: the elements sorted by group (``order``, with
    group g at ``order[bounds[g]:bounds[g + 1]]``), each group's shared matrix, and the sorted elements'
    factors (E, 1); zero matrices (dropped elements) form a group of their own. None when the matrices
    fall into more than ``max_groups`` times E groups (nothing to share), or when a matrix differs from its
    group's shared one times its factor by more than 1e-12 of its size."""
    E = len(K)
    if E == 0:
        return None
    flat = K.reshape(E, -1)
    size = np.abs(flat).max(axis=1)
    scale = np.where(size > 0, size, 1.0)
    key = np.round(flat / scale[:, None] * 1e9).astype(np.int64)
    # each matrix's rounded entries hashed to one integer (a fixed random weighting, wrapping on overflow),
    # so the grouping is a 1-D unique: a unique of whole rows sorts them entry by entry, about ten times
    # slower, and most calls (a bone's tetrahedra, a grid rebased on a deformed pose) find no groups at
    # all. Two different matrices sharing a hash fail the check below (the batched product then serves).
    h = key @ _group_hash_weights(key.shape[1])
    _, first, inverse = np.unique(h, return_index=True, return_inverse=True)
    if len(first) > max(1, max_groups * E):
        return None
    shared = flat[first] / scale[first, None]
    if np.abs(flat - scale[:, None] * shared[inverse]).max(initial=0.0) > 1e-12 * size.max():
        return None
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(first) + 1))
    m = K.shape[1]
    return order, bounds, [np.ascontiguousarray(S.reshape(m, m)) for S in shared], scale[order, None]


class CorotationalElements:
    """A set of co-rotational elements of one kind sharing a node array.

    Parameters
    ----------
    X : (N, 3) float
        Rest positions (mm).
    cells : (E, 4) or (E, 8) int
        Tetrahedra or hexahedra.
    E, nu : float
        Young's modulus (MPa) and Poisson's ratio.
    weights : (E,) float, optional
        Per-element stiffness factors (for example the fill fraction of boundary grid cells).
    hex_element : str
        The hexahedra's stiffness (:data:`HEX_ELEMENTS`): ``"trilinear"`` (2x2x2 Gauss,
        :func:`hex_stiffness`, as the paper's) or ``"incompatible"`` (:func:`hex_stiffness_incompatible`).
    """

    def __init__(self, X, cells, E, nu, weights=None, hex_element: str = "trilinear"):
        if hex_element not in HEX_ELEMENTS:
            raise KneeInputError(f"the hexahedra's element must be one of {', '.join(HEX_ELEMENTS)}, got "
                                 f"{hex_element!r}")
        self._hex_stiffness = HEX_ELEMENTS[hex_element]
        self.X = np.asarray(X, dtype=float)
        self.cells = np.asarray(cells, dtype=np.int64)
        if self.cells.ndim != 2 or self.cells.shape[1] not in (4, 8):
            raise KneeInputError(f"cells must be (E, 4) tetrahedra or (E, 8) hexahedra, got {self.cells.shape}")
        if self.cells.size and (self.cells.min() < 0 or self.cells.max() >= len(self.X)):
            raise KneeInputError("cells refer to nodes that do not exist")
        self.kind = "tet" if self.cells.shape[1] == 4 else "hex"
        D = elasticity_matrix(E, nu)
        self._D = D
        self._w = np.ones(len(self.cells)) if weights is None else np.asarray(weights, float)
        stiff = tet_stiffness if self.kind == "tet" else self._hex_stiffness
        self.K = stiff(self.X, self.cells, D)
        if weights is not None:
            self.K = self.K * self._w[:, None, None]
        self._frames = tet_frames if self.kind == "tet" else hex_frames
        self.Xe = self.X[self.cells]  # per-element rest coordinates (E, n, 3)
        self._F0 = self._frames(self.Xe)
        self._F0t = np.ascontiguousarray(np.swapaxes(self._F0, 1, 2))
        self.R = np.broadcast_to(np.eye(3), (len(self.cells), 3, 3)).copy()
        self.alive = np.ones(len(self.cells), bool)  # False for elements dropped by :meth:`rebase`
        self._groups_of = self._groups = None  # stiffness_product()'s groups, and the K they were found for

    @property
    def R(self) -> np.ndarray:
        """Element rotations (E, 3, 3), rest to now."""
        return self._R

    @R.setter
    def R(self, value) -> None:
        self._R = np.asarray(value, float)
        self._Rt = None

    @property
    def Rt(self) -> np.ndarray:
        """The rotations' transposes, (E, 3, 3) contiguous (kept until the rotations change: products with
        a transposed view cost about three times as much)."""
        if self._Rt is None:
            self._Rt = np.ascontiguousarray(np.swapaxes(self._R, 1, 2))
        return self._Rt

    def stiffness_product(self, u: np.ndarray) -> np.ndarray:
        """``K_e u_e`` for every element, ``u`` (E, 3n) -> (E, 3n).

        Elements whose stiffness is one shared matrix times a factor (a regular grid's cells: one per
        cell shape, scaled by the boundary cells' weights) are multiplied group by group, one matrix
        product of the group's rows with the shared matrix each: several times cheaper than a batched
        product of E small matrices. Otherwise (e.g. a bone's tetrahedra, or a grid rebased on a deformed
        pose) the batched product. The groups are found again whenever ``K`` is replaced (as :meth:`rebase`
        does); ``K`` is not to be edited in place once products have been taken."""
        if self._groups_of is not self.K:
            self._groups = shared_stiffness_groups(self.K)
            self._groups_of = self.K
        if self._groups is None:
            return (self.K @ u[:, :, None])[:, :, 0]
        order, bounds, shared, scale = self._groups
        us = u[order]
        out = np.empty_like(us)
        for g, Kg in enumerate(shared):  # K_g symmetric: the rows u^T K_g are (K_g u)^T
            np.matmul(us[bounds[g]:bounds[g + 1]], Kg, out=out[bounds[g]:bounds[g + 1]])
        out *= scale
        res = np.empty_like(out)
        res[order] = out
        return res

    @property
    def n_nodes_per_element(self) -> int:
        return self.cells.shape[1]

    def rebase(self, x: np.ndarray, drop_inverted: bool = True) -> int:
        """Make positions ``x`` (N, 3) the stress-free reference of every element that is not inverted there
        (stiffness, rest shape and frame rebuilt). Elements inverted at ``x`` are dropped (zero stiffness)
        or, with ``drop_inverted=False``, keep their old reference. Returns the number of inverted ones."""
        x = np.asarray(x, dtype=float)
        xe = x[self.cells]
        if self.kind == "tet":
            vol = np.einsum("ij,ij->i", np.cross(xe[:, 1] - xe[:, 0], xe[:, 2] - xe[:, 0]), xe[:, 3] - xe[:, 0])
            ok = vol > 1e-9 * np.abs(vol).max()
        else:
            ok = ~hex_inverted(xe)
        stiff = tet_stiffness if self.kind == "tet" else self._hex_stiffness
        K = self.K.copy()
        K[ok] = stiff(x, self.cells[ok], self._D) * self._w[ok, None, None]
        if drop_inverted:
            K[~ok] = 0.0
            self.alive = self.alive & ok
        self.K = K
        Xe = self.Xe.copy()
        Xe[ok] = xe[ok]
        self.Xe = Xe
        F0 = self._F0.copy()
        F0[ok] = self._frames(xe[ok])
        self._F0 = F0
        self._F0t = np.ascontiguousarray(np.swapaxes(F0, 1, 2))
        self.R = np.broadcast_to(np.eye(3), (len(self.cells), 3, 3)).copy()
        return int((~ok).sum())

    def update_rotations(self, x: np.ndarray, xe: np.ndarray | None = None) -> np.ndarray:
        """Element rotations (E, 3, 3) from current positions ``x`` (N, 3) (or their per-element gather
        ``xe``); stored in ``self.R``."""
        if xe is None:
            xe = np.asarray(x, float)[self.cells]
        self.R = self._frames(xe) @ self._F0t
        return self.R

    def element_forces(self, x: np.ndarray, corotational: bool = True, xe: np.ndarray | None = None) -> np.ndarray:
        """Internal (restoring) forces per element node, (E, n, 3): ``-R K (R^T x - X)``, from node positions
        ``x`` (N, 3) or their per-element gather ``xe`` (E, n, 3).

        With ``corotational=False``, the small-strain force ``-K (x - X)`` (for comparison).
        """
        if xe is None:
            xe = np.asarray(x, float)[self.cells]
        Xe = self.Xe
        E, n = self.cells.shape
        if corotational:
            R = self.update_rotations(x, xe)
            u = xe @ R - Xe  # rows: (R^T x_a)^T - X_a
            f = self.stiffness_product(u.reshape(E, 3 * n)).reshape(E, n, 3)
            return -(f @ self.Rt)
        return -self.stiffness_product((xe - Xe).reshape(E, 3 * n)).reshape(E, n, 3)

    def forces(self, x: np.ndarray, corotational: bool = True) -> np.ndarray:
        """Internal forces gathered on the nodes, (N, 3)."""
        fe = self.element_forces(x, corotational)
        out = np.zeros((len(self.X), 3))
        np.add.at(out, self.cells, fe)
        return out

    def rotated_stiffness(self) -> np.ndarray:
        """Element tangents ``R K R^T`` for the current rotations, (E, 3n, 3n) (R acting on every node's
        xyz block). Two products of each element's (3n n, 3) rows with R^T: ``Y = K R^T``, then, K being
        symmetric, ``R K R^T = (K R^T)^T R^T = Y^T R^T`` (contiguous operands throughout)."""
        E, n = self.cells.shape
        Rt = self.Rt
        Y = (self.K.reshape(E, 3 * n * n, 3) @ Rt).reshape(E, 3 * n, 3 * n)   # K R^T
        Yt = np.ascontiguousarray(np.swapaxes(Y, 1, 2))                      # R K (K symmetric)
        return (Yt.reshape(E, 3 * n * n, 3) @ Rt).reshape(E, 3 * n, 3 * n)   # R K R^T


def element_strains(X: np.ndarray, cells: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Small strains (Voigt, engineering shear) of displacement ``u`` (N, 3): at the 2x2x2 Gauss points
    of hexahedra, (E, 8, 6), or once per tetrahedron, (E, 1, 6)."""
    cells = np.asarray(cells)
    ue = np.asarray(u, float)[cells].reshape(len(cells), -1)
    if cells.shape[1] == 4:
        dN, _ = tet_gradients(np.asarray(X, float)[cells])
        return np.einsum("eij,ej->ei", _b_matrix(dN), ue)[:, None, :]
    dN, _ = hex_gradients(np.asarray(X, float)[cells])
    return np.einsum("eqij,ej->eqi", _b_matrix(dN), ue)
