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
  perfect skin and perfect kinematics: only the leg's pose unknown).

The separate registration's flexion error says the same of the flexion target.

A method that registers skin gets below the separate floor only with knowledge of how the bones move
together (a kinematic prior, which the joined floor has exactly), and below the joined one only with
knowledge of the field itself (its statistics); they say how much of a method's error at a mismatch is the
mismatch itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from knee.app.experiments.case_set import case_points_cam, iter_cases, read_case_set
from knee.app.experiments.subject_cases import anatomy_targets
from knee.foundations.conventions import invert_poses, matrix_to_cardan, pose_to_joint, transform_points
from knee.foundations.errors import KneeInputError
from knee.foundations.pointclouds import icp, voxel_downsample
from knee.models.evaluation import pose_errors
from knee.models.fem.methods import initialise_from_prior, quasi_static, register_to_posed_skin, tibia_path
from knee.models.fem.scene import build_knee_model
from knee.models.prior import VOXEL_MM

#: The ICP's reach (mm): the posed-skin registration's first reach, well beyond a 2 mm field.
FLOOR_REACH_MM = 15.0
FLOOR_ITERATIONS = 60


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

    @property
    def separate_mm(self) -> float:
        return 0.5 * (self.separate_femur_mm + self.separate_tibia_mm)

    @property
    def joined_mm(self) -> float:
        return 0.5 * (self.joined_femur_mm + self.joined_tibia_mm)


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


def tissue_floor(folder, progress: Callable[[int, int, str], None] | None = None,
                 select: Callable[[dict], bool] | None = None) -> list[tuple[str, float]]:
    """(case id, the femur's mean footprint error in mm) of :func:`tissue_floor_pose` on every case without
    skin mismatch (``select``: a filter), where the truth's skin differs from the model's only by its
    other model of the tissue. An error naming the case set when it has no such case."""
    folder = Path(folder)
    wanted = {c["id"] for c in read_case_set(folder)["case"] if float(c["mismatch_mm"]) == 0.0
              and (select is None or select(c))}
    if not wanted:
        raise KneeInputError(f"{folder}: no case without skin mismatch; nothing to measure the tissue's floor on")
    out = []
    for c, (anatomy, prior, T_ct_model), i, n in iter_cases(folder, lambda c: c["id"] in wanted):
        if progress:
            progress(i, n, c["id"])
        T_cam_femur = np.asarray(c["T_camera_femur_ct"]) @ T_ct_model
        T_cam_tibia = np.asarray(c["T_camera_tibia_ct"]) @ T_ct_model
        Tf = tissue_floor_pose(anatomy, prior, _cloud(folder, c), T_cam_femur, T_cam_tibia)
        e = pose_errors(anatomy_targets(anatomy, prior), T_cam_femur, T_cam_tibia, Tf, T_cam_tibia)
        out.append((c["id"], e.femur.footprints.mean))
    if progress:
        progress(len(out), len(out), "done")
    return out


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
        poses = floor_poses(_cloud(folder, c), _cloud(folder, clean[_twin_key(c)]), T_cam_femur, T_cam_tibia,
                            anatomy.joint_y)
        e = {k: pose_errors(tg, T_cam_femur, T_cam_tibia, Tf, Tt) for k, (Tf, Tt) in poses.items()}
        rows.append(SkinFloorRow(c["id"], c["anatomy"], c["family"], float(c["mismatch_mm"]),
                                 e["separate"].femur.footprints.mean, e["separate"].tibia.footprints.mean,
                                 e["joined"].femur.footprints.mean, e["joined"].tibia.footprints.mean,
                                 _flexion_deg(*poses["separate"], anatomy.tibia_pose)
                                 - _flexion_deg(T_cam_femur, T_cam_tibia, anatomy.tibia_pose)))
    if progress:
        progress(len(rows), len(rows), "done")
    return rows
