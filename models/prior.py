"""The mechanism as a kinematic prior for depth data (issue "kinematic priors for the FEM", first part).

Flexion from depth: the knee's skin, posed by the (fitted) mechanism at a candidate flexion, is
registered to the one-sided point cloud by ICP; the candidate whose registered skin lies closest to the
points wins. A coarse scan over the assembly range (10 deg) is refined by a golden-section search to
0.5 deg. The posed skin is never built as one mesh: its parts (thigh, shank, knee and patella solids)
are meshed, sampled and put in ray-casting scenes once and only moved per candidate (a union per
candidate took about two thirds of the time). The fit quality reported: the points' RMS distance to the
registered skin, the inlier fraction
and the flatness of the score around the optimum.

Kinematics alone (method iv of the comparison): the bones posed by the mechanism at the estimated angle,
placed in the camera's frame by the registration (:func:`kinematic_estimate`).

Frames: the point cloud and every pose are in one world frame; the model's femur frame is the reference
(the skin is built in it). ``T_world_model`` takes model (femur-frame) coordinates to the world.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from trimesh.sample import sample_surface

from knee.foundations.conventions import invert_poses, joint_to_pose, transform_points
from knee.foundations.errors import KneeInputError
from knee.foundations.pointclouds import connected_parts, icp, seeded_subsample, voxel_downsample
from knee.foundations.surfaces import BandDistances, SurfaceQuery, clip_to_slab
from knee.models.mechanism.solver import Mechanism
from knee.models.phantom import Phantom

GOLDEN = (math.sqrt(5) - 1) / 2
#: Voxel size (mm) the cloud is thinned to before registration.
VOXEL_MM = 4.0


#: ICP iterations per candidate of the coarse scan (it only ranks the candidates; the refinement uses 30).
COARSE_ICP_ITERATIONS = 15
#: Most points the coarse scan's ICPs take (a random, seeded subsample, the same for every candidate; each
#: candidate is scored on all of them, and the refinement registers all of them). The scan only brackets
#: the flexion for the refinement: on ten cases of the honest benchmark's seed 1 (views of 3,000-7,000
#: thinned points) the footprints' median change is 0.000 mm, at 0.92 of the case's time
#: (``scripts/bench_subsamples.py --subsample coarse``).
COARSE_ICP_POINTS = 2000
#: Fewest points, and fewest below the knee (shank), to attempt an estimate.
MIN_POINTS = 500
MIN_SHANK_POINTS = 150
#: How near the shank's skin (mm), posed at a candidate flexion, a point of the roughly placed cloud counts as
#: the shank's when the cloud shows little below the knee (the rough placement is good to a few mm).
SHANK_SEARCH_MM = 10.0
#: Fewest registered points on the shank's own skin (nearest to it, within 5 mm) below which the estimate
#: warns that the flexion is seen only through the knee's outline.
MIN_SEEN_SHANK = 100
#: The estimate's fit (mm: the RMS of the nearest 90 % of the points' distances to the posed skin) above which
#: it warns that the points do not match the subject's skin. A depth camera's noise at a knee's distance (a
#: D435's rated 1.6 mm at 400 mm) and a skin 2 mm RMS off the scanned one (the honest benchmark's largest
#: mismatch) give about 2.6 mm together. Measured: the benchmark's views fit within 2.5 mm (328 of the 329 views
#: of its five seeds and of lenhart2015's seed 0; the other, 10.0 mm, is a registration settled in a wrong
#: place, the mechanism alone 16 mm off there), a synthetic subject's view read with the intrinsics of half
#: its resolution 9.7 mm.
POOR_FIT_RMS_MM = 3.0
#: The thigh's and the shank's indices among the skin's parts (:meth:`knee.models.phantom.Phantom.skin_parts`:
#: thigh, shank, knee, patella).
THIGH, SHANK = 0, 1


@dataclass
class FlexionEstimate:
    """Estimated flexion (rad) and pose ``T_world_model`` (4, 4); the fit quality: ``rms`` (mm, points to
    the registered skin), ``inliers`` (fraction within 5 mm), ``scores`` {deg: rms} of every candidate (the
    coarse scan's measured to the skin samples' tangent planes, the refinement's to the skin) and
    ``contrast`` (the coarse scan's second-best score over the best; near 1 means ambiguous);
    ``shank_points``: the registered points on the shank's own skin (nearer to it than to any other part
    of the skin, within 5 mm; after voxel down-sampling)."""

    flexion: float
    T_world_model: np.ndarray
    rms: float
    inliers: float
    scores: dict = field(default_factory=dict)
    contrast: float = float("nan")
    shank_points: int = -1
    warnings: list = field(default_factory=list)
    skin: "SkinModel | None" = field(default=None, repr=False)  # the posed-skin model the estimate used

    @property
    def at_range_end(self) -> bool:
        return any("end of" in w for w in self.warnings)


class PosedSkin:
    """The phantom's envelope at one pose, queried part by part (no union mesh is built): the signed
    distance to the union of solids is the smallest of the parts' (exact away from the creases where two
    parts meet)."""

    def __init__(self, parts):
        self.parts = parts  # [(SurfaceQuery in the part's frame, pose (4, 4))]
        self.inverse = [invert_poses(T) for _, T in parts]

    def signed_distance(self, points, margin: float = 10.0) -> np.ndarray:
        """The smallest of the parts' signed distances, each part queried only for the points within
        ``margin`` of its bounding box (a point farther than that is at least ``margin`` outside it); a
        point that ends up farther than ``margin`` from every part queried is queried against all of them.
        The same values as querying every part for every point, for about a third of the queries."""
        points = np.asarray(points, float)
        out = np.full(len(points), np.inf)
        local = [transform_points(Ti, points) for Ti in self.inverse]
        for (q, _), p in zip(self.parts, local):
            near = np.nonzero(np.all((p >= q.lo - margin) & (p <= q.hi + margin), axis=1))[0]
            if near.size:
                out[near] = np.minimum(out[near], q.signed_distance(p[near]))
        far = np.nonzero(out > margin)[0]
        if far.size:
            out[far] = np.min([q.signed_distance(p[far]) for (q, _), p in zip(self.parts, local)], axis=0)
        return out

    def part_distances(self, points) -> np.ndarray:
        """(parts, P): each part's signed distance at every point (no bounding-box shortcut)."""
        points = np.asarray(points, float)
        return np.array([q.signed_distance(transform_points(Ti, points)) for (q, _), Ti in zip(self.parts, self.inverse)])

    def inside_part(self, i: int, points) -> np.ndarray:
        """(P,) bool: the points lie inside part ``i`` (ray parity, much cheaper than a distance)."""
        q, _ = self.parts[i]
        return q.inside(transform_points(self.inverse[i], points))


