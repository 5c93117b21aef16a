"""A second, independent model of a knee's soft tissue: hyperelastic tetrahedra between the bones and the
skin, for making the truth skin of a flexed knee in the benchmark (issue "an honest benchmark").

The association model (:mod:`knee.models.fem.scene`) is a co-rotational linear hexahedral grid that
embeds the skin and the bones and is stepped by an implicit integrator. A truth skin made by that model
favours the methods that use it. This one shares none of it:

- discretisation: linear tetrahedra that conform to the bones and to the skin (a Delaunay
  tetrahedralisation of nodes on the skin, on the bones and on an interior lattice, about a tenth of the
  femur's width apart: finer than the grid's cells away from the joint line), not a grid that embeds them;
- material: a compressible neo-Hookean energy per unit volume
  ``W(F) = mu/2 (tr(F^T F) - 3) - mu (J - 1) + lambda/2 (J - 1)^2`` (stress-free at rest, rotation
  invariant, finite for inverted elements), Poisson's ratio 0.4 by default (the model uses 0.3);
- boundary conditions: the nodes on the bone surfaces move exactly with their bone (the femur held, the
  tibia at the given pose, and, when a patella is given, the patella moved as given), and so do the skin's
  nodes at its two ends along the leg, the thigh's with the femur and the shank's with the tibia: a scan
  ends where its field of view does, the leg goes on, and tissue left free at a cut end lags its bone
  (measured: with free ends, the Visible Human clipped to one femoral width either side of the joint line
  read 8.6 deg too little flexion under method (iii), 0 of 29 views within 2 deg; with held ends 1.2 deg,
  20 of 29); nothing else holds the tissue;
- solution: the static equilibrium as the minimum of the total energy over the free nodes (Newton's
  method with each element's Hessian projected to positive semi-definite, a backtracking line search),
  reached through increments of the tibia's motion of at most 20 deg.

The skin surface posed is the skin's own triangulation brought to the node spacing: coarsened where it is
finer, its long edges bisected where it is coarser (its vertices are the mesh's skin nodes; the few that no
tetrahedron of some volume holds follow their neighbours). A skin given as long faces (a capsule's sides, or a
scan's flat cut ends) is thereby given nodes along them, so the tissue bends it there too (before, the phantom's
skin kept its 1,246 vertices at every spacing: faces up to 16 spacings long, which no finer spacing refined). Everything is scaled by the anatomy's femoral width (no millimetre constants).
Frames: the femur's anatomical frame (:class:`knee.models.fem.anatomy.KneeAnatomy`), mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import trimesh
from scipy.spatial import Delaunay, cKDTree
from scipy.spatial.transform import Rotation

from knee.foundations.conventions import transform_points
from knee.foundations.errors import KneeError, KneeInputError
from knee.foundations.surfaces import SurfaceQuery, bisected_to_length, decimated, face_areas, vertex_areas
from knee.models.fem.bones import tet_quality
from knee.models.fem.factor import SparseFactor

#: Node spacing of the tissue mesh, in femur widths.
EDGE_WIDTHS = 0.1
#: The skin's nodes within this many node spacings of its ends along the leg move with the bone of their
#: side (:func:`tissue_mesh`).
END_SPACINGS = 0.25
#: The skin's longest edge in the tissue mesh, in node spacings (:func:`coarsened_skin`).
SKIN_EDGE_MAX = 1.5
#: Largest rotation (deg) of the tibia per increment.
INCREMENT_DEG = 20.0


def _edges(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(E, 3, 3): each tetrahedron's edges from its node 0, as columns."""
    p = x[tets]
    return np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)


