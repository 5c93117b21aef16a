"""The standard case of the association model, built from the phantom, and its evaluation (seed 000, 3).

Truth: the phantom's bones posed by the mechanism at a flexion angle, with the skin of that pose; a
virtual RGB-D camera sees the skin (one side, with depth noise). The model starts from extension (thigh
held, femur frame), is registered to the camera by ICP on the thigh, then deformed: bone forces until
the femur-tibia angle is below 100 degrees, then surface forces towards the depth points until the skin
stops moving. Where the forces cannot bend the knee that far (the phantom's tissue holds it near 36
degrees), the bone phase also ends when the knee has stopped flexing under them
(:func:`bone_phase_stalled`; the result says which criterion ended it), instead of pushing on to the
step cap: the extra steps only cost time (measured on the demo case: the same result, 135 steps
instead of 232). Errors are distances between estimated and true bone surface points: the ACL and PCL
footprints (surface within ``footprint_radius`` of the mechanism's attachment points) and the whole
epiphysis (surface within ``epiphysis_length`` of the joint line), mean and sd per bone.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

import numpy as np
import trimesh

from models.fem.depth import Camera, DepthNoise, backproject, icp, render_depth
from models.fem.elements import hex_inverted
from models.fem.forces import BoneForces, SurfaceForces
from models.fem.mapping import TrilinearMapping
from models.fem.scene import AssociationModel, FemSettings, build_association_model, knee_angles
from models.mechanism.solver import Mechanism
from toolkit.conventions import invert_poses, joint_to_pose, transform_points
from toolkit.errors import KneeInputError


def default_camera(distance: float = 350.0, azimuth_deg: float = 35.0, elevation_deg: float = 30.0,
                   target=(0.0, -20.0, 0.0)) -> Camera:
    """An oblique camera ``distance`` mm from the knee, anterior, turned ``azimuth`` towards lateral and
    raised ``elevation`` towards proximal (femur frame)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    d = np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
    t = np.asarray(target, float)
    return Camera.looking_at(t + distance * d, t, up=(0.0, 1.0, 0.0))


CAMERA_PLACEMENTS = {"oblique": 35.0, "frontal": 0.0, "lateral": 70.0}  # azimuth towards lateral, deg


def camera_from_spec(text: str) -> Camera:
    """A camera from a placement name (``oblique``, ``frontal``, ``lateral``: 350 mm away, raised 30 deg)
    or ``AZIMUTH,ELEVATION,DISTANCE`` (deg, deg, mm)."""
    t = str(text).strip().lower()
    if t in CAMERA_PLACEMENTS:
        return default_camera(azimuth_deg=CAMERA_PLACEMENTS[t])
    try:
        az, el, dist = (float(v) for v in t.split(","))
    except ValueError:
        raise KneeInputError(f"camera must be one of {', '.join(CAMERA_PLACEMENTS)} or AZIMUTH,ELEVATION,DISTANCE "
                             f"(deg, deg, mm), got {text!r}") from None
    if not (np.isfinite([az, el, dist]).all() and 100.0 <= dist <= 2000.0 and -80.0 <= el <= 80.0):
        raise KneeInputError(f"camera distance must be 100-2000 mm and elevation within +-80 deg, got {text!r}")
    return default_camera(distance=dist, azimuth_deg=az, elevation_deg=el)


def truth_phantom(mech: Mechanism, settings: FemSettings | None = None):
    """The phantom of a parameter set built like the association model's (the truth's bones of a case, or
    the bones a prior's model is built from)."""
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
    icp_fitness: float = float("nan")                # of the registration of the cloud to the model
    # why the bone-force phase ended: "angle" (femur-tibia angle below 100 deg, the paper's criterion),
    # "stalled" (the knee stopped flexing under the forces) or "cap" (a third of the step budget)
    bone_phase_end: str = ""
    bone_phase_flexion_deg: float = float("nan")     # the flexion the bone forces reached


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


