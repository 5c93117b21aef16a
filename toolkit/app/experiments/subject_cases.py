"""Experiment runner: the four methods on a subject's own knee, the truth from a measured motion
(``knee compare SUBJECT_DIR --prior FITTED.toml --truth-motion MOTION.csv``).

A case: a row of the measured motion (TF joint coordinates, e.g. from dynamic imaging) poses the subject's
CT bones; the skin is posed with them by another model of the tissue than the methods' (the tetrahedral
tissue around the subject's bones inside its CT skin, :class:`knee.models.fem.tissue.TetTissue`, as in the
honest benchmark's case sets), so that the truth is not made by the code that estimates it; a virtual
camera, placed relative to the knee, sees that skin with depth noise; the methods see only the points, in the camera's
own frame, and a rough pose of the knee in it (the truth turned by 15 deg and moved by 25 mm), and place
the bones in the camera's frame. The errors are measured there at the target points (ACL/PCL footprints
from the prior's attachments, the epiphysis).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from knee.app.experiments.cases import CompareRow, reconstruction_row, seen_depth
from knee.foundations.conventions import invert_poses, joint_to_pose, matrix_to_cardan, transform_points
from knee.foundations.errors import KneeError
from knee.foundations.pointclouds import backproject
from knee.models.evaluation import pose_errors, target_errors, target_points
from knee.models.fem.anatomy import KneeAnatomy
from knee.models.fem.depth import Camera, DepthNoise, default_camera
from knee.models.fem.methods import METHODS, STAGES, reconstruct_in_camera
from knee.models.fem.scene import FemSettings, build_knee_model
from knee.models.fem.tissue import TetTissue
from knee.models.mechanism.solver import Mechanism

#: The rough pose the methods are given: the truth turned by this much (deg) and moved by this much (mm).
ROUGH_DEG, ROUGH_MM = 15.0, 25.0


@dataclass
class SubjectCase:
    """One case: the true TF pose (4, 4, femur frame), the camera (placed in the femur frame), the
    depth points (P, 3) in the camera's frame."""

    label: str
    flexion_deg: float
    T_tibia: np.ndarray
    camera: Camera
    points: np.ndarray


def subject_cases(anatomy: KneeAnatomy, motion_tf, azimuths=(35.0,), noise=DepthNoise(),
                  seed: int = 0) -> list[SubjectCase]:
    """The cases of a measured motion's rows ``motion_tf`` (n, 6) (rad, mm), each seen from cameras at
    the given azimuths (deg toward lateral, 350 mm, raised 30 deg, aimed at the joint line); the skin is the
    subject's tetrahedral tissue (meshed once, from ``seed``) posed with the tibia at each row."""
    rng = np.random.default_rng(seed)
    tissue = TetTissue(anatomy, seed=seed)
    out = []
    for tf in np.atleast_2d(np.asarray(motion_tf, float)):
        T = joint_to_pose(tf)
        skin = tissue.pose(T).skin(tissue)
        for az in azimuths:
            cam = default_camera(azimuth_deg=az, target=(0.0, anatomy.joint_y, 0.0))
            depth = seen_depth(skin.vertices, skin.faces, cam, noise, rng)
            out.append(SubjectCase(f"az {az:g}", math.degrees(tf[0]), T, cam, backproject(depth, cam.K)))
    return out


def random_pose(rng, deg_range, mm_range, centre) -> np.ndarray:
    """A rotation of a random magnitude in ``deg_range`` about a random axis through ``centre``, then a
    translation of a random length in ``mm_range`` in a random direction (4, 4)."""
    axis, d = rng.normal(size=3), rng.normal(size=3)
    R = Rotation.from_rotvec(math.radians(rng.uniform(*deg_range)) * axis / np.linalg.norm(axis)).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre + rng.uniform(*mm_range) * d / np.linalg.norm(d)
    return T


def _rough_start(T_model_cam, rng) -> np.ndarray:
    return random_pose(rng, (ROUGH_DEG, ROUGH_DEG), (ROUGH_MM, ROUGH_MM), np.zeros(3)) @ T_model_cam


def anatomy_targets(anatomy: KneeAnatomy, prior: Mechanism):
    """The target points of the errors: ACL/PCL footprints from the prior's attachments, the epiphyses."""
    fa = np.vstack([prior.params.link(n).femur for n in ("acl", "pcl")])
    ta = transform_points(anatomy.tibia_pose, np.vstack([prior.params.link(n).tibia for n in ("acl", "pcl")]))
    return target_points(anatomy.femur.vertices, anatomy.tibia.vertices, fa, ta, anatomy.joint_y, anatomy.joint_y)


def camera_target_errors(anatomy: KneeAnatomy, prior: Mechanism, recon, T_cam_world, T_cam_femur, T_cam_tibia):
    """The target point errors (ACL/PCL footprints from the prior's attachments, the epiphyses) of a
    reconstruction in a camera's frame: ``T_cam_world`` takes the reconstruction's world to the camera;
    ``T_cam_femur``, ``T_cam_tibia`` (4, 4) take the true bones' rest model coordinates (the femur frame,
    the tibia at its scan) to the camera. The estimated points are carried by each bone's rigid pose, as
    ``knee fem`` reports it (:meth:`knee.models.fem.methods.Reconstruction.bone_points`)."""
    tg = anatomy_targets(anatomy, prior)
    return target_errors(tg, transform_points(T_cam_world, recon.bone_points("femur", tg.femur)),
                         transform_points(T_cam_world, recon.bone_points("tibia", tg.tibia)),
                         transform_points(T_cam_femur, tg.femur), transform_points(T_cam_tibia, tg.tibia))