class SkinModel:
    """The skin of a phantom posed by a mechanism at any flexion (cached by angle). The skin's parts
    (:meth:`knee.models.phantom.Phantom.skin_parts`) are meshed, sampled and put in ray-casting scenes once;
    a flexion only moves them.

    Attributes
    ----------
    mech : Mechanism
        The prior that poses the skin.
    shank_below : float
        The height (model frame y, mm) below which depth points count as the shank's.
    """

    def __init__(self, mech: Mechanism, phantom: Phantom, length: float | None = None, n_samples: int = 6000):
        self.mech, self.phantom, self.length = mech, phantom, length
        self.shank_below = -30.0  # the phantom's knee ends about 30 mm below its femur frame's origin
        self.width = float(np.ptp(np.asarray(phantom.femur.vertices)[:, 2]))  # medio-lateral (z)
        self._cache = {}
        meshes = [m for m, _ in phantom.skin_parts(np.eye(4), np.eye(4) if mech.has_pf else None, length)]
        self._setup(meshes, n_samples)

    def _setup(self, meshes, n_samples: int) -> None:
        """The parts' ray-casting scenes and surface samples (each in its part's own frame)."""
        area = sum(m.area for m in meshes)
        self._queries, self._local, self._faces = [], [], []
        for i, m in enumerate(meshes):
            pts, face = sample_surface(m, max(int(round(n_samples * m.area / area)), 50), seed=i)
            self._queries.append(SurfaceQuery.of(m))
            self._local.append((pts, m.face_normals[face]))
            self._faces.append(face)

    def _queries_at(self, alpha: float) -> list:
        """The parts' queries at ``alpha`` (rigid parts: the same every angle)."""
        return self._queries

    def _local_at(self, alpha: float) -> list:
        """The parts' samples and normals in their own frames at ``alpha`` (rigid parts: fixed)."""
        return self._local

    def _poses(self, alpha: float):
        tf, pf = self.mech.motion_at(np.array([alpha]))
        parts = self.phantom.skin_parts(joint_to_pose(tf[0]), joint_to_pose(pf[0]) if self.mech.has_pf else None,
                                        self.length)
        return [T for _, T in parts]

    def at(self, alpha: float) -> PosedSkin:
        """The posed skin's signed-distance query."""
        key = round(float(alpha), 6)
        if key not in self._cache:
            poses = self._poses(alpha)
            self._cache[key] = PosedSkin(list(zip(self._queries_at(alpha), poses)))
        return self._cache[key]

    def samples(self, alpha: float) -> tuple[np.ndarray, np.ndarray, cKDTree]:
        """Points spread over the posed skin (area-weighted, seeded: the same every call; the parts'
        samples that fall inside another part are dropped), their normals and a k-d tree of them."""
        key = ("s", round(float(alpha), 6))
        if key not in self._cache:
            skin = self.at(alpha)
            pts, nrm, owner = [], [], []
            for i, ((p, n), (_, T)) in enumerate(zip(self._local_at(alpha), skin.parts)):
                pts.append(transform_points(T, p))
                nrm.append(n @ T[:3, :3].T)
                owner.append(np.full(len(p), i))
            pts, nrm, owner = np.vstack(pts), np.vstack(nrm), np.concatenate(owner)
            keep = np.ones(len(pts), bool)
            for i in range(len(skin.parts)):
                other = np.nonzero(owner != i)[0]
                keep[other[skin.inside_part(i, pts[other])]] = False
            self._cache[key] = (pts[keep], nrm[keep], cKDTree(pts[keep]))
        return self._cache[key]


class SubjectSkinModel(SkinModel):
    """A subject's own skin, scanned at one pose, posed at any flexion by a prior (cached by angle).

    The skin is cut into three overlapping solids around the joint line ``y0`` (femur frame), with ``w``
    the femur's width: the thigh above ``y0 + 0.25 w`` moves with the femur (it stays), the shank below
    ``y0 - 0.25 w`` moves rigidly with the tibia along ``path`` (the prior's tibia poses, anchored at the
    scan), and the knee band between them blends the two: each of its vertices moves by the femur's and
    the tibia's motions weighted by a smooth step in its height (linear blend skinning). The knee band is
    rebuilt for each flexion; the thigh and the shank only move. Part order as the phantom's: thigh, shank
    (:data:`SHANK`), knee.

    ``anatomy``: a :class:`knee.models.fem.anatomy.KneeAnatomy`; ``path(alpha) -> (4, 4)``: the tibia's
    pose in the femur frame at flexion ``alpha`` (rad)."""

    BLEND = 0.25    # half height of the blended band, in femur widths
    OVERLAP = 0.08  # how far each solid reaches past its neighbour's boundary, in femur widths

    def __init__(self, mech: Mechanism, anatomy, path, n_samples: int = 6000):
        self.mech, self.path = mech, path
        self._cache = {}
        y0, w = anatomy.joint_y, anatomy.width
        self.width = float(w)
        self.shank_below = y0 - 0.05 * w
        self.T_scan = np.asarray(anatomy.tibia_pose, float)
        up, b, o = np.array([0.0, 1.0, 0.0]), self.BLEND * w, self.OVERLAP * w
        skin = anatomy.skin
        lo, hi = float(skin.vertices[:, 1].min()), float(skin.vertices[:, 1].max())
        if not (lo < y0 - b - o and hi > y0 + b + o):
            raise KneeInputError("the skin does not reach far enough above and below the joint line to pose it")
        thigh = clip_to_slab(skin, np.array([0.0, y0 + b - o, 0.0]), up, 0.0, hi - (y0 + b - o) + 1.0)
        shank = clip_to_slab(skin, np.array([0.0, y0 - b + o, 0.0]), up, (y0 - b + o) - lo + 1.0, 0.0)
        knee = clip_to_slab(skin, np.array([0.0, y0, 0.0]), up, b + o, b + o)
        self.shank_at_scan = shank  # the shank's solid in the femur frame at the scan (:class:`ShankReplaced`)
        shank_in_tibia = shank.copy().apply_transform(invert_poses(self.T_scan))
        self._knee_rest = np.asarray(knee.vertices, float)
        self._knee_faces = np.asarray(knee.faces)
        t = np.clip((y0 + b - self._knee_rest[:, 1]) / (2 * b), 0.0, 1.0)
        self._weight = t * t * (3 - 2 * t)  # the tibia's share: 0 above the band, 1 below, smooth between
        self._setup([thigh, shank_in_tibia, knee], n_samples)
        # the knee band's samples as barycentric coordinates of their faces, to follow the deformation
        pts, face = self._local[2][0], self._faces[2]
        tri = self._knee_rest[self._knee_faces[face]]
        self._bary = trimesh.triangles.points_to_barycentric(tri, pts)

    def _motion(self, alpha: float) -> np.ndarray:
        """The tibia's motion from the scan to ``alpha`` (4, 4), femur frame."""
        return np.asarray(self.path(alpha), float) @ invert_poses(self.T_scan)

    def _knee_vertices(self, alpha: float) -> np.ndarray:
        key = ("v", round(float(alpha), 6))
        if key not in self._cache:
            moved = transform_points(self._motion(alpha), self._knee_rest)
            w = self._weight[:, None]
            self._cache[key] = (1.0 - w) * self._knee_rest + w * moved
        return self._cache[key]

    def _poses(self, alpha: float):
        return [np.eye(4), np.asarray(self.path(alpha), float), np.eye(4)]

    def _queries_at(self, alpha: float) -> list:
        return [self._queries[0], self._queries[1], SurfaceQuery(self._knee_vertices(alpha), self._knee_faces)]

    def _local_at(self, alpha: float) -> list:
        v = self._knee_vertices(alpha)
        tri = v[self._knee_faces[self._faces[2]]]
        pts = np.einsum("pk,pkj->pj", self._bary, tri)
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        return [self._local[0], self._local[1], (pts, nrm)]


