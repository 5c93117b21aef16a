"""The association model with the mechanism as its kinematic prior (issue "kinematic priors for the FEM").

Methods compared on the same case (truth from one parameter set, the prior from another):

* ``"paper"`` (i): the paper's method (:func:`models.fem.case.run_standard_case`): bone forces, then
  surface forces, two collateral springs;
* ``"init"`` (ii): the prior as initialisation only: the flexion is estimated from the point cloud
  (:func:`models.prior.estimate_flexion`), femur and tibia are moved along the mechanism's path to that
  angle with the grid nodes of their cells prescribed (Dirichlet conditions in the implicit solver: the
  soft tissue inside a bone's cells moves with the bone), then released, and the surface phase runs with
  the paper's two springs;
* ``"links"`` (iii): as (ii), and during the surface phase the mechanism's five links act between points
  rigidly attached to the femur and tibia (minimum-norm affine combinations of each bone's nodes) as stiff
  springs (1000 N/mm, the paper's collateral stiffness). Springs rather than exact constraints: the
  implicit solver's matrix-free CG takes them without changing its unknowns, and 1000 N/mm keeps each
  link within a few micrometres per newton;
* ``"kinematics"`` (iv): the mechanism alone at the estimated angle, no FEM.

All four are evaluated with the same target points (ACL/PCL footprints and epiphysis, per bone).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from models.fem.case import case_points, default_camera, run_standard_case, target_points
from models.fem.depth import DepthNoise
from models.fem.fields import MappedSprings, affine_point_map
from models.fem.forces import SurfaceForces
from models.fem.mapping import TrilinearMapping
from models.fem.scene import AssociationModel, bone_cell_masks, build_association_model, knee_angles
from models.mechanism.solver import Mechanism
from models.prior import estimate_flexion
from toolkit.conventions import invert_poses, joint_to_pose, transform_points
from toolkit.errors import KneeInputError

METHODS = ("paper", "init", "links", "kinematics")


@dataclass
class MethodResult:
    method: str
    flexion_true_deg: float
    flexion_estimated_deg: float
    errors: dict
    steps: int
    wall_seconds: float
    converged: bool
    notes: list = field(default_factory=list)


def bone_cell_nodes(model: AssociationModel):
    """Grid nodes of the cells holding each bone's nodes (nodes shared by both bones excluded)."""
    return bone_cell_masks(model.grid, model.femur, model.tibia)


def initialise_from_prior(model: AssociationModel, prior: Mechanism, alpha: float, increments: int = 6,
                          settle: int = 3) -> int:
    """Move the tibia along the prior's path from extension to ``alpha`` (rad) with the bone cells'
    nodes prescribed (femur's held at rest), let the velocities settle, and make that configuration the
    model's stress-free reference; returns the steps taken."""
    s = model.solver
    mf, mt = bone_cell_nodes(model)
    mask = mf | mt
    X = model.grid.X
    T0 = joint_to_pose(prior.motion_at(np.array([0.0]))[0][0])
    path = alpha * np.arange(1, increments + 1) / increments
    poses = joint_to_pose(prior.motion_at(path)[0]) @ invert_poses(T0)
    steps = 0
    target = X.copy()
    for T in list(poses) + [poses[-1]] * settle:
        target[mt] = transform_points(T, X[mt])
        s.step(prescribed=(mask, target))
        steps += 1
    s.v[:] = 0.0
    # the initialised configuration becomes the stress-free reference: the model has no muscles to hold
    # the flexion, so without this the tissue's bending energy would return the knee to extension;
    # elements inverted by the motion (crushed tissue behind the knee) are dropped, and the bone contact
    # takes its activation distances from this configuration
    x = s.x
    kept = model.soft.el.rebase(x)
    kept += model.femur.el.rebase(model.femur.bone_positions(x))
    kept += model.tibia.el.rebase(model.tibia.bone_positions(x))
    model.contact.rebase(x)
    model.inverted_at_init = kept
    s._set_prescribed(None)
    s._lu = None
    return steps


def link_springs(model: AssociationModel, prior: Mechanism, k: float = 1000.0):
    """The prior's five TF links as springs between femur- and tibia-attached points (rest: extension)."""
    T0 = joint_to_pose(prior.motion_at(np.array([0.0]))[0][0])
    a = np.vstack([lk.femur for lk in prior.params.links])
    b = transform_points(T0, np.vstack([lk.tibia for lk in prior.params.links]))
    maps = (affine_point_map(model.femur, a), affine_point_map(model.tibia, b))
    return MappedSprings(model.grid, a, b, k, rest_length=[lk.length for lk in prior.params.links], maps=maps)


def _depth_points(truth: Mechanism, flexion_deg, camera, noise, seed, settings=None):
    return case_points(truth, flexion_deg, camera, noise, seed, settings)


