"""Experiment runner: the association model's standard cases on the phantom, and the comparison of the
four methods (``knee fem`` without a measured cloud, ``knee compare``, ``knee demo``, the benchmarks).

A case: the truth is a mechanism's phantom posed at a flexion angle, with the skin of that pose; a
virtual RGB-D camera sees the skin (one side, with depth noise); the model, built from the prior (the
truth itself, or a perturbed or fitted parameter set), starts from extension in its femur frame. A method
of :mod:`knee.models.fem.methods` reconstructs the bones from the depth points alone; the reconstruction
is then measured against the truth at the target points (:mod:`knee.models.evaluation`).

World frame: the truth's femur frame, in which the camera is placed and the cloud rendered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from knee.foundations.conventions import invert_poses, joint_to_pose, transform_points
from knee.foundations.errors import KneeError
from knee.foundations.pointclouds import backproject
from knee.models.evaluation import (
    TargetErrors,
    TargetPoints,
    target_errors,
    target_points,
)
from knee.models.fem.depth import Camera, DepthNoise, default_camera, render_depth
from knee.models.fem.methods import (
    METHODS,
    Reconstruction,
    StepCallback,
    paper_method,
    prior_method,
)
from knee.models.fem.scene import AssociationModel, FemSettings, build_association_model
from knee.models.fem.tissue import TetTissue
from knee.models.mechanism.solver import Mechanism
from knee.models.phantom import Phantom, build_phantom
from knee.models.prior import TibiaCorrection


def truth_phantom(mech: Mechanism, settings: FemSettings | None = None) -> Phantom:
    """The phantom of a parameter set built like the association model's (the truth's bones of a case, or
    the bones a prior's model is built from)."""
    s = settings or FemSettings()
    return build_phantom(mech.params, shaft_length=s.shaft_length, cartilage=s.cartilage)