class ShankReplaced:
    """A skin model's parts at one flexion ``alpha`` with the shank's surface replaced by ``shank`` (a
    :class:`SurfaceQuery` in the tibia's frame, which the tibia then carries rigidly), the thigh and the knee
    as ``skin`` poses them: what :func:`correct_tibia` asks of a skin model (``width`` and ``at(alpha)``),
    so that the tibia's correction can be made against a shank posed otherwise (by the association model:
    :func:`knee.models.fem.methods.fem_posed_shank`). The other parts only decide which points are the
    shank's."""

    def __init__(self, skin: SkinModel, alpha: float, shank: SurfaceQuery):
        self.width = skin.width
        self.alpha = float(alpha)
        parts = list(skin.at(alpha).parts)
        parts[SHANK] = (shank, parts[SHANK][1])
        self._posed = PosedSkin(parts)

    def at(self, alpha: float) -> PosedSkin:
        if round(float(alpha), 6) != round(self.alpha, 6):
            raise ValueError(f"this skin's shank was replaced at {math.degrees(self.alpha):.2f} deg, not "
                             f"{math.degrees(alpha):.2f} deg")
        return self._posed


def _checked_cloud(points) -> np.ndarray:
    """The cloud as (P, 3) floats, or a :class:`KneeInputError` saying what is wrong with it: its shape, too
    few points, or points that are not finite (counted)."""
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise KneeInputError(f"the point cloud must be (P, 3) points, got an array of shape {pts.shape}")
    bad = int(np.count_nonzero(~np.all(np.isfinite(pts), axis=1)))
    if len(pts) < MIN_POINTS or bad:
        raise KneeInputError(f"the point cloud needs at least {MIN_POINTS} points, all finite, got {len(pts)}"
                             + (f" ({bad} not finite)" if bad else ""))
    return pts


def _score(skin_model: SkinModel, alpha, points, init, iterations: int = 30, exact: bool = True, icp_points=None):
    """ICP of the points (or of ``icp_points``, a subsample of them) onto the skin posed at ``alpha``; the
    score is the trimmed RMS of all the points' distances to the skin: exact (the posed parts' signed
    distances), or with ``exact=False`` (the coarse scan, which only ranks candidates 10 deg apart) to the
    tangent plane of each point's nearest skin sample, about four times cheaper (the samples are about 5 mm
    apart on a skin of 60 mm radius: the plane is within 0.2 mm of the surface there)."""
    samples, normals, tree = skin_model.samples(alpha)
    T, fitness, _ = icp(points if icp_points is None else icp_points, samples, init=init, max_distance=15.0,
                        iterations=iterations, target_normals=normals)
    p = transform_points(T, points)
    if exact:
        d = np.abs(skin_model.at(alpha).signed_distance(p))
    else:
        _, j = tree.query(p)
        d = np.abs(np.einsum("ij,ij->i", p - samples[j], normals[j]))
    trimmed = np.sort(d)[: int(0.9 * d.size)]  # robust to outliers and unseen parts
    return float(np.sqrt(np.mean(trimmed ** 2))), T, float(np.mean(d < 5.0))


def estimate_flexion(skin: SkinModel, points, T_init=None, coarse_step_deg: float = 10.0,
                     tol_deg: float = 0.5) -> FlexionEstimate:
    """Estimate the flexion and the rigid pose of the knee from a point cloud (P, 3), world frame, by
    registering the skin posed by its prior (``skin``: a :class:`SkinModel` of a phantom or a
    :class:`SubjectSkinModel` of a subject's own skin) at candidate angles.

    ``T_init``: a first guess of the world -> model transform (default identity: the world is roughly the
    femur frame, as after the thigh registration of the standard case).

    Raises :class:`KneeInputError` when the cloud is empty or too small, or covers too little of the shank
    (below the knee) to see the flexion.
    """
    pts = _checked_cloud(points)
    init = np.eye(4) if T_init is None else np.asarray(T_init, float)
    pts = voxel_downsample(pts, VOXEL_MM)
    local = transform_points(init, pts)
    sk = skin
    lo, hi = sk.mech.assembly_range
    a0, a1 = max(lo, math.radians(-5.0)), min(hi, math.radians(150.0))
    # points of the shank: below the knee in the femur frame; a knee flexed to about 90 deg or more carries
    # its shank behind the knee rather than below it, so failing that, the points the shank's own skin
    # explains at some flexion of the prior's range (every 30 deg)
    shank = int(np.sum(local[:, 1] < sk.shank_below))
    if shank < MIN_SHANK_POINTS:
        shank = max(shank, max(seen_shank_points(sk.at(a), local, within_mm=SHANK_SEARCH_MM)
                               for a in np.arange(a0, a1 + 1e-9, math.radians(30.0))))
    if shank < MIN_SHANK_POINTS:
        raise KneeInputError(f"the point cloud covers too little of the shank to estimate flexion ({shank} points "
                             f"below the knee or on the shank's skin at any flexion; at least {MIN_SHANK_POINTS} "
                             "needed)")
    grid = np.arange(a0, a1 + 1e-9, math.radians(coarse_step_deg))
    scores = {}
    best = (np.inf, None, None, 0.0)
    few = seeded_subsample(pts, COARSE_ICP_POINTS)  # one subsample for every candidate
    for a in grid:  # a coarse scan: a handful of ICPs (each vectorised inside open3d), each scored on every point
        s, T, inl = _score(sk, a, pts, init, iterations=COARSE_ICP_ITERATIONS, exact=False, icp_points=few)
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
    if f(best[1]) < f(a):  # the coarse scan's best, scored the same way as the refinement
        a = best[1]
    s, T, inl = cache[a]
    warnings = []
    if min(abs(a - lo), abs(a - hi)) < math.radians(1.0) or min(abs(a - a0), abs(a - a1)) < math.radians(1.0):
        warnings.append(f"the best fit lies at the end of the prior's assembly range ({math.degrees(lo):.1f} to "
                        f"{math.degrees(hi):.1f} deg): the knee may be outside what the prior allows; the "
                        "estimate is a bound, not a measurement")
    if contrast < 1.02:
        warnings.append(f"the fit hardly changes with flexion (second-best / best score {contrast:.3f}): the view "
                        "shows too little of the flexion")
    if s > POOR_FIT_RMS_MM:
        warnings.append(f"the subject's skin fits the points poorly ({s:.1f} mm RMS over the nearest 90 %, "
                        f"{100 * inl:.0f} % within 5 mm; a view of the scanned skin fits within about "
                        f"{POOR_FIT_RMS_MM:.0f} mm): the points may not show this skin as scanned (the intrinsics, "
                        "the depth scale, the side, clothing), or the registration settled in a wrong place; the "
                        "flexion estimate is not reliable, and the result may not be")
    shank = seen_shank_points(sk.at(a), transform_points(T, pts))
    if shank < MIN_SEEN_SHANK:
        warnings.append(f"the shank is hardly seen ({shank} depth points on it, after {VOXEL_MM:.0f} mm voxels): the "
                        "flexion shows only through the knee's outline, so the estimate can be far off (on the "
                        f"honest benchmark's views that warn so, {UNSEEN_FLEXION_ERROR_DEG[0]:.0f} deg median and up "
                        f"to {UNSEEN_FLEXION_ERROR_DEG[1]:.0f}; e.g. a camera in front of a knee flexed beyond about "
                        "50 deg)")
    return FlexionEstimate(flexion=float(a), T_world_model=invert_poses(T), rms=s, inliers=inl, scores=scores,
                           contrast=float(contrast), warnings=warnings, skin=sk, shank_points=shank)


