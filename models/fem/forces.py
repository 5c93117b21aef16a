"""External forces of the association model (seed 000, 2.3).

* :class:`BoneForces`: F1, F2, F3 on the femur and F4 on the tibia, along directions from a principal
  component analysis of each bone's points: F1 at the end of the femoral shaft and F2 (opposite) at the
  intercondylar fossa, both along the femur's antero-posterior principal axis; F3 at the fossa along the
  femur's long axis (distally); F4 at the end of the tibial shaft along the tibia's antero-posterior
  principal axis (posteriorly, which flexes the knee). Magnitudes default to the paper's 9000, 23000,
  3000 and 6000 N, times ``scale``. Which principal axis is "antero-posterior" is decided by its
  alignment with the bone frame's x axis, since PCA alone fixes neither order nor sign.
* :class:`SurfaceForces`: each skin point is pulled towards its nearest depth point when that point is
  closer than the reference distance, with stiffness ``k`` per point (the paper's), or ``k`` per
  :data:`SKIN_AREA_PER_SPRING_MM2` of skin (the prior's methods: the pull then does not depend on how
  finely the skin is triangulated); the reference distance starts at
  10 mm and moves by 0.1 mm per step (down when more than half the skin points are within it, up
  otherwise), kept within 1-10 mm.
* :class:`DepthPointForces` (the prior's methods): each depth point pulls the nearest point of the skin's
  surface, along its face's normal; the pull per mm^2 as :class:`SurfaceForces`' spread by area. On a one-sided view
  the skin-to-cloud springs pull the skin behind the silhouette, which no depth point shows, towards the
  silhouette's points, so the leg is drawn towards the camera (measured on the honest benchmark: the
  femur 0.5-0.8 mm towards it over the surface phase, median per camera placement); a depth point's
  nearest skin point is a point the camera can have seen.

All act through the mapping (forces on embedded points -> grid forces by J^T); the two surface springs also
provide their stiffness (k J^T J over the active points) to the implicit solve.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from knee.foundations.geometry import principal_axes as _principal_axes, rigid_register
from knee.foundations.pointclouds import NearCloud, voxel_downsample
from knee.foundations.surfaces import SurfaceQuery, vertex_areas
from knee.models.fem.mapping import TrilinearMapping

PAPER_BONE_FORCES = (9000.0, 23000.0, 3000.0, 6000.0)


def principal_axes(points) -> np.ndarray:
    """Principal axes (3, 3), rows by decreasing variance (knee.foundations.geometry.principal_axes)."""
    return _principal_axes(points)[1]


class BoneForces:
    """The four bone forces; ``forces(x)`` gives grid forces (N, 3).

    The principal axes are recomputed from the bones' current points at every call, so the forces
    turn with the bones (the paper computes them by PCA of the bone models; recomputing keeps F4
    flexing the knee as the tibia turns). Which current axis is which is decided against the rest axis
    turned by the bone's current rotation (the least-squares rigid fit of its nodes), not against the
    rest axis itself: past 45 deg of flexion the tibia's long axis is closer to its rest antero-posterior
    axis than its own antero-posterior axis is, and F4 had turned along the shaft there, so that the knee
    sprang back and was kicked forward again in a saw-tooth that never passed about 72 deg. ``femur=False``
    drops F1-F3, for a model whose thigh is held (they would only push against the holder).
    """

    def __init__(self, femur, tibia, magnitudes=PAPER_BONE_FORCES, scale: float = 1.0, n_points: int = 5,
                 use_femur: bool = True):
        self.F = [scale * m for m in magnitudes]
        if not use_femur:
            self.F[:3] = [0.0, 0.0, 0.0]
        self.femur, self.tibia = femur, tibia
        Xf, Xt = femur.el.X, tibia.el.X
        self.shaft_f = np.argsort(-Xf[:, 1])[:n_points]                  # femoral shaft end
        cond = Xf[:, 1] < np.percentile(Xf[:, 1], 15)                    # distal femur
        self.fossa = np.nonzero(cond)[0][np.argsort(np.abs(Xf[cond, 2] - np.median(Xf[cond, 2])))[:n_points]]
        self.shaft_t = np.argsort(Xt[:, 1])[:n_points]                   # tibial shaft end
        self.n = n_points
        # the rest principal axes closest to the bone frames' x (antero-posterior) and y (long) axes
        af0, at0 = principal_axes(Xf), principal_axes(Xt)
        self._ap_f0 = self._axis(af0, np.array([1.0, 0.0, 0.0]))
        self._long_f0 = self._axis(af0, np.array([0.0, 1.0, 0.0]))
        self._ap_t0 = self._axis(at0, np.array([1.0, 0.0, 0.0]))
        self.directions = {}

    @staticmethod
    def _axis(axes, ref):
        a = axes[np.argmax(np.abs(axes @ ref))]
        return a * np.sign(a @ ref)

    def forces(self, x):
        F1, F2, F3, F4 = self.F
        pf, pt = self.femur.bone_positions(x), self.tibia.bone_positions(x)
        af, at_ = principal_axes(pf), principal_axes(pt)
        # which current axis is antero-posterior / long: the one closest to the rest one as the bone has
        # turned it (sign kept)
        Rf = rigid_register(self.femur.el.X, pf)[0][:3, :3]  # each bone's rotation from rest
        Rt = rigid_register(self.tibia.el.X, pt)[0][:3, :3]
        ap_f = self._axis(af, Rf @ self._ap_f0)
        long_f = self._axis(af, Rf @ self._long_f0)
        ap_t = self._axis(at_, Rt @ self._ap_t0)
        ff = np.zeros_like(pf)
        ff[self.shaft_f] += F1 * ap_f / self.n
        ff[self.fossa] += -F2 * ap_f / self.n - F3 * long_f / self.n
        ft = np.zeros_like(pt)
        ft[self.shaft_t] += -F4 * ap_t / self.n
        self.directions = {"F1": ap_f, "F2": -ap_f, "F3": -long_f, "F4": -ap_t}
        return self.femur.map.apply_transpose(ff) + self.tibia.map.apply_transpose(ft)

#: The skin area (mm^2) a surface spring of stiffness ``k`` stands for where the springs are spread by area
#: (:func:`skin_point_areas`): the Visible Human's skin has a vertex per 44 mm^2, the skin on which the
#: method's choices were measured with ``k`` per vertex. A spring per vertex alone makes the surface's pull
#: a property of the triangulation: per square millimetre, lenhart2015's carried skin (12 mm^2 a vertex)
#: pulled 3.6 times as hard as the Visible Human's and the phantom's (141 mm^2) a third as hard.
SKIN_AREA_PER_SPRING_MM2 = 44.0


def skin_point_areas(vertices, faces) -> np.ndarray:
    """Each skin vertex's share of the skin's area (mm^2; :func:`knee.foundations.surfaces.vertex_areas`)."""
    return vertex_areas(vertices, faces)


class SurfaceForces:
    """Springs from skin points (embedded in the grid) to their nearest depth points. ``weights`` (S,):
    each point's spring is ``k`` times its weight (None: ``k`` each, as in the paper)."""

    def __init__(self, grid, skin_points, depth_points, k: float = 2.0, start: float = 10.0,
                 step: float = 0.1, limits=(1.0, 10.0), weights=None):
        self.map = TrilinearMapping(grid, skin_points)
        self.tree = cKDTree(np.asarray(depth_points, float))
        self.depth = np.asarray(depth_points, float)
        self.k = float(k)
        self.kp = np.full(len(skin_points), self.k) if weights is None else self.k * np.asarray(weights, float)
        if self.kp.shape != (len(skin_points),) or np.any(self.kp < 0.0):
            raise ValueError(f"the springs' weights must be {len(skin_points)} values of at least 0")
        self.reference = float(start)
        self.step_size = float(step)
        self.lo, self.hi = limits
        self.active = np.zeros(len(skin_points), bool)
        self.within_fraction = 0.0
        # the skin points that may be within the largest reference distance of the cloud; only those are
        # searched (the same answer: on a one-sided cloud wrapped around the leg, the tree's bound alone
        # spent most of the step's search on the unseen side, 13 us a point on an MRI knee's lateral view)
        self.near = NearCloud(self.depth, max(self.hi, self.reference))

    def forces(self, x):
        p = self.map.apply(x)
        # only neighbours within the reference distance matter: the bound keeps the query short
        self.active = self.near(p)
        d, j = self.tree.query(p[self.active], distance_upper_bound=self.reference)
        found = d < self.reference
        j = j[found]
        self.active[self.active] = found
        self.within_fraction = float(self.active.mean())
        f = np.zeros_like(p)
        f[self.active] = self.kp[self.active, None] * (self.depth[j] - p[self.active])
        # adapt the reference distance for the next step
        if self.within_fraction > 0.5:
            self.reference = max(self.lo, self.reference - self.step_size)
        else:
            self.reference = min(self.hi, self.reference + self.step_size)
        return self.map.apply_transpose(f)

    def apply(self, p):
        q = self.map.apply(p) * np.where(self.active, self.kp, 0.0)[:, None]
        return self.map.apply_transpose(q)

    def matrix(self):
        Ja = self.map.J3[np.repeat(self.active, 3)]
        return (Ja.T @ sp.diags(np.repeat(self.kp[self.active], 3)) @ Ja).tocsr()


