"""Force fields of the association model, each acting on the grid's nodes (N, 3).

Every field offers ``forces(x)`` (N, 3) at grid positions x (updating its rotations), ``apply(p)`` the
product of its stiffness (tangent, at the last rotations) with a grid vector p (N, 3), and ``matrix()`` the
same stiffness as a sparse (3N, 3N) matrix (used to refresh the preconditioner). Internal forces are
restoring: ``forces`` returns -K (R^T x - X) rotated back, so a stretched element pulls its nodes in.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from knee.foundations.errors import KneeInputError
from knee.models.fem.assembly import PatternAssembler
from knee.models.fem.elements import CorotationalElements
from knee.models.fem.mapping import TrilinearMapping


class _Scatter:
    """Gather node values per element and scatter element values back, each one sparse product with a
    fixed matrix (several times cheaper than fancy indexing and ``np.add.at``).

    ``embedding``: an optional (3P, 3N) sparse map composed in front: the elements' nodes are then points
    embedded in the grid (a bone's nodes, ``x_points = J x_grid``), gathered straight from the grid's
    values, and their element values scatter straight back to the grid (through J^T)."""

    def __init__(self, cells, n_nodes, embedding=None):
        cells = np.asarray(cells)
        E, n = cells.shape
        dof = (3 * cells[:, :, None] + np.arange(3)).ravel()
        gather = sp.csr_matrix((np.ones(dof.size), (np.arange(dof.size), dof)), shape=(dof.size, 3 * n_nodes))
        if embedding is not None:
            gather = (gather @ sp.csr_matrix(embedding)).tocsr()
            gather.sum_duplicates()
        self.G = gather             # (E n 3, 3N): element values from node values
        self.S = gather.T.tocsr()   # (3N, E n 3): node values from element values
        self.shape = (E, n, 3)

    def gather(self, p):
        return (self.G @ np.asarray(p, float).ravel()).reshape(self.shape)

    def scatter(self, fe):
        return (self.S @ fe.ravel()).reshape(-1, 3)


def _apply_corot(el: CorotationalElements, pe: np.ndarray) -> np.ndarray:
    """R K R^T applied to element vectors pe (E, n, 3)."""
    E, n = el.cells.shape
    loc = (pe @ el.R).reshape(E, 3 * n)
    return el.stiffness_product(loc).reshape(E, n, 3) @ el.Rt


class GridElasticity:
    """Co-rotational hexahedra of the soft-tissue grid (weights scale boundary cells; ``element``: their
    stiffness, :data:`knee.models.fem.elements.HEX_ELEMENTS`)."""

    def __init__(self, grid, E=1.0, nu=0.3, element: str = "trilinear"):
        self.el = CorotationalElements(grid.X, grid.cells, E, nu, weights=grid.weights, hex_element=element)
        self.sc = _Scatter(grid.cells, grid.n_nodes)
        self.asm = PatternAssembler(grid.cells, grid.n_nodes)

    def forces(self, x):
        return self.sc.scatter(self.el.element_forces(None, xe=self.sc.gather(x)))

    def apply(self, p):
        return self.sc.scatter(_apply_corot(self.el, self.sc.gather(p)))

    def matrix(self):
        return self.asm.assemble(self.el.rotated_stiffness())


class MappedBoneElasticity:
    """Co-rotational tetrahedra of a bone whose nodes are embedded in the grid (x_bone = J x_grid);
    forces return through J^T and the stiffness enters as J^T K J."""

    def __init__(self, grid, X_bone, tets, E=1500.0, nu=0.3, name="bone"):
        self.map = TrilinearMapping(grid, X_bone)
        beyond = np.any(np.abs(self.map.natural) > 1.0 + 1e-9, axis=1)
        n_out = int(np.count_nonzero(beyond | self.map.outside_mask))
        if n_out:
            raise KneeInputError(f"{n_out} of {len(self.map.natural)} {name} nodes lie outside the soft-tissue grid "
                                 f"(outside the skin); the bones must lie inside the skin surface")
        self.el = CorotationalElements(X_bone, tets, E, nu)
        self.sc = _Scatter(np.asarray(tets), len(X_bone), embedding=self.map.J3)  # from and to grid nodes
        self.asm = PatternAssembler(np.asarray(tets), len(X_bone))

    def bone_positions(self, x):
        return self.map.apply(x)

    def pattern_reserve(self) -> sp.csr_matrix:
        """Every grid-DOF coupling J^T K J can hold: each tetrahedron couples every node of the cells its
        four nodes lie in, all three directions with all three. The matrix's own pattern is narrower where
        its entries cancel to exactly zero (a bone at its scanned pose, unrotated), and widens once the bone
        turns: reserved up front, the solver's pattern (and its symbolic analysis) does not change mid-motion.
        Values are placeholders; only the pattern counts."""
        J = self.map.J.copy()
        J.data[:] = 1.0  # the embedding's structure, zero weights included (a node on a cell's face)
        tets = np.asarray(self.el.cells)
        inc = sp.csr_matrix((np.ones(tets.size), (np.repeat(np.arange(len(tets)), tets.shape[1]), tets.ravel())),
                            shape=(len(tets), J.shape[0]))
        touched = inc @ J  # (E, N): the grid nodes each tetrahedron reaches
        nodes = (touched.T @ touched).tocsr()
        return sp.kron(nodes, np.ones((3, 3)), format="csr")

    def forces(self, x):
        return self.sc.scatter(self.el.element_forces(None, xe=self.sc.gather(x)))

    def apply(self, p):
        return self.sc.scatter(_apply_corot(self.el, self.sc.gather(p)))

    def matrix(self):
        Kb = self.asm.assemble(self.el.rotated_stiffness())
        J3 = self.map.J3
        return (J3.T @ Kb @ J3).tocsr()


class DisplacementTethers:
    """Zero-length springs between the displacements (from ``X_ref``) of grid nodes joined by a cell edge:
    ``f = -k L (x - X_ref)`` with L the graph Laplacian of ``edges`` (E, 2). A linear stand-in for tissue
    that has been dropped, valid for small motions from the reference."""

    def __init__(self, n_nodes: int, edges, X_ref, k: float):
        edges = np.asarray(edges, int).reshape(-1, 2)
        E = len(edges)
        inc = sp.csr_matrix((np.r_[np.ones(E), -np.ones(E)], (np.r_[np.arange(E), np.arange(E)], edges.T.ravel())),
                            shape=(E, n_nodes))
        self.L = (float(k) * (inc.T @ inc)).tocsr()
        self.K = sp.kron(self.L, sp.identity(3, format="csr"), format="csr")
        self.X_ref = np.array(X_ref, float)

    def forces(self, x):
        return -(self.L @ (np.asarray(x, float) - self.X_ref))

    def apply(self, p):
        return self.L @ np.asarray(p, float)

    def matrix(self):
        return self.K


class MappedAnchors:
    """Zero-length springs from points embedded in the grid (``x_points = J x``, a bone's nodes) to
    target positions: ``f = -k J^T (J x - targets)``, stiffness ``k J^T J``. ``targets`` (P, 3) may be
    changed between steps."""

    def __init__(self, mapping: TrilinearMapping, targets, k: float):
        self.map = mapping
        self.k = float(k)
        self.targets = np.array(targets, float)
        self.K = (self.k * (mapping.J3.T @ mapping.J3)).tocsr()

    def forces(self, x):
        return -self.k * self.map.apply_transpose(self.map.apply(x) - self.targets)

    def apply(self, p):
        return self.k * self.map.apply_transpose(self.map.apply(p))

    def matrix(self):
        return self.K


class MappedSprings:
    """Linear springs between pairs of embedded points (e.g. collateral ligaments).

    ``a``, ``b`` (S, 3) rest positions of the two ends; ``k`` (N/mm); rest length = the rest distance
    unless ``rest_length`` is given. Tangent: k n n^T + k (1 - L0/l) (I - n n^T) (the second term only
    when stretched, which keeps it positive semi-definite).
    """

    def __init__(self, grid, a, b, k=1000.0, rest_length=None, maps=None, low_rank=False):
        """``maps``: ``(ma, mb)`` mappings to use instead of embedding ``a`` and ``b`` in grid cells (for
        points attached to a bone, :func:`affine_point_map`); ``a``, ``b`` still give the rest length.

        ``low_rank``: the springs stay out of the assembled matrix (``matrix()`` is empty) and offer
        ``low_rank_factor()`` instead, which the implicit solver adds to its factorised preconditioner by
        the Woodbury identity: for springs whose ends couple many nodes (wide bone attachments), which
        would otherwise fill the factorisation with a dense block."""
        a, b = np.atleast_2d(a), np.atleast_2d(b)
        self.low_rank = bool(low_rank)
        self.ma, self.mb = maps if maps is not None else (TrilinearMapping(grid, a), TrilinearMapping(grid, b))
        self.k = float(k)
        self.L0 = np.linalg.norm(b - a, axis=1) if rest_length is None else np.atleast_1d(rest_length)
        self._K = np.zeros((len(a), 3, 3))
        d = b - a
        self._n = d / np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]
        self._ratio = np.zeros(len(a))  # 1 - L0 / l of the last forces(), 0 when not stretched

    def forces(self, x):
        pa, pb = self.ma.apply(x), self.mb.apply(x)
        d = pb - pa
        ln = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        nrm = d / ln[:, None]
        f = (self.k * (ln - self.L0))[:, None] * nrm  # on a, towards b when stretched
        ratio = np.clip(1 - self.L0 / ln, 0, None)
        nn = nrm[:, :, None] * nrm[:, None, :]
        self._K = self.k * (nn + ratio[:, None, None] * (np.eye(3) - nn))
        self._n, self._ratio = nrm, ratio
        return self.ma.apply_transpose(f) - self.mb.apply_transpose(f)

    def apply(self, p):
        dp = self.mb.apply(p) - self.ma.apply(p)
        g = np.einsum("sij,sj->si", self._K, dp)
        return self.mb.apply_transpose(g) - self.ma.apply_transpose(g)

    def matrix(self):
        if self.low_rank:  # in the preconditioner through low_rank_factor() instead
            n3 = 3 * self.ma.J.shape[1]
            return sp.csr_matrix((n3, n3))
        D = (self.mb.J3 - self.ma.J3).tocsr()
        blocks = sp.block_diag(list(self._K), format="csr")
        return (D.T @ blocks @ D).tocsr()

    def low_rank_factor(self):
        """U (3N, r) with U U^T the springs' whole tangent, ``D^T K D`` (K per spring: k n n^T, plus
        k (1 - L0/l) (I - n n^T) when stretched): per spring an axial column sqrt(k) D^T n and, when
        stretched, two transverse ones sqrt(k (1 - L0/l)) D^T t (t spanning the plane normal to n), at the
        directions of the last forces(). The transverse term matters: 1000 N/mm links stretched by a few
        per cent are tens of N/mm across, more than the tissue. None unless ``low_rank``."""
        if not self.low_rank:
            return None
        D = (self.mb.J - self.ma.J).T.toarray()  # (N, S)
        n = self._n
        # two unit vectors normal to each n: cross with the axis least aligned with it, then n x that
        helper = np.eye(3)[np.argmin(np.abs(n), axis=1)]
        t1 = np.cross(n, helper)
        t1 /= np.linalg.norm(t1, axis=1)[:, None]
        t2 = np.cross(n, t1)
        stretched = self._ratio > 0
        dirs = [np.sqrt(self.k) * n]
        if stretched.any():
            w = np.sqrt(self.k * self._ratio[stretched])[:, None]
            dirs += [w * t1[stretched], w * t2[stretched]]
        which = np.concatenate([np.arange(len(n))] + [np.nonzero(stretched)[0]] * (len(dirs) - 1))
        V = np.vstack(dirs)  # (r, 3): each column's direction, scaled
        return (D[:, None, which] * V.T[None, :, :]).reshape(-1, len(which))  # (3N, r)


class MappedPenaltyContact:
    """Penalty repulsion between surface points of one bone and the surface of another (seed 000: forces
    when the bones come within ``distance`` mm of each other).

    For each point of A closer than ``distance`` to a point of B (nearest neighbour among B's points),
    a force ``k (distance - d)`` pushes the pair apart along their separation.
    """

    def __init__(self, grid, points_a, points_b, k=50.0, distance=10.0):
        self.ma, self.mb = TrilinearMapping(grid, points_a), TrilinearMapping(grid, points_b)
        self._grid_cells = grid.cells
        self._rest_grid = grid.X
        xc = grid.X[grid.cells]
        self._cell_boxes = (xc.min(axis=1), xc.max(axis=1))
        self.k, self.distance = float(k), float(distance)
        # activation distance per point of A: 10 mm, or its rest distance to B if closer (bones that
        # touch at rest are force-free at rest)
        self.rebase(None, np.atleast_2d(points_a), np.atleast_2d(points_b))
        self._pairs = (np.zeros(0, int), np.zeros(0, int))
        self._nrm = np.zeros((0, 3))
        self._D = self._DT = None
        self.active = 0
        self.skin = 5.0  # mm, of the candidate list (see _candidates)
        self._cand = self._cand_ref = None

    def forces(self, x):
        pa, pb = self.ma.apply(x), self.mb.apply(x)
        cand = self._candidates(pa, pb)
        d, j = cKDTree(pb).query(pa[cand], distance_upper_bound=self.distance)
        keep = d < self.reach[cand]
        i, j = cand[keep], j[keep]
        sep = pa[i] - pb[j]
        ln = np.maximum(np.linalg.norm(sep, axis=1), 1e-9)
        nrm = sep / ln[:, None]
        mag = self.k * (self.reach[i] - ln)
        self._pairs, self._nrm, self.active = (i, j), nrm, i.size
        self._D = self._dmat() if i.size else None  # fixed for this step's solve
        self._DT = None if self._D is None else self._D.T.tocsr()
        if self._D is None:
            return np.zeros_like(x)
        return self._DT @ (mag[:, None] * nrm)  # +f on the A point, -f on the B point

    def pattern_reserve(self, margin: float = 0.0) -> sp.csr_matrix:
        """The grid-node couplings this field may bring into the solver's matrix: every node of a cell
        holding points of A with every node of a cell holding points of B (and with each other), for the
        cell pairs whose rest boxes are within the activation distance plus ``margin`` (mm) of each other
        along every axis, so that pairs switching on and off rarely change the matrix's pattern
        (:mod:`knee.models.fem.system`).
        Values are placeholders; only the pattern counts."""
        ca, cb = np.unique(self.ma.cell), np.unique(self.mb.cell)
        lo, hi = self._cell_boxes
        gap = np.maximum(lo[ca][:, None, :] - hi[cb][None, :, :], lo[cb][None, :, :] - hi[ca][:, None, :])
        ia, ib = np.nonzero(np.all(gap <= self.distance + margin, axis=2))
        return self._cell_pair_pattern(ca[ia], cb[ib])

    def pattern_reserve_for_motion(self, transforms, margin: float = 5.0) -> sp.csr_matrix:
        """The couplings of the pairs that can switch on while B's points move rigidly by each of
        ``transforms`` ((K, 4, 4), applied to B's rest points; A's held at rest): the cells of every A point
        within the activation distance plus ``margin`` of a moved B point, with those of that B point. For
        a planned motion (the prior's initialisation moves the tibia along the mechanism's path), reserved
        up front: one pattern, one symbolic analysis, instead of one each time new pairs appear."""
        pa = self.ma.apply(self._rest_grid)
        pb = self.mb.apply(self._rest_grid)
        tree = cKDTree(pa)
        n_cells = len(self._grid_cells)
        keys = []
        for T in np.asarray(transforms, float).reshape(-1, 4, 4):  # a handful of poses
            near = tree.sparse_distance_matrix(cKDTree(pb @ T[:3, :3].T + T[:3, 3]), self.distance + margin,
                                               output_type="ndarray")
            keys.append(self.ma.cell[near["i"]].astype(np.int64) * n_cells + self.mb.cell[near["j"]])
        keys = np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
        if not keys.size:
            n3 = 3 * self.ma.J.shape[1]
            return sp.csr_matrix((n3, n3))
        return self._cell_pair_pattern(keys // n_cells, keys % n_cells)

    def _cell_pair_pattern(self, cells_a, cells_b) -> sp.csr_matrix:
        """(3N, 3N) pattern coupling the 16 nodes of each (cell of A, cell of B) pair with each other."""
        nodes = np.concatenate([self._grid_cells[cells_a], self._grid_cells[cells_b]], axis=1)  # (pairs, 16)
        r = np.repeat(nodes, 16, axis=1).ravel()
        c = np.tile(nodes, (1, 16)).ravel()
        n = self.ma.J.shape[1]
        coupled = sp.csr_matrix((np.ones(r.size), (r, c)), shape=(n, n))
        return sp.kron(coupled, np.ones((3, 3)), format="csr")

    def rebase(self, x, pa=None, pb=None) -> None:
        """Take the activation distances from grid positions ``x`` (or the points ``pa``, ``pb`` directly):
        bones that touch there are force-free."""
        pa = self.ma.apply(x) if pa is None else pa
        pb = self.mb.apply(x) if pb is None else pb
        d0, _ = cKDTree(pb).query(pa)
        self.reach = np.minimum(self.distance, d0)

    def _candidates(self, pa, pb):
        """A's points that can be within ``distance`` of B: those within ``distance + skin`` of it when the
        list was made, valid while A's and B's points together have moved less than ``skin`` since (a
        Verlet list: most of A's points are far from B and skip the nearest-neighbour query)."""
        ref = self._cand_ref
        if ref is not None and ref[0].shape == pa.shape and ref[1].shape == pb.shape:
            moved = np.sqrt(((pa - ref[0]) ** 2).sum(axis=1).max()) + np.sqrt(((pb - ref[1]) ** 2).sum(axis=1).max())
            if moved < self.skin:
                return self._cand
        reach = self.distance + self.skin
        lo, hi = pb.min(axis=0) - reach, pb.max(axis=0) + reach
        box = np.nonzero(np.all((pa >= lo) & (pa <= hi), axis=1))[0]
        d, _ = cKDTree(pb).query(pa[box], distance_upper_bound=reach)
        self._cand = box[np.isfinite(d)]
        self._cand_ref = (pa.copy(), pb.copy())
        return self._cand

    def _dmat(self):
        """(pairs, N) sparse: grid weights of each pair's A point minus those of its B point."""
        i, j = self._pairs
        wa, wb = self.ma.weights[i], -self.mb.weights[j]  # (S, 8) each
        cols = np.concatenate([self.ma.nodes[i], self.mb.nodes[j]], axis=1)
        n = self.ma.J.shape[1]
        D = sp.csr_matrix((np.concatenate([wa, wb], axis=1).ravel(), cols.ravel(),
                           np.arange(0, 16 * len(i) + 1, 16)), shape=(len(i), n))
        D.sum_duplicates()
        return D

    def apply(self, p):
        if self._D is None:
            return np.zeros_like(p)
        dp = self._D @ p
        g = self.k * np.einsum("si,si->s", self._nrm, dp)[:, None] * self._nrm
        return self._DT @ g

    def matrix(self):
        n3 = 3 * self.ma.J.shape[1]
        if self._D is None:
            return sp.csr_matrix((n3, n3))
        # k D^T (n n^T) D per pair, as (D kron I3)^T blocks (D kron I3) without forming the block matrix:
        # rows of G = n_s^T (D_s kron I3), then k G^T G
        D = self._D.tocoo()
        nr = self._nrm[D.row]  # (nnz, 3)
        G = sp.csr_matrix(((D.data[:, None] * nr).ravel(), (np.repeat(D.row, 3), (3 * D.col[:, None] + np.arange(3)).ravel())),
                          shape=(D.shape[0], n3))
        return (self.k * (G.T @ G)).tocsr()


class MatrixMapping:
    """Points given by a fixed sparse linear map of the grid nodes, ``p = J x`` (P x N): the same interface
    as :class:`TrilinearMapping`, for points carried by a bone rather than by a grid cell."""

    def __init__(self, J):
        self.J = sp.csr_matrix(J)
        self.J3 = sp.kron(self.J, sp.identity(3, format="csr"), format="csr")
        self.JT = self.J.T.tocsr()

    def apply(self, x):
        return self.J @ np.asarray(x, float)

    def apply_transpose(self, f):
        return self.JT @ np.asarray(f, float)


def affine_point_map(bone: "MappedBoneElasticity", points, nearest: int = 12, reach: float | None = None) -> MatrixMapping:
    """Points (P, 3) rigidly attached to a bone: each is the minimum-norm affine combination of rest bone
    nodes (exact for any affine, so any rigid, motion of the nodes), composed with the bone's embedding
    in the grid.

    Which nodes: the ``nearest`` ones (few nodes keep the coupling sparse), or, with ``reach`` (mm), every
    node within ``reach`` of the nearest one's distance. A point far from its nearest nodes (a sphere
    centre above a concave facet) needs the wide set: an affine map of a few nearly coplanar nodes
    extrapolates their small elastic deformation into millimetres at that distance. The wide map couples
    many nodes; use it in springs with ``low_rank=True``."""
    X = bone.el.X
    P = np.atleast_2d(np.asarray(points, float))
    d2 = ((P[:, None, :] - X[None, :, :]) ** 2).sum(-1)  # (P, Nb)
    if reach is None:
        k = min(nearest, len(X))
        idx = np.argsort(d2, axis=1)[:, :k]
        sel = np.zeros(d2.shape, bool)
        np.put_along_axis(sel, idx, True, axis=1)
    else:
        d = np.sqrt(d2)
        sel = d <= d.min(axis=1, keepdims=True) + float(reach)
    # w = S Xh (Xh^T S Xh)^-1 [p; 1] over the selected nodes (S: selection), per point
    Xh = np.concatenate([X, np.ones((len(X), 1))], axis=1)  # (Nb, 4)
    G = np.einsum("pn,ni,nj->pij", sel.astype(float), Xh, Xh)  # (P, 4, 4)
    B = np.concatenate([P, np.ones((len(P), 1))], axis=1)
    lam = np.linalg.solve(G, B[:, :, None])[:, :, 0]  # (P, 4)
    w = sel * (lam @ Xh.T)  # (P, Nb)
    return MatrixMapping(sp.csr_matrix(w) @ bone.map.J)

