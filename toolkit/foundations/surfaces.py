"""Closed triangle meshes: signed distances and occupancy (open3d ``RaycastingScene``; negative inside,
positive outside, mm), closing small holes, and clipping to a slab (manifold3d booleans).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh

from knee.foundations.errors import KneeInputError


#: Rays cast from each point to tell inside from outside, the majority deciding (open3d's ``nsamples``, odd).
#: One ray, open3d's default, miscounts where it grazes an edge or a vertex: about one point in a million
#: taken at random around a convex hull of 300 points gets the wrong sign (tested), and on the honest
#: benchmark one bone vertex so flipped read the bones as overlapping by 5 mm where they were 3.5 mm apart,
#: and slid the tibia 9 mm (a phantom view at 90 deg: its footprints 3.3 or 5.9 mm, run to run, as the
#: FEM's last digits put that vertex). Three rays cost about 10 % more per signed distance.
SIGN_RAYS = 3


class SurfaceQuery:
    """Repeated signed-distance / inside queries against one closed mesh (vertices (V, 3), faces (F, 3)); the
    sign by :data:`SIGN_RAYS` rays per point."""

    def __init__(self, vertices, faces):
        v = np.asarray(vertices, float)
        self.vertices, self.faces = v, np.asarray(faces, np.int64)  # double precision, for :meth:`closest_on_faces`
        self.lo, self.hi = v.min(axis=0), v.max(axis=0)  # the mesh's bounding box
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                                 o3d.core.Tensor(np.asarray(faces, np.uint32)))

    @classmethod
    def of(cls, mesh) -> "SurfaceQuery":
        return cls(mesh.vertices, mesh.faces)

    def signed_distance(self, points) -> np.ndarray:
        """(P, 3) -> (P,) signed distances (negative inside)."""
        p = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
        return self.scene.compute_signed_distance(p, nsamples=SIGN_RAYS).numpy().astype(float)

    def inside(self, points) -> np.ndarray:
        """(P, 3) -> (P,) bool, by ray parity (watertight meshes), the majority of :data:`SIGN_RAYS` rays."""
        p = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
        return self.scene.compute_occupancy(p, nsamples=SIGN_RAYS).numpy() > 0.5

    def closest_points(self, points) -> np.ndarray:
        """(P, 3) -> (P, 3) closest points on the surface."""
        return self.closest(points)[0]

    def ray_hits(self, origins, directions) -> np.ndarray:
        """(P, 3), (P, 3) -> (P,) how far along each ray (unit directions: mm) it first meets the surface;
        ``inf`` where it meets nothing."""
        rays = np.concatenate([np.asarray(origins, float).reshape(-1, 3), np.asarray(directions, float).reshape(-1, 3)], 1)
        return self.scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy().astype(float)

    def closest_faces(self, points) -> np.ndarray:
        """(P, 3) -> (P,) the index of the face nearest each point (single precision: of two faces within
        about 1e-3 mm of equally near, either)."""
        p = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
        return self.scene.compute_closest_points(p)["primitive_ids"].numpy().astype(np.int64)

    def on_nearest_faces(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(P, 3) -> each point's nearest face (P,; found in single precision, :meth:`closest_faces`), the
        closest point on that face in double precision (P, 3), the face's unit normal (P, 3) and the closest
        point's barycentric weights on the face (P, 3; NaN on a degenerate face)."""
        p = np.asarray(points, float).reshape(-1, 3)
        face = self.closest_faces(p)
        t = self.vertices[self.faces[face]]
        c = trimesh.triangles.closest_point(t, p)
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        with np.errstate(divide="ignore", invalid="ignore"):  # a degenerate face: NaN weights
            w = trimesh.triangles.points_to_barycentric(t, c)
        return face, c, n, w

    def closest_on_faces(self, points) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) -> closest points on the surface (P, 3) and unit normals there (P, 3) for point-to-plane fits,
        in double precision on the nearest face (found in single precision: :meth:`closest_faces`). The normal
        is the face's where the closest point lies inside it, and otherwise (on an edge or a corner) the
        direction from the closest point to the point, the distance's own gradient, oriented as the face's.
        Where two faces are equally near (the closest point on their shared edge, the choice between them left
        to single precision) either gives the same point and normal, so both change continuously as the points
        move, which an iterative fit that stops on small steps needs (with :meth:`closest`'s single-precision
        points and each chosen face's own normal, a registration's answer wandered by 1e-3 mm with the last
        digits of its input)."""
        p = np.asarray(points, float).reshape(-1, 3)
        _, c, n, w = self.on_nearest_faces(p)  # a degenerate face (NaN weights) is kept on its normal
        d = p - c
        dn = np.linalg.norm(d, axis=1)
        rim = (np.min(w, axis=1) < 1e-9) & (dn > 1e-9)  # on an edge or a corner, and off the surface
        n[rim] = d[rim] / dn[rim, None] * np.where(np.einsum("ij,ij->i", d[rim], n[rim]) < 0.0, -1.0, 1.0)[:, None]
        return c, n

    def closest(self, points) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) -> closest points on the surface (P, 3) and the normals of their triangles (P, 3)."""
        p = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
        r = self.scene.compute_closest_points(p)
        return r["points"].numpy().astype(float), r["primitive_normals"].numpy().astype(float)


