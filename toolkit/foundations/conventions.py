"""Conventions of the toolkit: units, bone frames, poses and joint coordinates.

Units
    Millimetres, newtons, MPa and seconds inside the toolkit; radians inside, degrees only at the
    command line and in CSV files. Helpers in this module take radians.

Bone frames (seed 002)
    x anterior, y proximal, z lateral, for a **right** knee. Left knees are mirrored on the way in
    and out (z flipped, :func:`mirror_points`, :func:`mirror_poses`) so the models always see a
    right knee.

Poses
    The pose of body B in body A is a rotation ``R_AB`` (B's axes as columns, in A) and a position
    ``P_AB`` (B's origin in A); as homogeneous matrices ``(n, 4, 4)`` or pinocchio ``SE3``.
    A point ``p_B`` given in B is ``R_AB @ p_B + P_AB`` in A.

Joint coordinates (Grood & Suntay, as a Cardan sequence)
    ``R = Rz(-alpha) @ Rx(beta) @ Ry(gamma)`` with alpha flexion [+], beta adduction [+],
    gamma internal rotation [+]. Translations are the components of P (the distal body's origin)
    in the proximal (femur) frame: anterior [+], proximal [+], lateral [+]. The same
    decomposition serves tibia-in-femur (TF) and patella-in-femur (PF).
    The six coordinates are stored in this order:
    ``(alpha, beta, gamma, anterior, proximal, lateral)`` (radians, mm).

Example
-------
>>> import numpy as np
>>> q = np.array([np.radians(30), 0.05, -0.1, 2.0, -25.0, 1.0])
>>> T = joint_to_pose(q)
>>> np.allclose(pose_to_joint(T), q)
True
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from knee.foundations.errors import KneeInputError

#: Names of the six joint coordinates, in storage order.
JOINT_COORDINATES = ("flexion", "adduction", "internal_rotation", "anterior", "proximal", "lateral")

def rot_x(a):
    """Rotation matrices about x. ``a`` : scalar or (n,) radians -> (3, 3) or (n, 3, 3)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(a):
    """Rotation matrices about y. ``a`` : scalar or (n,) radians -> (3, 3) or (n, 3, 3)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(a):
    """Rotation matrices about z. ``a`` : scalar or (n,) radians -> (3, 3) or (n, 3, 3)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def cardan_to_matrix(alpha, beta, gamma):
    """``R = Rz(-alpha) @ Rx(beta) @ Ry(gamma)``; angles scalar or (n,) radians -> (3,3)/(n,3,3)."""
    return rot_z(-np.asarray(alpha, float)) @ rot_x(beta) @ rot_y(gamma)


def matrix_to_cardan(R):
    """Inverse of :func:`cardan_to_matrix`.

    Parameters
    ----------
    R : (3, 3) or (n, 3, 3) float
        Rotation matrices.

    Returns
    -------
    (3,) or (n, 3) float
        ``(alpha, beta, gamma)`` in radians; beta in [-pi/2, pi/2] (gimbal lock at |beta| = pi/2).
    """
    R = np.asarray(R, dtype=float)
    beta = np.arcsin(np.clip(R[..., 2, 1], -1.0, 1.0))
    gamma = np.arctan2(-R[..., 2, 0], R[..., 2, 2])
    alpha = np.arctan2(R[..., 0, 1], R[..., 1, 1])
    return np.stack([alpha, beta, gamma], axis=-1)


def joint_to_pose(q):
    """Joint coordinates to homogeneous poses.

    Parameters
    ----------
    q : (6,) or (n, 6) float
        ``(alpha, beta, gamma, anterior, proximal, lateral)``, radians and mm.

    Returns
    -------
    (4, 4) or (n, 4, 4) float
        Pose of the distal body in the proximal (femur) frame.
    """
    q = np.asarray(q, dtype=float)
    if q.shape[-1] != 6:
        raise KneeInputError(f"joint coordinates need 6 components, got shape {q.shape}")
    T = np.zeros(q.shape[:-1] + (4, 4))
    T[..., :3, :3] = cardan_to_matrix(q[..., 0], q[..., 1], q[..., 2])
    T[..., :3, 3] = q[..., 3:6]
    T[..., 3, 3] = 1.0
    return T


