"""The mechanism as a kinematic prior for depth data (issue "kinematic priors for the FEM", first part).

Flexion from depth: the knee's skin, posed by the (fitted) mechanism at a candidate flexion, is
registered to the one-sided point cloud by ICP; the candidate whose registered skin lies closest to the
points wins. A coarse scan over the assembly range (10 deg) is refined by a golden-section search to
0.5 deg. The fit quality reported: the points' RMS distance to the registered skin, the inlier fraction
and the flatness of the score around the optimum.

Kinematics alone (method iv of the comparison): the bones posed by the mechanism at the estimated angle,
placed in the camera's frame by the registration. :func:`pose_errors` measures any estimated bone poses
against the truth at target points (epiphysis and ACL/PCL footprints), as the FEM evaluation does.

Frames: the point cloud and every pose are in one world frame; the model's femur frame is the reference
(the skin is built in it). ``T_world_model`` takes model (femur-frame) coordinates to the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from models.fem.depth import icp
from models.fem.geometry import SurfaceQuery
from models.mechanism.solver import Mechanism
from models.phantom import Phantom
from toolkit.conventions import invert_poses, joint_to_pose, transform_points
from toolkit.errors import KneeInputError

GOLDEN = (math.sqrt(5) - 1) / 2
#: Voxel size (mm) the cloud is thinned to before registration.
VOXEL_MM = 4.0


def voxel_downsample(points, voxel: float) -> np.ndarray:
    """One point (the mean) per occupied voxel, vectorised."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    out = np.zeros((counts.size, 3))
    np.add.at(out, inv.ravel(), points)
    return out / counts[:, None]


#: ICP iterations per candidate of the coarse scan (it only ranks the candidates; the refinement uses 30).
COARSE_ICP_ITERATIONS = 15
#: Fewest points, and fewest below the knee (shank), to attempt an estimate.
MIN_POINTS = 500
MIN_SHANK_POINTS = 150


@dataclass
class FlexionEstimate:
    """Estimated flexion (rad) and pose ``T_world_model`` (4, 4); the fit quality: ``rms`` (mm, points to
    the registered skin), ``inliers`` (fraction within 5 mm), ``scores`` {deg: rms} of every candidate and
    ``contrast`` (the coarse scan's second-best score over the best; near 1 means ambiguous)."""

    flexion: float
    T_world_model: np.ndarray
    rms: float
    inliers: float
    scores: dict = field(default_factory=dict)
    contrast: float = float("nan")
    warnings: list = field(default_factory=list)

    @property
    def at_range_end(self) -> bool:
        return any("end of" in w for w in self.warnings)


class SkinModel:
    """The skin of a phantom posed by a mechanism at any flexion (cached by angle)."""

    def __init__(self, mech: Mechanism, phantom: Phantom, length: float | None = None):
        self.mech, self.phantom, self.length = mech, phantom, length
        self._cache = {}

    def at(self, alpha: float):
        key = round(float(alpha), 6)
        if key not in self._cache:
            tf, pf = self.mech.motion_at(np.array([alpha]))
            skin = self.phantom.skin(joint_to_pose(tf[0]), joint_to_pose(pf[0]) if self.mech.has_pf else None,
                                     self.length)
            self._cache[key] = (skin, SurfaceQuery.of(skin))
        return self._cache[key]

    def samples(self, alpha: float, n: int = 6000) -> tuple[np.ndarray, np.ndarray]:
        """Points spread over the posed skin (area-weighted, seeded: the same every call) and their faces'
        normals."""
        skin, _ = self.at(alpha)
        key = ("s", round(float(alpha), 6))
        if key not in self._cache:
            from trimesh.sample import sample_surface

            pts, face = sample_surface(skin, n, seed=0)
            self._cache[key] = (pts, skin.face_normals[face])
        return self._cache[key]


def _score(skin_model: SkinModel, alpha, points, init, iterations: int = 30):
    skin, q = skin_model.at(alpha)
    samples, normals = skin_model.samples(alpha)
    T, fitness, _ = icp(points, samples, init=init, max_distance=15.0, iterations=iterations, target_normals=normals)
    d = np.abs(q.signed_distance(transform_points(T, points)))
    trimmed = np.sort(d)[: int(0.9 * d.size)]  # robust to outliers and unseen parts
    return float(np.sqrt(np.mean(trimmed ** 2))), T, float(np.mean(d < 5.0))


