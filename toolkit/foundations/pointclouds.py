"""Point clouds: depth images back-projected to points, point-cloud files, voxel thinning and rigid
(ICP) registration.

Camera conventions: a pinhole camera with intrinsics ``K`` (3, 3) (pixels); the pose ``T_world_cam``
(4, 4) gives the camera's axes in the world (x right, y down, z forward: the optical axis); a depth
image holds, per pixel, the depth along the optical axis (0 where nothing was seen), in mm after
``depth_scale``. Pixel (u, v) (column, row) looks through the pixel centre ``(u + 0.5, v + 0.5)``.
Points are ``(P, 3)`` float arrays in mm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from knee.foundations.errors import KneeInputError


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
    """Points (P, 3) from a depth image file (16-bit PNG or a .npy array) with intrinsics ``K`` (3, 3)
    (pixels): in mm after ``depth_scale`` (image units to mm), in the camera's frame, or in the world
    with the camera pose ``T_world_cam`` (4, 4)."""
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


def voxel_downsample(points, voxel: float) -> np.ndarray:
    """One point (the mean) per occupied voxel, vectorised (the voxel's three indices packed into one
    integer key, so the grouping is a 1-D unique)."""
    points = np.asarray(points, float)
    ijk = np.floor(points / voxel).astype(np.int64)
    ijk -= ijk.min(axis=0)
    span = ijk.max(axis=0) + 1
    keys = (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]
    _, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
    out = np.zeros((counts.size, 3))
    for k in range(3):
        out[:, k] = np.bincount(inv, weights=points[:, k], minlength=counts.size)
    return out / counts[:, None]


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