#: The voxel (mm) a depth cloud is thinned to before :class:`DepthPointForces` pulls with it: each point then
#: stands for about ``DEPTH_VOXEL_MM ** 2`` of skin, whatever the camera's distance or resolution.
DEPTH_VOXEL_MM = 4.0
#: How far (mm) a depth point may lie from its nearest skin point and still pull it: the largest reference
#: distance of :class:`SurfaceForces`.
DEPTH_REACH_MM = 10.0


class DepthPointForces:
    """Springs from each depth point to the nearest point of the skin's surface (a point on one of its
    faces; the skin's vertices embedded in the grid), acting along that face's normal: the skin may slide
    under the points, only its distance to them is measured, and a skin through the points is not pulled.
    The cloud is thinned to :data:`DEPTH_VOXEL_MM` voxels and each point's spring is ``k`` times the skin
    area it stands for over :data:`SKIN_AREA_PER_SPRING_MM2`, so that a skin seen all over is pulled per
    mm^2 as :class:`SurfaceForces` spread by area pulls it. Points further than ``reach`` mm from the skin
    do not pull. The nearest face is the exact one (:meth:`knee.foundations.surfaces.SurfaceQuery.closest_faces`
    on the skin as the grid has it), the nearest point on it in double precision.

    The correspondence runs from the data to the model, as the camera sees: every depth point lies on skin
    the camera saw, while a skin point need not have been seen. :class:`SurfaceForces` (the paper's springs,
    skin to cloud) pulls the skin just behind the silhouette towards the silhouette's points, a net pull
    towards the camera however well the skin fits; pairing a point with the nearest skin *vertex* instead of
    the surface pulls a convex skin inwards (a point on a face lies under its corners' tangent planes).

    ``forces(x)`` re-pairs the points with the skin as the grid ``x`` has it; ``apply`` and ``matrix`` give
    the stiffness of those pairs (fixed until the next ``forces``). ``active`` marks the skin vertices
    pulled, ``within_fraction`` is the share of the depth points within ``reach``."""

    def __init__(self, grid, skin_points, skin_faces, depth_points, k: float = 2.0, reach: float = DEPTH_REACH_MM,
                 voxel: float = DEPTH_VOXEL_MM):
        self.map = TrilinearMapping(grid, skin_points)
        self.faces = np.asarray(skin_faces, np.int64)
        self.depth = np.asarray(depth_points, float)  # the cloud as given
        self.thinned = voxel_downsample(self.depth, voxel)  # the points that pull
        self.k_point = float(k) * voxel ** 2 / SKIN_AREA_PER_SPRING_MM2
        self.reference = float(reach)
        self.n_skin = len(skin_points)
        self._pairs = (np.zeros((0, 3), np.int64), np.zeros((0, 3)), np.zeros((0, 3)))  # corners, weights, normals
        self.active = np.zeros(self.n_skin, bool)
        self.within_fraction = 0.0

    def forces(self, x):
        p = self.map.apply(x)
        # the nearest face, the closest point on it in double precision, its normal and the point's weights
        face, c, n, w = SurfaceQuery(p, self.faces).on_nearest_faces(self.thinned)
        near = np.linalg.norm(c - self.thinned, axis=1) < self.reference
        corners, c, n, w = self.faces[face[near]], c[near], n[near], w[near]
        w = np.where(np.isfinite(w).all(axis=1, keepdims=True), w, 1.0 / 3.0)  # a degenerate face: its centre
        self._pairs = (corners, w, n)
        self.active = np.bincount(corners.ravel(), minlength=self.n_skin) > 0
        self.within_fraction = float(near.mean()) if len(near) else 0.0
        r = np.einsum("ij,ij->i", self.thinned[near] - c, n)  # along the face's normal
        return self.map.apply_transpose(self._spread(self.k_point * r))

    def _spread(self, s) -> np.ndarray:
        """Point forces s n at each pair's surface point, onto the skin's vertices by the point's weights (S, 3)."""
        corners, w, n = self._pairs
        f = (w[:, :, None] * (s[:, None] * n)[:, None, :]).reshape(-1, 3)
        idx = corners.ravel()
        return np.column_stack([np.bincount(idx, weights=f[:, k], minlength=self.n_skin) for k in range(3)])

    def apply(self, v):
        corners, w, n = self._pairs
        q = self.map.apply(v)
        at = np.einsum("ij,ijk->ik", w, q[corners])  # the pairs' surface points moved by v
        return self.map.apply_transpose(self._spread(self.k_point * np.einsum("ij,ij->i", at, n)))

    def matrix(self):
        corners, w, n = self._pairs
        m = len(corners)
        # C (m, 3 S): each pair's normal displacement n . sum_v w_v q_v; the stiffness is k C^T C through the map
        rows = np.repeat(np.arange(m), 9)
        cols = (3 * corners[:, :, None] + np.arange(3)[None, None, :]).ravel()
        vals = (w[:, :, None] * n[:, None, :]).ravel()
        C = sp.csr_matrix((vals, (rows, cols)), shape=(m, 3 * self.n_skin)) @ self.map.J3
        return (self.k_point * (C.T @ C)).tocsr()

    def factor_matrix(self):
        """What the solver factorises for these springs (its preconditioner; its iterations use
        :meth:`apply`): :meth:`matrix` less the couplings between a pair's three skin vertices, each vertex
        keeping its own block k w_v^2 n n^T. A face's corners lie in up to three different cells, so the
        whole matrix couples grid nodes two cells apart, entries the tissue's pattern lacks: they changed
        the pattern each time the pairs did (a symbolic analysis each) and made the factors a quarter
        larger. The blocks kept couple only the nodes of the cell each vertex lies in."""
        corners, w, n = self._pairs
        vals = (w ** 2)[:, :, None, None] * (n[:, None, :, None] * n[:, None, None, :])  # (P, 3 corners, 3, 3)
        dof = 3 * corners[:, :, None, None]
        shape = vals.shape
        rows = np.broadcast_to(dof + np.arange(3)[:, None], shape).ravel()
        cols = np.broadcast_to(dof + np.arange(3), shape).ravel()
        # each corner with itself only; repeated (vertex, i, j) entries are summed
        B = sp.csr_matrix((vals.ravel(), (rows, cols)), shape=(3 * self.n_skin, 3 * self.n_skin))
        J3 = self.map.J3
        return (self.k_point * (J3.T @ B @ J3)).tocsr()