def truth_targets(model: AssociationModel, mech: Mechanism, truth_tf):
    """The target points of ``model`` (built from ``mech``) and where they truly are: the femur's at
    rest, the tibia's moved from the model's extension pose to the true TF pose ``truth_tf``.
    Returns (TargetPoints, true femur points, true tibia points)."""
    targets = target_points(model, mech)
    T0 = joint_to_pose(mech.solve(0.0)[0])
    truth_t = transform_points(joint_to_pose(np.asarray(truth_tf, float)) @ invert_poses(T0), targets.tibia)
    return targets, targets.femur, truth_t


def target_errors(targets: TargetPoints, est_f, est_t, truth_f, truth_t):
    """Per bone {"footprints": (mean, sd), "epiphysis": (mean, sd)} (mm) of the distances between the
    estimated and true target points, and the distances themselves {bone: (P,)}."""
    out, dist = {}, {}
    for bone, est, tru, fp in (("femur", est_f, truth_f, targets.femur_footprints),
                               ("tibia", est_t, truth_t, targets.tibia_footprints)):
        d = np.linalg.norm(np.asarray(est) - np.asarray(tru), axis=1)
        out[bone] = {"footprints": (float(d[fp].mean()), float(d[fp].std())),
                     "epiphysis": (float(d.mean()), float(d.std()))}
        dist[bone] = d
    return out, dist


def bone_phase_stalled(flexions, steps: int = 10, deg: float = 0.5) -> bool:
    """Whether the knee has stopped flexing under the bone forces: the largest flexion reached (a running
    maximum, as the flexion oscillates under the forces) grew less than ``deg`` over the last ``steps``
    steps of ``flexions`` (deg, one per bone-force step). ``steps=0`` or ``deg=0`` never stalls (the running
    maximum cannot fall)."""
    f = np.asarray(flexions, float)
    if steps <= 0 or len(f) <= steps:
        return False
    reached = np.maximum.accumulate(f)
    return bool(reached[-1] - reached[-1 - steps] < deg)


def bone_phase_note(r: CaseResult) -> str:
    """One line on how the bone-force phase of the paper's method ended (empty when no bone phase ran)."""
    if r.bone_phase_end == "angle":
        return (f"bone forces stopped at {r.bone_phase_flexion_deg:.1f} deg flexion: femur-tibia angle below 100 deg "
                f"(the paper's criterion) after {r.steps_bone_phase} steps")
    if r.bone_phase_end == "stalled":
        return (f"bone forces stopped at {r.bone_phase_flexion_deg:.1f} deg flexion after {r.steps_bone_phase} steps: "
                f"the knee stopped flexing under them (the paper's femur-tibia angle below 100 deg not reached)")
    if r.bone_phase_end == "cap":
        return (f"bone forces stopped at {r.bone_phase_flexion_deg:.1f} deg flexion at the step cap "
                f"({r.steps_bone_phase} steps; femur-tibia angle below 100 deg not reached)")
    return ""


class FemDivergence(KneeInputError):
    """The simulation stopped: non-finite values, inverted elements or an energy blow-up at ``step``."""

    def __init__(self, message: str, step: int):
        super().__init__(message)
        self.step = step


MIN_POINTS = 500          # fewer depth points than this cannot place the knee
MIN_ICP_FITNESS = 0.3     # fraction of the seen thigh's points matched by the registration
MAX_INVERTED_FRACTION = 0.05


def check_state(model: AssociationModel, step: int, x0_extent: float) -> int:
    """Stop with :class:`FemDivergence` (naming the step) on non-finite positions, an energy blow-up (a node
    moved more than twice the model's extent, or faster than 20 m/s) or more than 5 % of the grid's (not
    dropped) cells inverted; returns the number of inverted cells."""
    s = model.solver
    if not (np.all(np.isfinite(s.x)) and np.all(np.isfinite(s.v))):
        raise FemDivergence(f"the FEM diverged at step {step}: non-finite positions or velocities", step)
    disp = float(np.abs(s.x - model.grid.X).max())
    speed = float(np.abs(s.v).max())
    if disp > 2.0 * x0_extent or speed > 2.0e4:
        raise FemDivergence(f"the FEM diverged at step {step}: energy blow-up (largest displacement {disp:.0f} mm, "
                            f"largest speed {speed:.0f} mm/s)", step)
    alive = model.soft.el.alive  # cells dropped at a re-reference carry no stiffness and are not counted
    inverted = int(hex_inverted(s.x[model.grid.cells[alive]]).sum())
    model.inverted_cells = inverted
    if inverted > MAX_INVERTED_FRACTION * alive.sum():
        raise FemDivergence(f"the FEM diverged at step {step}: {inverted} of {int(alive.sum())} grid cells "
                            f"inverted", step)
    return inverted


