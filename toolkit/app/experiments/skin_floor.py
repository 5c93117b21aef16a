"""How far the skin mismatch alone moves a skin-based answer: a floor for the footprint errors at 1 and 2 mm
skin mismatch on a case set (:mod:`knee.app.experiments.case_set`).

Every pose of the case set is rendered from the paper's placement at each mismatch, the 0 mm image being the
truth's own flexed skin (its other model of the tissue, no random field). A case at 1 or 2 mm is registered
rigidly (point-to-plane ICP) onto its 0 mm twin, so the model is the truth's own skin and the only error is
the random field (and the two images' sensor noise). Two floors:

- ``separate``: each bone from its side of the knee, the femur by the points above the joint line in the true
  femur's frame, the tibia by those below it in the true tibia's frame (a perfect skin, no knowledge of how
  the bones move together);
- ``joined``: the whole cloud as one body, the tibia carried with the femur at its true relative pose (a
  perfect skin and perfect kinematics: only the leg's pose unknown);
- ``prior``: the whole cloud, the tibia's pose relative to the femur what the case set's kinematic prior
  gives at a free flexion, corrected as far as the points show it (a maximum a posteriori estimate with the
  prior's Gaussian, :func:`knee.models.prior.tibia_prior_weights`: ``TIBIA_PRIOR_MM`` per translation,
  ``TIBIA_PRIOR_DEG`` about the tibia's x and z and ``TIBIA_PRIOR_AXIAL_DEG`` about its own axis, as the
  methods' tibia correction weighs it; each point with the field's RMS as its error, inflated for the
  field's correlation as :func:`knee.models.prior.effective_point_sd` inflates it): a perfect skin and the
  kinematics the methods are given. This is the floor of a method that reads the bones from the skin
  with this prior, whatever its tissue model.

The separate registration's flexion error says the same of the flexion target.

A method that registers skin gets below the separate floor only with knowledge of how the bones move
together (a kinematic prior, which the joined floor has exactly and the prior floor as well as the case
set's prior knows it), and below the joined one only with knowledge of the field itself (its statistics);
they say how much of a method's error at a mismatch is the mismatch itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from knee.app.experiments.case_set import (FIELD_WIDTHS, case_points_cam, case_rng, check_truth_edge, iter_cases,
                                           placement_camera, read_case_set, seen_shank_points)
from knee.app.experiments.subject_cases import anatomy_targets
from knee.foundations.conventions import invert_poses, joint_to_pose, matrix_to_cardan, pose_to_joint, transform_points
from knee.foundations.errors import KneeInputError
from knee.foundations.pointclouds import backproject, icp, point_normals, voxel_downsample
from knee.foundations.surfaces import SurfaceQuery
from knee.models.evaluation import pose_errors
from knee.models.fem.depth import DepthNoise, render_depth
from knee.models.fem.tissue import TetTissue, smooth_surface_field
from knee.models.fem.methods import initialise_from_prior, quasi_static, register_to_posed_skin, tibia_path
from knee.models.fem.scene import FemSettings, build_knee_model
from knee.models.prior import (MIN_SEEN_SHANK, TIBIA_PRIOR_AXIAL_DEG, TIBIA_PRIOR_DEG, TIBIA_PRIOR_MM, VOXEL_MM,
                               effective_point_sd, right_jacobian, small_pose, tibia_prior_weights)

#: The ICP's reach (mm): the posed-skin registration's first reach, well beyond a 2 mm field.
FLOOR_REACH_MM = 15.0
FLOOR_ITERATIONS = 60
#: The prior floor's Gauss-Newton: at most so many steps, and done when no step moves more than the tolerance
#: (mm, rad).
PRIOR_FLOOR_ITERATIONS = 40
PRIOR_FLOOR_TOLERANCE = 1e-6
#: rad: the step of the flexion's finite difference along the prior's path.
PRIOR_FLOOR_DALPHA = 1e-4


@dataclass
class SkinFloorRow:
    """One case's floors: mean ACL/PCL footprint errors (mm; femur, tibia, and their mean) with the truth's
    own skin as the model, each bone registered from its side of the knee (``separate``) or the leg as one
    body (``joined``), and the flexion's error (deg; estimate less truth) of the separate registration (the
    joined one has the true flexion by construction)."""

    case: str
    anatomy: str
    family: str
    mismatch_mm: float
    separate_femur_mm: float
    separate_tibia_mm: float
    joined_femur_mm: float
    joined_tibia_mm: float
    separate_flexion_error_deg: float
    prior_femur_mm: float = float("nan")
    prior_tibia_mm: float = float("nan")
    prior_flexion_error_deg: float = float("nan")

    @property
    def separate_mm(self) -> float:
        return 0.5 * (self.separate_femur_mm + self.separate_tibia_mm)

    @property
    def joined_mm(self) -> float:
        return 0.5 * (self.joined_femur_mm + self.joined_tibia_mm)

    @property
    def prior_mm(self) -> float:
        return 0.5 * (self.prior_femur_mm + self.prior_tibia_mm)


def _cloud(folder: Path, case: dict) -> np.ndarray:
    return voxel_downsample(case_points_cam(folder, case), VOXEL_MM)


def _register(points, clean, T_cam_bone) -> np.ndarray:
    """The bone's pose (bone frame to camera) a registration of the clean skin (carried by ``T_cam_bone``)
    onto ``points`` gives: the points in the true bone's frame registered onto the clean ones by E, the
    bone is at ``T_cam_bone @ inv(E)``."""
    to_bone = invert_poses(T_cam_bone)
    E, _, _ = icp(transform_points(to_bone, points), transform_points(to_bone, clean), max_distance=FLOOR_REACH_MM,
                  iterations=FLOOR_ITERATIONS)
    return T_cam_bone @ invert_poses(E)


def floor_poses(points, clean, T_cam_femur, T_cam_tibia, joint_y: float) -> dict:
    """The femur's and tibia's poses (4, 4; rest model coordinates to the camera) a rigid registration of a
    clean skin cloud ``clean`` (P, 3; camera frame, the bones at ``T_cam_femur``, ``T_cam_tibia``) onto
    ``points`` (Q, 3) gives: ``{"separate": (Tf, Tt), "joined": (Tf, Tt)}`` (see the module docstring).
    The sides of the knee are the model frame's joint line ``joint_y`` (mm) in each true bone's frame."""
    points, clean = np.asarray(points, float), np.asarray(clean, float)
    T_cam_femur, T_cam_tibia = np.asarray(T_cam_femur, float), np.asarray(T_cam_tibia, float)
    side = {}
    for bone, T, above in (("femur", T_cam_femur, True), ("tibia", T_cam_tibia, False)):
        def keep(p):
            y = transform_points(invert_poses(T), p)[:, 1]
            return p[(y > joint_y) if above else (y < joint_y)]
        side[bone] = _register(keep(points), keep(clean), T)
    Tf = _register(points, clean, T_cam_femur)
    return {"separate": (side["femur"], side["tibia"]),
            "joined": (Tf, Tf @ invert_poses(T_cam_femur) @ T_cam_tibia)}


def prior_floor_poses(points, clean, T_cam_femur, T_cam_tibia, joint_y: float, tibia_pose, path, point_sd_mm: float,
                      sigma_mm: float = TIBIA_PRIOR_MM, sigma_deg: float = TIBIA_PRIOR_DEG,
                      reach_mm: float = FLOOR_REACH_MM,
                      sigma_axial_deg: float | None = TIBIA_PRIOR_AXIAL_DEG) -> tuple[np.ndarray, np.ndarray, float]:
    """The femur's and tibia's poses (4, 4; rest model coordinates to the camera) and the flexion (rad) that a
    clean skin cloud ``clean`` (P, 3; camera frame, the bones at ``T_cam_femur``, ``T_cam_tibia``) matched to
    ``points`` (Q, 3) gives with a kinematic prior: the femur's pose free; the tibia's anatomical frame in the
    femur's ``path(alpha) @ small_pose(xi)``, ``path`` (n,) rad -> (n, 4, 4) the prior's poses along its
    flexion (:func:`knee.models.fem.methods.tibia_path`), ``alpha`` free and the correction ``xi`` (rotation
    vector, rad; translation, mm; in the tibia's frame) with the methods' Gaussian prior
    (:func:`knee.models.prior.tibia_prior_weights`: sd ``sigma_deg`` about the tibia's x and z,
    ``sigma_axial_deg`` about its own axis, ``sigma_mm`` per translation); the clean skin carried rigidly by each bone from its side of the
    knee (the model frame's joint line ``joint_y``, mm, in each true bone's frame; ``tibia_pose``: the
    tibia's frame in the femur's at the scan). The maximum a posteriori estimate, Gauss-Newton on the
    point-to-plane distances (each point's error ``point_sd_mm``) of each point's nearest clean point within
    ``reach_mm``, started from the true femur and the true flexion on the prior's path (a floor: the
    estimate's start is the answer's)."""
    points, clean = np.asarray(points, float), np.asarray(clean, float)
    Tf, T_cam_tibia = np.asarray(T_cam_femur, float).copy(), np.asarray(T_cam_tibia, float)
    A_true = T_cam_tibia @ np.asarray(tibia_pose, float)  # the tibia's anatomical frame to the camera
    side_f = transform_points(invert_poses(Tf), points)[:, 1] > joint_y
    side_t = transform_points(invert_poses(T_cam_tibia), points)[:, 1] < joint_y
    q_f, q_t = points[side_f], points[side_t]
    c_f = transform_points(invert_poses(Tf), clean)
    c_f = c_f[c_f[:, 1] > joint_y]
    c_t = transform_points(invert_poses(A_true), clean[transform_points(invert_poses(T_cam_tibia), clean)[:, 1] < joint_y])
    if min(len(q_f), len(q_t), len(c_f), len(c_t)) < 10:
        raise KneeInputError("the prior floor needs points on both sides of the knee (fewer than 10 on one side)")
    n_f, n_t = point_normals(c_f), point_normals(c_t)
    tree_f, tree_t = cKDTree(c_f), cKDTree(c_t)
    alpha = float(pose_to_joint(invert_poses(Tf) @ A_true)[0])
    xi = np.zeros(6)
    prior_w = tibia_prior_weights(sigma_mm, sigma_deg, sigma_axial_deg)

    def tibia_local(v, a, S):
        return transform_points(invert_poses(path(np.array([a]))[0] @ S), v)

    for _ in range(PRIOR_FLOOR_ITERATIONS):
        S = small_pose(xi)
        M = path(np.array([alpha]))[0] @ S
        v_f = transform_points(invert_poses(Tf), q_f)
        v_t = transform_points(invert_poses(Tf), q_t)
        u = transform_points(invert_poses(M), v_t)
        d_f, i_f = tree_f.query(v_f, distance_upper_bound=reach_mm)
        d_t, i_t = tree_t.query(u, distance_upper_bound=reach_mm)
        kf, kt = np.isfinite(d_f), np.isfinite(d_t)
        v_f, v_t, u = v_f[kf], v_t[kt], u[kt]
        nf, nt = n_f[i_f[kf]], n_t[i_t[kt]]
        r = np.r_[np.einsum("ij,ij->i", v_f - c_f[i_f[kf]], nf), np.einsum("ij,ij->i", u - c_t[i_t[kt]], nt)]
        # a femur step D (Tf <- Tf D) moves a point, in the femur's frame, by -(dw x v) - dt; a tibia point's
        # normal carried into the femur's frame is M_R n; the correction's step as in correct_tibia; the
        # flexion's by a finite difference along the path
        m = nt @ M[:3, :3].T
        du = (tibia_local(v_t, alpha + PRIOR_FLOOR_DALPHA, S) - u) / PRIOR_FLOOR_DALPHA
        J = np.zeros((len(r), 13))
        J[:len(v_f), :3], J[:len(v_f), 3:6] = -np.cross(v_f, nf), -nf
        J[len(v_f):, :3], J[len(v_f):, 3:6] = -np.cross(v_t, m), -m
        J[len(v_f):, 6:9] = -np.cross(u, nt) @ right_jacobian(xi[:3])
        J[len(v_f):, 9:12] = -nt @ S[:3, :3].T
        J[len(v_f):, 12] = np.einsum("ij,ij->i", du, nt)
        H = J.T @ J / point_sd_mm ** 2
        H[6:12, 6:12] += np.diag(prior_w)
        g = J.T @ r / point_sd_mm ** 2
        g[6:12] += prior_w * xi
        step = -np.linalg.solve(H, g)
        Tf = Tf @ small_pose(step[:6])
        xi = xi + step[6:12]
        alpha += float(step[12])
        if np.abs(step).max() < PRIOR_FLOOR_TOLERANCE:
            break
    A = Tf @ path(np.array([alpha]))[0] @ small_pose(xi)
    return Tf, A @ invert_poses(np.asarray(tibia_pose, float)), alpha


def _flexion_deg(T_cam_femur, T_cam_tibia, tibia_pose) -> float:
    """The Cardan flexion (deg) of the tibia relative to the femur, both posed in the camera's frame (rest
    model coordinates to the camera; ``tibia_pose``: the tibia's frame in the femur frame at the scan)."""
    rel = invert_poses(T_cam_femur) @ T_cam_tibia @ np.asarray(tibia_pose, float)
    return float(np.degrees(matrix_to_cardan(rel[:3, :3])[0]))


def tissue_floor_pose(anatomy, prior, points_cam, T_cam_femur, T_cam_tibia, model=None) -> np.ndarray:
    """The femur's pose (4, 4; model frame to the camera) that the placement of methods (ii)/(iii) on the
    FEM-posed skin (:func:`knee.models.fem.methods.register_to_posed_skin`) gives when everything before it
    is exact: the association model posed with the true tibia (its skin as the FEM then has it), the depth
    points ``points_cam`` (camera frame) taken into the true femur's frame. Its error is the model's tissue
    against the truth's, with nothing else wrong. ``model``: the anatomy's association model, when built."""
    model = build_knee_model(anatomy, prior=prior) if model is None else model
    model.reset()  # from the model as built, whatever ran on it before
    T_cam_femur = np.asarray(T_cam_femur, float)
    rel = invert_poses(T_cam_femur) @ np.asarray(T_cam_tibia, float) @ anatomy.tibia_pose
    alpha = float(pose_to_joint(rel)[0])
    D = invert_poses(tibia_path(prior, model, alpha)[0]) @ rel  # what takes the prior's path to the truth
    with quasi_static(model.solver):
        initialise_from_prior(model, prior, alpha, correction_xi=np.r_[Rotation.from_matrix(D[:3, :3]).as_rotvec(),
                                                                       D[:3, 3]])
        T_fix, _ = register_to_posed_skin(model, transform_points(invert_poses(T_cam_femur), points_cam))
    return T_cam_femur @ invert_poses(T_fix)


#: Femoral widths below the joint line from which a depth point counts as the shank's in the tibia's tissue floor
#: (:func:`tibia_tissue_floor_poses`): below the flexion estimate's blended knee band.
TIBIA_FLOOR_BELOW_WIDTHS = 0.25
#: Samples spread over the model's skin for the tibia's tissue floor.
TIBIA_FLOOR_SAMPLES = 40000


def tibia_tissue_floor_poses(model, points_cam, T_cam_femur, T_cam_tibia) -> dict:
    """The tibia's poses (4, 4; rest model coordinates to the camera) that the shank's depth points give,
    registered rigidly (point-to-plane ICP, no prior, the femur exact) onto the model's shank at the true
    tibia: as scanned and carried by the bone (``"scanned"``, the flexion estimate's shank) and as the
    association model poses it (``"posed"``, the shank :func:`knee.models.fem.methods.fem_posed_shank` gives
    the tibia's second correction). ``model``: posed with the true bones (by :func:`tissue_floor_pose`). The
    shank: the skin more than :data:`TIBIA_FLOOR_BELOW_WIDTHS` femoral widths below the joint line at the
    scan, and the points below it once taken back to the scan by the true tibia's motion."""
    anatomy = model.anatomy
    T_cam_femur, T_cam_tibia = np.asarray(T_cam_femur, float), np.asarray(T_cam_tibia, float)
    T_tib = invert_poses(T_cam_femur) @ T_cam_tibia  # the tibia's rest coordinates to the femur frame, true
    cut = anatomy.joint_y - TIBIA_FLOOR_BELOW_WIDTHS * anatomy.width
    pts = transform_points(invert_poses(T_cam_femur), np.asarray(points_cam, float))
    pts = pts[transform_points(invert_poses(T_tib), pts)[:, 1] < cut]
    rest = trimesh.Trimesh(model.skin_vertices, model.skin_faces, process=False)
    posed = trimesh.Trimesh(model.posed_skin_vertices(), model.skin_faces, process=False)
    on, face = trimesh.sample.sample_surface(rest, TIBIA_FLOOR_SAMPLES, seed=0)
    shank = on[:, 1] < cut  # the rest model coordinates: the femur frame at the scan
    out = {}
    for name, target, normals in (
            ("scanned", transform_points(T_tib, on[shank]), rest.face_normals[face[shank]] @ T_tib[:3, :3].T),
            ("posed", trimesh.triangles.barycentric_to_points(
                posed.triangles[face[shank]], trimesh.triangles.points_to_barycentric(rest.triangles[face[shank]],
                                                                                      on[shank])),
             posed.face_normals[face[shank]])):
        E, _, _ = icp(pts, target, max_distance=FLOOR_REACH_MM, iterations=FLOOR_ITERATIONS, target_normals=normals)
        out[name] = T_cam_femur @ invert_poses(E) @ T_tib
    return out


@dataclass
class TissueFloorRow:
    """One case's tissue floors (mean footprint errors, mm): the femur placed on the FEM-posed skin
    (:func:`tissue_floor_pose`), the tibia from the shank's points on the scanned and on the FEM-posed shank
    (:func:`tibia_tissue_floor_poses`); and the flexion errors (deg, signed: the Cardan flexion of the tibia
    relative to the femur, less the truth's) of those floors: the femur's with the true tibia, each of the
    tibia's with the true femur, and both floors together (the femur's floor with the tibia's on the posed
    shank). ``shank_points_true``: the depth points on the true shank's skin, as ``knee compare`` counts
    them (the flexion target counts the views that see the shank); where fewer than
    :data:`knee.models.prior.MIN_SEEN_SHANK`, the tibia's flexion floors are nan (its fit stays at the truth
    it starts from)."""

    case: str
    femur_mm: float
    tibia_scanned_mm: float
    tibia_posed_mm: float
    anatomy: str = ""
    camera: str = ""
    mismatch_mm: float = 0.0
    shank_points_true: int = 0
    femur_flexion_error_deg: float = float("nan")
    tibia_scanned_flexion_error_deg: float = float("nan")
    tibia_posed_flexion_error_deg: float = float("nan")
    flexion_error_deg: float = float("nan")


def tissue_floor(folder, progress: Callable[[int, int, str], None] | None = None,
                 select: Callable[[dict], bool] | None = None, mismatches=(0.0,),
                 settings: FemSettings | None = None) -> list[TissueFloorRow]:
    """The tissue's floors (:class:`TissueFloorRow`) on every case of the case set at the skin mismatches
    ``mismatches`` (mm; ``select``: a further filter). At 0 mm (the default) the truth's skin differs from the
    model's only by its other model of the tissue; at 1 or 2 mm the floor holds the random field too (the
    only cases seen from the placements other than the paper's are at 1 mm). ``settings``: the association
    model's (None: the default model). An error naming the case set when it has no such case."""
    folder = Path(folder)
    levels = {float(m) for m in mismatches}
    wanted = {c["id"] for c in read_case_set(folder)["case"] if float(c["mismatch_mm"]) in levels
              and (select is None or select(c))}
    if not wanted:
        raise KneeInputError(f"{folder}: no case at {' or '.join(f'{m:g}' for m in sorted(levels))} mm skin "
                             "mismatch; nothing to measure the tissue's floor on")
    out = []
    models = {}
    for c, (anatomy, prior, T_ct_model), i, n in iter_cases(folder, lambda c: c["id"] in wanted):
        if progress:
            progress(i, n, c["id"])
        T_cam_femur = np.asarray(c["T_camera_femur_ct"]) @ T_ct_model
        T_cam_tibia = np.asarray(c["T_camera_tibia_ct"]) @ T_ct_model
        model = models.get(c["anatomy"])
        if model is None:
            model = models[c["anatomy"]] = build_knee_model(anatomy, settings, prior=prior)
        raw = case_points_cam(folder, c)
        points = voxel_downsample(raw, VOXEL_MM)
        Tf = tissue_floor_pose(anatomy, prior, points, T_cam_femur, T_cam_tibia, model=model)
        tibia = tibia_tissue_floor_poses(model, points, T_cam_femur, T_cam_tibia)
        tg = anatomy_targets(anatomy, prior)
        e = pose_errors(tg, T_cam_femur, T_cam_tibia, Tf, T_cam_tibia)
        et = {k: pose_errors(tg, T_cam_femur, T_cam_tibia, T_cam_femur, T).tibia.footprints.mean for k, T in tibia.items()}
        T_tib = np.asarray(anatomy.tibia_pose, float)
        true = _flexion_deg(T_cam_femur, T_cam_tibia, T_tib)
        seen = seen_shank_points(anatomy, raw, T_cam_tibia)
        # a shank the view hardly shows leaves the tibia's fit where it started, at the truth: no floor there
        shown = 0.0 if seen >= MIN_SEEN_SHANK else float("nan")
        out.append(TissueFloorRow(
            c["id"], e.femur.footprints.mean, et["scanned"], et["posed"], anatomy=c["anatomy"], camera=c["camera"],
            mismatch_mm=float(c["mismatch_mm"]), shank_points_true=seen,
            femur_flexion_error_deg=_flexion_deg(Tf, T_cam_tibia, T_tib) - true,
            tibia_scanned_flexion_error_deg=_flexion_deg(T_cam_femur, tibia["scanned"], T_tib) - true + shown,
            tibia_posed_flexion_error_deg=_flexion_deg(T_cam_femur, tibia["posed"], T_tib) - true + shown,
            flexion_error_deg=_flexion_deg(Tf, tibia["posed"], T_tib) - true + shown))
    if progress:
        progress(len(out), len(out), "done")
    return out


#: The grid's placements :func:`placement_floor` measures by default: its cells moved by these fractions of a cell
#: (:class:`knee.models.fem.scene.FemSettings`' ``grid_offset``).
PLACEMENT_OFFSETS = (0.0, 0.25, 0.5, 0.75)


@dataclass
class PlacementFloorRow:
    """One case's tissue floors (mean footprint errors, mm; :class:`TissueFloorRow`) under one grid: ``cells_across``
    cells across the limb (:class:`knee.models.fem.scene.FemSettings`' ``n_across``) moved by ``offset`` of a
    cell (its ``grid_offset``)."""

    case: str
    anatomy: str
    camera: str
    mismatch_mm: float
    cells_across: int
    offset: float
    femur_mm: float
    tibia_posed_mm: float


def _grid_counts(cells_across) -> list[int]:
    """The model grids' cells across the limb as whole numbers, or a one-line error."""
    counts = [int(n) for n in cells_across]
    if not counts or any(n < 1 or n != float(m) for n, m in zip(counts, cells_across)):
        raise KneeInputError("the cells across the limb must be whole numbers of at least 1, got "
                             + ", ".join(f"{float(m):g}" for m in cells_across))
    return counts


def placement_floor(folder, cells_across=(7,), offsets=PLACEMENT_OFFSETS, mismatches=(0.0, 1.0),
                    progress: Callable[[int, int, str], None] | None = None,
                    select: Callable[[dict], bool] | None = None) -> list[PlacementFloorRow]:
    """How much the association model's discretisation moves the tissue's floors (:func:`tissue_floor`): the floors
    of every case at the skin mismatches ``mismatches`` (mm; ``select``: a further filter) under each grid of
    ``cells_across`` cells across the limb, each moved by each of ``offsets`` (fractions of a cell in [0, 1); the
    model's own grid: 7 across, offset 0). Where the floors of one case differ from one placement to the next,
    the model's answer carries that much of where its cells happen to fall on the leg. Raises
    :class:`KneeInputError` for a count below 1 or an offset outside [0, 1), before anything is measured."""
    counts = _grid_counts(cells_across)
    offs = [float(o) for o in offsets]
    if not offs or any(not 0.0 <= o < 1.0 for o in offs):
        raise KneeInputError("the grid's offsets must be fractions of a cell in [0, 1), got "
                             + ", ".join(f"{o:g}" for o in offs))
    out = []
    grids = [(n, o) for n in counts for o in offs]
    for k, (n, o) in enumerate(grids):
        def said(i, m, text, k=k, n=n, o=o):
            if progress:
                progress(k * m + i, len(grids) * m, f"{n} across, offset {o:g}: {text}")
        for r in tissue_floor(folder, said, select, mismatches, FemSettings(n_across=n, grid_offset=o)):
            out.append(PlacementFloorRow(r.case, r.anatomy, r.camera, r.mismatch_mm, n, o, r.femur_mm, r.tibia_posed_mm))
    return out


def placement_spread(rows) -> dict:
    """Per anatomy, grid (cells across) and skin mismatch, from :func:`placement_floor`'s rows:
    ``{(anatomy, cells_across, mismatch_mm): {"offsets": the offsets (ascending), "table": each case's femur
    floor (mm) at each offset (cases, offsets; NaN where not measured), "median": the median at each offset,
    "spread": each case's standard deviation over the offsets, averaged over the cases (mm), "cases": how
    many}}``."""
    groups = {}
    for r in rows:
        groups.setdefault((r.anatomy, r.cells_across, r.mismatch_mm), []).append(r)
    out = {}
    for key in sorted(groups):
        g = groups[key]
        offsets = sorted({r.offset for r in g})
        cases = {c: i for i, c in enumerate(sorted({r.case for r in g}))}
        table = np.full((len(cases), len(offsets)), np.nan)
        column = {o: j for j, o in enumerate(offsets)}
        for r in g:
            table[cases[r.case], column[r.offset]] = r.femur_mm
        out[key] = {"offsets": offsets, "table": table, "median": [float(m) for m in np.nanmedian(table, axis=0)],
                    "spread": float(np.nanmean(np.nanstd(table, axis=1))), "cases": len(cases)}
    return out


def flexion_floor_table(rows, method_errors: dict | None = None, min_seen: int = MIN_SEEN_SHANK) -> list[str]:
    """A Markdown table of the tissue's flexion floors (:func:`tissue_floor` rows) by anatomy, camera and skin
    mismatch, over the views that see the shank (at least ``min_seen`` depth points on the true shank, as the
    flexion target counts them): how many of each floor's flexions lie within 2 deg of the truth (the femur's
    with the true tibia, the tibia's on the FEM-posed shank with the true femur, both together) and the median
    signed error of both; with ``method_errors`` ({case: a method's signed flexion error, deg}), that
    method's views within 2 deg and how many of its misses are views where the floor of both misses too
    (there the model's skin itself reads the flexion off by more than 2 deg with every other step exact)."""
    head = ["anatomy", "camera", "skin mismatch", "views", "floor within 2 deg: femur / tibia / both",
            "floor's signed error (deg)"]
    if method_errors is not None:
        head += ["method within 2 deg", "method's misses where the floor misses"]
    lines = ["| " + " | ".join(head) + " |", "|---|---|" + "---:|" * (len(head) - 2)]
    seen = [r for r in rows if r.shank_points_true >= min_seen]
    keys = sorted({(r.anatomy, r.camera, r.mismatch_mm) for r in seen})
    for key in [*keys, ("all", "all", None)]:
        g = [r for r in seen if key[0] == "all" or (r.anatomy, r.camera, r.mismatch_mm) == key]
        if not g:
            continue
        within = [sum(abs(getattr(r, f)) <= 2.0 for r in g)
                  for f in ("femur_flexion_error_deg", "tibia_posed_flexion_error_deg", "flexion_error_deg")]
        cells = [key[0], key[1], "all" if key[2] is None else f"{key[2]:g} mm", str(len(g)),
                 " / ".join(map(str, within)), f"{float(np.median([r.flexion_error_deg for r in g])):+.2f}"]
        if method_errors is not None:
            known = [r for r in g if r.case in method_errors]
            misses = [r for r in known if abs(method_errors[r.case]) > 2.0]
            cells += [f"{len(known) - len(misses)} of {len(known)}",
                      f"{sum(abs(r.flexion_error_deg) > 2.0 for r in misses)} of {len(misses)}"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _twin_key(case: dict) -> tuple:
    return (case["anatomy"], case["family"], case["camera"], tuple(case["truth_tf"]),
            tuple(map(tuple, case["T_camera_femur_ct"])))


def skin_floor(folder, progress: Callable[[int, int, str], None] | None = None,
               select: Callable[[dict], bool] | None = None) -> list[SkinFloorRow]:
    """The floors of every case (``select``: a filter) with a skin mismatch whose view was also rendered at
    0 mm (the paper's placement). An error naming the case set when no case has such a twin."""
    folder = Path(folder)
    index = read_case_set(folder)
    clean = {_twin_key(c): c for c in index["case"] if float(c["mismatch_mm"]) == 0.0}
    wanted = {c["id"] for c in index["case"] if float(c["mismatch_mm"]) > 0.0 and _twin_key(c) in clean
              and (select is None or select(c))}
    if not wanted:
        raise KneeInputError(f"{folder}: no case with a skin mismatch has its view rendered at 0 mm too; "
                             "nothing to measure a floor against")
    rows = []
    for c, (anatomy, prior, T_ct_model), i, n in iter_cases(folder, lambda c: c["id"] in wanted):
        if progress:
            progress(i, n, c["id"])
        tg = anatomy_targets(anatomy, prior)
        T_cam_femur = np.asarray(c["T_camera_femur_ct"]) @ T_ct_model
        T_cam_tibia = np.asarray(c["T_camera_tibia_ct"]) @ T_ct_model
        points, twin = _cloud(folder, c), _cloud(folder, clean[_twin_key(c)])
        poses = floor_poses(points, twin, T_cam_femur, T_cam_tibia, anatomy.joint_y)
        mm = float(c["mismatch_mm"])
        Tf, Tt, _ = prior_floor_poses(points, twin, T_cam_femur, T_cam_tibia, anatomy.joint_y, anatomy.tibia_pose,
                                      lambda a: tibia_path(prior, anatomy, a), effective_point_sd(anatomy.width, mm))
        poses["prior"] = (Tf, Tt)
        e = {k: pose_errors(tg, T_cam_femur, T_cam_tibia, Tf, Tt) for k, (Tf, Tt) in poses.items()}
        true_flexion = _flexion_deg(T_cam_femur, T_cam_tibia, anatomy.tibia_pose)
        rows.append(SkinFloorRow(c["id"], c["anatomy"], c["family"], mm,
                                 e["separate"].femur.footprints.mean, e["separate"].tibia.footprints.mean,
                                 e["joined"].femur.footprints.mean, e["joined"].tibia.footprints.mean,
                                 _flexion_deg(*poses["separate"], anatomy.tibia_pose) - true_flexion,
                                 e["prior"].femur.footprints.mean, e["prior"].tibia.footprints.mean,
                                 _flexion_deg(*poses["prior"], anatomy.tibia_pose) - true_flexion))
    if progress:
        progress(len(rows), len(rows), "done")
    return rows


#: How :func:`redrawn_floor` may draw the skin mismatch field: "area", as the case sets draw it (the bumps' centres
#: uniform over the skin's area, the RMS over its area); "vertex", as sets built before the field was spread by area
#: drew it (the centres at random vertices, the RMS over the vertices), for comparison.
FIELD_KINDS = ("area", "vertex")


@dataclass
class RedrawnFloorRow:
    """One draw of :func:`redrawn_floor`: a view (its 0 mm case's id), the field's kind and draw number, the prior
    floor's footprint error (mm; the mean of the femur's and the tibia's) and its flexion error (deg)."""

    case: str
    anatomy: str
    mismatch_mm: float
    field: str
    draw: int
    prior_mm: float
    prior_flexion_error_deg: float


def check_redraw(draws, mismatch_mm, fields) -> tuple:
    """:func:`redrawn_floor`'s settings checked (the field kinds returned as a tuple): a one-line
    :class:`KneeInputError` for fewer than one draw, a mismatch that is not a number above 0 and at most 10 mm, or
    a field kind not in :data:`FIELD_KINDS`."""
    if isinstance(draws, bool) or not isinstance(draws, (int, np.integer)) or draws < 1:
        raise KneeInputError(f"the floor's draws must be a whole number from 1, got {draws!r}")
    number = isinstance(mismatch_mm, (int, float, np.integer, np.floating)) and not isinstance(mismatch_mm, bool)
    if not (number and 0.0 < float(mismatch_mm) <= 10.0):  # also refuses NaN
        raise KneeInputError(f"the redrawn floor's skin mismatch must lie above 0 and at most 10 mm, got {mismatch_mm!r}")
    fields = tuple(fields)
    unknown = [f for f in fields if f not in FIELD_KINDS]
    if unknown or not fields:
        raise KneeInputError(f"unknown field kind {unknown[0]!r}: one or more of {', '.join(FIELD_KINDS)}" if unknown
                             else f"no field kind given: one or more of {', '.join(FIELD_KINDS)}")
    return fields


def redrawn_floor(folder, draws: int = 6, mismatch_mm: float = 1.0, fields=("area",),
                  progress: Callable[[int, int, str], None] | None = None,
                  select: Callable[[dict], bool] | None = None) -> list[RedrawnFloorRow]:
    """The prior floor (:func:`prior_floor_poses`) over fresh draws of the skin mismatch field, many per view: a case
    set draws one field per view, so the median of its dozen views a mismatch is only as steady as a dozen draws.
    For each 0 mm view from the paper's placement (``select``: a further filter) the truth's flexed skin is made
    again by the set's own tissue (:class:`knee.models.fem.tissue.TetTissue`, its spacing and seed), and each of
    ``draws`` draws renders a fresh 0 mm cloud and, per field kind of ``fields`` (:data:`FIELD_KINDS`), a cloud with
    a field of ``mismatch_mm`` RMS, both with the set's depth noise; the floor matches the 0 mm cloud to the other
    with the set's prior. Every kind of one draw sees the same 0 mm cloud, so kinds compare draw for draw. Each
    view's draws are the same on every run (their own random streams). The truth's tissue is posed once a view
    (5-110 s on the 2-core machine), the draws take about 0.3 s each. Raises :class:`KneeInputError` for fewer
    than one draw, a mismatch that is not a positive number, an unknown field kind, a set built with the truth's
    patella (its tissue needs the truth mechanism's patellar motion) or no 0 mm paper view."""
    fields = check_redraw(draws, mismatch_mm, fields)
    folder = Path(folder)
    index = read_case_set(folder)
    if index.get("truth_patella", False):
        raise KneeInputError(f"{folder}: built with the truth's patella, whose tissue the redrawn floor cannot pose "
                             "again (it needs the truth mechanism's patellar motion); use a set built without --patella")
    seed = int(index.get("seed", 0))
    edge = float(index.get("truth_edge_widths", 0.1))
    noise = DepthNoise(sigma_at_ref=float(index.get("noise_sigma_mm_at_400_mm", 1.0)),
                       flying=float(index.get("flying_pixels", 0.0)),
                       correlation_px=float(index.get("noise_correlation_px", 0.0)),
                       hole_px=float(index.get("hole_px", 0.0)))
    wanted = {c["id"] for c in index["case"] if float(c["mismatch_mm"]) == 0.0 and c["camera"] == "paper"
              and (select is None or select(c))}
    if not wanted:
        raise KneeInputError(f"{folder}: no 0 mm view from the paper's placement to draw the field on")
    per_anatomy = {}
    for c, setup, _, _ in iter_cases(folder, lambda c: c["id"] in wanted):
        per_anatomy.setdefault(c["anatomy"], (setup, []))[1].append(c)
    total = sum(len(cs) for _, cs in per_anatomy.values())
    rows, done = [], 0
    mm = float(mismatch_mm)
    for name, ((anatomy, prior, _), cases) in per_anatomy.items():
        tg = anatomy_targets(anatomy, prior)
        tissue = TetTissue(anatomy, edge=edge * anatomy.width, seed=seed)
        point_sd = effective_point_sd(anatomy.width, mm)
        for c in cases:
            if progress:
                progress(done, total, f"{c['id']}: the truth's skin posed again, {draws} draws")
            done += 1
            T_tibia = joint_to_pose(np.asarray(c["truth_tf"], float))
            skin = tissue.pose(T_tibia).skin(tissue)
            verts, faces = np.asarray(skin.vertices), np.asarray(skin.faces)
            normals = np.asarray(skin.vertex_normals)
            cam = placement_camera(anatomy, "paper")
            to_model = invert_poses(cam.T_cam_world)
            rel = T_tibia @ invert_poses(anatomy.tibia_pose)
            clean_depth = render_depth(verts, faces, cam)

            def cloud(depth, rng):
                return voxel_downsample(backproject(noise.apply(depth, rng), cam.K, to_model, drop_mixed=True), VOXEL_MM)

            true_flexion = _flexion_deg(np.eye(4), rel, anatomy.tibia_pose)
            for k in range(draws):
                rng = case_rng(seed, c["id"], "redrawn floor", f"{mm:g}", str(k))
                clean = cloud(clean_depth, rng)
                for kind in fields:
                    moved = smooth_surface_field(verts, normals, mm, FIELD_WIDTHS * anatomy.width, rng,
                                                 faces=faces if kind == "area" else None)
                    points = cloud(render_depth(moved, faces, cam), rng)
                    Tf, Tt, _ = prior_floor_poses(points, clean, np.eye(4), rel, anatomy.joint_y, anatomy.tibia_pose,
                                                  lambda a: tibia_path(prior, anatomy, a), point_sd)
                    e = pose_errors(tg, np.eye(4), rel, Tf, Tt)
                    rows.append(RedrawnFloorRow(c["id"], name, mm, kind, k,
                                                0.5 * (e.femur.footprints.mean + e.tibia.footprints.mean),
                                                _flexion_deg(Tf, Tt, anatomy.tibia_pose) - true_flexion))
    if progress:
        progress(total, total, "done")
    return rows


def redrawn_floor_table(rows) -> list[str]:
    """Markdown lines: per anatomy (and over all) and field kind, the draws, the prior floor's median footprint
    error with its quartiles and the flexions within 2 deg; with two kinds, the mean difference per draw of each
    kind against the first (the same 0 mm cloud, the same view) with its standard error."""
    kinds = list(dict.fromkeys(r.field for r in rows))
    lines = ["| anatomy | field | draws | floor: prior, median (quartiles) | flexion within 2 deg | against "
             f"{kinds[0]!r}, per draw (se) |", "|---|---|---:|---:|---:|---:|"]
    anatomies = list(dict.fromkeys(r.anatomy for r in rows))
    for name in anatomies + (["all"] if len(anatomies) > 1 else []):
        mine = [r for r in rows if name == "all" or r.anatomy == name]
        first = {(r.case, r.draw): r.prior_mm for r in mine if r.field == kinds[0]}
        for kind in kinds:
            g = [r for r in mine if r.field == kind]
            v = np.array([r.prior_mm for r in g])
            q1, q2, q3 = np.percentile(v, [25, 50, 75])
            diff = "-"
            if kind != kinds[0]:
                d = np.array([r.prior_mm - first[(r.case, r.draw)] for r in g if (r.case, r.draw) in first])
                if len(d) > 1:
                    diff = f"{d.mean():+.2f} ({d.std(ddof=1) / math.sqrt(len(d)):.2f})"
            within = sum(abs(r.prior_flexion_error_deg) <= 2.0 for r in g)
            lines.append(f"| {name} | {kind} | {len(g)} | {q2:.2f} ({q1:.2f}-{q3:.2f}) | {within} of {len(g)} | {diff} |")
    return lines


@dataclass
class TruthEdgeRow:
    """One view's femur tissue floor (:func:`tissue_floor_pose`, mm) against the truth's skin re-posed with its
    tissue on a spacing of ``truth_edge`` femur widths, under a model grid of ``cells_across`` cells across the
    limb, and how far that skin lies from the finest spacing's over the knee (the median distance of its
    vertices within a femur width of the joint line, mm; 0 at the finest)."""

    case: str
    anatomy: str
    truth_edge: float
    cells_across: int
    femur_mm: float
    skin_to_finest_mm: float
    inverted: int


def truth_edge_floor(folder, truth_edges=(0.1, 0.07, 0.05), cells_across=(7,),
                     progress: Callable[[int, int, str], None] | None = None,
                     select: Callable[[dict], bool] | None = None) -> list[TruthEdgeRow]:
    """Whether the case set's truth is converged: every 0 mm view (``select``: a further filter) with its truth's
    flexed skin made again by the truth's tissue (:class:`knee.models.fem.tissue.TetTissue`, the set's seed) on
    each spacing of ``truth_edges`` (femur widths), rendered noise-free from the view's placement, and the femur's
    tissue floor measured on those points under each model grid of ``cells_across`` cells across
    (:class:`TruthEdgeRow`). Where a finer truth moves the floor, the case set's figures carry that much of the
    truth's own discretisation. Raises :class:`KneeInputError` for a spacing outside
    :func:`knee.app.experiments.case_set.check_truth_edge`'s range, a count below 1 or no 0 mm view."""
    edges = sorted({check_truth_edge(e) for e in truth_edges}, reverse=True)
    if not edges:
        raise KneeInputError("give one or more truth spacings")
    counts = _grid_counts(cells_across)
    folder = Path(folder)
    index = read_case_set(folder)
    wanted = {c["id"] for c in index["case"] if float(c["mismatch_mm"]) == 0.0 and (select is None or select(c))}
    if not wanted:
        raise KneeInputError(f"{folder}: no view at 0 mm skin mismatch to re-make the truth's skin for")
    per_anatomy = {}
    for c, setup, _, _ in iter_cases(folder, lambda c: c["id"] in wanted):
        per_anatomy.setdefault(c["anatomy"], (setup, []))[1].append(c)
    total = sum(len(cs) for _, cs in per_anatomy.values()) * len(edges)
    out, done = [], 0
    for name, ((anatomy, prior, _), cases) in per_anatomy.items():
        models = {n: build_knee_model(anatomy, FemSettings(n_across=n), prior=prior) for n in counts}
        tg = anatomy_targets(anatomy, prior)
        skins, rows = {}, []
        for e in edges:
            tissue = TetTissue(anatomy, edge=e * anatomy.width, seed=int(index.get("seed", 0)))
            for c in cases:
                if progress:
                    progress(done, total, f"{c['id']}: the truth at {e:g} femur widths")
                done += 1
                T_tibia = joint_to_pose(np.asarray(c["truth_tf"], float))
                posed = tissue.pose(T_tibia)
                skin = posed.skin(tissue)
                cam = placement_camera(anatomy, c["camera"])  # the view's own camera, in the model frame
                pts = voxel_downsample(backproject(render_depth(skin.vertices, skin.faces, cam), cam.K,
                                                   invert_poses(cam.T_cam_world), drop_mixed=True), VOXEL_MM)
                rel = T_tibia @ invert_poses(anatomy.tibia_pose)
                skins[(e, c["id"])] = skin
                for n, model in models.items():
                    Tf = tissue_floor_pose(anatomy, prior, pts, np.eye(4), rel, model=model)
                    rows.append(TruthEdgeRow(c["id"], name, e, n, pose_errors(tg, np.eye(4), rel, Tf, rel).femur.footprints.mean,
                                             0.0, posed.inverted))
        finest = {c["id"]: SurfaceQuery(np.asarray(skins[(edges[-1], c["id"])].vertices),
                                        np.asarray(skins[(edges[-1], c["id"])].faces)) for c in cases}
        moved = {}  # (spacing, case): the skin's median distance to the finest truth's over the knee, once each
        for (e, cid), skin in skins.items():
            v = np.asarray(skin.vertices)
            v = v[np.abs(v[:, 1] - anatomy.joint_y) < anatomy.width]
            moved[(e, cid)] = 0.0 if e == edges[-1] else float(np.median(np.abs(finest[cid].signed_distance(v))))
        for r in rows:
            r.skin_to_finest_mm = moved[(r.truth_edge, r.case)]
        out += rows
    if progress:
        progress(total, total, "done")
    return out


def truth_edge_table(rows) -> list[str]:
    """A Markdown table of :func:`truth_edge_floor`'s rows: per anatomy and grid, at each truth spacing (coarsest
    first), the median femur floor over the views (mm), the median of the views' skin distance to the finest
    truth's over the knee (mm) and the inverted tetrahedra (median)."""
    lines = ["| anatomy | cells across | truth spacing (femur widths) | views | femur floor, median (mm) | "
             "skin to the finest truth's over the knee (mm) | inverted tetrahedra |", "|---|---:|---:|---:|---:|---:|---:|"]
    for key in sorted({(r.anatomy, r.cells_across, -r.truth_edge) for r in rows}):
        g = [r for r in rows if (r.anatomy, r.cells_across, -r.truth_edge) == key]
        lines.append(f"| {key[0]} | {key[1]} | {-key[2]:g} | {len(g)} | {np.median([r.femur_mm for r in g]):.2f} | "
                     f"{np.median([r.skin_to_finest_mm for r in g]):.2f} | {np.median([r.inverted for r in g]):.0f} |")
    return lines
