"""Geometry helpers: least-squares sphere and plane fits, rigid registration, principal axes, and the
least-varying pair of points over a motion. Shapes: points ``(n, 3)``; poses ``(F, 4, 4)``; mm.

Example
-------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> d = rng.normal(size=(200, 3)); d /= np.linalg.norm(d, axis=1, keepdims=True)
>>> c, r, rms = fit_sphere(np.array([1.0, 2.0, 3.0]) + 25.0 * d)
>>> np.allclose(c, [1, 2, 3]) and abs(r - 25.0) < 1e-9
True
"""

from __future__ import annotations

import numpy as np

from knee.foundations.errors import KneeInputError


def _points(p, n_min, what):
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise KneeInputError(f"{what}: points must be an (n, 3) array, got shape {p.shape}")
    if len(p) < n_min:
        raise KneeInputError(f"{what}: needs at least {n_min} points, got {len(p)}")
    if not np.all(np.isfinite(p)):
        raise KneeInputError(f"{what}: points must be finite")
    return p


def fit_sphere(points, refine: bool = True, iterations: int = 20):
    """Least-squares sphere through points (a cap is enough).

    The algebraic fit (|p|^2 = 2 c.p + k, linear) starts a geometric Gauss-Newton refinement of
    sum (|p - c| - r)^2.

    Returns
    -------
    centre : (3,) float, radius : float, rms : float (geometric residual, mm)
    """
    p = _points(points, 4, "sphere fit")
    sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    if sv[2] < 1e-3 * sv[0]:
        raise KneeInputError(f"sphere fit: the {len(p)} points are (nearly) coplanar; a sphere needs a curved patch")
    A = np.column_stack([2 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(A, (p * p).sum(axis=1), rcond=None)
    c = sol[:3]
    r = float(np.sqrt(max(sol[3] + c @ c, 0.0)))
    if refine:
        x = np.r_[c, r]
        for _ in range(iterations):
            d = p - x[:3]
            L = np.linalg.norm(d, axis=1)
            res = L - x[3]
            J = np.column_stack([-d / L[:, None], -np.ones(len(p))])
            step, *_ = np.linalg.lstsq(J, -res, rcond=None)
            x += step
            if np.abs(step).max() < 1e-12:
                break
        c, r = x[:3], float(x[3])
    rms = float(np.sqrt(np.mean((np.linalg.norm(p - c, axis=1) - r) ** 2)))
    return c, r, rms


def fit_plane(points):
    """Least-squares plane: ``(point (3,), unit normal (3,), rms)``; the normal's sign is arbitrary."""
    p = _points(points, 3, "plane fit")
    c = p.mean(axis=0)
    _, s, Vt = np.linalg.svd(p - c, full_matrices=False)
    n = Vt[2]
    rms = float(np.sqrt(np.mean(((p - c) @ n) ** 2)))
    return c, n, rms


def principal_axes(points):
    """``(centroid (3,), axes (3, 3))``: rows by decreasing variance (signs arbitrary)."""
    p = _points(points, 3, "principal axes")
    c = p.mean(axis=0)
    return c, np.linalg.svd(p - c, full_matrices=False)[2]


def rigid_register(source, target):
    """Least-squares rigid transform taking ``source`` onto ``target`` (paired fiducials, Kabsch).

    Returns
    -------
    T : (4, 4) float, fre : (n,) float (the fiducial registration error of each point, mm)
    """
    a = _points(source, 3, "rigid registration (source)")
    b = _points(target, 3, "rigid registration (target)")
    if a.shape != b.shape:
        raise KneeInputError(f"rigid registration: {len(a)} source and {len(b)} target points do not pair up")
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, s, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise KneeInputError("rigid registration: the fiducials are collinear")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cb - R @ ca
    fre = np.linalg.norm(a @ R.T + T[:3, 3] - b, axis=1)
    return T, fre


def least_varying_pair(a_points, b_points, poses, chunk: int = 256):
    """The pair (a_i, b_j) whose distance varies least while body B moves by ``poses``.

    Parameters
    ----------
    a_points : (A, 3) float, in frame A (fixed).
    b_points : (B, 3) float, in frame B.
    poses : (F, 4, 4) float, pose of B in A at each frame.

    Returns
    -------
    (i, j, lengths (F,), sd): the indices, the pair's distance at each frame and its standard deviation.
    Vectorised over pairs and frames (in chunks of ``chunk`` A-points to bound memory).
    """
    a = _points(a_points, 1, "isometric search (first area)")
    b = _points(b_points, 1, "isometric search (second area)")
    T = np.asarray(poses, dtype=float)
    bw = np.einsum("fij,bj->fbi", T[:, :3, :3], b) + T[:, None, :3, 3]  # (F, B, 3)
    best = (np.inf, 0, 0)
    for k in range(0, len(a), chunk):
        d = np.linalg.norm(a[None, k:k + chunk, None, :] - bw[:, None, :, :], axis=3)  # (F, a, B)
        sd = d.std(axis=0)
        i, j = np.unravel_index(np.argmin(sd), sd.shape)
        if sd[i, j] < best[0]:
            best = (float(sd[i, j]), k + i, j)
    _, i, j = best
    lengths = np.linalg.norm(a[i] - bw[:, j], axis=1)
    return int(i), int(j), lengths, float(lengths.std())


#: A bone piece counts as long when it is at least this many times its own width long.
LONG_BONE = 3.0


def epicondyles(vertices, heights, lateral, width: float) -> tuple[np.ndarray, np.ndarray]:
    """The lateral and medial epicondyles (3,) of a femur's surface: among the vertices (V, 3) within
    0.75 ``width`` above the distal-most one (``heights`` (V,) along the proximal axis), the centroids of
    those within 2 % of ``width`` of the most lateral and of the most medial along ``lateral`` (3,) (a
    flat side has no single extreme vertex)."""
    v = np.asarray(vertices, float)
    h = np.asarray(heights, float)
    distal = v[h < h.min() + 0.75 * width]
    s = distal @ np.asarray(lateral, float)
    return distal[s > s.max() - 0.02 * width].mean(axis=0), distal[s < s.min() + 0.02 * width].mean(axis=0)


def end_width(vertices, heights, lateral, end: str) -> float:
    """The medio-lateral width (mm) of a bone at one end: the extent along ``lateral`` (3,) of the
    vertices (V, 3) within a tenth of the bone's length from its ``end`` (``"low"`` or ``"high"`` of
    ``heights`` (V,)); a short piece (under :data:`LONG_BONE` widths long) is measured over its whole
    length."""
    v = np.asarray(vertices, float)
    h = np.asarray(heights, float)
    lat = np.asarray(lateral, float)
    span = h.max() - h.min()
    w_all = np.ptp(v @ lat)
    depth = min(0.1 * span, w_all) if span > LONG_BONE * w_all else span
    sel = h <= h.min() + depth if end == "low" else h >= h.max() - depth
    return float(np.ptp(v[sel] @ lat))