#: Flexions (deg) at which a rough registration tries the prior's posed skin.
ROUGH_FLEXIONS_DEG = (15.0, 45.0, 75.0, 105.0)
#: The ICP reaches (mm) a rough registration refines each start with: a wide schedule and a narrow one,
#: the better match kept. Either alone fails on some partial views (measured on the honest benchmark's
#: cases: the wide one pulled a Visible Human knee at 60 deg seen from the paper's placement 34 deg and
#: 40 mm off, leaving 99 of its 2300 shank points below the knee; the narrow one left two phantom views at
#: 30 deg 19 deg and 22-26 mm off, where the wide one lands within 9 deg and 8 mm).
ROUGH_REACHES_MM = ((60.0, 30.0, 15.0), (30.0, 15.0))
#: How far (deg, mm) a rough guess of the knee's pose may be off (``knee fem --initial-pose``, the honest
#: benchmark's rough poses: 15-30 deg, 25-50 mm).
ROUGH_GUESS_WITHIN = (30.0, 50.0)
#: A match from a rough guess that holds fewer than this share of the points within 5 mm of the skin is no
#: match: the global search is tried as well (the share under which the methods take the points not to
#: show the knee, :data:`knee.models.fem.methods.MIN_REGISTERED`). A guess far beyond its bounds (the knee
#: turned 120 deg and 300 mm away) can leave the ICP where it started, with none of the points near the
#: skin and so within the guess's bounds.
ROUGH_LOCAL_HELD = 0.3
#: Most points (after the 4 mm voxels) a rough registration searches with; a larger cloud is searched with
#: a random (seeded) subsample of this many, its best match then scored on all of them. A view of a knee
#: holds fewer (the honest benchmark's 300 depth images: 3,000-7,000); a frame that also shows a table or a
#: wall holds many more (32,000 for a table under a leg), and each ICP's cost grows with them.
ROUGH_MAX_POINTS = 10_000


#: The global search (no rough pose): rotations spread over all of them, about 30 deg apart (the long axis
#: pointed along each of ``GLOBAL_DIRECTIONS`` directions spread over the sphere, then turned about it in
#: ``GLOBAL_SPINS`` steps), each tried at every candidate flexion as the camera would see the skin posed so.
GLOBAL_DIRECTIONS, GLOBAL_SPINS = 32, 12
#: How many of the cloud's thinned points score each rotation, the translation steps that move it onto the
#: skin (mm reach), how many starts per flexion are kept and how many are refined by ICP in all.
GLOBAL_POINTS, GLOBAL_REACHES_MM = 200, (30.0, 30.0, 30.0)
GLOBAL_KEEP, GLOBAL_REFINED = 6, 12
#: The share of the rotations a global search's starts carry on after their first mean shift: those whose
#: points then lie nearest the skin (each point's distance capped at the next reach). Measured on the honest
#: benchmark's seed 0 without the rough poses: a quarter gives the same match on all 60 views as all of
#: them, the starts' CPU time 1.9 s down to 1.1 s.
GLOBAL_PRUNED = 0.25
#: How many next best matches apart from the best a global search reports (:class:`RoughRegistration`).
GLOBAL_ALTERNATIVES = 2
#: A cloud's separate pieces for the global search: points joined where they lie within ``PIECE_GAP_MM``
#: (2.5 of the 4 mm voxels); a cloud whose largest piece holds less than ``ONE_PIECE`` of it is searched also
#: piece by piece, each piece holding at least ``PIECE_SHARE`` of it. Where the largest piece holds more,
#: the rest moves the cloud's centre off it by at most a fifth of their distance (30 mm for bits 150 mm
#: away), within the starts' mean shifts (the synthetic frame with a table: its leg 88 % of what the table
#: leaves, the rest its edges' bits).
PIECE_GAP_MM, ONE_PIECE, PIECE_SHARE = 10.0, 0.8, 0.15
#: How many steps (each half the candidate flexions' spacing, 15 deg) either side a global search follows
#: each of its best distinct matches in flexion (:func:`register_roughly`). Measured on the honest
#: benchmark's seed 0 without the rough poses: one step finds the knee in all 60 views at 3.9 s CPU a view
#: (median), three steps in all 60 too at 5.0 s.
FOLLOW_STEPS = 1
#: Most points a global search's starts are refined with (a random, seeded subsample; the matches are scored,
#: followed in flexion and compared on all of the cloud's points). Measured on the honest benchmark's seeds 0
#: and 1 without the rough poses (views of 3,000-7,000 points): 2,000 find the knee in all 120 views as every
#: point does, each match within 0.6 deg of every point's but two (one 5.6 mm further along, one closer to the
#: truth), the search's CPU time 3.65 -> 2.41 s (seed 0) and 3.55 -> 2.50 s (seed 1) a view; 1,500 left a
#: lateral view on a poorer match (75 % of its points within 5 mm against 85 %), 1,000 three.
GLOBAL_ICP_POINTS = 2000

#: Most points the rough registration's start from a guess is refined with (a random, seeded subsample, as
#: the global search's starts: :data:`GLOBAL_ICP_POINTS`); its matches are scored on all of the cloud's
#: points. The guess's 20 ICPs (four flexions, two schedules) had taken every point of a view (3,000-7,000
#: after the 4 mm voxels), a fifth of method (iii)'s time; the flexion estimate then registers all of them
#: again from the match. Measured on the honest benchmark's seeds 0-2 (BENCHMARKS.md): the same footprint
#: errors per case (median change -0.001 to -0.004 mm), 0.89 of the case's time.
ROUGH_ICP_POINTS = GLOBAL_ICP_POINTS


@functools.lru_cache(maxsize=4)
def _spread_rotations(n_directions: int = GLOBAL_DIRECTIONS, n_spins: int = GLOBAL_SPINS) -> np.ndarray:
    """Rotations (n, 3, 3) spread over all of them: z taken to each of ``n_directions`` directions on a
    Fibonacci sphere, then turned about it in ``n_spins`` equal steps."""
    i = np.arange(n_directions) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * i / n_directions), math.pi * (1.0 + math.sqrt(5.0)) * i
    dirs = np.column_stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)])
    z = np.array([0.0, 0.0, 1.0])
    out = []
    for u in dirs:
        axis = np.cross(z, u)
        n = np.linalg.norm(axis)
        base = Rotation.from_rotvec(axis / n * math.atan2(n, z @ u)) if n > 1e-9 else \
            Rotation.from_rotvec([math.pi, 0.0, 0.0] if u[2] < 0 else [0.0, 0.0, 0.0])
        spins = Rotation.from_rotvec(np.outer(np.arange(n_spins) * 2.0 * math.pi / n_spins, u))
        out.append((spins * base).as_matrix())
    R = np.concatenate(out)
    R.flags.writeable = False  # cached: shared by every search
    return R