def case_points(truth: Mechanism, flexion_deg: float, camera: Camera, noise: DepthNoise | None, seed: int = 0,
                settings: FemSettings | None = None):
    """The standard case's input: the depth points (P, 3) a virtual camera sees of the skin of ``truth``'s
    phantom posed at ``flexion_deg`` (with noise), and the truth's TF joint coordinates."""
    ph = truth_phantom(truth, settings)
    tf, pf, _ = truth.solve(np.radians(flexion_deg))
    skin = ph.skin(joint_to_pose(tf), joint_to_pose(pf) if truth.has_pf else None)
    depth = render_depth(skin.vertices, skin.faces, camera)
    if noise is not None:
        depth = noise.apply(depth, np.random.default_rng(seed))
    return backproject(depth, camera.K, camera.T_world_cam), tf


def _thigh_samples(model: AssociationModel) -> tuple[np.ndarray, np.ndarray]:
    """Points spread densely over the model's thigh skin (the skin's vertices are ~15 mm apart) and their
    faces' normals; sampled once per model (the skin at extension does not change)."""
    cached = getattr(model, "_thigh_samples_cache", None)
    if cached is None:
        skin = trimesh.Trimesh(model.skin_vertices, model.skin_faces, process=False)
        dense, face = trimesh.sample.sample_surface(skin, 30000, seed=0)
        keep = dense[:, 1] > 60.0
        cached = model._thigh_samples_cache = (dense[keep], skin.face_normals[face[keep]])
    return cached


def register_to_model(model: AssociationModel, points, iterations: int = 60) -> tuple[np.ndarray, float, np.ndarray]:
    """Bring a point cloud (world/camera frame, roughly aligned with the model) to the model's frame by
    ICP of the seen thigh onto the model's thigh (the thigh is held, so the femur is where the model has
    it); returns the points in the model frame, the ICP fitness and the transform (4, 4) applied. Raises
    on too few points or a failed registration. ``iterations``: of the ICP (fewer suffice when the points
    come registered by the flexion estimate)."""
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < MIN_POINTS:
        raise KneeInputError(f"the point cloud has {len(pts) if pts.ndim == 2 else 0} points; at least {MIN_POINTS} "
                             f"are needed to place the knee")
    thigh_model, thigh_normals = _thigh_samples(model)
    thigh_seen = pts[pts[:, 1] > 70.0]
    if len(thigh_seen) < 200:
        raise KneeInputError(f"only {len(thigh_seen)} depth points on the thigh (more than 70 mm above the joint); "
                             f"at least 200 are needed for the registration")
    T_reg, fitness, _ = icp(thigh_seen[::3], thigh_model, max_distance=10.0, iterations=iterations,
                            target_normals=thigh_normals)
    if fitness < MIN_ICP_FITNESS:
        raise KneeInputError(f"the registration of the point cloud to the model failed (ICP fitness {fitness:.2f}, "
                             f"below {MIN_ICP_FITNESS})")
    return pts @ T_reg[:3, :3].T + T_reg[:3, 3], fitness, T_reg