def _volumes6(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(E,): six times each tetrahedron's signed volume."""
    return np.linalg.det(_edges(x, tets))


def _deformation(x: np.ndarray, tets: np.ndarray, Dm_inv: np.ndarray) -> np.ndarray:
    return _edges(x, tets) @ Dm_inv


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x (E, 3, 3) of vectors (E, 3)."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], axis=1)


def neo_hookean(F: np.ndarray, mu: float, lam: float, hessian: bool = False):
    """Energy density W (E,), first Piola stress P (E, 3, 3) and, with ``hessian``, d2W/dF2 (E, 9, 9)
    (F flattened by columns) of deformation gradients F (E, 3, 3); W as in the module docstring."""
    f1, f2, f3 = F[:, :, 0], F[:, :, 1], F[:, :, 2]
    cof = np.stack([np.cross(f2, f3), np.cross(f3, f1), np.cross(f1, f2)], axis=2)  # dJ/dF
    J = np.einsum("ei,ei->e", f1, cof[:, :, 0])
    W = 0.5 * mu * (np.einsum("eij,eij->e", F, F) - 3.0) - mu * (J - 1.0) + 0.5 * lam * (J - 1.0) ** 2
    s = lam * (J - 1.0) - mu
    P = mu * F + s[:, None, None] * cof
    if not hessian:
        return W, P, None
    g = np.transpose(cof, (0, 2, 1)).reshape(-1, 9)  # columns of cof, stacked
    H = mu * np.eye(9)[None] + lam * g[:, :, None] * g[:, None, :]
    HJ = np.zeros((len(F), 9, 9))
    a, b, c = _skew(f1), _skew(f2), _skew(f3)
    HJ[:, 0:3, 3:6], HJ[:, 0:3, 6:9], HJ[:, 3:6, 6:9] = -c, b, -a
    HJ[:, 3:6, 0:3], HJ[:, 6:9, 0:3], HJ[:, 6:9, 3:6] = c, -b, a
    return W, P, H + s[:, None, None] * HJ


def _spaced(points: np.ndarray, spacing: float, seed: int) -> np.ndarray:
    """Points at least about ``spacing`` apart: one per cell of a jittered voxel grid (vectorised)."""
    rng = np.random.default_rng(seed)
    shift = rng.random(3) * spacing
    key = np.floor((points + shift) / spacing).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return points[np.sort(first)]


def coarsened_skin(skin: trimesh.Trimesh, edge: float) -> trimesh.Trimesh:
    """The skin's triangulation brought to about ``edge`` mm edges, kept closed: coarsened (quadric decimation)
    where it is finer, and its edges longer than :data:`SKIN_EDGE_MAX` spacings bisected
    (:func:`knee.foundations.surfaces.bisected_to_length`) where it is coarser. Decimation leaves a flat or
    straight stretch of skin (a capsule's sides) as a few long faces, and a skin given as long faces would keep
    them: without nodes along them the tissue could bend the skin only at their ends, and no refinement of the
    tissue would refine the skin."""
    n_faces = int(max(200, round(4.0 * skin.area / (math.sqrt(3.0) * edge * edge))))
    return bisected_to_length(decimated(skin, n_faces, "skin (for the tissue mesh)"), SKIN_EDGE_MAX * edge)


@dataclass
class TissueMesh:
    """The tetrahedral tissue: rest nodes ``X`` (N, 3), tetrahedra (E, 4), the nodes that move with the
    femur and with the tibia (index arrays: those on the bone's surface, then the skin's nodes at that
    side's end of the leg), the skin's triangles over its nodes (F, 3), and the nodes on the patella (empty
    without one)."""

    X: np.ndarray
    tets: np.ndarray
    femur_nodes: np.ndarray
    tibia_nodes: np.ndarray
    skin_faces: np.ndarray
    edge: float
    patella_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, int))


def _passive_weights(X, tets, h, n_skin):
    """Skin vertices that no tetrahedron of some volume holds (a node the Delaunay left out, or one of
    two decimated vertices a fraction of a millimetre apart): each follows the displacements of its four
    nearest held nodes, inverse-distance weighted. Returns (passive (k,), neighbours (k, 4), weights (k, 4))."""
    vol = np.abs(_volumes6(X, tets)) / 6.0
    held = np.bincount(tets.ravel(), weights=np.repeat(vol, 4), minlength=len(X)) > 0.01 * h ** 3
    passive = np.nonzero(~held[:n_skin])[0]
    active = np.nonzero(held)[0]
    d, j = cKDTree(X[active]).query(X[passive], k=4)
    w = 1.0 / np.maximum(d, 1e-6)
    return passive, active[j], w / w.sum(axis=1, keepdims=True)