@dataclass
class StageError:
    """Where one stage of methods (ii)/(iii) put the bones, against the truth: the mean footprint errors
    (mm; femur, tibia), the stage's flexion (deg; the Cardan flexion of the tibia relative to the femur),
    the femur's error as a rotation vector (deg) and a translation at the knee's centre (mm; on the femur's
    axis at the joint line), both in the true femur's frame, the tibia's error relative to the femur as a
    rotation vector (deg) in the true tibia's frame (its z: the flexion's error, with the sign reversed), and
    the tibia's own error as a rotation vector (deg) in the true tibia's frame. About the medio-lateral axis
    (z) the flexion's error is about the femur's z less the tibia's: which bone's tilt a flexion error comes
    from."""

    stage: str
    femur_footprints_mm: float
    tibia_footprints_mm: float
    flexion_deg: float
    femur_rotation_deg: np.ndarray
    femur_translation_mm: np.ndarray
    relative_rotation_deg: np.ndarray
    tibia_rotation_deg: np.ndarray

    @property
    def footprints_mm(self) -> float:
        return 0.5 * (self.femur_footprints_mm + self.tibia_footprints_mm)


def camera_stage_errors(anatomy: KneeAnatomy, prior: Mechanism, recon, T_cam_world, T_cam_femur,
                        T_cam_tibia) -> list[StageError]:
    """The errors of each stage a reconstruction recorded (:attr:`knee.models.fem.methods.Reconstruction.
    stages`, in :data:`knee.models.fem.methods.STAGES` order) and of its final bones ("final", their rigid
    poses), in a camera's frame (arguments as :func:`camera_target_errors`)."""
    tg = anatomy_targets(anatomy, prior)
    T_tib = np.asarray(anatomy.tibia_pose, float)
    T_cam_femur, T_cam_tibia = np.asarray(T_cam_femur, float), np.asarray(T_cam_tibia, float)
    rel_true = invert_poses(T_cam_femur) @ T_cam_tibia @ T_tib
    centre = np.array([0.0, anatomy.joint_y, 0.0])
    poses = []
    for k in STAGES:
        if k in recon.stages:
            Tw, rel = recon.stages[k]
            poses.append((k, T_cam_world @ Tw, T_cam_world @ Tw @ rel @ invert_poses(T_tib)))
    if recon.grid_x is not None and recon.bone_nodes is not None:
        poses.append(("final", T_cam_world @ recon.rigid_pose("femur"), T_cam_world @ recon.rigid_pose("tibia")))
    out = []
    for name, Tf, Tt in poses:
        e = pose_errors(tg, T_cam_femur, T_cam_tibia, Tf, Tt)
        Ef = invert_poses(T_cam_femur) @ Tf
        rel = invert_poses(Tf) @ Tt @ T_tib
        Er = invert_poses(rel_true) @ rel
        Et = invert_poses(T_cam_tibia @ T_tib) @ Tt @ T_tib
        out.append(StageError(name, e.femur.footprints.mean, e.tibia.footprints.mean,
                              float(np.degrees(matrix_to_cardan(rel[:3, :3])[0])),
                              np.degrees(Rotation.from_matrix(Ef[:3, :3]).as_rotvec()),
                              Ef[:3, :3] @ centre + Ef[:3, 3] - centre,
                              np.degrees(Rotation.from_matrix(Er[:3, :3]).as_rotvec()),
                              np.degrees(Rotation.from_matrix(Et[:3, :3]).as_rotvec())))
    return out


def run_subject_case(case: SubjectCase, method: str, anatomy: KneeAnatomy, prior: Mechanism, seed: int = 0,
                     settings: FemSettings | None = None):
    """One method on one case: a :class:`CompareRow`. ``settings``: the association model's (None: its
    defaults)."""
    model = build_knee_model(anatomy, settings, prior=prior)
    t0 = time.perf_counter()
    T_model_cam = case.camera.T_world_cam  # the camera's frame to the model (femur) frame, the truth
    recon, rough = reconstruct_in_camera(model, prior, case.points,
                                         _rough_start(T_model_cam, np.random.default_rng(seed)), method)
    wall = time.perf_counter() - t0
    T_cam_model = invert_poses(T_model_cam)
    e = camera_target_errors(anatomy, prior, recon, invert_poses(rough.T_model_world), T_cam_model,
                             T_cam_model @ case.T_tibia @ invert_poses(anatomy.tibia_pose))
    return reconstruction_row(method, case.label, case.flexion_deg, recon, e, wall)


def compare_subject(anatomy: KneeAnatomy, prior: Mechanism, motion_tf, methods=METHODS, azimuths=(35.0,),
                    noise=DepthNoise(), seed: int = 0,
                    progress: Callable[[int, int, str], None] | None = None,
                    settings: FemSettings | None = None) -> list[CompareRow]:
    """Every method on every case of :func:`subject_cases` (``settings``: the association model's); a run
    that fails is a row with its reason."""
    cases = subject_cases(anatomy, motion_tf, azimuths, noise, seed)
    rows, total = [], len(cases) * len(methods)
    for i, case in enumerate(cases):
        for j, method in enumerate(methods):
            if progress:
                progress(i * len(methods) + j, total, f"{method} at {case.flexion_deg:.1f} deg, {case.label}")
            try:
                rows.append(run_subject_case(case, method, anatomy, prior, seed, settings))
            except KneeError as e:
                rows.append(CompareRow(method, case.label, case.flexion_deg, failed=str(e)))
    if progress:
        progress(total, total, "done")
    return rows