def view_starts(skin: SkinModel, points, flexions, viewpoint=(0.0, 0.0, 0.0)) -> list[tuple[float, float, np.ndarray]]:
    """Starts for placing a one-sided view (points (P, 3) thinned, seen from ``viewpoint``: the camera's
    position in the points' frame, the origin for a depth image's points) on the skin posed at each of
    ``flexions`` (rad) without any guess of its pose. For each of the spread rotations
    (:func:`_spread_rotations`) the camera's line of sight to the cloud is turned into the model; the cloud's
    centre goes to the centre of the skin samples that face that line (what such a camera sees), then moves
    onto the skin by one mean shift of :data:`GLOBAL_POINTS` of its points towards their nearest samples
    per reach of :data:`GLOBAL_REACHES_MM` (after the first, only the :data:`GLOBAL_PRUNED` share nearest the
    skin carry on); the share of those points within 8 mm scores it.
    Vectorised over the rotations. Returns the :data:`GLOBAL_KEEP` best per flexion as (score, flexion,
    T (4, 4) cloud to model), best first. Measured on the honest benchmark's seed 0, without the rough poses
    (the rough registration alone, its match within 30 deg and 40 mm at the knee of the true femur's): shape
    features (FPFH + RANSAC) found the knee in 45 of the 60 views, turning a near-round leg over in most of
    the rest; these starts in 59 (the one miss: a frontal view at 30 deg whose turned-over match holds more
    of its points at 15 deg, 60.5 %, than the right one, 59.8 %), and in all 60 once the best matches are
    looked at again between the candidate flexions (:func:`register_roughly`). Cheaper searches measured on
    the same views: 6 starts refined instead of :data:`GLOBAL_REFINED` missed 4 more, 100 points 2 more, two
    mean shifts 1 more; 9 starts refined none more, for 0.4 s of 3.1 s."""
    pts = np.asarray(points, float)
    sub = seeded_subsample(pts, GLOBAL_POINTS)
    centre = sub.mean(axis=0)
    sight = centre - np.asarray(viewpoint, float)
    sight /= max(np.linalg.norm(sight), 1e-9)
    R = _spread_rotations()
    local = np.einsum("nij,pj->npi", R, sub - centre)            # (n, p, 3) each rotation's cloud, centred
    out = []
    for a in flexions:
        samples, normals, tree = skin.samples(a)
        facing = (normals @ (R @ sight).T) < 0.0                 # (S, n) the samples each rotation's camera faces
        seen = np.maximum(facing.sum(axis=0), 1)[:, None]
        X = local + ((facing.T.astype(float) @ samples) / seen)[:, None, :]
        live = np.arange(len(R))
        for i, reach in enumerate(GLOBAL_REACHES_MM):
            d, j = tree.query(X.reshape(-1, 3), distance_upper_bound=reach, workers=-1)
            near = np.isfinite(d).reshape(X.shape[:2])
            if i == 1 and GLOBAL_PRUNED < 1.0:  # after the first shift: the rotations nearest the skin carry on
                d, j = d.reshape(X.shape[:2]), j.reshape(X.shape[:2])
                keep = np.argsort(np.where(near, d, reach).mean(axis=1), kind="stable")[
                    :max(GLOBAL_KEEP, int(GLOBAL_PRUNED * len(live)))]
                live, X, near, j = live[keep], X[keep], near[keep], j[keep]
            pull = np.where(near[..., None], samples[np.where(near, j.reshape(X.shape[:2]), 0)] - X, 0.0)
            X = X + (pull.sum(axis=1) / np.maximum(near.sum(axis=1), 1)[:, None])[:, None, :]
        d, _ = tree.query(X.reshape(-1, 3), workers=-1)
        score = np.mean(d.reshape(X.shape[:2]) < 8.0, axis=1)
        t = X.mean(axis=1) - R[live] @ centre
        for k in np.argsort(-score, kind="stable")[:GLOBAL_KEEP]:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R[live[k]], t[k]
            out.append((float(score[k]), float(a), T))
    return sorted(out, key=lambda c: -c[0])


@dataclass
class RoughRegistration:
    """A first placement of a point cloud on the model: ``T_model_world`` (4, 4) taking the cloud's
    frame to the model's, the flexion (rad) of the posed skin it matched best, and the match: the
    fraction of points within 5 mm of that skin and their RMS distance (mm)."""

    T_model_world: np.ndarray
    flexion: float
    inliers: float
    rms: float
    #: from a global search: the next best matches that lie apart from this one (over 30 deg or 40 mm at the
    #: knee), best first, for a caller that can judge them better (:func:`knee.models.fem.methods.drop_background`)
    alternatives: list = field(default_factory=list, repr=False, compare=False)


#: How far apart (deg, mm at the knee) two matches of a global search must lie to count as different ones.
DISTINCT_MATCHES = (30.0, 40.0)


def placements_apart(skin: SkinModel, T1, T2) -> tuple[float, float]:
    """How far apart two placements (4, 4) are: the rotation between them (deg) and the motion of the knee's
    centre (mm; model frame, on the femur's axis where the shank begins)."""
    D = np.asarray(T1, float) @ invert_poses(np.asarray(T2, float))
    c = np.array([0.0, skin.shank_below, 0.0])
    return math.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()), float(np.linalg.norm(D[:3, :3] @ c + D[:3, 3] - c))