def pose_to_joint(T):
    """Homogeneous poses to joint coordinates; inverse of :func:`joint_to_pose`.

    Parameters
    ----------
    T : (4, 4) or (n, 4, 4) float

    Returns
    -------
    (6,) or (n, 6) float
    """
    T = np.asarray(T, dtype=float)
    return np.concatenate([matrix_to_cardan(T[..., :3, :3]), T[..., :3, 3]], axis=-1)


def mirror_points(points):
    """Mirror points between a left and a right knee (z flipped). ``points`` : (..., 3) float."""
    p = np.array(points, dtype=float, copy=True)
    p[..., 2] *= -1.0
    return p


def mirror_poses(T):
    """Mirror poses between a left and a right knee: ``M @ T @ M`` with M = diag(1, 1, -1, 1).

    Applied to a left knee's poses (in frames whose z points to the subject's right, i.e. medially)
    it gives the equivalent right-knee poses, whose joint coordinates are the anatomical ones.
    ``T`` : (4, 4) or (n, 4, 4) float.
    """
    M = np.diag([1.0, 1.0, -1.0, 1.0])
    return M @ np.asarray(T, dtype=float) @ M


def joint_coordinates(T, side="right"):
    """Anatomical joint coordinates of poses of a ``side`` ('right' or 'left') knee."""
    if side not in ("right", "left"):
        raise KneeInputError(f"side must be 'right' or 'left', got {side!r}")
    return pose_to_joint(mirror_poses(T) if side == "left" else T)


def to_se3(T):
    """A (4, 4) pose as a pinocchio ``SE3`` (rotation and translation in mm)."""
    import pinocchio as pin  # deferred: 0.3 s to import, needed here only, by few callers

    T = np.asarray(T, dtype=float)
    return pin.SE3(T[:3, :3].copy(), T[:3, 3].copy())


def from_se3(M):
    """A pinocchio ``SE3`` as a (4, 4) homogeneous matrix."""
    return np.asarray(M.homogeneous, dtype=float)


def read_pose_file(path, what: str) -> np.ndarray:
    """A rigid pose (4, 4) from a text file of 16 numbers (row by row); ``what`` names it in the one-line
    error (:class:`KneeInputError`) when the file is missing, cut short or not numbers, or its upper-left
    3x3 block is not a rotation (a scale, a reflection or a transposed matrix's last row in its place)."""
    path = Path(path)
    if not path.is_file():
        raise KneeInputError(f"{what} {path}: no such file")
    try:
        T = np.loadtxt(path, dtype=float, ndmin=2)
        T = T.reshape(4, 4)
    except (OSError, ValueError, UnicodeDecodeError):
        raise KneeInputError(f"{what} {path}: not a readable 4x4 matrix (16 numbers)") from None
    R_ = T[:3, :3]
    if not (np.all(np.isfinite(T)) and np.allclose(R_ @ R_.T, np.eye(3), atol=1e-3) and np.linalg.det(R_) > 0):
        raise KneeInputError(f"{what} {path}: its upper-left 3x3 block is not a rotation")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise KneeInputError(f"{what} {path}: its last row must be 0 0 0 1 (a transposed matrix?)")
    return T


def invert_poses(T):
    """Inverse of poses, (4, 4) or (n, 4, 4)."""
    T = np.asarray(T, dtype=float)
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    Ti[..., 3, 3] = 1.0
    return Ti


def transform_points(T, points):
    """Apply pose(s) ``T`` (4,4) or (n,4,4) to ``points`` (m, 3) -> (m, 3) or (n, m, 3)."""
    T = np.asarray(T, dtype=float)
    p = np.asarray(points, dtype=float)
    return np.einsum("...ij,mj->...mi", T[..., :3, :3], p) + T[..., None, :3, 3]
