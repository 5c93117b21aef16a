"""The fitting pipeline, from a subject folder to a fitted mechanism (seed 002, sections 2.2-2.4;
``knee fit SUBJECT_DIR --out OUT_DIR``).

Steps, each a function of this module:

1. :func:`anatomical_frames`: femur, tibia and patella frames from the CT landmarks.
2. :func:`align_mri`: MRI-to-CT rigid alignment per bone from the fiducials (least squares), with the
   fiducial registration error of each point.
3. :func:`contact_spheres`: sphere fits to the posterior femoral condyles and the tibial facets (MRI, with
   cartilage) -> the two contact links; :func:`helical_axis`: spheres fitted to the anterior condyles give
   the patellar helical axis; :func:`helical_pitch`: the plane fitted to the intercondylar space (CT)
   gives its pitch.
4. :func:`ligament_fibres`: the isometric fibre of each ligament within its attachment areas over the
   measured motion (restricted to the bundle named in subject.toml).
5. :func:`first_estimate`: the patellar tendon link (area centroids, optionally projected onto the CT
   surfaces), the PF reference pose mid-arc, link lengths at full extension, assembled into a parameter
   set.
6. :func:`fitting.optimize.fit_tf` then :func:`fitting.pf.fit_pf`: the bounded optimisation.
7. :func:`validate`: MAE and MAX of every component (seed 002 Table 2 layout); :func:`write_outputs`
   writes the parameter files, the report (JSON, Markdown), the figure and the Rerun recording.

All geometry of a step is expressed in the bone frames (mm, x anterior, y proximal, z lateral).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from fitting.frames import FIDUCIALS, FRAME_FUNCTIONS, check_consistent
from fitting.isometric import isometric_fibre
from fitting.optimize import Motion, fit_tf, noise_weights
from fitting.pf import fit_pf
from fitting.subject import LIGAMENTS, Subject, load_subject
from models.mechanism.params import InitialPose, Link, MechanismParams, PFGroup, load_model, save_toml
from models.mechanism.solver import Mechanism, quick_tf_sweep
from toolkit.conventions import invert_poses, joint_to_pose, transform_points
from toolkit.errors import AssemblyError, KneeInputError
from toolkit.geometry import fit_plane, fit_sphere, rigid_register

TF_NAMES = ("flexion", "adduction", "internal_rotation", "anterior", "proximal", "lateral")
UNITS = ("deg", "deg", "deg", "mm", "mm", "mm")


# ----------------------------------------------------------------------------------------------
# Steps 1-2


def anatomical_frames(subject: Subject) -> dict[str, np.ndarray]:
    """``T_ct_bone`` (4, 4) for each bone (patella when the subject has one)."""
    bones = ("femur", "tibia", "patella") if subject.has_pf else ("femur", "tibia")
    frames = {b: FRAME_FUNCTIONS[b](subject.ct_landmarks) for b in bones}
    check_consistent(frames)
    return frames


def align_mri(subject: Subject) -> dict[str, dict]:
    """Per bone: ``T`` (MRI -> CT, (4, 4)) and ``fre`` {label: mm} from the paired fiducials."""
    out = {}
    bones = ("femur", "tibia", "patella") if subject.has_pf else ("femur", "tibia")
    for b in bones:
        labels = FIDUCIALS[b]
        T, fre = rigid_register(subject.mri_landmarks.require(labels), subject.ct_landmarks.require(labels))
        out[b] = {"T": T, "fre": dict(zip(labels, (float(v) for v in fre)))}
    return out


@dataclass
class Geometry:
    """Frames and alignment: maps points of either scan into bone frames."""

    frames: dict
    alignment: dict

    def to_bone(self, points, bone: str, space: str = "mri") -> np.ndarray:
        T = invert_poses(self.frames[bone])
        if space == "mri":
            T = T @ self.alignment[bone]["T"]
        return transform_points(T, np.asarray(points, float))


# ----------------------------------------------------------------------------------------------
# Step 3


def _sphere(subject, geo, region, bone):
    pts = geo.to_bone(subject.area(region).points, bone)
    try:
        c, r, rms = fit_sphere(pts)
    except KneeInputError as e:
        raise KneeInputError(f"region {region}: {e}") from None
    return {"centre": c, "radius": r, "rms": rms, "points": len(pts)}


def contact_spheres(subject: Subject, geo: Geometry) -> dict[str, dict]:
    """The lateral and medial contacts: femoral condyle and tibial facet spheres (bone frames), the facet's
    shape (``convex`` when its centre lies below the facet) and the link length (``R_t + R_f`` convex,
    ``R_t - R_f`` concave)."""
    out = {}
    for side in ("lateral", "medial"):
        f = _sphere(subject, geo, f"femur_{side}_condyle", "femur")
        t = _sphere(subject, geo, f"tibia_{side}_facet", "tibia")
        facet = geo.to_bone(subject.area(f"tibia_{side}_facet").points, "tibia")
        convex = t["centre"][1] < facet[:, 1].mean()
        length = t["radius"] + f["radius"] if convex else t["radius"] - f["radius"]
        if length <= 0:
            raise KneeInputError(f"{side} contact: the tibial facet (R {t['radius']:.1f} mm) is concave and smaller "
                                 f"than the femoral condyle (R {f['radius']:.1f} mm)")
        out[side] = {"femur": f, "tibia": t, "surface": "convex" if convex else "concave", "length": float(length)}
    return out


def helical_axis(subject: Subject, geo: Geometry) -> dict:
    """The helical axis in the femur frame: unit ``n`` (medial -> lateral) through the centres of the
    spheres fitted to the anterior condyles, and ``q``, its intersection with the sagittal plane z = 0."""
    lat = _sphere(subject, geo, "femur_lateral_trochlea", "femur")
    med = _sphere(subject, geo, "femur_medial_trochlea", "femur")
    d = lat["centre"] - med["centre"]
    if np.linalg.norm(d) < 5.0:
        raise KneeInputError("helical axis: the anterior condyle spheres are less than 5 mm apart")
    n = d / np.linalg.norm(d)
    if abs(n[2]) < 0.5:
        raise KneeInputError(f"helical axis: the axis is {math.degrees(math.acos(abs(n[2]))):.0f} deg from the "
                             "medio-lateral axis; check the trochlea regions")
    q = med["centre"] - med["centre"][2] / n[2] * n
    return {"n": n, "q": q, "lateral": lat, "medial": med}


def helical_pitch(subject: Subject, geo: Geometry, n, q, patella_origin) -> dict:
    """The pitch lambda1 (mm/rad) from the plane fitted to the intercondylar space (CT): a patella point at
    radius rho from the axis that follows a planar groove of normal m moves along the axis at
    ``-rho ((n x u) . m) / (n . m)`` per radian (u: the unit direction from the axis to the point)."""
    pts = geo.to_bone(subject.area("femur_intercondylar", "ct").points, "femur", "ct")
    try:
        _, m, rms = fit_plane(pts)
    except KneeInputError as e:
        raise KneeInputError(f"region femur_intercondylar: {e}") from None
    if m @ n < 0:
        m = -m
    d = patella_origin - q
    d = d - (d @ n) * n
    rho = float(np.linalg.norm(d))
    u = d / rho
    lam1 = -rho * float(np.cross(n, u) @ m) / float(n @ m)
    angle = math.degrees(math.acos(min(1.0, abs(float(m @ n)))))
    return {"lambda1": lam1, "normal": m, "rms": rms, "points": len(pts), "angle_to_axis_deg": angle, "rho": rho}


# ----------------------------------------------------------------------------------------------
# Steps 4-5


def ligament_fibres(subject: Subject, geo: Geometry, tf_motion) -> dict:
    """Isometric fibres of ACL, PCL and MCL (bone frames) over the measured motion."""
    out = {}
    for lig in LIGAMENTS:
        fa, ta = subject.area(f"{lig}_femur"), subject.area(f"{lig}_tibia")
        fm = tm = None
        if lig in subject.bundles:
            b = subject.bundles[lig]
            fm = np.array([lb == b for lb in fa.labels])
            tm = np.array([lb == b for lb in ta.labels])
            if not fm.any() or not tm.any():
                raise KneeInputError(f"bundle {b!r} of {lig}: no points labelled {b!r} in "
                                     f"{fa.source if not fm.any() else ta.source}")
        fib = isometric_fibre(geo.to_bone(fa.points, "femur"), geo.to_bone(ta.points, "tibia"), tf_motion, fm, tm)
        out[lig] = {"femur": fib.femur, "tibia": fib.tibia, "length": fib.length_at_extension,
                    "length_sd": fib.sd, "candidates": [int(len(fa.points) if fm is None else fm.sum()),
                                                        int(len(ta.points) if tm is None else tm.sum())]}
    return out


def _interp_pose(motion: Motion, group: str, flexion: float) -> np.ndarray:
    q = motion.tf if group == "tf" else motion.pf
    order = np.argsort(motion.flexion)
    a = motion.flexion[order]
    return np.array([np.interp(flexion, a, q[order, k]) for k in range(6)])


def _project(mesh_bone, p):
    from models.fem.geometry import SurfaceQuery

    return SurfaceQuery.of(mesh_bone).closest_points(np.asarray(p, float)[None])[0]


def pf_first_estimate(subject: Subject, geo: Geometry, motion: Motion, ref_deg: float) -> tuple[PFGroup, dict]:
    """The PF group from imaging and the measured motion at the reference flexion ``ref_deg``."""
    ax = helical_axis(subject, geo)
    n_f, q_f = ax["n"], ax["q"]
    a_ref = math.radians(ref_deg)
    T_tf = joint_to_pose(_interp_pose(motion, "tf", a_ref))
    T_pf = joint_to_pose(_interp_pose(motion, "pf", a_ref))
    R, P = T_pf[:3, :3], T_pf[:3, 3]
    n_p = R.T @ n_f
    a_p = R.T @ (q_f - P)
    if abs(n_p[2]) < 0.5:
        raise KneeInputError("helical axis: nearly parallel to the patella's sagittal plane at the reference pose")
    q_p = a_p - a_p[2] / n_p[2] * n_p
    lam0 = float((R @ q_p + P - q_f) @ n_f)
    pitch = helical_pitch(subject, geo, n_f, q_f, P)
    ends = {}
    for bone, area in (("tibia", "tendon_tibia"), ("patella", "tendon_patella")):
        c = geo.to_bone(subject.area(area).points, bone).mean(axis=0)
        if subject.project_tendon:
            mesh = subject.ct[bone].copy().apply_transform(invert_poses(geo.frames[bone]))
            c = _project(mesh, c)
        ends[bone] = c
    l6 = float(np.linalg.norm(transform_points(T_pf, ends["patella"][None])[0]
                              - transform_points(T_tf, ends["tibia"][None])[0]))
    pf = PFGroup(axis_femur=n_f, point_femur=q_f, axis_patella=n_p, point_patella=q_p, tendon_tibia=ends["tibia"],
                 tendon_patella=ends["patella"], tendon_length=l6, lambda0=lam0, lambda1=pitch["lambda1"],
                 reference_flexion=a_ref)
    return pf, {"axis": ax, "pitch": pitch}


def first_estimate(subject: Subject, motion: Motion | None = None) -> tuple[MechanismParams, dict]:
    """Steps 1-5: the first-estimate parameter set and what each step found (for the report)."""
    motion = motion or Motion(subject.motion.tf, subject.motion.pf)
    frames = anatomical_frames(subject)
    align = align_mri(subject)
    geo = Geometry(frames, align)
    contacts = contact_spheres(subject, geo)
    fibres = ligament_fibres(subject, geo, motion.tf)
    links = [Link(name=lig, role="ligament", kind="distance", femur=f["femur"], tibia=f["tibia"], length=f["length"])
             for lig, f in fibres.items()]
    for side, name in (("lateral", "lc"), ("medial", "mc")):
        c = contacts[side]
        links.append(Link(name=name, role="contact", kind="distance", femur=c["femur"]["centre"],
                          tibia=c["tibia"]["centre"], length=c["length"], femur_radius=c["femur"]["radius"],
                          tibia_surface=c["surface"]))
    pf, pf_info = None, {}
    if subject.has_pf:
        lo, hi = float(np.degrees(motion.flexion.min())), float(np.degrees(motion.flexion.max()))
        ref = subject.reference_flexion_deg if subject.reference_flexion_deg is not None else 0.5 * (lo + hi)
        if not lo <= ref <= hi:
            raise KneeInputError(f"PF reference flexion {ref:.1f} deg is outside the measured range {lo:.1f}..{hi:.1f}")
        pf, pf_info = pf_first_estimate(subject, geo, motion, ref)
    params = MechanismParams(name=f"{subject.name}-first-estimate", links=tuple(links), pf=pf,
                             initial=InitialPose(float(motion.tf[0, 0]), motion.tf[0, 1:].copy()),
                             description=f"First estimate of subject {subject.name} from imaging (knee fit)",
                             source=str(subject.root), side=subject.side)
    info = {"frames": frames, "alignment": align, "contacts": contacts, "fibres": fibres, "pf": pf_info,
            "geometry": geo}
    return params, info


# ----------------------------------------------------------------------------------------------
# Step 7


def model_motion(params: MechanismParams, flexion) -> tuple[np.ndarray, np.ndarray | None]:
    """The model's (tf, pf) at the given flexion angles (rad); AssemblyError when it does not assemble."""
    mech = Mechanism(params)
    sw = mech.sweep(np.asarray(flexion, float))
    if not sw.complete:
        raise AssemblyError(f"{params.name}: {sw.message}")
    return sw.tf, (sw.pf if params.has_pf else None)