def case_depth(truth: Mechanism, flexion_deg: float, camera: Camera, noise: DepthNoise | None, seed: int = 0,
               settings: FemSettings | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The depth image (H, W) (mm, 0 where nothing is seen) a virtual camera takes of the skin of
    ``truth``'s phantom posed at ``flexion_deg`` (with noise), and the truth's TF joint coordinates (6,)."""
    ph = truth_phantom(truth, settings)
    tf, pf, _ = truth.solve(np.radians(flexion_deg))
    skin = ph.skin(joint_to_pose(tf), joint_to_pose(pf) if truth.has_pf else None)
    return seen_depth(skin.vertices, skin.faces, camera, noise, np.random.default_rng(seed)), tf


def seen_depth(vertices, faces, camera: Camera, noise: DepthNoise | None, rng: np.random.Generator) -> np.ndarray:
    """The depth image (H, W) (mm, 0 where nothing is seen) a virtual camera takes of a surface (vertices in
    the camera's world frame), with ``noise`` drawn from ``rng`` (None: exact)."""
    depth = render_depth(vertices, faces, camera)
    return depth if noise is None else noise.apply(depth, rng)


def case_points(truth: Mechanism, flexion_deg: float, camera: Camera, noise: DepthNoise | None, seed: int = 0,
                settings: FemSettings | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The standard case's input: the depth points (P, 3) (mm, world frame) a virtual camera sees of the
    skin of ``truth``'s phantom posed at ``flexion_deg`` (with noise), and the truth's TF joint
    coordinates (6,)."""
    depth, tf = case_depth(truth, flexion_deg, camera, noise, seed, settings)
    return backproject(depth, camera.K, camera.T_world_cam), tf


def tissue_case_depth(tissue: TetTissue, truth_tf, camera: Camera, noise: DepthNoise | None,
                      seed: int = 0) -> np.ndarray:
    """The depth image (H, W) (mm, 0 where nothing is seen) a virtual camera (placed in the tissue's femur
    frame) takes of a truth skin made independently of the association model: the tetrahedral tissue around
    the knee's bones (the honest benchmark's truth, :class:`knee.models.fem.tissue.TetTissue`) with its femur
    held and its tibia moved to the TF joint coordinates ``truth_tf`` (6,), with noise drawn from ``seed``."""
    skin = tissue.pose(joint_to_pose(np.asarray(truth_tf, float))).skin(tissue)
    return seen_depth(skin.vertices, skin.faces, camera, noise, np.random.default_rng(seed))


def tissue_case_points(tissue: TetTissue, truth_tf, camera: Camera, noise: DepthNoise | None,
                       seed: int = 0) -> np.ndarray:
    """The depth points (P, 3) (mm, world frame: the tissue's femur frame) of :func:`tissue_case_depth`'s
    image."""
    return backproject(tissue_case_depth(tissue, truth_tf, camera, noise, seed), camera.K, camera.T_world_cam)


def model_targets(model: AssociationModel, mech: Mechanism) -> TargetPoints:
    """The target points of a model built from ``mech``, in the model frame: the femur's at rest, the
    tibia's at the model's rest (scanned) pose; the joint line at the model's ``joint_y``."""
    fa = np.vstack([mech.params.link(n).femur for n in ("acl", "pcl")])
    ta = transform_points(model.tibia_pose, np.vstack([mech.params.link(n).tibia for n in ("acl", "pcl")]))
    return target_points(model.femur_surface.vertices, model.tibia_surface.vertices, fa, ta,
                         model.joint_y, model.joint_y)


def phantom_targets(mech: Mechanism, phantom: Phantom) -> TargetPoints:
    """The target points of a phantom's bones in their own frames (the joint line at y = 0), around
    ``mech``'s ACL and PCL attachments: for measuring rigid bone poses (:func:`pose_errors`)."""
    fa = np.vstack([mech.params.link(n).femur for n in ("acl", "pcl")])
    ta = np.vstack([mech.params.link(n).tibia for n in ("acl", "pcl")])
    return target_points(phantom.femur.vertices, phantom.tibia.vertices, fa, ta)


def true_target_positions(model: AssociationModel, mech: Mechanism, truth_tf) -> tuple[TargetPoints, np.ndarray,
                                                                                        np.ndarray]:
    """The target points of ``model`` (built from ``mech``) and where they truly are, world frame: the
    femur's at rest, the tibia's moved from the model's rest pose to the true TF pose ``truth_tf``."""
    targets = model_targets(model, mech)
    truth_t = transform_points(joint_to_pose(np.asarray(truth_tf, float)) @ invert_poses(model.tibia_pose),
                               targets.tibia)
    return targets, targets.femur, truth_t


def evaluate(model: AssociationModel, mech: Mechanism, recon: Reconstruction, truth_tf) -> TargetErrors:
    """The target point errors of a reconstruction against the true TF pose (world frame)."""
    targets, true_f, true_t = true_target_positions(model, mech, truth_tf)
    return target_errors(targets, recon.bone_points("femur", targets.femur), recon.bone_points("tibia", targets.tibia),
                         true_f, true_t)


@dataclass
class CaseTruth:
    """What the recording of a case shows of its truth: the model's target points, where they truly are
    ((P, 3) each, world frame) and the true bones' meshes, posed."""

    targets: TargetPoints
    femur: np.ndarray
    tibia: np.ndarray
    meshes: dict


def case_truth(model: AssociationModel, mech: Mechanism, truth: Mechanism, truth_tf) -> CaseTruth:
    targets, true_f, true_t = true_target_positions(model, mech, truth_tf)
    ph = truth_phantom(truth, model.settings)
    return CaseTruth(targets, true_f, true_t,
                     {"femur": ph.femur, "tibia": ph.tibia.copy().apply_transform(joint_to_pose(truth_tf))})


@dataclass
class CaseResult:
    """A method's reconstruction of one case and its errors (None when the case has no truth)."""

    flexion_true_deg: float
    reconstruction: Reconstruction
    errors: TargetErrors | None
    targets: TargetPoints | None = field(default=None, repr=False)

    @property
    def flexion_estimated_deg(self) -> float:
        return self.reconstruction.flexion_deg

    def estimated_targets(self) -> dict:
        """{bone: (P, 3)}: where the reconstruction puts the target points (world frame)."""
        if self.targets is None:
            return {}
        return {"femur": self.reconstruction.bone_points("femur", self.targets.femur),
                "tibia": self.reconstruction.bone_points("tibia", self.targets.tibia)}


def run_standard_case(mech: Mechanism, flexion_deg: float = 90.0, camera: Camera | None = None,
                      noise: DepthNoise | None = DepthNoise(), settings: FemSettings | None = None,
                      model: AssociationModel | None = None, seed: int = 0, truth: Mechanism | None = None,
                      points=None, truth_tf=None, on_step: StepCallback | None = None, **paper_options) -> CaseResult:
    """The paper's method on the phantom standard case (see the module docstring). ``truth``: another
    parameter set that generates the truth (default ``mech``: the model is built from ``mech``).

    ``points``: a measured point cloud (P, 3) in mm, in place of the virtual camera's; there is no truth
    then (unless ``truth_tf``, the true TF joint coordinates, is given) and no errors. ``paper_options``
    go to :func:`knee.models.fem.methods.paper_method`."""
    model = model or build_association_model(mech, settings)
    tmech = truth or mech
    if points is None:
        pts, tf = case_points(tmech, flexion_deg, camera or default_camera(), noise, seed, model.settings)
    else:
        pts, tf = np.asarray(points, float), truth_tf
    recon = paper_method(model, pts, on_step=on_step, **paper_options)
    if tf is None:
        return CaseResult(float("nan"), recon, None)
    return CaseResult(float(np.degrees(tf[0])), recon, evaluate(model, mech, recon, tf), model_targets(model, mech))


@dataclass
class MethodResult:
    """One method on one case: its reconstruction, the errors, and the bones' surfaces (world frame) for
    the comparison's recording."""

    method: str
    flexion_true_deg: float
    reconstruction: Reconstruction
    errors: TargetErrors
    surfaces: dict = field(default_factory=dict, repr=False)  # bone -> final surface vertices (V, 3)

    @property
    def flexion_estimated_deg(self) -> float:
        return self.reconstruction.flexion_deg

    @property
    def tibia_correction(self) -> TibiaCorrection | None:
        return self.reconstruction.tibia_correction


def run_method(method: str, truth: Mechanism, prior: Mechanism, flexion_deg: float, camera: Camera | None = None,
               noise: DepthNoise | None = DepthNoise(), seed: int = 0, max_steps: int = 80,
               model: AssociationModel | None = None, points=None) -> MethodResult:
    """One method on one case (the model built from ``prior``, the truth from ``truth``). ``points``: the
    case's depth points, when already rendered (rendered from ``truth`` otherwise)."""
    model = model or build_association_model(prior)
    if points is None:
        pts, truth_tf = case_points(truth, flexion_deg, camera or default_camera(), noise, seed, model.settings)
    else:
        pts, truth_tf = points, truth.solve(math.radians(flexion_deg))[0]
    recon = prior_method(method, model, prior, pts, max_steps=max_steps)
    surfaces = {name: recon.bone_points(name, m.vertices)
                for name, m in (("femur", model.femur_surface), ("tibia", model.tibia_surface))}
    return MethodResult(method, float(flexion_deg), recon, evaluate(model, prior, recon, truth_tf), surfaces)


@dataclass
class FloorRow:
    """:func:`prior_floor` at one true flexion (deg, mm)."""

    flexion_deg: float
    prior_flexion_deg: float
    tibia_footprints_mm: float
    tibia_epiphysis_mm: float
    axial_rotation_deg: float
    tibia_footprints_axial_mm: float


def prior_floor(model: AssociationModel, truth: Mechanism, prior: Mechanism, flexions_deg,
                step_deg: float = 0.25) -> list[FloorRow]:
    """What the prior's links allow at best: for each true flexion, the tibia's target point errors of the
    prior posed at its best-matching flexion (footprints), with the femur placed exactly. A method that
    holds the bones to the prior's links (iii) cannot do better on the tibia than this unless the depth
    points move the tibia off the prior's path.

    The remaining pose error is split into the rotation about the tibia's long axis (its y axis: the axial
    rotation, which the phantom's skin around the shank, a surface of revolution about that axis, cannot
    show) and the rest (which the skin can show); ``tibia_footprints_axial_mm`` is the footprint error that the axial
    part alone leaves, i.e. what even a perfect use of the depth points would be left with."""
    tg = model_targets(model, prior)
    local = transform_points(invert_poses(model.tibia_pose), tg.tibia)
    lo, hi = prior.assembly_range
    alphas = np.arange(lo, hi, math.radians(step_deg))
    Tp = joint_to_pose(prior.motion_at(alphas)[0])  # (A, 4, 4)
    est = np.einsum("aij,pj->api", Tp[:, :3, :3], local) + Tp[:, None, :3, 3]  # (A, P, 3)
    fp_local = local[tg.tibia_footprints]
    rows = []
    for fl in flexions_deg:
        if not truth.in_range(math.radians(fl)):
            continue
        T_true = joint_to_pose(truth.solve(math.radians(fl))[0])
        true = transform_points(T_true, local)
        d = np.linalg.norm(est - true[None], axis=2)  # (A, P)
        fp = d[:, tg.tibia_footprints].mean(axis=1)
        i = int(fp.argmin())
        # swing-twist split of the correction from the prior's pose to the truth, in the tibia's frame
        q = Rotation.from_matrix((invert_poses(Tp[i]) @ T_true)[:3, :3]).as_quat()  # x, y, z, w
        twist = Rotation.from_quat([0.0, q[1], 0.0, q[3]] / np.hypot(q[1], q[3]))
        axial = np.linalg.norm(fp_local - twist.inv().apply(fp_local), axis=1).mean()
        rows.append(FloorRow(float(fl), math.degrees(alphas[i]), float(fp[i]), float(d[i].mean()),
                             float(np.degrees(twist.magnitude()) * np.sign(q[1] * q[3])), float(axial)))
    return rows


@dataclass
class CompareRow:
    """One row of the comparison table: a method on a case (a failed run has ``failed`` set and NaN
    errors). Errors are mean target point errors (mm), the correction's size in deg / mm."""

    method: str
    camera: str
    flexion_true_deg: float
    flexion_estimated_deg: float = float("nan")
    femur_footprints_mm: float = float("nan")
    tibia_footprints_mm: float = float("nan")
    femur_epiphysis_mm: float = float("nan")
    tibia_epiphysis_mm: float = float("nan")
    steps: int = 0
    wall_seconds: float = float("nan")
    converged: bool = False
    tibia_correction_deg: float = float("nan")
    tibia_correction_mm: float = float("nan")
    notes: str = ""
    failed: str = ""
    #: methods ii/iii: the flexion's standard error from the fits that set it (deg;
    #: :func:`knee.models.fem.methods.flexion_sd_deg`), NaN otherwise
    flexion_sd_deg: float = float("nan")

    @property
    def footprints_mm(self) -> float:
        """Mean of the femur and tibia footprint errors (mm)."""
        return 0.5 * (self.femur_footprints_mm + self.tibia_footprints_mm)

    @property
    def epiphysis_mm(self) -> float:
        """Mean of the femur and tibia epiphysis errors (mm)."""
        return 0.5 * (self.femur_epiphysis_mm + self.tibia_epiphysis_mm)


def _norm_or_nan(corr: TibiaCorrection | None, which: str) -> float:
    if corr is None or not corr.applied:
        return float("nan")
    return float(np.linalg.norm(corr.rotation_deg if which == "deg" else corr.translation_mm))


def reconstruction_row(method: str, camera_name: str, flexion_deg: float, rec: Reconstruction, e: TargetErrors,
                       wall_seconds: float, row=CompareRow, **extra) -> CompareRow:
    """One row of a comparison table (``row``: :class:`CompareRow` or a subclass, with its ``extra``
    fields) from a reconstruction and its errors."""
    return row(method, camera_name, float(flexion_deg), rec.flexion_deg, e.femur.footprints.mean,
               e.tibia.footprints.mean, e.femur.epiphysis.mean, e.tibia.epiphysis.mean, rec.steps, wall_seconds,
               rec.converged, _norm_or_nan(rec.tibia_correction, "deg"), _norm_or_nan(rec.tibia_correction, "mm"),
               "; ".join(rec.notes), flexion_sd_deg=rec.flexion_sd_deg, **extra)


def result_row(camera_name: str, flexion_deg: float, r: MethodResult) -> CompareRow:
    """One row of the comparison table from a method's result."""
    return reconstruction_row(r.method, camera_name, flexion_deg, r.reconstruction, r.errors,
                              r.reconstruction.wall_seconds)


#: ``progress(done, total, text)`` before each run of a comparison.
Progress = Callable[[int, int, str], None]
#: ``on_result(camera_name, flexion_deg, method, result, truth_tf)`` after each successful run.
OnResult = Callable[[str, float, str, MethodResult, np.ndarray], None]


def compare_cases(truth: Mechanism, prior: Mechanism, flexions_deg, cameras: dict, methods=METHODS,
                  noise: DepthNoise | None = DepthNoise(), seed: int = 0, progress: Progress | None = None,
                  on_result: OnResult | None = None) -> list[CompareRow]:
    """Every method on every (flexion, camera) case; one row per run with the errors and timings.
    ``cameras``: {name: Camera}. A case whose flexion lies outside the truth's assembly range is reported
    as failed for every method; so is a run that fails (bad input or a numerical failure), with its
    one-line reason."""
    rows = []
    total = len(cameras) * len(flexions_deg) * len(methods)
    done = 0
    for cam_name, cam in cameras.items():
        for fl in flexions_deg:
            fl = float(fl)
            if not truth.in_range(math.radians(fl)):
                lo, hi = (math.degrees(v) for v in truth.assembly_range)
                rows += [CompareRow(m, cam_name, fl, failed=f"{fl:g} deg is outside the truth's assembly range "
                                                               f"({lo:.1f} to {hi:.1f})") for m in methods]
                done += len(methods)
                continue
            pts, truth_tf = case_points(truth, fl, cam, noise, seed)
            for method in methods:
                if progress:
                    progress(done, total, f"{method} at {fl:g} deg, camera {cam_name}")
                done += 1
                try:
                    r = run_method(method, truth, prior, fl, cam, noise, seed, points=pts,
                                   model=build_association_model(prior))
                except KneeError as e:
                    rows.append(CompareRow(method, cam_name, fl, failed=str(e)))
                    continue
                if on_result:
                    on_result(cam_name, fl, method, r, truth_tf)
                rows.append(result_row(cam_name, fl, r))
    if progress:
        progress(total, total, "done")
    return rows
