"""The association model with the mechanism as its kinematic prior (issue "kinematic priors for the FEM").

Methods compared on the same case (truth from one parameter set, the prior from another):

* ``"paper"`` (i): the paper's method (:func:`models.fem.case.run_standard_case`): bone forces, then
  surface forces, two collateral springs;
* ``"init"`` (ii): the prior as initialisation only: the flexion is estimated from the point cloud
  (:func:`models.prior.estimate_flexion`), the tibia's pose there is corrected from the shank's depth
  points as far as they show it (:func:`models.prior.correct_tibia`: a MAP estimate weighed by the
  prior's accuracy, the rotation about the shank's axis left at the prior's), femur and tibia are moved
  along the mechanism's path to that pose with the grid nodes of their cells prescribed (Dirichlet
  conditions: the soft tissue inside a bone's cells moves with the bone; the rest of the grid in static
  equilibrium at each of 4 increments, the correction blended in along them), then released, and the
  surface phase runs with the paper's two springs;
* ``"links"`` (iii): as (ii), and during the surface phase the mechanism's five links act between points
  rigidly attached to the femur and tibia as stiff springs (1000 N/mm, the paper's collateral
  stiffness), their rest lengths the links' lengths at the corrected pose (the prior with its five lengths
  re-fitted so that its path passes through the pose the depth points show; the prior's own lengths when
  the shank was not seen well enough to correct it). Each link end is the minimum-norm affine combination of every bone node within 60 mm of
  its nearest node (a wide, non-coplanar set: the medial contact's tibial end, a sphere centre 58 mm
  above the facet, extrapolated the bone's small elastic deformation into millimetres when attached to
  its 12 nearest nodes). Springs rather than exact constraints: the implicit solver's matrix-free CG
  takes them without changing its unknowns, their wide coupling enters its factorised preconditioner
  as a rank-5 (Woodbury) term instead of a dense block, and 1000 N/mm keeps each link within a few
  micrometres per newton;
* ``"kinematics"`` (iv): the mechanism alone at the estimated angle, no FEM.

All four are evaluated with the same target points (ACL/PCL footprints and epiphysis, per bone).
Methods (ii) and (iii) look for an equilibrium, not a motion: their phases take quasi-static steps
(:class:`quasi_static`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from models.fem.case import (bone_phase_note, case_points, check_state, default_camera, register_to_model,
                             run_standard_case, target_errors, truth_targets)
from models.fem.depth import DepthNoise
from models.fem.fields import MappedSprings, affine_point_map
from models.fem.forces import SurfaceForces
from models.fem.mapping import TrilinearMapping
from models.fem.scene import AssociationModel, bone_cell_masks, build_association_model, knee_angles
from models.mechanism.solver import Mechanism
from models.prior import TibiaCorrection, correct_tibia, estimate_flexion, small_pose
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
    surfaces: dict = field(default_factory=dict)  # bone -> final surface vertices (V, 3), world frame
    tibia_correction: TibiaCorrection | None = None  # (ii), (iii): the tibia's pose corrected from the shank


def bone_cell_nodes(model: AssociationModel):
    """Grid nodes of the cells holding each bone's nodes (nodes shared by both bones excluded)."""
    return bone_cell_masks(model.grid, model.femur, model.tibia)