def _errors(model, measured):
    d = np.asarray(model, float) - np.asarray(measured, float)
    d[:, :3] = np.degrees(d[:, :3])
    a = np.abs(d)
    return {"mae": a.mean(axis=0), "max": a.max(axis=0), "argmax": a.argmax(axis=0), "diff": d}


def validate(params: MechanismParams, motion: Motion) -> dict:
    """MAE and MAX of each component, model against ``motion`` at its flexion angles (seed 002 Table 2
    layout: TF flexion is the input; deg and mm)."""
    tf, pf = model_motion(params, motion.flexion)
    out = {"tf": _errors(tf, motion.tf), "model_tf": tf, "model_pf": pf}
    if pf is not None and motion.pf is not None:
        out["pf"] = _errors(pf, motion.pf)
    return out


# ----------------------------------------------------------------------------------------------
# The whole pipeline


@dataclass
class FitOutcome:
    subject: Subject
    first: MechanismParams
    fitted: MechanismParams
    info: dict
    motion: Motion
    first_errors: dict
    fitted_errors: dict
    truth_errors: dict | None
    truth_first_errors: dict | None
    seconds: dict
    warnings: list = field(default_factory=list)
    files: dict = field(default_factory=dict)


def _check_out(subject_dir: Path, out_dir: Path, force: bool) -> None:
    s, o = subject_dir.resolve(), out_dir.resolve()
    if o == s or s in o.parents:
        raise KneeInputError(f"output folder {out_dir} is inside the subject folder {subject_dir}; the input "
                             "folder is never written to")
    if o in s.parents:
        raise KneeInputError(f"output folder {out_dir} contains the subject folder; choose a separate folder")
    if out_dir.exists() and any(out_dir.iterdir()) and not force:
        raise KneeInputError(f"output folder {out_dir} exists and is not empty; not overwritten (use --force)")