def _evaluate(model, prior, truth_tf, x=None, T_femur=None, T_tibia=None, T_world=None):
    """Target point errors in the world (camera scene) frame: from the FEM state ``x`` (model frame, taken
    to the world by ``T_world``), or from world bone poses (method iv)."""
    targets = target_points(model, prior)
    T0 = joint_to_pose(prior.motion_at(np.array([0.0]))[0][0])
    T_true = joint_to_pose(truth_tf)
    truth_f = targets.femur
    truth_t = transform_points(T_true @ invert_poses(T0), targets.tibia)
    if x is not None:
        Tw = np.eye(4) if T_world is None else T_world
        est_f = transform_points(Tw, TrilinearMapping(model.grid, targets.femur).apply(x))
        est_t = transform_points(Tw, TrilinearMapping(model.grid, targets.tibia).apply(x))
    else:
        est_f = transform_points(T_femur, targets.femur)
        est_t = transform_points(T_tibia @ invert_poses(T0), targets.tibia)
    out = {}
    for bone, est, tru, fp in (("femur", est_f, truth_f, targets.femur_footprints),
                               ("tibia", est_t, truth_t, targets.tibia_footprints)):
        d = np.linalg.norm(est - tru, axis=1)
        out[bone] = {"footprints": (float(d[fp].mean()), float(d[fp].std())), "epiphysis": (float(d.mean()), float(d.std()))}
    return out


def run_method(method: str, truth: Mechanism, prior: Mechanism, flexion_deg: float, camera=None,
               noise=DepthNoise(), seed: int = 0, max_steps: int = 80, model: AssociationModel | None = None,
               progress=False) -> MethodResult:
    """Run one method on one case (see the module docstring)."""
    if method not in METHODS:
        raise KneeInputError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    cam = camera or default_camera()
    t0 = time.perf_counter()
    if method == "paper":
        r = run_standard_case(prior, flexion_deg, cam, noise, model=model or build_association_model(prior),
                              seed=seed, progress=progress, truth=truth)
        return MethodResult("paper", r.flexion_true_deg, r.flexion_estimated_deg, r.errors, r.steps, r.wall_seconds,
                            r.converged)
    model = model or build_association_model(prior)
    t0 = time.perf_counter()  # the model is built once per prior, outside the per-case time
    pts, truth_tf = _depth_points(truth, flexion_deg, cam, noise, seed, model.settings)
    notes = []
    est = estimate_flexion(prior, model.phantom, pts)
    notes += est.warnings
    if method == "kinematics":
        tf, _ = prior.motion_at(np.array([est.flexion]))
        errors = _evaluate(model, prior, truth_tf, T_femur=est.T_world_model,
                           T_tibia=est.T_world_model @ joint_to_pose(tf[0]))
        return MethodResult(method, flexion_deg, math.degrees(est.flexion), errors, 0, time.perf_counter() - t0,
                            True, notes)
    # the cloud in the model frame (the registration of the prior-posed skin)
    pts_model = transform_points(invert_poses(est.T_world_model), pts)
    steps = initialise_from_prior(model, prior, est.flexion)
    s = model.solver
    surf = SurfaceForces(model.grid, model.skin_vertices, pts_model, k=2.0)
    s.fields.append(surf)
    links = None
    if method == "links":
        links = link_springs(model, prior)
        s.fields.append(links)
    s._lu = None
    skin_prev = surf.map.apply(s.x)
    calm, converged = 0, False
    for k in range(max_steps):
        s.step()
        steps += 1
        if not np.all(np.isfinite(s.x)):
            raise KneeInputError(f"the FEM diverged at step {steps} (non-finite positions)")
        skin = surf.map.apply(s.x)
        motion = float(np.linalg.norm(skin - skin_prev, axis=1).mean())
        skin_prev = skin
        calm = calm + 1 if motion < 0.02 else 0
        if calm >= 3:
            converged = True
            break
    for f in (surf, links):
        if f is not None and f in s.fields:
            s.fields.remove(f)
    s._lu = None
    flex, _ = knee_angles(model)
    errors = _evaluate(model, prior, truth_tf, x=s.x, T_world=est.T_world_model)
    return MethodResult(method, flexion_deg, flex, errors, steps, time.perf_counter() - t0, converged, notes)


def compare_cases(truth: Mechanism, prior: Mechanism, flexions_deg, cameras: dict, methods=METHODS,
                  noise=DepthNoise(), seed: int = 0, progress=None) -> list[dict]:
    """Every method on every (flexion, camera) case; one row per run with the errors and timings.
    ``cameras``: {name: Camera}. ``progress(text)`` is called before each run."""
    rows = []
    for cam_name, cam in cameras.items():
        for fl in flexions_deg:
            for method in methods:
                if progress:
                    progress(f"{method} at {fl:g} deg, camera {cam_name}")
                try:
                    r = run_method(method, truth, prior, float(fl), cam, noise, seed,
                                   model=None if method == "kinematics" else build_association_model(prior))
                except KneeInputError as e:
                    rows.append({"method": method, "camera": cam_name, "flexion_true_deg": fl, "failed": str(e)})
                    continue
                rows.append({"method": method, "camera": cam_name, "flexion_true_deg": fl,
                             "flexion_estimated_deg": r.flexion_estimated_deg,
                             "femur_footprints_mm": r.errors["femur"]["footprints"][0],
                             "tibia_footprints_mm": r.errors["tibia"]["footprints"][0],
                             "femur_epiphysis_mm": r.errors["femur"]["epiphysis"][0],
                             "tibia_epiphysis_mm": r.errors["tibia"]["epiphysis"][0],
                             "steps": r.steps, "wall_seconds": r.wall_seconds, "converged": r.converged,
                             "notes": "; ".join(r.notes), "failed": ""})
    return rows