def initialise_from_prior(model: AssociationModel, prior: Mechanism, alpha: float, increments: int = 4,
                          settle: int = 1, correction_xi: np.ndarray | None = None) -> int:
    """Move the tibia along the prior's path from extension to ``alpha`` (rad) with the bone cells'
    nodes prescribed (femur's held at rest), solving the grid's static equilibrium at each increment
    (quasi-static steps, see :func:`quasi_static`), and make that configuration the model's stress-free
    reference; returns the steps taken. ``correction_xi`` (6,): a pose correction of the tibia in its own
    frame at ``alpha``, rotation vector (rad) and translation (mm) (:class:`models.prior.TibiaCorrection`),
    blended in along the increments."""
    s = model.solver
    mf, mt = bone_cell_nodes(model)
    mask = mf | mt
    X = model.grid.X
    T0 = joint_to_pose(prior.motion_at(np.array([0.0]))[0][0])
    fractions = np.arange(1, increments + 1) / increments
    poses = joint_to_pose(prior.motion_at(alpha * fractions)[0])
    if correction_xi is not None:
        poses = poses @ np.stack([small_pose(f * np.asarray(correction_xi, float)) for f in fractions])
    poses = poses @ invert_poses(T0)
    steps = 0
    target = X.copy()
    # the contact pairs the tibia's motion along the increments can bring, in the pattern from the start
    # (one symbolic analysis instead of one per increment that brings new pairs)
    s.reserve_pattern(model.contact.pattern_reserve_for_motion(np.concatenate([np.eye(4)[None], poses])))
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
    # grid nodes left with no element at all (every cell around them was dropped, and no bone node is
    # embedded next to them) carry only their tiny mass: held still, they stay out of the solve, which
    # otherwise sees a million-fold change of their diagonal whenever a surface spring switches on them
    alive = np.zeros(len(X), bool)
    alive[model.grid.cells[model.soft.el.alive].ravel()] = True
    for bone in (model.femur, model.tibia):
        alive[np.unique(bone.map.J.indices)] = True
    s.fixed = s.fixed | ~alive
    model.isolated_at_init = int((~alive).sum())
    s._set_prescribed(None)
    s.invalidate()
    return steps


LINK_REACH = 60.0  # mm: a link end is attached to every bone node within this of its nearest node's distance


def link_springs(model: AssociationModel, prior: Mechanism, k: float = 1000.0, T_tibia: np.ndarray | None = None):
    """The prior's five TF links as springs between femur- and tibia-attached points (attached at
    extension). Rest lengths: the prior's link lengths, or with ``T_tibia`` (the tibia's pose relative to
    the femur, model frame, e.g. corrected from the depth points) the links' lengths at that pose: the
    prior with its five lengths re-fitted so that its path passes through that pose."""
    T0 = joint_to_pose(prior.motion_at(np.array([0.0]))[0][0])
    a = np.vstack([lk.femur for lk in prior.params.links])
    local = np.vstack([lk.tibia for lk in prior.params.links])
    b = transform_points(T0, local)
    rest = [lk.length for lk in prior.params.links]
    if T_tibia is not None:
        rest = np.linalg.norm(a - transform_points(T_tibia, local), axis=1)
    maps = (affine_point_map(model.femur, a, reach=LINK_REACH), affine_point_map(model.tibia, b, reach=LINK_REACH))
    return MappedSprings(model.grid, a, b, k, rest_length=rest, maps=maps, low_rank=True)


def _evaluate(model, prior, truth_tf, x=None, T_femur=None, T_tibia=None, T_world=None):
    """Target point errors in the world (camera scene) frame: from the FEM state ``x`` (model frame, taken
    to the world by ``T_world``), or from world bone poses (method iv)."""
    targets, truth_f, truth_t = truth_targets(model, prior, truth_tf)
    if x is not None:
        Tw = np.eye(4) if T_world is None else T_world
        est_f = transform_points(Tw, TrilinearMapping(model.grid, targets.femur).apply(x))
        est_t = transform_points(Tw, TrilinearMapping(model.grid, targets.tibia).apply(x))
    else:
        T0 = joint_to_pose(prior.solve(0.0)[0])
        est_f = transform_points(T_femur, targets.femur)
        est_t = transform_points(T_tibia @ invert_poses(T0), targets.tibia)
    return target_errors(targets, est_f, est_t, truth_f, truth_t)[0]


LINK_TOLERANCE = 4.0  # mm: beyond the prior's accuracy (2 mm per endpoint, so up to 4 mm on a length)


def _surfaces_fem(model, x, T_world=None):
    Tw = np.eye(4) if T_world is None else T_world
    return {name: transform_points(Tw, TrilinearMapping(model.grid, np.asarray(m.vertices)).apply(x))
            for name, m in (("femur", model.femur_surface), ("tibia", model.tibia_surface))}


