"""The standard case of the association model, built from the phantom, and its evaluation (seed 000, 3).

Truth: the phantom's bones posed by the mechanism at a flexion angle, with the skin of that pose; a
virtual RGB-D camera sees the skin (one side, with depth noise). The model starts from extension (thigh
held, femur frame), is registered to the camera by ICP on the thigh, then deformed: bone forces until
the femur-tibia angle is below 100 degrees, then surface forces towards the depth points until the skin
stops moving. Errors are distances between estimated and true bone surface points: the ACL and PCL
footprints (surface within ``footprint_radius`` of the mechanism's attachment points) and the whole
epiphysis (surface within ``epiphysis_length`` of the joint line), mean and sd per bone.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

import numpy as np

from models.fem.depth import Camera, DepthNoise, backproject, icp, render_depth
from models.fem.forces import BoneForces, SurfaceForces
from models.fem.mapping import TrilinearMapping
from models.fem.scene import AssociationModel, FemSettings, build_association_model, knee_angles
from models.mechanism.solver import Mechanism
from toolkit.conventions import invert_poses, joint_to_pose, transform_points


def default_camera(distance: float = 350.0, azimuth_deg: float = 35.0, elevation_deg: float = 30.0,
                   target=(0.0, -20.0, 0.0)) -> Camera:
    """An oblique camera ``distance`` mm from the knee, anterior, turned ``azimuth`` towards lateral and
    raised ``elevation`` towards proximal (femur frame)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    d = np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
    t = np.asarray(target, float)
    return Camera.looking_at(t + distance * d, t, up=(0.0, 1.0, 0.0))


def truth_phantom(mech: Mechanism, settings: FemSettings | None = None):
    """The phantom of the parameter set that generates a case's truth, built like the model's."""
    from models.phantom import build_phantom

    s = settings or FemSettings()
    return build_phantom(mech.params, shaft_length=s.shaft_length, cartilage=s.cartilage)


@dataclass
class TargetPoints:
    """Bone surface points to evaluate, in each bone's rest position (the model's extension)."""

    femur: np.ndarray
    tibia: np.ndarray
    femur_footprints: np.ndarray  # bool masks over the points
    tibia_footprints: np.ndarray


@dataclass
class CaseResult:
    flexion_true_deg: float
    flexion_estimated_deg: float
    errors: dict  # bone -> {"footprints": (mean, sd), "epiphysis": (mean, sd)} in mm
    steps: int
    steps_bone_phase: int
    wall_seconds: float
    converged: bool
    history: dict = field(default_factory=dict)
    distances: dict = field(default_factory=dict)  # bone -> per-point error (mm), for distance maps
    points: dict = field(default_factory=dict)     # bone -> estimated target points (P, 3)


def target_points(model: AssociationModel, mech: Mechanism, footprint_radius=10.0, epiphysis_length=40.0):
    fv = np.asarray(model.femur_surface.vertices)
    tv = np.asarray(model.tibia_surface.vertices)
    y0 = model.joint_y
    fe = fv[fv[:, 1] < y0 + epiphysis_length]
    te = tv[tv[:, 1] > y0 - epiphysis_length]
    T0 = joint_to_pose(mech.solve(0.0)[0])
    fa = np.vstack([mech.params.link(n).femur for n in ("acl", "pcl")])
    ta = transform_points(T0, np.vstack([mech.params.link(n).tibia for n in ("acl", "pcl")]))
    # footprints: surface points around the attachment's nearest surface point (attachment points can
    # lie inside the phantom's simplified bone)
    fa = fe[np.linalg.norm(fe[:, None] - fa[None], axis=2).argmin(axis=0)]
    ta = te[np.linalg.norm(te[:, None] - ta[None], axis=2).argmin(axis=0)]
    ffp = (np.linalg.norm(fe[:, None] - fa[None], axis=2) < footprint_radius).any(axis=1)
    tfp = (np.linalg.norm(te[:, None] - ta[None], axis=2) < footprint_radius).any(axis=1)
    return TargetPoints(fe, te, ffp, tfp)


