"""A synthetic subject folder generated from a mechanism parameter set (``knee synth-subject``).

It holds everything :mod:`knee.fitting.subject` reads, made from the procedural phantom of the parameter set
(:mod:`knee.models.phantom`), so that the fitting pipeline can be run, and its recovery measured, against a
known truth:

* ``ct/``: bone surfaces of femur, tibia and patella with the cartilage set back by 2 mm (subchondral
  bone), posed at 5 deg flexion in a CT scanner's LPS space (STL, ``SPACE=LPS``); the anatomical and
  alignment landmarks; the intercondylar-space region (``ct/areas/femur_intercondylar.mrk.json``); the
  phantom's skin envelope at the CT pose (``ct/skin.stl``).
* ``mri/``: the same bones with cartilage (the contact spheres), posed at 10 deg flexion in a second
  scanner space, written in RAS (PLY, ``SPACE=RAS``); the alignment fiducials with 0.3 mm
  identification noise; the ligament and patellar-tendon attachment areas and the
  articular regions for the sphere fits (markups point lists). All markups are written in LPS.
* ``motion.csv``: the measured TF and PF motion, 0 to 120 deg, with fluoroscopy-like noise
  (:data:`knee.fitting.optimize.NOISE_SD`).
* ``truth.toml``: the generating parameter set (only synthetic subjects have it; the fit report then
  compares the fitted motion with the noise-free truth).

Phantom simplifications, stated because they shape the data: the bones are schematic (spheres,
cylinders), so the ligament attachment points are not on the bone surfaces; the attachment areas are
point grids (1 mm spacing, 3 mm radius; 4 mm for the tendon) around a centre up to 1 mm from the true
endpoint, and ``subject.toml`` turns off the projection of the tendon-area centroids onto the surfaces.
The phantom has no trochlear groove: the intercondylar-space points lie on the plane that gives the
true helical pitch. The landmarks are placed so that the frames of :mod:`knee.fitting.frames` coincide with
the phantom's bone frames.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from knee.fitting.frames import FIDUCIALS, LANDMARKS
from knee.fitting.optimize import synthetic_motion
from knee.foundations.conventions import (
    joint_to_pose,
    rot_x,
    rot_y,
    rot_z,
    transform_points,
)
from knee.foundations.errors import KneeInputError
from knee.foundations.imaging import write_markups, write_motion_csv, write_surface
from knee.models.mechanism import Mechanism
from knee.models.mechanism.params import load_model, save_toml, toml_string
from knee.models.phantom import TROCHLEA_OFFSET, build_phantom, trochlea_radius

#: Anatomical (right knee) axes in LPS: x anterior = -P, y proximal = +S, z lateral = -L.
ANATOMICAL_IN_LPS = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

#: Landmark positions in each bone's frame (mm), placed so the frame definitions give the bone frame.
BONE_LANDMARKS = {
    "femur": {"LE": [0.0, 0.0, 45.0], "ME": [0.0, 0.0, -45.0], "HIP": [0.0, 430.0, 0.0]},
    "tibia": {"LIT": [0.0, 0.0, 6.0], "MIT": [0.0, 0.0, -6.0], "PMP": [-30.0, -8.0, -28.0],
              "PLP": [-30.0, -8.0, 28.0], "LM": [-5.0, -370.0, 30.0], "MM": [5.0, -370.0, -30.0]},
    "patella": {"PSUP": [0.0, 22.0, 0.0], "PINF": [0.0, -22.0, 0.0], "PLAT": [0.0, 0.0, 20.0],
                "PMED": [0.0, 0.0, -20.0]},
}
CT_FLEXION_DEG = 5.0
MRI_FLEXION_DEG = 10.0
FIDUCIAL_NOISE_MM = 0.3
CARTILAGE_MM = 2.0


def _scanner_pose(rng, t) -> np.ndarray:
    """Pose of the femur frame in a scanner's LPS space: the anatomical orientation, tilted by up to
    8 deg about each axis, at ``t``."""
    a = np.radians(rng.uniform(-8, 8, size=3))
    T = np.eye(4)
    T[:3, :3] = ANATOMICAL_IN_LPS @ rot_x(a[0]) @ rot_y(a[1]) @ rot_z(a[2])
    T[:3, 3] = t
    return T


def _sphere_region(mesh, centre, radius, direction, min_cos, tol=0.05):
    """Vertices of ``mesh`` on the sphere (within ``tol``) within acos(min_cos) of ``direction``."""
    v = mesh.vertices
    d = v - centre
    r = np.linalg.norm(d, axis=1)
    u = direction / np.linalg.norm(direction)
    keep = (np.abs(r - radius) < tol) & ((d @ u) > min_cos * r)
    return v[keep]


def _ball_grid(centre, radius, spacing=1.0):
    k = np.arange(-radius, radius + 1e-9, spacing)
    g = np.stack(np.meshgrid(k, k, k, indexing="ij"), axis=-1).reshape(-1, 3)
    return centre + g[np.linalg.norm(g, axis=1) <= radius + 1e-9]


#: Frames of a synthetic subject's measured motion: the fewest a fit can use, the most worth writing.
MIN_FRAMES, MAX_FRAMES = 10, 10_000


def make_subject(out_dir, model: str = "volunteer", seed: int = 0, frames: int = 60, flexion_to: float = 120.0,
                 noise: bool = True) -> Path:
    """Write a synthetic subject folder from a bundled parameter set (see the module docstring) and return
    its path. ``out_dir`` must not exist or be empty; ``frames`` of measured motion from 0 to
    ``flexion_to`` deg, with fluoroscopy-like noise unless ``noise`` is False; surfaces in mm (LPS STL for
    the CT, RAS PLY for the MRI)."""
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise KneeInputError(f"{out} exists and is not empty; not overwritten")
    params = load_model(model)
    if not params.has_pf:
        raise KneeInputError(f"model {params.name!r} has no patella; the synthetic subject needs TF and PF groups")
    if len([lk for lk in params.links if lk.role == "contact" and lk.kind == "distance"]) != 2:
        raise KneeInputError(f"model {params.name!r}: the synthetic subject needs two sphere-sphere contacts")
    if not MIN_FRAMES <= frames <= MAX_FRAMES:
        raise KneeInputError(f"the motion needs {MIN_FRAMES}-{MAX_FRAMES} frames, got {frames}")
    rng = np.random.default_rng(seed)
    mech = Mechanism(params)
    lo, hi = (math.degrees(v) for v in mech.assembly_range)
    if not (lo <= 0.0 and flexion_to <= hi):
        raise KneeInputError(f"model {params.name!r} assembles only from {lo:.1f} to {hi:.1f} deg; cannot "
                             f"generate a motion from 0 to {flexion_to:.0f} deg")
    ct = build_phantom(params, cartilage=CARTILAGE_MM, trochlea="spheres")
    mri = build_phantom(params, cartilage=0.0, trochlea="spheres")
    for d in ("ct/areas", "mri/areas"):
        (out / d).mkdir(parents=True, exist_ok=True)

    # ---- scanner spaces: bone poses in LPS
    def scene(flex_deg, t):
        Tf = _scanner_pose(rng, t)
        tf, pf, _ = mech.solve(math.radians(flex_deg))
        return {"femur": Tf, "tibia": Tf @ joint_to_pose(tf), "patella": Tf @ joint_to_pose(pf)}

    T_ct = scene(CT_FLEXION_DEG, np.array([-90.0, -140.0, 310.0]))
    T_mri = scene(MRI_FLEXION_DEG, np.array([35.0, 10.0, -60.0]))

    # ---- landmarks (PAL: the most anterior femur vertex of the lateral ridge region)
    fv = ct.femur.vertices
    ridge = fv[(fv[:, 2] > 8) & (fv[:, 1] > 10) & (fv[:, 1] < 40)]
    lm = {b: {k: np.asarray(v, float) for k, v in d.items()} for b, d in BONE_LANDMARKS.items()}
    lm["femur"]["PAL"] = ridge[np.argmax(ridge[:, 0])]
    ct_labels, ct_points, mri_labels, mri_points = [], [], [], []
    for bone in ("femur", "tibia", "patella"):
        for key in LANDMARKS[bone]:
            ct_labels.append(key)
            ct_points.append(transform_points(T_ct[bone], lm[bone][key][None])[0])
        for key in FIDUCIALS[bone]:
            mri_labels.append(key)
            p = transform_points(T_mri[bone], lm[bone][key][None])[0]
            mri_points.append(p + rng.normal(scale=FIDUCIAL_NOISE_MM, size=3))
    write_markups(out / "ct/landmarks.mrk.json", ct_labels, ct_points, "LPS")
    write_markups(out / "mri/landmarks.mrk.json", mri_labels, mri_points, "LPS")

    # ---- surfaces
    for bone in ("femur", "tibia", "patella"):
        write_surface(out / f"ct/{bone}.stl", getattr(ct, bone).copy().apply_transform(T_ct[bone]), "LPS")
        write_surface(out / f"mri/{bone}.ply", getattr(mri, bone).copy().apply_transform(T_mri[bone]), "RAS")
    tf_ct, pf_ct, _ = mech.solve(math.radians(CT_FLEXION_DEG))
    skin = ct.skin(joint_to_pose(tf_ct), joint_to_pose(pf_ct))  # the phantom's envelope at the CT pose
    write_surface(out / "ct/skin.stl", skin.apply_transform(T_ct["femur"]), "LPS")

    def mri_area(name, bone, pts, labels=None):
        pts = transform_points(T_mri[bone], np.asarray(pts, float))
        write_markups(out / f"mri/areas/{name}.mrk.json", labels or [name] * len(pts), pts, "LPS",
                      kind="PointList")

    # ---- articular regions for the sphere fits (on the MRI surfaces, bone frames)
    up = np.array([0.0, 1.0, 0.0])
    for lk in params.links:
        if lk.role != "contact":
            continue
        side = "lateral" if lk.femur[2] > 0 else "medial"
        rf = lk.femur_radius
        outward = np.array([0.0, 0.0, 1.0 if side == "lateral" else -1.0])
        mri_area(f"femur_{side}_condyle", "femur",
                 _sphere_region(mri.femur, lk.femur, rf, np.array([-1.0, -0.4, 0.0]) + 0.6 * outward, 0.55))
        rt = lk.length - rf if lk.tibia_surface == "convex" else lk.length + rf
        mri_area(f"tibia_{side}_facet", "tibia",
                 _sphere_region(mri.tibia, lk.tibia, rt, up if lk.tibia_surface == "convex" else -up, 0.9))
    pf = params.pf
    n = pf.axis_femur / np.linalg.norm(pf.axis_femur)
    rt = trochlea_radius(params)
    for s_, side in ((1, "lateral"), (-1, "medial")):
        c = pf.point_femur + s_ * TROCHLEA_OFFSET * n
        mri_area(f"femur_{side}_trochlea", "femur",
                 _sphere_region(mri.femur, c, rt, np.array([1.0, 0.2, 0.0]) + 0.5 * s_ * n, 0.5))

    # ---- attachment areas: grids around centres within 1 mm of the true endpoints
    def centre(p):
        d = rng.normal(size=3)
        return np.asarray(p, float) + rng.uniform(0, 1.0) * d / np.linalg.norm(d)

    for lk in params.links:
        if lk.role != "ligament":
            continue
        for bone, p in (("femur", lk.femur), ("tibia", lk.tibia)):
            c = centre(p)
            g = _ball_grid(c, 3.0)
            labels = (["am" if (q - c)[1] >= 0 else "pl" for q in g] if lk.name == "acl" else [lk.name] * len(g))
            mri_area(f"{lk.name}_{bone}", bone, g, labels)
    mri_area("tendon_tibia", "tibia", _ball_grid(centre(pf.tendon_tibia), 4.0))
    mri_area("tendon_patella", "patella", _ball_grid(centre(pf.tendon_patella), 4.0))

    # ---- intercondylar space (CT): the plane that gives the true pitch (module docstring)
    _, pf_ref, _ = mech.solve(pf.reference_flexion)
    d = pf_ref[3:] - pf.point_femur
    d -= (d @ n) * n
    rho = float(np.linalg.norm(d))
    u = d / rho
    m = n - pf.lambda1 / rho * np.cross(n, u)
    m /= np.linalg.norm(m)
    e1 = np.cross(m, u)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m, e1)
    k = np.linspace(-8, 8, 9)
    a, b = np.meshgrid(k, k)
    plane = pf.point_femur + 0.6 * rho * u + a.reshape(-1, 1) * e1 + b.reshape(-1, 1) * e2
    plane += rng.normal(scale=0.05, size=plane.shape)
    write_markups(out / "ct/areas/femur_intercondylar.mrk.json", ["intercondylar"] * len(plane),
                  transform_points(T_ct["femur"], plane), "LPS", kind="PointList")

    # ---- motion and truth
    flex = np.linspace(0.0, flexion_to, frames)
    measured, _ = synthetic_motion(params, flex, noise=noise, seed=seed)
    write_motion_csv(out / "motion.csv", measured.tf, measured.pf)
    save_toml(params, out / "truth.toml")
    (out / "subject.toml").write_text(
        f'# Synthetic subject generated by "knee synth-subject" from the parameter set '
        f'{" ".join(params.name.split())!r}, seed {seed}.\n'
        'format = "knee-subject"\nversion = 1\n'
        f'name = {toml_string("synthetic-" + params.name)}\nside = "{params.side}"\n\n[pf]\n'
        f"reference_flexion_deg = {math.degrees(pf.reference_flexion):.6g}\n"
        "# the phantom's tendon attachment points are not on its schematic bone surfaces (see the README)\n"
        "project_tendon = false\n", encoding="utf-8")
    return out