def tissue_mesh(anatomy, edge: float | None = None, seed: int = 0, patella: trimesh.Trimesh | None = None) -> TissueMesh:
    """Tetrahedra filling the skin around the bones of ``anatomy`` (a
    :class:`knee.models.fem.anatomy.KneeAnatomy`) and ``patella`` (a closed surface in the same frame, or
    None), about ``edge`` mm apart (default a tenth of the femur's width)."""
    h = float(edge or EDGE_WIDTHS * anatomy.width)
    skin = coarsened_skin(anatomy.skin, h)
    sq = SurfaceQuery.of(skin)
    bones = [anatomy.femur, anatomy.tibia] + ([patella] if patella is not None else [])
    bq = [SurfaceQuery.of(b) for b in bones]
    bone_pts = []
    for i, b in enumerate(bones):
        dense, _ = trimesh.sample.sample_surface(b, max(2000, int(8 * b.area / (h * h))), seed=seed + i)
        p = _spaced(np.asarray(dense), 0.7 * h, seed + i)
        bone_pts.append(p[sq.signed_distance(p) < -0.2 * h])  # bone points well inside the skin only
    lo, hi = skin.bounds
    axes = [np.arange(a + 0.5 * h, b, h) for a, b in zip(lo, hi)]
    lattice = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    lattice = lattice + np.random.default_rng(seed).uniform(-0.15 * h, 0.15 * h, lattice.shape)
    keep = sq.signed_distance(lattice) < -0.5 * h
    for q in bq:
        keep &= q.signed_distance(lattice) > 0.5 * h
    sv = np.asarray(skin.vertices, float)
    X = np.vstack([sv, *bone_pts, lattice[keep]])
    starts = np.cumsum([len(sv)] + [len(b) for b in bone_pts])  # each bone's first node, then the lattice's
    tets = Delaunay(X).simplices
    c = X[tets].mean(axis=1)
    inside = sq.signed_distance(c) < 0.0
    for q in bq:
        inside &= q.signed_distance(c) > 0.0
    tets = tets[inside]
    # a tetrahedron of four nodes on one bone carries nothing (its nodes are all prescribed); one that
    # spans the joint space from one bone to another stands for cartilage, menisci and capsule, which this
    # tissue does not model: crushed by the bones' relative motion, it would only stall the solution
    kind = np.zeros(len(X), int)
    for b in range(len(bones)):
        kind[starts[b]:starts[b + 1]] = b + 1
    k = kind[tets]
    n_bones = sum((k == b + 1).any(axis=1).astype(int) for b in range(len(bones)))
    tets = tets[~((n_bones >= 2) | (k > 0).all(axis=1))]
    # orientation and slivers
    flip = _volumes6(X, tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    tets = tets[tet_quality(X[tets]) > 0.02]
    nodes = [np.arange(starts[b], starts[b + 1]) for b in range(len(bones))]
    # the skin's two ends along the leg (where a scan's field of view cut it) move with the bone of their
    # side: the thigh's end with the femur, the shank's with the tibia (the leg goes on past the scan)
    y = sv[:, 1]
    top, bottom = np.nonzero(y > y.max() - END_SPACINGS * h)[0], np.nonzero(y < y.min() + END_SPACINGS * h)[0]
    return TissueMesh(X, tets, np.concatenate([nodes[0], top]), np.concatenate([nodes[1], bottom]),
                      np.asarray(skin.faces), h, nodes[2] if patella is not None else np.zeros(0, int))


class TetTissue:
    """The tetrahedral tissue of a knee (see the module docstring), posed with its bones.

    ``anatomy``: a :class:`knee.models.fem.anatomy.KneeAnatomy`; ``E`` (MPa, the moduli's scale: with the
    bones' motion prescribed and no load, the shape does not depend on it), ``nu``; ``patella``: the
    patella's closed surface in the femur frame at the scan, a third bone whose motion :meth:`pose` takes
    (None: the tissue has none, and the skin over the knee's front follows the femur and the tibia only)."""

    def __init__(self, anatomy, edge: float | None = None, E: float = 1.0, nu: float = 0.4, seed: int = 0,
                 patella: trimesh.Trimesh | None = None):
        self.anatomy = anatomy
        m = tissue_mesh(anatomy, edge, seed, patella)
        n_skin = int(m.skin_faces.max()) + 1
        self._passive = _passive_weights(m.X, m.tets, m.edge, n_skin)
        m.tets = m.tets[~np.isin(m.tets, self._passive[0]).any(axis=1)]
        self.mesh = m
        self.mu = E / (2.0 * (1.0 + nu))
        self.lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        Dm = _edges(m.X, m.tets)
        self.Dm_inv = np.linalg.inv(Dm)
        self.vol = np.abs(np.linalg.det(Dm)) / 6.0
        # dF/dx: F's column j takes node (k + 1) with weight Dm^-1[k, j], node 0 with minus their sum
        G = np.zeros((len(m.tets), 3, 4))
        G[:, :, 1:] = np.transpose(self.Dm_inv, (0, 2, 1))
        G[:, :, 0] = -G[:, :, 1:].sum(axis=2)
        self.G = G
        fixed = np.zeros(len(m.X), bool)
        fixed[m.femur_nodes] = fixed[m.tibia_nodes] = fixed[m.patella_nodes] = True
        used = np.zeros(len(m.X), bool)
        used[m.tets.ravel()] = True
        self.free = np.nonzero(~fixed & used)[0]
        self._skin_free = np.nonzero(self.free < n_skin)[0]  # the free list's skin nodes
        dof = np.full((len(m.X), 3), -1)
        dof[self.free] = np.arange(3 * len(self.free)).reshape(-1, 3)
        e = dof[m.tets].reshape(len(m.tets), 12)  # (E, 12): free dof index or -1
        # the stiffness's sparse pattern, once: each element entry's slot in the CSC data
        self._ok = ok = ((e[:, :, None] >= 0) & (e[:, None, :] >= 0)).ravel()
        n = 3 * len(self.free)
        rows = np.broadcast_to(e[:, :, None], (len(e), 12, 12)).ravel()[ok]
        cols = np.broadcast_to(e[:, None, :], (len(e), 12, 12)).ravel()[ok]
        keys, self._slot = np.unique(cols.astype(np.int64) * n + rows, return_inverse=True)
        self._indices = (keys % n).astype(np.int32)
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(keys // n, minlength=n))]).astype(np.int32)
        self._n = n
        self.T_scan = np.asarray(anatomy.tibia_pose, float)
        # the first guess of a pose's free nodes: each moves by the bones' motions weighted by its inverse
        # distances to them (a guess only: the energy's minimum does not depend on it)
        inv = np.column_stack([1.0 / np.maximum(cKDTree(m.X[b]).query(m.X)[0], 1e-9)
                               for b in (m.femur_nodes, m.tibia_nodes, m.patella_nodes) if len(b)])
        self._w = inv / inv.sum(axis=1, keepdims=True)  # (N, bones): femur, tibia[, patella] shares

    def energy(self, x: np.ndarray, hessian: bool = False):
        """Total energy (N mm), its gradient (N, 3) and, with ``hessian``, the free nodes' stiffness (the
        energy's Hessian with each element's projected to positive semi-definite), sparse (3F, 3F)."""
        m = self.mesh
        F = _deformation(x, m.tets, self.Dm_inv)
        W, P, H = neo_hookean(F, self.mu, self.lam, hessian)
        # gradient on the element's nodes: vol * P G  (3 x 4), node a's force the column a
        ge = self.vol[:, None, None] * (P @ self.G)
        g = np.column_stack([np.bincount(m.tets.ravel(), weights=ge[:, i, :].ravel(), minlength=len(x))
                             for i in range(3)])
        if not hessian:
            return float(np.dot(self.vol, W)), g, None
        lam_, V = np.linalg.eigh(H)
        H = (V * np.maximum(lam_, 0.0)[:, None, :]) @ np.transpose(V, (0, 2, 1))
        # K = vol B^T H B with B (9 x 12) = G (x) I3: K[a i, b k] = sum_jl G[j a] H[j i, l k] G[l b]
        H5 = H.reshape(len(F), 3, 3, 3, 3)  # (e, j, i, l, k)
        T = np.einsum("eja,ejilk->eailk", self.G, H5)
        K = np.einsum("eailk,elb->eaibk", T, self.G).reshape(len(F), 144) * self.vol[:, None]
        data = np.bincount(self._slot, weights=K.ravel()[self._ok], minlength=len(self._indices))
        return float(np.dot(self.vol, W)), g, sp.csc_matrix((data, self._indices, self._indptr),
                                                               shape=(self._n, self._n))

    def pose(self, T_tibia, patella_motion=None, tolerance: float = 1e-2, max_iterations: int = 150) -> "PosedTissue":
        """The tissue's equilibrium with the femur held, the tibia at ``T_tibia`` (4, 4; the tibia's frame
        in the femur frame) and, for a tissue with a patella, the patella moved from the scan by
        ``patella_motion`` (4, 4, femur frame; None: held where it was scanned), through increments of at
        most :data:`INCREMENT_DEG` of either bone's rotation. ``tolerance``: the largest Newton step at
        convergence, in node spacings. Raises :class:`KneeError` when an increment does not converge in
        ``max_iterations`` (the fold behind a knee flexed to 90 deg can take 70: measured on the Visible Human
        at 90 deg with a 2-5 deg deviation, 73 iterations, 2 min, 157 inverted tetrahedra; most increments
        take 3-16), and :class:`KneeInputError` for a patella's motion without a patella."""
        m = self.mesh
        if patella_motion is not None and not len(m.patella_nodes):
            raise KneeInputError("a patella's motion was given to a tissue without a patella")
        motions = [np.asarray(T_tibia, float) @ np.linalg.inv(self.T_scan)]  # the tibia's motion from the scan
        if len(m.patella_nodes):
            motions.append(np.eye(4) if patella_motion is None else np.asarray(patella_motion, float))
        rots = [Rotation.from_matrix(M[:3, :3]) for M in motions]
        n = max(1, int(math.ceil(max(math.degrees(r.magnitude()) for r in rots) / INCREMENT_DEG)))
        moving = [m.tibia_nodes, m.patella_nodes][: len(motions)]
        x = m.X.copy()
        prev = [np.eye(4)] * len(motions)
        iterations, residual = 0, 0.0
        for k in range(1, n + 1):
            f = k / n
            now = []
            for rel, rot in zip(motions, rots):
                M = np.eye(4)
                M[:3, :3] = Rotation.from_rotvec(f * rot.as_rotvec()).as_matrix()
                M[:3, 3] = f * rel[:3, 3]
                now.append(M)
            x = self._w[:, :1] * x + sum(self._w[:, i + 1:i + 2] * transform_points(M @ np.linalg.inv(P), x)
                                         for i, (M, P) in enumerate(zip(now, prev)))
            x[m.femur_nodes] = m.X[m.femur_nodes]
            for nodes, M in zip(moving, now):
                x[nodes] = transform_points(M, m.X[nodes])
            x, its, residual = self._newton(x, tolerance, max_iterations)
            iterations += its
            prev = now
        passive, nb, w = self._passive
        x[passive] = m.X[passive] + np.einsum("pk,pkj->pj", w, x[nb] - m.X[nb])
        return PosedTissue(x, int((_volumes6(x, m.tets) <= 0).sum()), iterations, residual, n)

    def _newton(self, x, tolerance, max_iterations):
        """Newton's method on the free nodes with a backtracking line search on the energy; converged when
        a full step moves 99 % of the skin nodes by less than ``tolerance`` node spacings (the skin is what
        the tissue is solved for; without self-contact, a few skin nodes in the fold behind a flexed knee
        creep on into it for many iterations: measured, 0.15 mm per iteration at 60 deg)."""
        free = self.free
        h = self.mesh.edge
        for it in range(1, max_iterations + 1):
            e, g, K = self.energy(x, hessian=True)
            gf = g[free].ravel()
            K = K + sp.identity(K.shape[0], format="csc") * (1e-8 * K.diagonal().mean())
            d = -SparseFactor(K).solve(gf).reshape(-1, 3)
            step = float(np.percentile(np.linalg.norm(d[self._skin_free], axis=1), 99))
            if step < tolerance * h:
                return x, it - 1, step
            t, slope = 1.0, float(gf @ d.ravel())
            while True:
                y = x.copy()
                y[free] += t * d
                e1 = self.energy(y)[0]
                if np.isfinite(e1) and e1 <= e + 1e-4 * t * slope:
                    break
                t *= 0.5
                if t < 1e-6:
                    raise KneeError("the tissue model's equilibrium did not converge (no descent)")
            x = y
        raise KneeError(f"the tissue model's equilibrium did not converge in {max_iterations} Newton iterations "
                        f"(last step {step:.2g} mm)")


@dataclass
class PosedTissue:
    """A pose's equilibrium: node positions (N, 3), inverted tetrahedra, Newton iterations, the last
    step (mm, 99th percentile over the skin nodes), increments."""

    x: np.ndarray
    inverted: int
    iterations: int
    residual: float
    increments: int

    def skin(self, tissue: TetTissue) -> trimesh.Trimesh:
        f = tissue.mesh.skin_faces
        return trimesh.Trimesh(self.x[: f.max() + 1].copy(), f, process=False)


def smooth_surface_field(vertices, normals, rms_mm: float, correlation_mm: float, rng: np.random.Generator,
                         n_centres: int = 400, faces=None) -> np.ndarray:
    """The vertices (V, 3) moved along their normals by a smooth random field of RMS ``rms_mm``: a sum of
    Gaussian bumps of width ``correlation_mm`` with normal-distributed amplitudes, scaled to the RMS (0 returns
    the vertices unchanged). With the surface's ``faces`` (F, 3), the bumps' centres are drawn uniformly over its
    area and the RMS is over its area (each vertex weighted by a third of its faces' areas), so the field does not
    depend on how the surface is triangulated; without, over a point set, the centres are random points of it and
    the RMS is over the points (measured: on a skin whose vertices crowd its cut ends, centres at random vertices
    left the field over the knee at 0.76 mm RMS for a nominal 1 mm, and at 1.08 mm on the same skin decimated)."""
    v = np.asarray(vertices, float)
    if rms_mm <= 0:
        return v.copy()
    nrm = np.asarray(normals, float)
    if faces is None:
        centres = v[rng.choice(len(v), size=min(n_centres, len(v)), replace=False)]
        weight = np.ones(len(v))
    else:
        f = np.asarray(faces, np.int64)
        tri = v[f]
        area = face_areas(v, f)
        pick = rng.choice(len(f), size=n_centres, p=area / area.sum())
        a, b = rng.random((2, n_centres))
        flip = a + b > 1.0  # a uniform point of each picked triangle
        a, b = np.where(flip, 1.0 - a, a), np.where(flip, 1.0 - b, b)
        t = tri[pick]
        centres = t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])
        weight = vertex_areas(v, f)
    amp = rng.normal(size=len(centres))
    tree = cKDTree(centres)
    field = np.zeros(len(v))
    pairs = tree.query_ball_point(v, 3.0 * correlation_mm)
    idx = np.repeat(np.arange(len(v)), [len(p) for p in pairs])
    cen = np.concatenate([np.asarray(p, int) for p in pairs]) if len(idx) else np.zeros(0, int)
    d2 = ((v[idx] - centres[cen]) ** 2).sum(axis=1)
    np.add.at(field, idx, amp[cen] * np.exp(-0.5 * d2 / correlation_mm ** 2))
    field *= rms_mm / max(float(np.sqrt(np.sum(weight * field ** 2) / weight.sum())), 1e-12)
    return v + field[:, None] * nrm