class quasi_static:
    """Within this context the implicit solver takes quasi-static steps: the Rayleigh stiffness damping
    is off, so with the (tiny) lumped masses each step is a Newton step towards the static equilibrium,
    ((1 + dt a) M + dt^2 K) dx = dt^2 f, instead of a third of one as with the paper's damping (b = 0.1 s,
    dt = 0.05 s). The prior's methods look for the equilibrium, not for a motion: the same answer in
    about half the steps."""

    def __init__(self, solver):
        self.s = solver

    def __enter__(self):
        self.b, self.s.b = self.s.b, 0.0
        self.s.invalidate()
        return self.s

    def __exit__(self, *exc):
        self.s.b = self.b
        self.s.invalidate()
        return False


#: The surface phase stops when the skin's remaining motion to its equilibrium, extrapolated from the last
#: two steps, is below this (mm, mean over the skin points): a quarter of the depth noise (1 mm at 35 cm).
#: 0.1 mm took 20-40 % more steps for footprint errors within 0.05 mm (five standard cases, measured).
SETTLED_MM = 0.25


def _surface_phase(model, surf, max_steps, steps):
    """Steps with the surface forces until the skin has settled; returns (steps, converged).

    Quasi-static steps are Newton steps, whose skin motions m_k fall about geometrically: the motion still
    to come is about m_k r / (1 - r), r = m_k / m_(k-1) (capped at 0.9). The phase stops when m_k plus
    that is below :data:`SETTLED_MM`, at about half the steps of waiting for the motion itself to vanish."""
    s = model.solver
    skin_prev = surf.map.apply(s.x)
    extent = float(np.ptp(model.grid.X, axis=0).max())
    last = None
    for _ in range(max_steps):
        s.step()
        steps += 1
        check_state(model, steps, extent)  # the same divergence checks as the paper's method
        skin = surf.map.apply(s.x)
        motion = float(np.linalg.norm(skin - skin_prev, axis=1).mean())
        skin_prev = skin
        if last is not None and motion + remaining_motion(motion, last) < SETTLED_MM:
            return steps, True
        last = motion
    return steps, False


def remaining_motion(motion: float, previous: float, cap: float = 0.9) -> float:
    """The motion still to come after a step that moved ``motion`` following one that moved ``previous``,
    if the motions keep falling by their last ratio r (capped at ``cap``): the geometric tail
    motion r / (1 - r)."""
    r = min(motion / max(previous, 1e-12), cap)
    return motion * r / (1.0 - r)