class BandDistances:
    """Signed distances of moving points to a surface (a :class:`SurfaceQuery`), asked only where they may
    lie within a band: an iterative fit that moves a cloud a little at a time and keeps the points within
    ``band`` of the surface needs the distances of few of them. Each point's distance is kept with where it
    was computed; a point that has since moved by less than that distance's excess over the band is still
    outside it (a distance changes by no more than the point moves), so it is not asked again."""

    def __init__(self, query: SurfaceQuery, n: int):
        self.query = query
        self.known = np.zeros(n)  # nothing known yet: every point is asked
        self.at = np.zeros((n, 3))
        self.asked = 0

    def within(self, points, band: float) -> np.ndarray:
        """(P, 3) -> (P,) the signed distances of the points, exact wherever they are below ``band`` in size;
        ``inf`` for points known to be at least ``band`` from the surface."""
        p = np.asarray(points, float)
        ask = np.abs(self.known) - np.linalg.norm(p - self.at, axis=1) < band + 1e-3  # 1e-3: float32 queries
        self.known[ask] = self.query.signed_distance(p[ask])
        self.at[ask] = p[ask]
        self.asked += int(ask.sum())
        return np.where(ask, self.known, np.inf)


def _fill_holes(vertices: np.ndarray, faces: np.ndarray):
    """Close each boundary loop of a triangle mesh with a fan around the loop's centroid (new faces wound
    like their neighbours). Returns (vertices, faces), or None when the boundary is not a set of simple
    loops (a vertex with more than one outgoing boundary edge)."""
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # directed edges as wound in the faces
    key = np.sort(e, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    b = e[cnt[inv.ravel()] == 1]  # boundary edges, a -> b
    if len(b) == 0:
        return vertices, faces
    nxt = {}
    for a, c in b:  # one pass over the boundary edges (a repair, not a hot path)
        if a in nxt:
            return None
        nxt[int(a)] = int(c)
    verts, new_faces, seen = [vertices], [faces], set()
    n = len(vertices)
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt.get(v)
            if v is None:
                return None
        loop = np.array(loop)
        verts.append(vertices[loop].mean(axis=0)[None])
        new_faces.append(np.column_stack([np.roll(loop, -1), loop, np.full(len(loop), n)]))
        n += 1
    return np.vstack(verts), np.vstack(new_faces)


def closed_surface(mesh: trimesh.Trimesh, what: str = "surface") -> trimesh.Trimesh:
    """The mesh, closed: returned as is when watertight, otherwise a copy with its holes filled (a fan
    per boundary loop); a mesh that stays open raises :class:`KneeInputError` naming ``what`` and counting
    its open edges (inside and outside are undefined for it)."""
    if mesh.is_watertight:
        return mesh
    merged = mesh.copy()
    merged.merge_vertices()
    filled = _fill_holes(np.asarray(merged.vertices, float), np.asarray(merged.faces, np.int64))
    fixed = None if filled is None else trimesh.Trimesh(*filled, process=False)
    if fixed is None or not fixed.is_watertight:
        e = np.sort(np.asarray(merged.faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        _, cnt = np.unique(e, axis=0, return_counts=True)
        raise KneeInputError(f"the {what} mesh is not closed ({int((cnt == 1).sum())} open edges) and its holes "
                             f"could not be filled; a closed surface is needed")
    return fixed


def decimated(mesh: trimesh.Trimesh, faces: int, what: str = "surface") -> trimesh.Trimesh:
    """The closed mesh coarsened by quadric decimation (open3d) to about ``faces`` triangles, kept closed
    (small holes the decimation leaves are filled); returned as a copy when it has no more than that.
    Raises :class:`KneeInputError` naming ``what`` when the result cannot be closed or has lost half the
    volume it enclosed (a sphere taken down to two faces is two triangles back to back: closed, and empty)."""
    if faces >= len(mesh.faces):
        return mesh.copy()
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices, float)),
                                  o3d.utility.Vector3iVector(np.asarray(mesh.faces, np.int32)))
    m = m.simplify_quadric_decimation(int(faces))
    m.remove_degenerate_triangles()
    m.remove_unreferenced_vertices()
    out = trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.triangles), process=True)
    if not out.is_watertight:
        trimesh.repair.fill_holes(out)
    if not out.is_volume or out.volume < 0.5 * abs(mesh.volume):
        raise KneeInputError(f"the {what} could not be coarsened into a closed surface around its volume "
                             f"({len(out.faces)} faces left)")
    return out