def run_standard_case(mech: Mechanism, flexion_deg: float = 90.0, camera: Camera | None = None,
                      noise: DepthNoise | None = DepthNoise(), settings: FemSettings | None = None,
                      bone_force_scale: float = 1.0, surface_k: float = 2.0, max_steps: int = 400,
                      bone_stall_deg: float = 0.5, bone_stall_steps: int = 10,
                      model: AssociationModel | None = None, seed: int = 0, progress=True,
                      truth: Mechanism | None = None, points=None, truth_tf=None, on_step=None) -> CaseResult:
    """Run the paper's method on the phantom standard case; see the module docstring. ``truth``: another
    parameter set that generates the truth (default ``mech``: the model is built from ``mech``).

    ``points``: a measured point cloud (P, 3) in mm, in place of the virtual camera's; there is no truth
    then (unless ``truth_tf``, the true TF joint coordinates, is given), and the errors are empty.
    ``on_step(k, phase, model, surface_forces, bone_forces)`` is called after every step (e.g. to record
    it; the surface forces act in the "surface" phase only). Divergence raises :class:`FemDivergence`
    naming the step."""
    t_start = time.perf_counter()
    model = model or build_association_model(mech, settings)
    tmech = truth or mech
    cam = camera or default_camera()
    if points is None:
        pts, tf = case_points(tmech, flexion_deg, cam, noise, seed, model.settings)
    else:
        pts, tf = np.asarray(points, float), truth_tf
    pts, fitness, _ = register_to_model(model, pts)
    targets = target_points(model, mech)
    fmap = TrilinearMapping(model.grid, targets.femur)
    tmap = TrilinearMapping(model.grid, targets.tibia)
    s = model.solver
    held = bool(s.fixed.any())
    bone = BoneForces(model.femur, model.tibia, scale=bone_force_scale, use_femur=not held)
    surf = SurfaceForces(model.grid, model.skin_vertices, pts, k=surface_k)
    hist = {"step": [], "flexion_deg": [], "reference_mm": [], "within": [], "skin_motion_mm": [],
            "iterations": [], "inverted": []}
    phase, bone_steps, calm, converged = "bone", 0, 0, False
    bone_end, bone_flex, bone_flexions = "", float("nan"), []
    skin_prev = model.skin_vertices.copy()
    smap = surf.map
    extent = float(np.ptp(model.grid.X, axis=0).max())
    try:
        for k in range(max_steps):
            if phase == "bone":
                info = s.step(bone.forces)
                inverted = check_state(model, k, extent)
                bone_steps += 1
                flex, between = knee_angles(model)
                bone_flexions.append(flex)
                stalled = bone_phase_stalled(bone_flexions, bone_stall_steps, bone_stall_deg)
                if between < 100.0 or stalled or bone_steps >= max_steps // 3:
                    bone_end = "angle" if between < 100.0 else ("stalled" if stalled else "cap")
                    bone_flex = flex
                    phase = "surface"
                    s.fields.append(surf)
                    s.invalidate()  # the surface springs enter the preconditioner
            else:
                info = s.step()
                inverted = check_state(model, k, extent)
                flex, between = knee_angles(model)
            skin_now = smap.apply(s.x)
            motion = float(np.linalg.norm(skin_now - skin_prev, axis=1).mean())
            skin_prev = skin_now
            hist["step"].append(k)
            hist["flexion_deg"].append(flex)
            hist["reference_mm"].append(surf.reference if phase == "surface" else np.nan)
            hist["within"].append(surf.within_fraction if phase == "surface" else np.nan)
            hist["skin_motion_mm"].append(motion)
            hist["iterations"].append(info.iterations)
            hist["inverted"].append(inverted)
            if on_step is not None:
                on_step(k, phase, model, surf, bone)
            if progress and k % 20 == 0:
                print(f"  step {k:4d} [{phase}] flexion {flex:6.1f} deg, skin motion {motion:7.3f} mm/step",
                      file=sys.stderr, flush=True)
            if phase == "surface":
                calm = calm + 1 if motion < 0.01 else 0
                if calm >= 5:
                    converged = True
                    break
    finally:
        if surf in s.fields:
            s.fields.remove(surf)
    flex, _ = knee_angles(model)
    est_f, est_t = fmap.apply(s.x), tmap.apply(s.x)
    errors, distances = {}, {}
    if tf is not None:
        _, truth_f, truth_t = truth_targets(model, mech, tf)
        errors, distances = target_errors(targets, est_f, est_t, truth_f, truth_t)
    return CaseResult(flexion_true_deg=float(np.degrees(tf[0])) if tf is not None else float("nan"),
                      flexion_estimated_deg=flex, errors=errors,
                      steps=len(hist["step"]), steps_bone_phase=bone_steps,
                      wall_seconds=time.perf_counter() - t_start, converged=converged,
                      history={k: np.asarray(v) for k, v in hist.items()},
                      distances=distances, points={"femur": est_f, "tibia": est_t}, icp_fitness=fitness,
                      bone_phase_end=bone_end, bone_phase_flexion_deg=bone_flex)