def run_method(method: str, truth: Mechanism, prior: Mechanism, flexion_deg: float, camera=None,
               noise=DepthNoise(), seed: int = 0, max_steps: int = 80, model: AssociationModel | None = None,
               progress=False, points=None) -> MethodResult:
    """Run one method on one case (see the module docstring). ``points``: the case's depth points, when
    already rendered (they are rendered from ``truth`` otherwise).

    Fallbacks, each stated in the result's notes: when the flexion cannot be estimated from the point cloud
    (too few points, too little of the shank seen), methods (ii) and (iii) fall back to the paper's method
    and (iv) fails; when the FEM bones cannot satisfy the prior's links (a link more than 4 mm off its
    length at convergence), (iii) releases the links and continues as (ii)."""
    if method not in METHODS:
        raise KneeInputError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    cam = camera or default_camera()
    t0 = time.perf_counter()
    notes = []
    model = model or build_association_model(prior)
    if points is None:
        pts, truth_tf = case_points(truth, flexion_deg, cam, noise, seed, model.settings)
    else:
        pts, truth_tf = points, truth.solve(math.radians(flexion_deg))[0]
    if method != "paper":
        t0 = time.perf_counter()  # the model is built once per prior, outside the per-case time
        try:
            est = estimate_flexion(prior, model.phantom, pts)
        except KneeInputError as e:
            if method == "kinematics":
                raise
            notes.append(f"flexion not estimated ({e}); fallback: the paper's method")
            method_run = "paper"
        else:
            method_run = method
            notes += est.warnings
    else:
        method_run = "paper"
    if method_run == "paper":
        r = run_standard_case(prior, flexion_deg, cam, noise, model=model, seed=seed, progress=progress,
                              truth=truth, points=pts, truth_tf=truth_tf)
        if r.bone_phase_end in ("stalled", "cap"):  # the paper's criterion not reached: say so
            notes.append(bone_phase_note(r))
        return MethodResult(method, r.flexion_true_deg, r.flexion_estimated_deg, r.errors, r.steps,
                            time.perf_counter() - t0, r.converged, notes, _surfaces_fem(model, model.solver.x))
    if method == "kinematics":
        tf, _ = prior.motion_at(np.array([est.flexion]))
        T0 = joint_to_pose(prior.motion_at(np.array([0.0]))[0][0])
        T_tib = est.T_world_model @ joint_to_pose(tf[0])
        errors = _evaluate(model, prior, truth_tf, T_femur=est.T_world_model, T_tibia=T_tib)
        surfaces = {"femur": transform_points(est.T_world_model, np.asarray(model.femur_surface.vertices)),
                    "tibia": transform_points(T_tib @ invert_poses(T0), np.asarray(model.tibia_surface.vertices))}
        return MethodResult(method, flexion_deg, math.degrees(est.flexion), errors, 0, time.perf_counter() - t0,
                            True, notes, surfaces)
    # the cloud in the model frame: the registration of the prior-posed skin, refined on the thigh alone
    # (the thigh is held in the model, so the femur is placed by the thigh as in the paper's method)
    # (30 ICP iterations: the estimate's registration is already close; 60 gave the same transforms)
    pts_model, _, T_reg = register_to_model(model, transform_points(invert_poses(est.T_world_model), pts), iterations=30)
    T_world = est.T_world_model @ invert_poses(T_reg)
    # the tibia off the prior's path as far as the shank's points show (its axial rotation stays the prior's)
    corr = correct_tibia(prior, model.phantom, pts_model, est.flexion, skin=est.skin)
    if not corr.applied:
        notes.append(corr.note)
    s = model.solver
    with quasi_static(s):
        return _fem_phases(method, model, prior, est, corr, pts_model, T_world, truth_tf, flexion_deg, max_steps,
                           notes, t0)


def _fem_phases(method, model, prior, est, corr, pts_model, T_world, truth_tf, flexion_deg, max_steps, notes, t0):
    """Methods (ii) and (iii) after the registration: initialisation, surface phase, evaluation."""
    s = model.solver
    steps = initialise_from_prior(model, prior, est.flexion, correction_xi=corr.xi)
    surf = SurfaceForces(model.grid, model.skin_vertices, pts_model, k=2.0)
    s.fields.append(surf)
    links = None
    if method == "links":
        links = link_springs(model, prior, T_tibia=corr.T)
        s.fields.append(links)
    s.invalidate()
    try:
        steps, converged = _surface_phase(model, surf, max_steps, steps)
        if links is not None:
            off = np.abs(np.linalg.norm(links.mb.apply(s.x) - links.ma.apply(s.x), axis=1) - links.L0)
            if off.max() > LINK_TOLERANCE:
                names = [lk.name for lk in prior.params.links]
                notes.append(f"the FEM bones do not satisfy the prior's links ({names[int(off.argmax())]} "
                             f"{off.max():.2f} mm off its length); fallback: links released, continued as (ii)")
                s.fields.remove(links)
                links = None
                s.invalidate()
                steps, converged = _surface_phase(model, surf, max_steps, steps)
    finally:
        for f in (surf, links):
            if f is not None and f in s.fields:
                s.fields.remove(f)
        s.invalidate()
    flex, _ = knee_angles(model)
    errors = _evaluate(model, prior, truth_tf, x=s.x, T_world=T_world)
    return MethodResult(method, flexion_deg, flex, errors, steps, time.perf_counter() - t0, converged, notes,
                        _surfaces_fem(model, s.x, T_world), corr)