def run_standard_case(mech: Mechanism, flexion_deg: float = 90.0, camera: Camera | None = None,
                      noise: DepthNoise | None = DepthNoise(), settings: FemSettings | None = None,
                      bone_force_scale: float = 1.0, surface_k: float = 2.0, max_steps: int = 400,
                      model: AssociationModel | None = None, seed: int = 0, progress=True,
                      truth: Mechanism | None = None) -> CaseResult:
    """Run the paper's method on the phantom standard case; see the module docstring. ``truth``: another
    parameter set that generates the truth (default ``mech``: the model is built from ``mech``)."""
    t_start = time.perf_counter()
    model = model or build_association_model(mech, settings)
    ph = model.phantom
    tmech = truth or mech
    ph_true = ph if truth is None else truth_phantom(truth, model.settings)
    tf, pf, _ = tmech.solve(np.radians(flexion_deg))
    T_true = joint_to_pose(tf)
    skin_true = ph_true.skin(T_true, joint_to_pose(pf) if tmech.has_pf else None)
    cam = camera or default_camera()
    rng = np.random.default_rng(seed)
    depth = render_depth(skin_true.vertices, skin_true.faces, cam)
    if noise is not None:
        depth = noise.apply(depth, rng)
    pts = backproject(depth, cam.K, cam.T_world_cam)
    # registration of the camera to the model: ICP of the seen thigh onto the model's thigh
    thigh_model = model.skin_vertices[model.skin_vertices[:, 1] > 60.0]
    thigh_seen = pts[pts[:, 1] > 70.0]
    if len(thigh_seen) > 200:
        T_reg, _, _ = icp(thigh_seen[::3], thigh_model, max_distance=10.0)
        pts = pts @ T_reg[:3, :3].T + T_reg[:3, 3]
    targets = target_points(model, mech)
    fmap = TrilinearMapping(model.grid, targets.femur)
    tmap = TrilinearMapping(model.grid, targets.tibia)
    s = model.solver
    held = bool(s.fixed.any())
    bone = BoneForces(model.femur, model.tibia, scale=bone_force_scale, use_femur=not held)
    surf = SurfaceForces(model.grid, model.skin_vertices, pts, k=surface_k)
    hist = {"step": [], "flexion_deg": [], "reference_mm": [], "within": [], "skin_motion_mm": []}
    phase, bone_steps, calm, converged = "bone", 0, 0, False
    skin_prev = model.skin_vertices.copy()
    smap = surf.map
    for k in range(max_steps):
        if phase == "bone":
            s.step(bone.forces)
            bone_steps += 1
            flex, between = knee_angles(model)
            if between < 100.0 or bone_steps >= max_steps // 3:
                phase = "surface"
                s.fields.append(surf)
                s._lu = None  # the surface springs enter the preconditioner
        else:
            s.step()
            flex, between = knee_angles(model)
        skin_now = smap.apply(s.x)
        motion = float(np.linalg.norm(skin_now - skin_prev, axis=1).mean())
        skin_prev = skin_now
        hist["step"].append(k)
        hist["flexion_deg"].append(flex)
        hist["reference_mm"].append(surf.reference if phase == "surface" else np.nan)
        hist["within"].append(surf.within_fraction if phase == "surface" else np.nan)
        hist["skin_motion_mm"].append(motion)
        if progress and k % 20 == 0:
            print(f"  step {k:4d} [{phase}] flexion {flex:6.1f} deg, skin motion {motion:7.3f} mm/step",
                  file=sys.stderr, flush=True)
        if phase == "surface":
            calm = calm + 1 if motion < 0.01 else 0
            if calm >= 5:
                converged = True
                break
    if surf in s.fields:
        s.fields.remove(surf)
    # evaluation
    T0 = joint_to_pose(mech.solve(0.0)[0])
    truth_f = targets.femur
    truth_t = transform_points(T_true @ invert_poses(T0), targets.tibia)
    est_f, est_t = fmap.apply(s.x), tmap.apply(s.x)
    df = np.linalg.norm(est_f - truth_f, axis=1)
    dt_ = np.linalg.norm(est_t - truth_t, axis=1)
    errors = {"femur": {"footprints": (float(df[targets.femur_footprints].mean()), float(df[targets.femur_footprints].std())),
                        "epiphysis": (float(df.mean()), float(df.std()))},
              "tibia": {"footprints": (float(dt_[targets.tibia_footprints].mean()), float(dt_[targets.tibia_footprints].std())),
                        "epiphysis": (float(dt_.mean()), float(dt_.std()))}}
    flex, _ = knee_angles(model)
    return CaseResult(flexion_true_deg=float(np.degrees(tf[0])), flexion_estimated_deg=flex, errors=errors,
                      steps=len(hist["step"]), steps_bone_phase=bone_steps,
                      wall_seconds=time.perf_counter() - t_start, converged=converged,
                      history={k: np.asarray(v) for k, v in hist.items()},
                      distances={"femur": df, "tibia": dt_}, points={"femur": est_f, "tibia": est_t})