def register_roughly(skin: SkinModel, points, T_init=None, flexions_deg=ROUGH_FLEXIONS_DEG,
                     reaches_mm=ROUGH_REACHES_MM, guess_within=ROUGH_GUESS_WITHIN,
                     local_below: float | None = None, max_points: int | None = None,
                     viewpoint=(0.0, 0.0, 0.0)) -> RoughRegistration:
    """Place a point cloud (P, 3; its own frame, e.g. the camera's) on the model when its pose is known
    only roughly: from ``T_init`` (cloud to model, within ``guess_within`` = (deg, mm), about 30 deg and
    50 mm; refined with at most :data:`ROUGH_ICP_POINTS` of the points), or, without one, from a global
    search: rotations spread over all of them as a camera at ``viewpoint`` (the origin of a depth image's
    points) would see the skin (:func:`view_starts`, the best :data:`GLOBAL_REFINED` refined with at most
    :data:`GLOBAL_ICP_POINTS` of the points; a cloud in separate pieces, as two legs or a leg and a box are,
    searched also from each large piece, its starts refined with its own points: :data:`PIECE_GAP_MM`).

    Against the prior's skin posed at a few flexions (within the prior's range), each start is refined by
    ICP with each schedule of shrinking reaches in ``reaches_mm`` (:data:`ROUGH_REACHES_MM`; a global
    search's starts with the first, the widest, only); the best match (most points within 5 mm, then the
    lowest RMS) wins. A global search follows its best distinct matches :data:`FOLLOW_STEPS` steps of 15 deg
    either side in flexion (refined with the last schedule), each judged at its best: a view can hold as
    many points turned over as the right way round at a candidate flexion 15 deg off its own. Measured on
    the honest benchmark's seed 0 without the rough poses (60 views): the knee found in 59 of them by the
    starts refined with both schedules, as by these with the wide one alone, in all 60 once followed;
    shape features (FPFH + RANSAC, an earlier search) found 45 and added none to these starts.

    Where the best match from ``T_init`` lies further from it than twice what the guess allows (the knee's
    centre moved more than twice the mm, or turned more than twice the deg: a right match can lie beyond the
    guess's bounds by the rough match's own error, the candidate flexions being 30 deg apart), the ICP has
    left the guess's basin and the global search is tried as well, the better match kept (measured on the
    honest benchmark: a lateral view of the phantom at 45 deg, its guess 24 deg and 44 mm off, matched the
    skin at 15 deg flexion 122 mm away with 53 % of the points; the global starts found 86 %, 4 mm from the
    truth). A cloud of more than ``max_points`` (:data:`ROUGH_MAX_POINTS` unless given; after 4 mm voxels)
    is searched with a subsample of that many; the match it finds is scored on all of them. So is a match
    from ``T_init`` that holds fewer than :data:`ROUGH_LOCAL_HELD` of the points (no match at all: a guess
    far beyond its bounds can leave the ICP where it started, and so within them), unless ``local_below``
    is given. ``local_below``: where the match from ``T_init`` holds fewer than this share of the points within 5 mm,
    it is returned without the global starts (a caller that first leaves out the background, then tries
    them). Raises :class:`KneeInputError` when the cloud is too small."""
    every = voxel_downsample(_checked_cloud(points), VOXEL_MM)
    pts = seeded_subsample(every, ROUGH_MAX_POINTS if max_points is None else int(max_points))
    lo, hi = skin.mech.assembly_range
    cands = sorted({float(np.clip(math.radians(d), lo, hi)) for d in flexions_deg})

    def scored(T, a, points) -> RoughRegistration:
        d, _ = skin.samples(a)[2].query(transform_points(T, points))
        trimmed = np.sort(d)[: max(1, int(0.9 * d.size))]
        return RoughRegistration(T, a, float(np.mean(d < 5.0)), float(np.sqrt(np.mean(trimmed ** 2))))

    def refined(a, starts, schedules) -> list[RoughRegistration]:
        # each start (a transform, the points to refine it with)
        samples, normals, _ = skin.samples(a)
        out = []
        for T0, src in starts:
            for schedule in schedules:
                T = T0
                for reach in schedule:
                    T, _, _ = icp(src, samples, init=T, max_distance=reach, iterations=30, target_normals=normals)
                out.append(scored(T, a, pts))
        return out

    def distinct(matches, n):
        # the best n matches apart from each other (DISTINCT_MATCHES), best first
        out = []
        for m in sorted(matches, key=lambda m: (-m.inliers, m.rms)):
            if len(out) == n:
                break
            if all(max(np.subtract(placements_apart(skin, m.T_model_world, o.T_model_world), DISTINCT_MATCHES)) > 0
                   for o in out):
                out.append(m)
        return out

    def followed(m, step):
        # the match refined at the flexions up to FOLLOW_STEPS steps either side, each from the last (the last
        # schedule), and judged at its best
        best = m
        for sign in (-1.0, 1.0):
            cur = m
            for _ in range(FOLLOW_STEPS):
                if not lo < cur.flexion + sign * step * 0.5 < hi:
                    break
                a = float(np.clip(cur.flexion + sign * step, lo, hi))
                cur = refined(a, [(cur.T_model_world, pts)], reaches_mm[-1:])[0]
                if (cur.inliers, -cur.rms) > (best.inliers, -best.rms):
                    best = cur
        return best

    def search(starts_at, alternatives: int = 0, schedules=reaches_mm, examine: bool = False) -> RoughRegistration:
        top = distinct([m for a in cands for m in refined(a, starts_at(a), schedules)], 1 + alternatives)
        if examine and len(cands) > 1:
            # each distinct match followed in flexion, in steps of half the candidates' spacing, and judged at
            # its best: the candidates lie 30 deg apart, and a view of a knee flexed
            # between two of them can hold as many points turned over as the right way round at either
            # (measured: a frontal view at 30 deg, 60.5 % turned over against 59.8 % at 15 deg; 64 % against
            # 84 % at 30 deg)
            step = 0.5 * float(np.min(np.diff(cands)))
            top = distinct([followed(m, step) for m in top], 1 + alternatives)
        if pts is not every:
            top = [scored(m.T_model_world, m.flexion, every) for m in top]
        best = top[0]
        best.alternatives = top[1:]
        return best

    def global_starts():
        # rotations spread over all of them, each as the camera would see the skin (view_starts), from the
        # whole cloud and, where it falls into separate pieces (two legs, a leg and a box), from each large one:
        # the whole cloud's centre then lies between them, beyond the starts' mean shifts
        few = seeded_subsample(pts, GLOBAL_ICP_POINTS)
        top = [(a, T, few) for _, a, T in view_starts(skin, pts, cands, viewpoint)[:GLOBAL_REFINED]]
        pieces = connected_parts(pts, PIECE_GAP_MM)
        sizes = np.bincount(pieces)
        if sizes[0] < ONE_PIECE * len(pts):
            for k in np.nonzero(sizes >= PIECE_SHARE * len(pts))[0]:
                # a piece's starts refined with its own points (at most GLOBAL_ICP_POINTS; scored, as every
                # match, on all of the cloud's)
                piece = pts[pieces == k]
                few = seeded_subsample(piece, GLOBAL_ICP_POINTS)
                top += [(a, T, few) for _, a, T in view_starts(skin, piece, cands, viewpoint)[:GLOBAL_REFINED]]
        return lambda a: [(T, src) for b, T, src in top if b == a]

    def global_search() -> RoughRegistration:
        return search(global_starts(), GLOBAL_ALTERNATIVES, reaches_mm[:1], examine=True)

    if T_init is None:
        return global_search()
    T_init = np.asarray(T_init, float)
    few = seeded_subsample(pts, ROUGH_ICP_POINTS)  # one subsample for every candidate flexion
    best = search(lambda a: [(T_init, few)])
    # how far the match lies from the guess, as the guess's own bounds are stated: a rotation, and the
    # motion of the knee's centre (model frame: on the femur's axis at the joint line, where the shank begins)
    turned, moved = placements_apart(skin, best.T_model_world, T_init)
    poor = local_below is not None and best.inliers < local_below
    left = turned > 2.0 * guess_within[0] or moved > 2.0 * guess_within[1]
    if (left or (local_below is None and best.inliers < ROUGH_LOCAL_HELD)) and not poor:
        other = global_search()
        if (other.inliers, -other.rms) > (best.inliers, -best.rms):
            best = other
    return best


def seen_part_points(skin: PosedSkin, points_model, part: int, within_mm: float = 5.0) -> int:
    """How many points (model frame) lie on one part's own skin (:data:`THIGH`, :data:`SHANK`): within
    ``within_mm`` of it and nearer to it than to every other part of the posed skin."""
    d = np.abs(skin.part_distances(points_model))
    others = np.delete(d, part, axis=0).min(axis=0)
    return int(np.count_nonzero((d[part] < within_mm) & (d[part] < others)))


def seen_shank_points(skin: PosedSkin, points_model, within_mm: float = 5.0) -> int:
    """How many points (model frame) lie on the shank's own skin (:func:`seen_part_points`)."""
    return seen_part_points(skin, points_model, SHANK, within_mm)


def kinematic_estimate(mech: Mechanism, est: FlexionEstimate) -> tuple[np.ndarray, np.ndarray]:
    """Method (iv): world poses of femur and tibia from the mechanism at the estimated flexion."""
    tf, _ = mech.motion_at(np.array([est.flexion]))
    return est.T_world_model, est.T_world_model @ joint_to_pose(tf[0])