OUTPUT_FILES = ("first_estimate.toml", "fitted.toml", "report.json", "report.md", "motion.png", "fit.rrd")


#: Global-stage effort (differential evolution population factor and generations) per setting.
EFFORT = {"full": {"tf": (12, 15), "pf": (10, 12)}, "quick": {"tf": (5, 4), "pf": (5, 3)}}


def run_fit(subject_dir, out_dir, seed: int = 0, global_stage: bool = True, progress=None, force: bool = False,
            recording: bool = True, figure: bool = True, effort: str = "full") -> FitOutcome:
    """Run every step on a subject folder and write the outputs (see the module docstring).

    ``progress(fraction, text)`` is called as the work advances (fraction of the whole fit, 0..1).
    ``effort``: ``"full"`` (the defaults of :func:`fit_tf`/:func:`fit_pf`) or ``"quick"`` (a small global
    stage, for trying a folder out). Without the global stage the local stage starts from the first
    estimate alone, which must then assemble over the measured range.
    """
    if effort not in EFFORT:
        raise KneeInputError(f"effort must be one of {', '.join(EFFORT)}, got {effort!r}")
    subject_dir, out_dir = Path(subject_dir), Path(out_dir)
    _check_out(subject_dir, out_dir, force)
    say = progress or (lambda f, t: None)
    t_all = time.perf_counter()
    say(0.0, "reading the subject folder")
    subject = load_subject(subject_dir)
    motion = Motion(subject.motion.tf, subject.motion.pf if subject.has_pf else None)
    warnings = []
    if subject.motion.skipped:
        warnings.append(f"{subject.motion.skipped} of {subject.motion.rows} motion rows skipped (missing or "
                        "non-finite values)")
    if subject.motion.pf is not None and not subject.has_pf:
        warnings.append("PF motion given but the patella surface or landmarks are missing: TF-only fit")
    t0 = time.perf_counter()
    say(0.02, "first estimate from imaging")
    first, info = first_estimate(subject, motion)
    try:
        first_err = validate(first, motion)
    except AssemblyError as e:
        first_err = None
        warnings.append(f"the first estimate does not assemble over the measured range ({e})")
    t_first = time.perf_counter() - t0

    def part(lo, hi):
        return lambda f, t: say(lo + (hi - lo) * f, t)

    t0 = time.perf_counter()
    if not global_stage and first_err is None:
        raise KneeInputError("the first estimate does not assemble over the measured range, so the local stage "
                             "alone cannot start; run with the global stage")
    pop, gens = EFFORT[effort]["tf"]
    tf_fit = fit_tf(first, motion, seed=seed, global_stage=global_stage, popsize=pop, maxiter=gens,
                    progress=part(0.05, 0.5 if subject.has_pf else 0.95), weights=noise_weights())
    t_tf = time.perf_counter() - t0
    # the fitted geometry's own assembly at the first frame selects its branch from now on
    tf_model, _, ok, _ = quick_tf_sweep(tf_fit.params.to_vector(), tf_fit.params.kinds, motion.tf[0, 1:],
                                        motion.flexion[:1])
    fitted = replace(tf_fit.params, initial=InitialPose(float(motion.tf[0, 0]), tf_model[0, 1:].copy()))
    t_pf = 0.0
    if subject.has_pf:
        t0 = time.perf_counter()
        pop, gens = EFFORT[effort]["pf"]
        pf_res = fit_pf(fitted, motion, seed=seed, global_stage=global_stage, popsize=pop, maxiter=gens,
                        progress=part(0.5, 0.95))
        fitted = pf_res.params
        t_pf = time.perf_counter() - t0
    fitted = replace(fitted, name=f"{subject.name}-fitted",
                     description=f"Subject {subject.name}: mechanism fitted to the measured motion (knee fit, "
                                 f"seed {seed})")
    say(0.96, "validation")
    fitted_err = validate(fitted, motion)
    fitted = replace(fitted, initial=InitialPose(float(motion.tf[0, 0]), fitted_err["model_tf"][0, 1:].copy()))
    truth_err = truth_first = None
    if subject.truth is not None:
        truth = load_model(subject.truth)
        ttf, tpf = model_motion(truth, motion.flexion)
        tm = Motion(ttf, tpf if subject.has_pf else None)
        truth_err = validate(fitted, tm)
        truth_first = validate(first, tm) if first_err is not None else None
    seconds = {"first_estimate": t_first, "tf_fit": t_tf, "pf_fit": t_pf, "fit": t_tf + t_pf,
               "total": time.perf_counter() - t_all}
    out = FitOutcome(subject, first, fitted, info, motion, first_err, fitted_err, truth_err, truth_first, seconds,
                     warnings)
    write_outputs(out, out_dir, seed, recording=recording, figure=figure, progress=say)
    say(1.0, "done")
    return out