def face_areas(vertices, faces) -> np.ndarray:
    """(F,) each triangle's area (mm^2)."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def vertex_areas(vertices, faces) -> np.ndarray:
    """(V,) each vertex's share of the surface's area (mm^2; a third of each face it is a corner of)."""
    f = np.asarray(faces, np.int64)
    return np.bincount(f.ravel(), weights=np.repeat(face_areas(vertices, f) / 3.0, 3), minlength=len(vertices))


def bisected_to_length(mesh: trimesh.Trimesh, max_edge: float, max_rounds: int = 64) -> trimesh.Trimesh:
    """The mesh with its long edges bisected until none is longer than ``max_edge`` (mm): in each round every
    face whose longest edge is too long has that edge split at its midpoint, and so does every face that shares a
    split edge (longest-edge bisection: each face split along its longest edge first, so a long thin face becomes
    faces about as long as they are wide, and the mesh stays conforming and closed). The surface is unchanged;
    only its vertices are more (a skin of a few long faces, as a capsule's sides are, gets vertices wherever a
    model that moves them needs them). Vectorised over the faces. Each round halves the longest edges, so
    ``max_rounds`` is never reached for a finite mesh. Raises :class:`KneeInputError` for a ``max_edge`` that is
    not a positive length (every round would split every edge, four times the faces a round)."""
    if not (isinstance(max_edge, (int, float, np.integer, np.floating)) and max_edge > 0):  # also refuses NaN
        raise KneeInputError(f"the longest edge to bisect to must be a positive length (mm), got {max_edge!r}")
    v = np.asarray(mesh.vertices, float).copy()
    f = np.asarray(mesh.faces, np.int64).copy()
    for _ in range(max_rounds):
        ends = np.stack([f, np.roll(f, -1, axis=1)], axis=2)  # (F, 3, 2): edge i runs from node i to node i + 1
        length = np.linalg.norm(v[ends[:, :, 0]] - v[ends[:, :, 1]], axis=2)
        if not len(f) or length.max() <= max_edge:
            break
        longest = length.argmax(axis=1)
        edges, inv = np.unique(np.sort(ends, axis=2).reshape(-1, 2), axis=0, return_inverse=True)
        inv = inv.reshape(-1, 3)
        rows = np.arange(len(f))
        marked = np.zeros(len(edges), bool)
        marked[inv[rows, longest][length[rows, longest] > max_edge]] = True
        while True:  # a face with any edge split has its longest edge split too (keeps the faces well shaped)
            has = marked[inv].any(axis=1)
            need = inv[rows[has], longest[has]]
            if marked[need].all():
                break
            marked[need] = True
        mid = np.full(len(edges), -1, np.int64)
        split_edges = np.nonzero(marked)[0]
        mid[split_edges] = len(v) + np.arange(len(split_edges))
        v = np.vstack([v, 0.5 * (v[edges[split_edges, 0]] + v[edges[split_edges, 1]])])
        order = (longest[:, None] + np.arange(3)[None, :]) % 3  # each face turned so its longest edge is edge 0
        F = np.take_along_axis(f, order, axis=1)
        M = mid[np.take_along_axis(inv, order, axis=1)]  # midpoints of edges (p q), (q r), (r p); -1 unsplit
        cut = M[:, 0] >= 0
        p, q, r = F[cut].T
        m0, m1, m2 = M[cut].T
        right_cut, left_cut = m1 >= 0, m2 >= 0
        f = np.concatenate([
            F[~cut],
            np.stack([p, m0, r], 1)[~left_cut], np.stack([p, m0, m2], 1)[left_cut], np.stack([m2, m0, r], 1)[left_cut],
            np.stack([m0, q, r], 1)[~right_cut], np.stack([m0, q, m1], 1)[right_cut], np.stack([m0, m1, r], 1)[right_cut]])
    return trimesh.Trimesh(v, f, process=False)


def clip_to_slab(mesh: trimesh.Trimesh, origin, axis, below: float, above: float) -> trimesh.Trimesh:
    """The part of a closed mesh between two planes normal to ``axis`` (3,), at ``origin - below * axis``
    and ``origin + above * axis`` (mm), closed by the planes' cross-sections (a boolean intersection with a
    box, exact and watertight). A mesh that lies wholly inside the slab is returned unchanged."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    o = np.asarray(origin, float)
    h = (mesh.vertices - o) @ a
    if h.min() >= -below and h.max() <= above:
        return mesh
    # a box as long as the slab and wider than the mesh, turned so that its z axis is ``axis``
    size = 4.0 * float(np.linalg.norm(mesh.extents)) + 1.0
    T = np.eye(4)
    T[:3, :3] = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], a)[:3, :3]
    T[:3, 3] = o + 0.5 * (above - below) * a
    box = trimesh.creation.box(extents=[size, size, below + above], transform=T)
    out = trimesh.boolean.intersection([closed_surface(mesh), box], engine="manifold")
    if out.is_empty or not out.is_watertight:
        raise KneeInputError("clipping the surface to the region around the joint left nothing closed")
    return out