#: The prior's uncertainty about the tibia's pose relative to the femur (about 2 mm per link endpoint),
#: and the depth points' (noise plus skin-model mismatch); they weigh the shank correction.
TIBIA_PRIOR_MM = 2.0
TIBIA_PRIOR_DEG = 3.0
#: The prior's uncertainty about the tibia's turn about its own axis (its y) relative to the femur, wider than
#: about the other two axes: a mechanism fitted to a knee carries its axial rotation least well (measured
#: motion turns the tibia up to 8 deg more about its axis than the honest benchmark's priors do), and a real
#: shank shows it (the tibia's crest, the calf). Measured on the honest benchmark (BENCHMARKS.md, "The tibia's
#: turn about its axis weighed more loosely"): 3 -> 5 deg takes the Visible Human's relative axial error (mean)
#: from 1.6 to 0.6 deg under the mechanism's motion and from 2.5 to 1.2 deg under the measured motion on seeds
#: 0-4 (held out: 3.8 to 2.6 and 3.0 to 1.4 deg), its cases 0.04-0.05 mm better on average on every seed (held
#: out 0.00-0.24); on a round shank (the phantom's capsule) the points carry nothing about it and the prior
#: keeps its own (the phantom's cases within 0.01 mm).
TIBIA_PRIOR_AXIAL_DEG = 5.0
POINT_SD_MM = 2.0
#: The least sd (mm) a depth point is given when :func:`correct_tibia` takes it from the fit's own residuals
#: (``adapt_point_sd``, an option): about the depth noise that remains of a RealSense-like camera at 30-40 cm
#: in a 4 mm voxel's mean, so that a shank skin that happens to fit its patch of points closely is not trusted
#: beyond its sensor.
MIN_POINT_SD_MM = 0.5
#: How far (in femoral widths) a skin model's error stays alike over the skin: a muscle's bulge, a fat pad,
#: the skin flattened over a tendon. Points within it err together, so a shank seen by N depth points (4 mm
#: voxels) tells what about N voxel^2 / (pi l^2) independent ones would (:func:`effective_point_sd`).
ERROR_CORRELATION_WIDTHS = 0.25


def effective_point_sd(width_mm: float, point_sd_mm: float = POINT_SD_MM,
                       correlation_widths: float = ERROR_CORRELATION_WIDTHS) -> float:
    """The standard deviation (mm) to give each depth point (4 mm voxels) in a least-squares fit to a skin
    model whose error is correlated over ``correlation_widths`` of the knee's femoral width ``width_mm``:
    ``point_sd_mm`` inflated by sqrt(pi) l / voxel, so that N points weigh as the N voxel^2 / (pi l^2)
    independent patches they cover. Treated as independent, two thousand shank points let a skin mismatch
    of 1-2 mm outweigh the prior's 2 mm and slide the tibia 10-15 mm along its own axis, into the femur
    (measured on the honest benchmark's Visible Human)."""
    return float(point_sd_mm * math.sqrt(math.pi) * correlation_widths * width_mm / VOXEL_MM)


#: Fewest shank points to attempt the correction.
MIN_CORRECTION_POINTS = 200

#: What the warnings of a hardly seen shank say the flexion's error can be (deg: median, largest), as measured:
#: method (iii) on the honest benchmark's ten seeds, the 18 views (the phantom's and the Visible Human's,
#: mostly frontal at 90 deg) whose run warned that the shank is hardly seen: 8.3 deg median, 17.7 at most,
#: none within 2 deg (BENCHMARKS.md). A figure of the views measured, not a bound.
UNSEEN_FLEXION_ERROR_DEG = (8.0, 18.0)
#: The band (mm) around the prior's shank skin whose points the tibia's correction starts from, before it
#: narrows to 8 mm: a tibia a few degrees off the prior's path moves the shank's skin 10-20 mm a hand's
#: breadth below the knee. Measured on the honest benchmark's 60 cases (method iii): 45 flexions within 2 deg
#: instead of 43, three Visible Human cases under a measured motion 2-4 mm better, the others unchanged.
WIDE_BAND_MM = 20.0


def tibia_prior_weights(sigma_mm: float = TIBIA_PRIOR_MM, sigma_deg: float = TIBIA_PRIOR_DEG,
                        sigma_axial_deg: float | None = TIBIA_PRIOR_AXIAL_DEG) -> np.ndarray:
    """The inverse variances (6,) of the prior's Gaussian on a tibia correction ``xi`` (a rotation vector, rad,
    then a translation, mm, in the tibia's frame): ``sigma_deg`` about the tibia's x and z, ``sigma_axial_deg``
    about its own axis, y (None: ``sigma_deg``), ``sigma_mm`` along each axis. One definition for the
    methods' correction (:func:`correct_tibia`) and the benchmark's floor with the methods' prior."""
    axial = sigma_deg if sigma_axial_deg is None else sigma_axial_deg
    return np.array([math.radians(sigma_deg) ** -2, math.radians(axial) ** -2, math.radians(sigma_deg) ** -2]
                    + [float(sigma_mm) ** -2] * 3)


@dataclass
class TibiaCorrection:
    """The tibia's pose relative to the femur (model frame, (4, 4)) as the prior gives it (``T_prior``)
    and the correction found from the shank's depth points, ``xi`` (6,): a rotation vector (rad) and a
    translation (mm) in the tibia's frame, ``T = T_prior @ small_pose(xi)``. Also the shank points used and
    their RMS distance to the shank before and after (mm); ``note`` says why no correction was made, when
    none was."""

    T_prior: np.ndarray
    xi: np.ndarray
    points: int
    rms_before: float
    rms_after: float
    note: str | None = None
    #: The Laplace covariance (6, 6) of ``xi`` at the solution (rad^2, mm^2; the rotation vector first): the
    #: inverse of the fit's normal matrix there, the points' term with the sd they were weighed by and the
    #: prior's. None where no correction was made.
    cov: np.ndarray | None = None

    @property
    def applied(self) -> bool:
        return self.note is None

    @property
    def T(self) -> np.ndarray:
        return self.T_prior @ small_pose(self.xi)

    @property
    def rotation_deg(self) -> np.ndarray:
        return np.degrees(self.xi[:3])

    @property
    def translation_mm(self) -> np.ndarray:
        return self.xi[3:]


def right_jacobian(w) -> np.ndarray:
    """The right Jacobian (3, 3) of the rotation vector ``w``: R(w + dw) = R(w) exp(J_r(w) dw) to first order."""
    th = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-8:
        return np.eye(3) - 0.5 * K
    return np.eye(3) - (1.0 - math.cos(th)) / th ** 2 * K + (th - math.sin(th)) / th ** 3 * K @ K


def small_pose(xi) -> np.ndarray:
    """(4, 4) pose from a rotation vector (rad) and a translation: ``xi`` (6,)."""
    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix()
    D[:3, 3] = xi[3:]
    return D