# ----------------------------------------------------------------------------------------------
# Outputs


def _table_rows(err, group):
    rng = range(1, 6) if group == "tf" else range(6)
    return {TF_NAMES[k]: {"mae": float(err[group]["mae"][k]), "max": float(err[group]["max"][k]),
                          "unit": UNITS[k]} for k in rng}


def report_dict(o: FitOutcome, seed: int) -> dict:
    info = o.info
    rep = {
        "subject": o.subject.name, "side": o.subject.side, "folder": str(o.subject.root), "seed": seed,
        "motion": {"frames_used": int(len(o.motion.tf)), "rows": o.subject.motion.rows,
                   "rows_skipped": o.subject.motion.skipped,
                   "flexion_range_deg": [float(np.degrees(o.motion.flexion.min())),
                                         float(np.degrees(o.motion.flexion.max()))],
                   "patella": o.subject.has_pf},
        "frames": {b: {"origin_ct": T[:3, 3].tolist(), "axes_ct": T[:3, :3].T.tolist()}
                   for b, T in info["frames"].items()},
        "mri_to_ct_fre_mm": {b: a["fre"] for b, a in info["alignment"].items()},
        "contact_spheres": {s: {"femur_centre": c["femur"]["centre"].tolist(), "femur_radius": c["femur"]["radius"],
                                "femur_rms": c["femur"]["rms"], "femur_points": c["femur"]["points"],
                                "tibia_centre": c["tibia"]["centre"].tolist(), "tibia_radius": c["tibia"]["radius"],
                                "tibia_rms": c["tibia"]["rms"], "tibia_points": c["tibia"]["points"],
                                "tibia_surface": c["surface"], "link_length": c["length"]}
                            for s, c in info["contacts"].items()},
        "isometric_fibres": {k: {"femur": v["femur"].tolist(), "tibia": v["tibia"].tolist(), "length": v["length"],
                                 "length_sd": v["length_sd"], "candidates": v["candidates"]}
                             for k, v in info["fibres"].items()},
        "seconds": o.seconds, "warnings": o.warnings,
        "first_estimate": None if o.first_errors is None else {"tf": _table_rows(o.first_errors, "tf")},
        "fitted": {"tf": _table_rows(o.fitted_errors, "tf")},
    }
    if info["pf"]:
        ax, pt = info["pf"]["axis"], info["pf"]["pitch"]
        rep["helical_axis"] = {"n_femur": ax["n"].tolist(), "q_femur": ax["q"].tolist(),
                               "sphere_rms": [ax["lateral"]["rms"], ax["medial"]["rms"]],
                               "pitch_mm_per_rad": pt["lambda1"], "groove_plane_angle_to_axis_deg":
                                   pt["angle_to_axis_deg"], "groove_plane_rms": pt["rms"]}
        if o.first_errors is not None and "pf" in o.first_errors:
            rep["first_estimate"]["pf"] = _table_rows(o.first_errors, "pf")
        rep["fitted"]["pf"] = _table_rows(o.fitted_errors, "pf")
    if o.truth_errors is not None:
        rep["fitted_vs_truth"] = {"tf": _table_rows(o.truth_errors, "tf")}
        if "pf" in o.truth_errors:
            rep["fitted_vs_truth"]["pf"] = _table_rows(o.truth_errors, "pf")
        if o.truth_first_errors is not None:
            rep["first_estimate_vs_truth"] = {"tf": _table_rows(o.truth_first_errors, "tf")}
    return rep