def estimate_flexion(mech: Mechanism, phantom: Phantom, points, T_init=None, coarse_step_deg: float = 10.0,
                     tol_deg: float = 0.5, skin_length: float | None = None) -> FlexionEstimate:
    """Estimate the flexion and the rigid pose of the knee from a point cloud (P, 3), world frame.

    ``T_init``: a first guess of the world -> model transform (default identity: the world is roughly the
    femur frame, as after the thigh registration of the standard case).

    Raises :class:`KneeInputError` when the cloud is empty or too small, or covers too little of the shank
    (below the knee) to see the flexion.
    """
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < MIN_POINTS or not np.all(np.isfinite(pts)):
        raise KneeInputError(f"the point cloud needs at least {MIN_POINTS} finite (P, 3) points, got "
                             f"{pts.shape[0] if pts.ndim == 2 else pts.size}")
    init = np.eye(4) if T_init is None else np.asarray(T_init, float)
    pts = voxel_downsample(pts, VOXEL_MM)
    local = transform_points(init, pts)
    lo, hi = mech.assembly_range
    # points of the shank: below the knee in the femur frame, in front of nothing else
    shank = int(np.sum(local[:, 1] < -30.0))
    if shank < MIN_SHANK_POINTS:
        raise KneeInputError(f"the point cloud covers too little of the shank to estimate flexion ({shank} points "
                             f"more than 30 mm below the knee; at least {MIN_SHANK_POINTS} needed)")
    sk = SkinModel(mech, phantom, skin_length)
    a0, a1 = max(lo, math.radians(-5.0)), min(hi, math.radians(150.0))
    grid = np.arange(a0, a1 + 1e-9, math.radians(coarse_step_deg))
    scores = {}
    best = (np.inf, None, None, 0.0)
    for a in grid:  # a coarse scan: a handful of ICPs (each vectorised inside open3d)
        s, T, inl = _score(sk, a, pts, init, iterations=COARSE_ICP_ITERATIONS)
        scores[round(math.degrees(a), 3)] = s
        if s < best[0]:
            best = (s, a, T, inl)
    ordered = sorted(scores.values())
    contrast = ordered[1] / ordered[0] if len(ordered) > 1 and ordered[0] > 0 else float("inf")
    # golden-section refinement within one coarse step either side
    step = math.radians(coarse_step_deg)
    x0, x3 = max(a0, best[1] - step), min(a1, best[1] + step)
    cache = {}

    def f(a):
        if a not in cache:
            cache[a] = _score(sk, a, pts, best[2] if best[2] is not None else init)
            scores[round(math.degrees(a), 3)] = cache[a][0]
        return cache[a][0]

    x1, x2 = x3 - GOLDEN * (x3 - x0), x0 + GOLDEN * (x3 - x0)
    while x3 - x0 > math.radians(tol_deg):
        if f(x1) < f(x2):
            x3, x2 = x2, x1
            x1 = x3 - GOLDEN * (x3 - x0)
        else:
            x0, x1 = x1, x2
            x2 = x0 + GOLDEN * (x3 - x0)
    a = 0.5 * (x0 + x3)
    s, T, inl = _score(sk, a, pts, best[2])
    if best[0] < s:
        a, s, T, inl = best[1], best[0], best[2], best[3]
    warnings = []
    if min(abs(a - lo), abs(a - hi)) < math.radians(1.0) or min(abs(a - a0), abs(a - a1)) < math.radians(1.0):
        warnings.append(f"the best fit lies at the end of the prior's assembly range ({math.degrees(lo):.1f} to "
                        f"{math.degrees(hi):.1f} deg): the knee may be outside what the prior allows; the "
                        "estimate is a bound, not a measurement")
    if contrast < 1.02:
        warnings.append(f"the fit hardly changes with flexion (second-best / best score {contrast:.3f}): the view "
                        "shows too little of the flexion")
    return FlexionEstimate(flexion=float(a), T_world_model=invert_poses(T), rms=s, inliers=inl, scores=scores,
                           contrast=float(contrast), warnings=warnings)


@dataclass
class TargetSet:
    """Target points in each bone's own frame (mm) with footprint masks: the epiphysis (bone surface within
    ``epiphysis_length`` of the joint) and the ACL/PCL footprints (within ``radius`` of the attachments'
    nearest surface points)."""

    femur: np.ndarray
    tibia: np.ndarray
    femur_footprints: np.ndarray
    tibia_footprints: np.ndarray


def target_set(mech: Mechanism, phantom: Phantom, radius: float = 10.0, epiphysis_length: float = 40.0) -> TargetSet:
    fv, tv = phantom.femur.vertices, phantom.tibia.vertices
    fe, te = fv[fv[:, 1] < epiphysis_length], tv[tv[:, 1] > -epiphysis_length]
    fa = np.vstack([mech.params.link(n).femur for n in ("acl", "pcl")])
    ta = np.vstack([mech.params.link(n).tibia for n in ("acl", "pcl")])
    fa = fe[np.linalg.norm(fe[:, None] - fa[None], axis=2).argmin(axis=0)]
    ta = te[np.linalg.norm(te[:, None] - ta[None], axis=2).argmin(axis=0)]
    return TargetSet(fe, te, (np.linalg.norm(fe[:, None] - fa[None], axis=2) < radius).any(axis=1),
                     (np.linalg.norm(te[:, None] - ta[None], axis=2) < radius).any(axis=1))


def pose_errors(targets: TargetSet, T_femur_true, T_tibia_true, T_femur_est, T_tibia_est) -> dict:
    """Distances (mm) between target points carried by the true and by the estimated bone poses (world):
    {bone: {"footprints": (mean, sd), "epiphysis": (mean, sd)}}."""
    out = {}
    for bone, P, mask, Tt, Te in (("femur", targets.femur, targets.femur_footprints, T_femur_true, T_femur_est),
                                  ("tibia", targets.tibia, targets.tibia_footprints, T_tibia_true, T_tibia_est)):
        d = np.linalg.norm(transform_points(Te, P) - transform_points(Tt, P), axis=1)
        out[bone] = {"footprints": (float(d[mask].mean()), float(d[mask].std())),
                     "epiphysis": (float(d.mean()), float(d.std()))}
    return out


def kinematic_estimate(mech: Mechanism, est: FlexionEstimate) -> tuple[np.ndarray, np.ndarray]:
    """Method (iv): world poses of femur and tibia from the mechanism at the estimated flexion."""
    tf, _ = mech.motion_at(np.array([est.flexion]))
    return est.T_world_model, est.T_world_model @ joint_to_pose(tf[0])