def correct_tibia(skin: SkinModel, points_model, alpha: float, sigma_mm: float = TIBIA_PRIOR_MM, sigma_deg: float = TIBIA_PRIOR_DEG,
                  point_sd_mm: float | None = None, band_mm: float = 8.0, iterations: int = 20,
                  wide_band_mm: float | None = WIDE_BAND_MM, wide_iterations: int = 5,
                  sigma_axial_deg: float | None = TIBIA_PRIOR_AXIAL_DEG, adapt_point_sd: bool = False) -> TibiaCorrection:
    """Move the tibia off the prior's path as far as the shank's depth points show, and no further.

    The mechanism at ``alpha`` places the tibia (relative to the femur) only as well as its parameters
    (about 2 mm per link endpoint); the skin around the shank, seen by the camera, shows where the shank
    is. A maximum a posteriori estimate of the tibia's pose correction ``D`` (``T = T_prior @ D``, in the
    tibia's frame): Gauss-Newton on the points' point-to-plane distances to the shank's skin (sd
    ``point_sd_mm``; None: :func:`effective_point_sd` of the skin's width, the skin model's error being
    alike over a quarter of it) plus the prior's Gaussian (sd ``sigma_mm`` per translation, ``sigma_deg`` per
    rotation; ``sigma_axial_deg`` about the shank's own axis, the tibia's y, :data:`TIBIA_PRIOR_AXIAL_DEG` by
    default, None: ``sigma_deg``). That
    axial rotation is estimated as the others: a real shank is not a surface of revolution (the tibia's
    crest, the calf), and where its skin is one (a phantom's capsule) the points carry nothing about it and
    the prior keeps its own. Measured on the honest benchmark's 60 cases (method iii): the Visible Human's
    relative axial rotation 3.3 -> 1.9 deg off (median, 0-1 mm skin mismatch), its tibia's footprints 2.44
    -> 2.00 mm, the phantom's unchanged (BENCHMARKS.md).

    ``points_model`` (P, 3): the depth points in the model (femur) frame, the thigh registered. Points are
    used when within ``band_mm`` of the shank's skin and at least 2 mm closer to it than to the thigh, the
    knee or the patella; in the first ``wide_iterations`` within ``wide_band_mm`` (:data:`WIDE_BAND_MM`;
    None: the narrow band throughout), so that a shank further off the prior's path than the narrow band
    is drawn in before the band narrows. With fewer than :data:`MIN_CORRECTION_POINTS` such points the
    prior's pose is kept (stated in ``note``).

    ``adapt_point_sd`` (with ``point_sd_mm`` None; off by default): the points' sd is :data:`POINT_SD_MM` only
    as a bound. Once the fit has converged with it, the RMS of its residuals is taken as the sd instead where
    smaller (not below :data:`MIN_POINT_SD_MM`), inflated for the error's correlation as before, and the fit
    goes on from where it was: a shank whose skin the model matches closely moves the tibia further from the
    prior's path. Not the default: the residuals show the skin model's error only where the pose cannot take
    it up, not the part that shifts the shank as a whole. Measured (BENCHMARKS.md, "The shank's points weighed
    by their own residuals"): on the honest benchmark's phantom and Visible Human sets it lowers (iii)'s median
    footprint error at 0-1 mm skin mismatch (2.10 -> 1.98 mm on seeds 0-4, 2.32 -> 2.24 on the held-out
    seeds 5-9), and on lenhart2015's bones under the Visible Human's carried skin it raises it (five seeds 1.95
    -> 2.03 mm, 85 of 150 cases worse and 34 better): a close fit of the shank is not a skin model's error
    small in every anatomy."""
    adapt = point_sd_mm is None and adapt_point_sd
    if point_sd_mm is None:
        point_sd_mm = effective_point_sd(skin.width)
    posed = skin.at(alpha)
    T_prior = posed.parts[SHANK][1]
    shank = posed.parts[SHANK][0]
    pts = voxel_downsample(np.asarray(points_model, float), VOXEL_MM)
    # the other parts stay where the prior has them: they only decide which points belong to the shank
    others = np.delete(posed.part_distances(pts), SHANK, axis=0).min(axis=0)
    prior_w = tibia_prior_weights(sigma_mm, sigma_deg, sigma_axial_deg)
    near = BandDistances(shank, len(pts))  # most of the cloud (the thigh, the knee) is asked once

    def jacobian(xi, D, p, nrm):
        """How the points' residuals move with ``xi`` (P, 6), at the correction ``xi`` (``D`` its pose) and
        the points ``p`` in the tibia's current frame with their skin normals ``nrm``."""
        return np.hstack([-np.cross(p, nrm) @ right_jacobian(xi[:3]), -nrm @ D[:3, :3].T])

    def fit(xi, sd, first_wide):
        """Gauss-Newton from ``xi`` with each point's sd ``sd``; the first ``first_wide`` iterations in the
        wide band. Returns xi, the points used in the last iteration (mask), their count and the RMS of the
        first iteration's residuals (nan when too few points were seen)."""
        D, first, n, sel = small_pose(xi), float("nan"), 0, np.zeros(len(pts), bool)
        for it in range(iterations):
            wide = wide_band_mm is not None and it < first_wide
            band = wide_band_mm if wide else band_mm
            local = transform_points(invert_poses(T_prior @ D), pts)
            d = near.within(local, band)
            sel = (np.abs(d) < band) & (d < others - 2.0)
            n = int(sel.sum())
            if n < MIN_CORRECTION_POINTS:
                break
            p = local[sel]
            c, nrm = shank.closest(p)
            r = np.einsum("ij,ij->i", p - c, nrm)
            if it == 0:
                first = float(np.sqrt(np.mean(r ** 2)))
            # a change dxi of the rotation vector turns the tibia by dw = J_r(xi) dxi in its current frame (the
            # rotation's right Jacobian) and one of the translation moves it by R^T dt there: a point, in the
            # tibia's current frame, moves by -(dw x p) - R^T dt
            J = jacobian(xi, D, p, nrm)
            H = J.T @ J / sd ** 2 + np.diag(prior_w)
            g = J.T @ r / sd ** 2 + prior_w * xi
            dxi = -np.linalg.solve(H, g)
            xi = xi + dxi
            D = small_pose(xi)
            if np.abs(dxi).max() < 1e-5 and not wide:
                break
        return xi, sel, n, first

    def residual_rms(xi, sel):
        local = transform_points(invert_poses(T_prior @ small_pose(xi)), pts[sel])
        c, nrm = shank.closest(local)
        return float(np.sqrt(np.mean(np.einsum("ij,ij->i", local - c, nrm) ** 2)))

    def posterior(xi, sel, sd):
        """The Laplace covariance (6, 6) of ``xi`` at the solution: the inverse of the Gauss-Newton's normal
        matrix there (the points' term and the prior's)."""
        D = small_pose(xi)
        p = transform_points(invert_poses(T_prior @ D), pts[sel])
        _, nrm = shank.closest(p)
        J = jacobian(xi, D, p, nrm)
        return np.linalg.inv(J.T @ J / sd ** 2 + np.diag(prior_w))

    sd_used = point_sd_mm
    xi, sel, n, before = fit(np.zeros(6), point_sd_mm, wide_iterations)
    if adapt and n >= MIN_CORRECTION_POINTS:
        # the points' own sd, as far as their residuals show it, in place of the assumed one where smaller; the
        # fit goes on from where it converged (kept as it was should the narrow band then hold too few points)
        sd = min(POINT_SD_MM, max(residual_rms(xi, sel), MIN_POINT_SD_MM))
        if sd < POINT_SD_MM:
            xi2, sel2, n2, _ = fit(xi, effective_point_sd(skin.width, sd), 0)
            if n2 >= MIN_CORRECTION_POINTS:
                xi, sel, n, sd_used = xi2, sel2, n2, effective_point_sd(skin.width, sd)
    if n < MIN_CORRECTION_POINTS:
        return TibiaCorrection(T_prior, np.zeros(6), n, float("nan"), float("nan"),
                               note=f"the shank is seen by {n} depth points (at least {MIN_CORRECTION_POINTS} "
                                    "needed to correct the tibia's pose): the prior's pose is kept, so the flexion is the "
                                    "skin fit's alone and can be far off (on the honest benchmark's views that say so, "
                                    f"{UNSEEN_FLEXION_ERROR_DEG[0]:.0f} deg median and up to "
                                    f"{UNSEEN_FLEXION_ERROR_DEG[1]:.0f})")
    return TibiaCorrection(T_prior, xi, n, before, residual_rms(xi, sel), cov=posterior(xi, sel, sd_used))