def prior_floor(model: AssociationModel, truth: Mechanism, prior: Mechanism, flexions_deg,
                step_deg: float = 0.25) -> list[dict]:
    """What the prior's links allow at best: for each true flexion, the tibia's target point errors of the
    prior posed at its best-matching flexion (footprints), with the femur placed exactly. A method that
    holds the bones to the prior's links (iii) cannot do better on the tibia than this unless the depth
    points move the tibia off the prior's path.

    The remaining pose error is split into the rotation about the tibia's long axis (its y axis: the axial
    rotation, which the skin around the shank, a surface of revolution about that axis, cannot show) and
    the rest (which the skin can show); ``tibia_footprints_axial_mm`` is the footprint error that the axial
    part alone leaves, i.e. what even a perfect use of the depth points would be left with.

    Rows: flexion, best prior flexion, tibia footprints and epiphysis (mm), the axial rotation still off
    (deg) and the footprint error it alone leaves (mm)."""
    from scipy.spatial.transform import Rotation

    from models.fem.case import target_points

    tg = target_points(model, prior)
    T0 = joint_to_pose(prior.solve(0.0)[0])
    local = transform_points(invert_poses(T0), tg.tibia)
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
        rows.append({"flexion_deg": float(fl), "prior_flexion_deg": math.degrees(alphas[i]),
                     "tibia_footprints_mm": float(fp[i]), "tibia_epiphysis_mm": float(d[i].mean()),
                     "axial_rotation_deg": float(np.degrees(twist.magnitude()) * np.sign(q[1] * q[3])),
                     "tibia_footprints_axial_mm": float(axial)})
    return rows


def result_row(camera_name: str, flexion_deg: float, r: MethodResult) -> dict:
    """One row of the comparison table from a method's result."""
    return {"method": r.method, "camera": camera_name, "flexion_true_deg": float(flexion_deg),
            "flexion_estimated_deg": r.flexion_estimated_deg,
            "femur_footprints_mm": r.errors["femur"]["footprints"][0],
            "tibia_footprints_mm": r.errors["tibia"]["footprints"][0],
            "femur_epiphysis_mm": r.errors["femur"]["epiphysis"][0],
            "tibia_epiphysis_mm": r.errors["tibia"]["epiphysis"][0],
            "steps": r.steps, "wall_seconds": r.wall_seconds, "converged": r.converged,
            "tibia_correction_deg": _norm_or_nan(r.tibia_correction, "rotation_deg"),
            "tibia_correction_mm": _norm_or_nan(r.tibia_correction, "translation_mm"),
            "notes": "; ".join(r.notes), "failed": ""}


def _norm_or_nan(corr: TibiaCorrection | None, attr: str) -> float:
    return float(np.linalg.norm(getattr(corr, attr))) if corr is not None and corr.applied else float("nan")


def compare_cases(truth: Mechanism, prior: Mechanism, flexions_deg, cameras: dict, methods=METHODS,
                  noise=DepthNoise(), seed: int = 0, progress=None, on_result=None) -> list[dict]:
    """Every method on every (flexion, camera) case; one row per run with the errors and timings.
    ``cameras``: {name: Camera}. ``progress(done, total, text)`` is called before each run;
    ``on_result(camera_name, flexion_deg, method, result, truth_tf)`` after each successful one. A case
    whose flexion lies outside the truth's assembly range is reported as failed for every method."""
    rows = []
    total = len(cameras) * len(flexions_deg) * len(methods)
    done = 0
    for cam_name, cam in cameras.items():
        for fl in flexions_deg:
            fl = float(fl)
            if not truth.in_range(math.radians(fl)):
                lo, hi = (math.degrees(v) for v in truth.assembly_range)
                for method in methods:
                    rows.append({"method": method, "camera": cam_name, "flexion_true_deg": fl,
                                 "failed": f"{fl:g} deg is outside the truth's assembly range ({lo:.1f} to {hi:.1f})"})
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
                except KneeInputError as e:
                    rows.append({"method": method, "camera": cam_name, "flexion_true_deg": fl, "failed": str(e)})
                    continue
                if on_result:
                    on_result(cam_name, fl, method, r, truth_tf)
                rows.append(result_row(cam_name, fl, r))
    if progress:
        progress(total, total, "done")
    return rows
