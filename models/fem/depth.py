"""The depth input of the association model: a virtual RGB-D camera, real depth images, point clouds,
and the rigid (ICP) registration of the model's surface to the observed points (seed 000, 2.3 and 3).

Camera conventions: a pinhole camera with intrinsics ``K`` (3, 3) (pixels); the pose ``T_world_cam``
(4, 4) gives the camera's axes in the world (x right, y down, z forward: the optical axis); a depth
image holds, per pixel, the depth along the optical axis in mm (0 where nothing was seen). Pixel (u, v)
(column, row) looks through the pixel centre ``(u + 0.5, v + 0.5)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from toolkit.errors import KneeInputError


@dataclass
class Camera:
    """A pinhole depth camera.

    Attributes
    ----------
    K : (3, 3) float
        Intrinsics in pixels.
    width, height : int
    T_world_cam : (4, 4) float
        Camera pose in the world (mm).
    """

    K: np.ndarray
    width: int
    height: int
    T_world_cam: np.ndarray

    @classmethod
    def looking_at(cls, eye, target, up=(0.0, 1.0, 0.0), width=1280, height=720, hfov_deg=69.0):
        """A camera at ``eye`` looking at ``target`` (mm), image-up roughly along ``up``; the default
        matches an RGB-D camera's colour stream (1280 x 720, 69 degrees horizontal field of view)."""
        eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
        z = target - eye
        if np.linalg.norm(z) < 1e-9:
            raise KneeInputError("camera eye and target coincide")
        z /= np.linalg.norm(z)
        x = np.cross(z, up)  # image right
        if np.linalg.norm(x) < 1e-9:
            raise KneeInputError("camera 'up' is parallel to the viewing direction")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)  # image down
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, y, z])
        T[:3, 3] = eye
        f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
        K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
        return cls(K, int(width), int(height), T)

    @property
    def T_cam_world(self) -> np.ndarray:
        T = np.eye(4)
        R = self.T_world_cam[:3, :3]
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ self.T_world_cam[:3, 3]
        return T


def render_depth(vertices, faces, camera: Camera) -> np.ndarray:
    """Depth image (height, width) in mm of a triangle mesh seen by ``camera`` (0 = no surface)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    rays = scene.create_rays_pinhole(o3d.core.Tensor(camera.K), o3d.core.Tensor(camera.T_cam_world),
                                     camera.width, camera.height)
    t = scene.cast_rays(rays)["t_hit"].numpy().astype(float)
    t[~np.isfinite(t)] = 0.0
    return t


@dataclass
class DepthNoise:
    """Depth noise of a stereo RGB-D camera: zero-mean Gaussian with ``sigma = sigma_at_ref *
    (z / ref_depth)^2`` (error growing with the square of the depth), and a fraction of pixels lost.
    Defaults: 1 mm at 400 mm, 2% dropout."""

    sigma_at_ref: float = 1.0
    ref_depth: float = 400.0
    dropout: float = 0.02

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        d = np.array(depth, dtype=float, copy=True)
        seen = d > 0
        sigma = self.sigma_at_ref * (d[seen] / self.ref_depth) ** 2
        d[seen] += rng.normal(size=sigma.size) * sigma
        lost = rng.random(d.shape) < self.dropout
        d[lost] = 0.0
        return d


def backproject(depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray | None = None,
                depth_scale: float = 1.0, max_depth: float | None = None) -> np.ndarray:
    """Points (P, 3) in mm, in the world (or the camera frame without a pose), from a depth image.

    ``depth_scale`` converts the image's units to mm (e.g. 1.0 for a 16-bit image in mm, 1000 for one in
    metres). Pixels with depth 0 (or beyond ``max_depth`` mm) are skipped.
    """
    d = np.asarray(depth, dtype=float) * depth_scale
    if d.ndim != 2:
        raise KneeInputError(f"a depth image must be 2-D, got shape {d.shape}")
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise KneeInputError("intrinsics must be a 3x3 matrix with positive focal lengths")
    v, u = np.nonzero((d > 0) & (np.isfinite(d)) & ((d <= max_depth) if max_depth else True))
    z = d[v, u]
    x = (u + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (v + 0.5 - K[1, 2]) / K[1, 1] * z
    p = np.column_stack([x, y, z])
    if T_world_cam is not None:
        T = np.asarray(T_world_cam, float)
        p = p @ T[:3, :3].T + T[:3, 3]
    return p


def load_depth_image(path, K, T_world_cam=None, depth_scale: float = 1.0) -> np.ndarray:
    """Points from a depth image file (16-bit PNG or a .npy array) with intrinsics ``K``."""
    path = Path(path)
    if not path.is_file():
        raise KneeInputError(f"{path}: no such depth image")
    if path.suffix.lower() == ".npy":
        depth = np.load(path)
    else:
        img = o3d.io.read_image(str(path))
        depth = np.asarray(img)
        if depth.size == 0:
            raise KneeInputError(f"{path}: not a readable depth image")
    return backproject(depth, K, T_world_cam, depth_scale)


def load_point_cloud(path) -> np.ndarray:
    """Points (P, 3) in mm from a point-cloud file open3d reads (.ply, .pcd, .xyz, .pts)."""
    path = Path(path)
    if not path.is_file():
        raise KneeInputError(f"{path}: no such point-cloud file")
    pc = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pc.points, dtype=float)
    if len(pts) == 0:
        raise KneeInputError(f"{path}: no points read (unsupported or empty file)")
    return pts


def icp(source_points, target_points, init=None, max_distance: float = 20.0, iterations: int = 60,
        target_normals=None):
    """Rigid registration of ``source_points`` onto ``target_points`` (point-to-plane ICP, open3d).
    ``target_normals`` (P, 3): the target's normals when known (e.g. the faces' normals of points sampled
    on a mesh); estimated from the points otherwise.

    Returns
    -------
    T : (4, 4) float, the transform to apply to the source; fitness (fraction of source points matched)
    and inlier RMSE (mm).
    """
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(source_points, float)))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(target_points, float)))
    if target_normals is None:
        dst.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=8.0, max_nn=30))
    else:
        dst.normals = o3d.utility.Vector3dVector(np.asarray(target_normals, float))
    reg = o3d.pipelines.registration.registration_icp(
        src, dst, max_distance, np.eye(4) if init is None else np.asarray(init, float),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=iterations))
    return np.asarray(reg.transformation), float(reg.fitness), float(reg.inlier_rmse)