def _md_table(title, block):
    cols = [n for n in TF_NAMES]
    lines = [f"### {title}", "", "| Group | | " + " | ".join(f"{c} ({u})" for c, u in zip(cols, UNITS)) + " |",
             "|---|---|" + "---|" * 6]
    for g in ("tf", "pf"):
        if g not in block:
            continue
        for stat in ("mae", "max"):
            cells = [f"{block[g][c][stat]:.2f}" if c in block[g] else "input" for c in cols]
            lines.append(f"| {g.upper()} | {stat.upper()} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def report_markdown(rep: dict) -> str:
    s = [f"# Fit report: subject {rep['subject']} ({rep['side']} knee)", "",
         f"Seed {rep['seed']}; {rep['motion']['frames_used']} frames used "
         f"({rep['motion']['rows_skipped']} of {rep['motion']['rows']} rows skipped), flexion "
         f"{rep['motion']['flexion_range_deg'][0]:.1f} to {rep['motion']['flexion_range_deg'][1]:.1f} deg. "
         f"Fit time {rep['seconds']['fit']:.1f} s (TF {rep['seconds']['tf_fit']:.1f} s, PF "
         f"{rep['seconds']['pf_fit']:.1f} s); total {rep['seconds']['total']:.1f} s.", ""]
    if rep["warnings"]:
        s += ["**Warnings**", ""] + [f"- {w}" for w in rep["warnings"]] + [""]
    s += ["## Accuracy (model against the measured motion; seed 002 Table 2 layout)", ""]
    s.append(_md_table("Fitted model", rep["fitted"]))
    if rep.get("first_estimate"):
        s.append(_md_table("First estimate", rep["first_estimate"]))
    if "fitted_vs_truth" in rep:
        s += ["## Against the noise-free truth (synthetic subject)", ""]
        s.append(_md_table("Fitted model vs truth", rep["fitted_vs_truth"]))
        if "first_estimate_vs_truth" in rep:
            s.append(_md_table("First estimate vs truth", rep["first_estimate_vs_truth"]))
    s += ["## Steps", "", "MRI-to-CT fiducial registration error (mm):", ""]
    for b, fre in rep["mri_to_ct_fre_mm"].items():
        s.append(f"- {b}: " + ", ".join(f"{k} {v:.2f}" for k, v in fre.items()))
    s += ["", "Contact spheres (bone frames, mm):", ""]
    for side, c in rep["contact_spheres"].items():
        s.append(f"- {side}: femur R {c['femur_radius']:.2f} (rms {c['femur_rms']:.3f}, {c['femur_points']} pts), "
                 f"tibia R {c['tibia_radius']:.2f} {c['tibia_surface']} (rms {c['tibia_rms']:.3f}, "
                 f"{c['tibia_points']} pts), link length {c['link_length']:.2f}")
    s += ["", "Isometric fibres:", ""]
    for k, v in rep["isometric_fibres"].items():
        s.append(f"- {k}: length at extension {v['length']:.2f} mm, sd over the motion {v['length_sd']:.3f} mm "
                 f"({v['candidates'][0]} x {v['candidates'][1]} candidate pairs)")
    if "helical_axis" in rep:
        h = rep["helical_axis"]
        s += ["", f"Helical axis: n = {np.round(h['n_femur'], 4).tolist()}, q = {np.round(h['q_femur'], 2).tolist()} "
                  f"mm; pitch {h['pitch_mm_per_rad']:.3f} mm/rad (intercondylar plane normal "
                  f"{h['groove_plane_angle_to_axis_deg']:.2f} deg from the axis)."]
    return "\n".join(s) + "\n"


def plot_motion(o: FitOutcome, path) -> Path:
    """Measured (black dashed) against model (blue) motion per component over TF flexion, the largest
    discrepancy circled in red (like seed 002 Fig. 3); PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [("tf", o.motion.tf, o.fitted_errors["model_tf"])]
    if o.fitted_errors.get("model_pf") is not None and o.motion.pf is not None:
        groups.append(("pf", o.motion.pf, o.fitted_errors["model_pf"]))
    fig, axes = plt.subplots(len(groups), 6, figsize=(18, 3.2 * len(groups)), squeeze=False)
    x = np.degrees(o.motion.flexion)
    for r, (g, meas, model) in enumerate(groups):
        for k in range(6):
            ax = axes[r, k]
            if g == "tf" and k == 0:
                ax.axis("off")
                ax.text(0.05, 0.5, f"{o.subject.name}\nTF flexion is the input\nblack dashed: measured\n"
                        "blue: model\nred: largest difference", transform=ax.transAxes, va="center")
                continue
            scale = 180 / math.pi if k < 3 else 1.0
            ax.plot(x, meas[:, k] * scale, "k--", lw=1)
            ax.plot(x, model[:, k] * scale, "-", color="tab:blue", lw=1.5)
            i = int(o.fitted_errors[g]["argmax"][k])
            ax.plot(x[i], meas[i, k] * scale, "o", mfc="none", mec="red", ms=9)
            ax.set_title(f"{g.upper()} {TF_NAMES[k].replace('_', ' ')} ({UNITS[k]})", fontsize=9)
            ax.set_xlabel("TF flexion (deg)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def write_recording(o: FitOutcome, path) -> Path:
    """Measured and model bones side by side (two 3D views) on the ``frame`` timeline, and each component's
    measured and model series."""
    import rerun as rr
    import rerun.blueprint as rrb

    from toolkit import recording as R

    rec = R.new_recording()
    views = [rrb.Spatial3DView(origin="measured", name="Measured motion"),
             rrb.Spatial3DView(origin="model", name="Fitted model")]
    bp = rrb.Blueprint(rrb.Vertical(rrb.Horizontal(*views),
                                    rrb.Horizontal(rrb.TimeSeriesView(origin="metrics/tf", name="TF"),
                                                   rrb.TimeSeriesView(origin="metrics/pf", name="PF")),
                                    row_shares=[3, 2]), collapse_panels=True)
    R.save(rec, path, bp)
    frames = np.arange(len(o.motion.tf))
    meshes = {b: o.subject.ct[b].copy().apply_transform(invert_poses(o.info["frames"][b]))
              for b in o.info["frames"]}
    poses = {"measured": {"tibia": joint_to_pose(o.motion.tf)},
             "model": {"tibia": joint_to_pose(o.fitted_errors["model_tf"])}}
    if o.fitted_errors.get("model_pf") is not None and o.motion.pf is not None:
        poses["measured"]["patella"] = joint_to_pose(o.motion.pf)
        poses["model"]["patella"] = joint_to_pose(o.fitted_errors["model_pf"])
    for root in ("measured", "model"):
        rec.log(root, rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        for b, m in meshes.items():
            if b != "femur" and b not in poses[root]:
                continue
            R.log_mesh(rec, f"{root}/{b}", m, R.BONE_COLOURS[b])
            if b in poses[root]:
                R.send_poses(rec, f"{root}/{b}", "frame", frames, poses[root][b])
    for g, meas, model in (("tf", o.motion.tf, o.fitted_errors["model_tf"]),
                           ("pf", o.motion.pf, o.fitted_errors.get("model_pf"))):
        if meas is None or model is None:
            continue
        for k in range(6):
            sc = 180 / math.pi if k < 3 else 1.0
            R.send_scalars(rec, f"metrics/{g}/{TF_NAMES[k]}/measured", "frame", frames, meas[:, k] * sc)
            R.send_scalars(rec, f"metrics/{g}/{TF_NAMES[k]}/model", "frame", frames, model[:, k] * sc)
    rec.flush()
    return Path(path)


def write_outputs(o: FitOutcome, out_dir, seed: int, recording: bool = True, figure: bool = True,
                  progress=None) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda f, t: None)
    files = {"first_estimate": out_dir / "first_estimate.toml", "fitted": out_dir / "fitted.toml",
             "report_json": out_dir / "report.json", "report_md": out_dir / "report.md"}
    save_toml(o.first, files["first_estimate"], overwrite=True)
    save_toml(o.fitted, files["fitted"], overwrite=True)
    rep = report_dict(o, seed)
    files["report_json"].write_text(json.dumps(rep, indent=1, default=float), encoding="utf-8")
    files["report_md"].write_text(report_markdown(rep), encoding="utf-8")
    if figure:
        say(0.97, "figure")
        files["figure"] = plot_motion(o, out_dir / "motion.png")
    if recording:
        say(0.98, "recording")
        files["recording"] = write_recording(o, out_dir / "fit.rrd")
    o.files = files
    return files
