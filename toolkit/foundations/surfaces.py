"""Signed distances and occupancy against closed triangle meshes (open3d ``RaycastingScene``).

Negative inside, positive outside (mm).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d


class SurfaceQuery:
    """Repeated signed-distance / inside queries against one closed mesh (vertices (V, 3), faces (F, 3))."""

    def __init__(self, vertices, faces):
        v = np.asarray(vertices, float)
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
        return self.scene.compute_signed_distance(p).numpy().astype(float)

    def inside(self, points) -> np.ndarray:
        """(P, 3) -> (P,) bool, by ray parity (robust for watertight meshes)."""
        p = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
        return self.scene.compute_occupancy(p).numpy() > 0.5

    def closest_points(self, points) -> np.ndarray:
        """(P, 3) -> (P, 3) closest points on the surface."""
        return self.closest(points)[0]

    def closest(self, points) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) -> closest points on the surface (P, 3) and the normals of their triangles (P, 3)."""
        p = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
        r = self.scene.compute_closest_points(p)
        return r["points"].numpy().astype(float), r["primitive_normals"].numpy().astype(float)
