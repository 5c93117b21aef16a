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
6. :func:`knee.fitting.optimize.fit_tf` then :func:`knee.fitting.pf.fit_pf`: the bounded optimisation.
7. :func:`validate`: MAE and MAX of every component (seed 002 Table 2 layout).

:func:`fit_subject` runs them all and returns a :class:`FitOutcome`; nothing is written here (``knee fit``
writes the parameter files, the report, the figure and the recording: :mod:`knee.app.reports.fit`).

All geometry of a step is expressed in the bone frames (mm, x anterior, y proximal, z lateral).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from knee.fitting.frames import FIDUCIALS, FRAME_FUNCTIONS, check_consistent
from knee.fitting.isometric import isometric_fibre
from knee.fitting.optimize import FitBounds, Motion, average_cycle_halves, fit_tf, noise_sd, noise_weights
from knee.fitting.pf import fit_pf
from knee.fitting.subject import LIGAMENTS, Subject, load_subject
from knee.foundations.conventions import invert_poses, joint_to_pose, transform_points
from knee.foundations.errors import AssemblyError, KneeInputError
from knee.foundations.geometry import fit_plane, fit_sphere, rigid_register
from knee.foundations.imaging import read_motion_csv
from knee.foundations.surfaces import SurfaceQuery
from knee.models.mechanism.params import (
    InitialPose,
    Link,
    MechanismParams,
    PFGroup,
    load_model,
)
from knee.models.mechanism.solver import Mechanism, quick_tf_sweep

#: ``progress(fraction, text)``: the fraction of the work done (0..1) and what is being done.
Progress = Callable[[float, str], None]

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


@dataclass(frozen=True)
class Alignment:
    """One bone's MRI-to-CT alignment: ``T`` (4, 4) taking MRI points to CT, and the fiducial registration
    error of each fiducial, ``fre`` {label: mm}."""

    T: np.ndarray
    fre: dict


#: MRI-to-CT fiducial registration error above which the alignment is refused (RMS, mm): picking error
#: is 1-2 mm; a swapped or misplaced fiducial gives tens.
MAX_FIDUCIAL_RMS_MM = 5.0


def align_mri(subject: Subject) -> dict[str, Alignment]:
    """Per bone, its :class:`Alignment` from the paired fiducials (least squares)."""
    out = {}
    bones = ("femur", "tibia", "patella") if subject.has_pf else ("femur", "tibia")
    for b in bones:
        labels = FIDUCIALS[b]
        T, fre = rigid_register(subject.mri_landmarks.require(labels), subject.ct_landmarks.require(labels))
        rms = float(np.sqrt(np.mean(np.square(fre))))
        if rms > MAX_FIDUCIAL_RMS_MM:
            k = int(np.argmax(fre))
            raise KneeInputError(f"the {b}'s MRI and CT fiducials do not match: registration error RMS {rms:.1f} mm "
                                 f"(at most {MAX_FIDUCIAL_RMS_MM:g}; worst {labels[k]} {fre[k]:.1f} mm): a mislabelled "
                                 f"or misplaced fiducial in {subject.root / 'mri'} or {subject.root / 'ct'}")
        out[b] = Alignment(T, dict(zip(labels, (float(v) for v in fre))))
    return out


@dataclass
class Geometry:
    """Frames and alignment: maps points of either scan into bone frames."""

    frames: dict
    alignment: dict

    def to_bone(self, points, bone: str, space: str = "mri") -> np.ndarray:
        T = invert_poses(self.frames[bone])
        if space == "mri":
            T = T @ self.alignment[bone].T
        return transform_points(T, np.asarray(points, float))


# ----------------------------------------------------------------------------------------------
# Step 3


@dataclass(frozen=True)
class SphereFit:
    """A sphere fitted to a region's points: centre (3,) in the bone frame, radius and RMS residual (mm),
    and the number of points."""

    centre: np.ndarray
    radius: float
    rms: float
    points: int


def _sphere(subject, geo, region, bone) -> SphereFit:
    pts = geo.to_bone(subject.area(region).points, bone)
    try:
        c, r, rms = fit_sphere(pts)
    except KneeInputError as e:
        raise KneeInputError(f"region {region}: {e}") from None
    return SphereFit(c, float(r), float(rms), len(pts))


@dataclass(frozen=True)
class ContactFit:
    """One condylar contact: the femoral condyle's and the tibial facet's spheres (bone frames), the facet's
    shape (``"convex"`` or ``"concave"``) and the link length (mm)."""

    femur: SphereFit
    tibia: SphereFit
    surface: str
    length: float


def contact_spheres(subject: Subject, geo: Geometry) -> dict[str, ContactFit]:
    """The lateral and medial contacts: femoral condyle and tibial facet spheres (bone frames), the facet's
    shape (``convex`` when its centre lies below the facet) and the link length (``R_t + R_f`` convex,
    ``R_t - R_f`` concave)."""
    out = {}
    for side in ("lateral", "medial"):
        f = _sphere(subject, geo, f"femur_{side}_condyle", "femur")
        t = _sphere(subject, geo, f"tibia_{side}_facet", "tibia")
        facet = geo.to_bone(subject.area(f"tibia_{side}_facet").points, "tibia")
        convex = t.centre[1] < facet[:, 1].mean()
        length = t.radius + f.radius if convex else t.radius - f.radius
        if length <= 0:
            raise KneeInputError(f"{side} contact: the tibial facet (R {t.radius:.1f} mm) is concave and smaller "
                                 f"than the femoral condyle (R {f.radius:.1f} mm)")
        out[side] = ContactFit(f, t, "convex" if convex else "concave", float(length))
    return out


@dataclass(frozen=True)
class HelicalAxisFit:
    """The patellar helical axis in the femur frame: unit ``n`` (medial -> lateral), ``q`` its intersection
    with the sagittal plane z = 0, and the two anterior-condyle spheres it passes through."""

    n: np.ndarray
    q: np.ndarray
    lateral: SphereFit
    medial: SphereFit


def helical_axis(subject: Subject, geo: Geometry) -> HelicalAxisFit:
    """The helical axis in the femur frame: unit ``n`` (medial -> lateral) through the centres of the
    spheres fitted to the anterior condyles, and ``q``, its intersection with the sagittal plane z = 0."""
    lat = _sphere(subject, geo, "femur_lateral_trochlea", "femur")
    med = _sphere(subject, geo, "femur_medial_trochlea", "femur")
    d = lat.centre - med.centre
    if np.linalg.norm(d) < 5.0:
        raise KneeInputError("helical axis: the anterior condyle spheres are less than 5 mm apart")
    n = d / np.linalg.norm(d)
    if abs(n[2]) < 0.5:
        raise KneeInputError(f"helical axis: the axis is {math.degrees(math.acos(abs(n[2]))):.0f} deg from the "
                             "medio-lateral axis; check the trochlea regions")
    q = med.centre - med.centre[2] / n[2] * n
    return HelicalAxisFit(n, q, lat, med)


@dataclass(frozen=True)
class PitchFit:
    """The helical pitch from the intercondylar plane: ``lambda1`` (mm/rad), the plane's unit normal (3,),
    its RMS residual (mm) and number of points, the normal's angle to the axis (deg) and the patella
    point's radius from the axis (mm)."""

    lambda1: float
    normal: np.ndarray
    rms: float
    points: int
    angle_to_axis_deg: float
    rho: float


def helical_pitch(subject: Subject, geo: Geometry, n, q, patella_origin) -> PitchFit:
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
    return PitchFit(float(lam1), m, float(rms), len(pts), float(angle), rho)


# ----------------------------------------------------------------------------------------------
# Steps 4-5


@dataclass(frozen=True)
class FibreFit:
    """A ligament's isometric fibre: femoral and tibial endpoints (3,) in the bone frames, its length at
    extension and the sd of its length over the motion (mm), and the candidate points on each side."""

    femur: np.ndarray
    tibia: np.ndarray
    length: float
    length_sd: float
    candidates: tuple


def ligament_fibres(subject: Subject, geo: Geometry, tf_motion) -> dict[str, FibreFit]:
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
        out[lig] = FibreFit(fib.femur, fib.tibia, float(fib.length_at_extension), float(fib.sd),
                            (int(len(fa.points) if fm is None else fm.sum()), int(len(ta.points) if tm is None else tm.sum())))
    return out


def _interp_pose(motion: Motion, group: str, flexion: float) -> np.ndarray:
    q = motion.tf if group == "tf" else motion.pf
    order = np.argsort(motion.flexion)
    a = motion.flexion[order]
    return np.array([np.interp(flexion, a, q[order, k]) for k in range(6)])


def _project(mesh_bone, p):
    return SurfaceQuery.of(mesh_bone).closest_points(np.asarray(p, float)[None])[0]


@dataclass(frozen=True)
class MotionAxis:
    """The patella's mean helical axis relative to the femur over the measured PF motion (femur frame):
    unit ``n`` (medial -> lateral), ``q`` on the sagittal plane z = 0, the pitch ``lambda1`` (mm/rad), the
    patella's rotation it spans (deg), and its angle (deg) and distance (mm, between the q points) to the
    imaging axis (:func:`helical_axis`)."""

    n: np.ndarray
    q: np.ndarray
    lambda1: float
    span_deg: float
    angle_to_imaging_deg: float
    distance_to_imaging_mm: float


#: The patellar rotation (deg) the measured PF motion must span for its helical axis to be used.
MIN_AXIS_SPAN_DEG = 10.0


def motion_helical_axis(pf, imaging: HelicalAxisFit | None = None) -> MotionAxis | None:
    """The mean helical axis of the patella's measured poses ``pf`` (n, 6) relative to the femur: the
    finite helical axes from the first pose to each other pose (rotations of 5 deg or more), their mean
    direction weighted by the squared rotation (a finite axis's direction error falls as 1/rotation), the point nearest all of them in least squares ((I - R_k) q = t_k minus its axial part), and
    the pitch as the slope of the axial translation against the rotation. None when the motion spans less
    than :data:`MIN_AXIS_SPAN_DEG`."""
    T = joint_to_pose(np.asarray(pf, float))
    M = T[1:] @ np.linalg.inv(T[0])
    R, t = M[:, :3, :3], M[:, :3, 3]
    ang = np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    use = ang >= math.radians(5.0)
    if not use.any() or math.degrees(ang.max()) < MIN_AXIS_SPAN_DEG:
        return None
    R, t, ang = R[use], t[use], ang[use]
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    n_k = w / (2.0 * np.sin(ang))[:, None]
    sign = np.where(n_k[:, 2] < 0.0, -1.0, 1.0)  # medial -> lateral
    n_k, theta = n_k * sign[:, None], ang * sign
    n = (n_k * (theta ** 2)[:, None]).sum(axis=0)  # large rotations define the axis best (noise ~ 1/theta)
    n /= np.linalg.norm(n)
    A = np.eye(3) - R  # (k, 3, 3)
    rhs = t - (t @ n)[:, None] * n
    q = np.linalg.lstsq(A.reshape(-1, 3), rhs.reshape(-1), rcond=None)[0]
    q = q - q[2] / n[2] * n
    d = t @ n
    lam1 = float((theta @ d) / (theta @ theta))
    angle = dist = math.nan
    if imaging is not None:
        angle = math.degrees(math.acos(min(1.0, abs(float(n @ imaging.n)))))
        dist = float(np.linalg.norm(q - imaging.q))
    return MotionAxis(n, q, lam1, float(math.degrees(np.abs(theta).max())), angle, dist)


def pf_first_estimate(subject: Subject, geo: Geometry, motion: Motion, ref_deg: float,
                      bounds: FitBounds | None = None) -> tuple[PFGroup, HelicalAxisFit, PitchFit, "MotionAxis | None"]:
    """The PF group from imaging and the measured motion at the reference flexion ``ref_deg``, with the
    helical axis and pitch fits it came from. The helical axis and pitch come from the imaging (the
    anterior condyles' spheres and the intercondylar plane), unless the measured motion's own axis
    (:func:`motion_helical_axis`, when the patella turns :data:`MIN_AXIS_SPAN_DEG` or more) lies outside
    the fit's bounds around it (``bounds.pf_axis_deg``, ``bounds.pf_axis_point_mm``): a fit started from
    the imaging axis could not reach it, so the first estimate starts from the motion's axis and pitch."""
    ax = helical_axis(subject, geo)
    b = bounds or FitBounds()
    mo = motion_helical_axis(motion.pf, ax) if motion.pf is not None else None
    if mo is not None and mo.angle_to_imaging_deg <= b.pf_axis_deg and mo.distance_to_imaging_mm <= b.pf_axis_point_mm:
        mo = None  # within reach of the imaging axis: the imaging's first estimate stands (seed 002)
    n_f, q_f = (ax.n, ax.q) if mo is None else (mo.n, mo.q)
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
    pitch = helical_pitch(subject, geo, ax.n, ax.q, P)
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
                 tendon_patella=ends["patella"], tendon_length=l6, lambda0=lam0,
                 lambda1=pitch.lambda1 if mo is None else mo.lambda1, reference_flexion=a_ref)
    return pf, ax, pitch, mo


@dataclass(frozen=True)
class FirstEstimateInfo:
    """What each step of the first estimate found, for the report: the anatomical frames ``T_ct_bone``
    (4, 4) per bone, the MRI alignments, the two contacts, the three fibres, and (with a patella) the
    imaging's helical axis and pitch, and the measured motion's helical axis."""

    frames: dict
    alignment: dict
    contacts: dict
    fibres: dict
    geometry: Geometry
    axis: HelicalAxisFit | None = None
    pitch: PitchFit | None = None
    #: The measured motion's mean helical axis when the first estimate uses it (out of the bounds' reach of
    #: the imaging axis), else None.
    motion_axis: MotionAxis | None = None


def first_estimate(subject: Subject, motion: Motion | None = None,
                   bounds: FitBounds | None = None) -> tuple[MechanismParams, FirstEstimateInfo]:
    """Steps 1-5: the first-estimate parameter set and what each step found (for the report); ``bounds``
    the fit's (default: the subject's), which decide whether the PF axis comes from the imaging or the
    motion (:func:`pf_first_estimate`)."""
    motion = motion or Motion(subject.motion.tf, subject.motion.pf)
    frames = anatomical_frames(subject)
    align = align_mri(subject)
    geo = Geometry(frames, align)
    contacts = contact_spheres(subject, geo)
    fibres = ligament_fibres(subject, geo, motion.tf)
    links = [Link(name=lig, role="ligament", kind="distance", femur=f.femur, tibia=f.tibia, length=f.length)
             for lig, f in fibres.items()]
    for side, name in (("lateral", "lc"), ("medial", "mc")):
        c = contacts[side]
        links.append(Link(name=name, role="contact", kind="distance", femur=c.femur.centre,
                          tibia=c.tibia.centre, length=c.length, femur_radius=c.femur.radius,
                          tibia_surface=c.surface))
    pf, axis, pitch, motion_axis = None, None, None, None
    if subject.has_pf:
        lo, hi = float(np.degrees(motion.flexion.min())), float(np.degrees(motion.flexion.max()))
        ref = subject.reference_flexion_deg if subject.reference_flexion_deg is not None else 0.5 * (lo + hi)
        if not lo <= ref <= hi:
            raise KneeInputError(f"PF reference flexion {ref:.1f} deg is outside the measured range {lo:.1f}..{hi:.1f}")
        pf, axis, pitch, motion_axis = pf_first_estimate(subject, geo, motion, ref, bounds or subject.bounds)
    params = MechanismParams(name=f"{subject.name}-first-estimate", links=tuple(links), pf=pf,
                             initial=InitialPose(float(motion.tf[0, 0]), motion.tf[0, 1:].copy()),
                             description=f"First estimate of subject {subject.name} from imaging (knee fit)",
                             source=str(subject.root), side=subject.side)
    return params, FirstEstimateInfo(frames, align, contacts, fibres, geo, axis, pitch, motion_axis)


# ----------------------------------------------------------------------------------------------
# Step 7


def model_motion(params: MechanismParams, flexion) -> tuple[np.ndarray, np.ndarray | None]:
    """The model's (tf, pf) at the given flexion angles (rad); AssemblyError when it does not assemble."""
    mech = Mechanism(params)
    sw = mech.sweep(np.asarray(flexion, float))
    if not sw.complete:
        raise AssemblyError(f"{params.name}: {sw.message}")
    return sw.tf, (sw.pf if params.has_pf else None)


@dataclass(frozen=True)
class ComponentErrors:
    """Model minus measured, per frame and component: ``diff`` (frames, 6) in deg for the three rotations
    and mm for the three translations; ``mae``, ``max`` (6,) of its absolute value and ``argmax`` (6,) the
    frame of each maximum."""

    mae: np.ndarray
    max: np.ndarray
    argmax: np.ndarray
    diff: np.ndarray

    @classmethod
    def of(cls, model, measured) -> "ComponentErrors":
        d = np.asarray(model, float) - np.asarray(measured, float)
        d[:, :3] = np.degrees(d[:, :3])
        a = np.abs(d)
        return cls(a.mean(axis=0), a.max(axis=0), a.argmax(axis=0), d)


@dataclass(frozen=True)
class Validation:
    """A parameter set against a motion at its flexion angles (seed 002 Table 2 layout; TF flexion is the
    input): the model's motion ``model_tf`` and ``model_pf`` (frames, 6) (rad, mm; ``model_pf`` None
    without a patella) and the errors of each group (``pf`` None when either side has no PF)."""

    tf: ComponentErrors
    pf: ComponentErrors | None
    model_tf: np.ndarray
    model_pf: np.ndarray | None


def validate(params: MechanismParams, motion: Motion) -> Validation:
    """MAE and MAX of each component, model against ``motion``; :class:`AssemblyError` when the model does
    not assemble over the motion's flexion angles."""
    tf, pf = model_motion(params, motion.flexion)
    pf_err = ComponentErrors.of(pf, motion.pf) if pf is not None and motion.pf is not None else None
    return Validation(ComponentErrors.of(tf, motion.tf), pf_err, tf, pf)


# ----------------------------------------------------------------------------------------------
# The whole pipeline


@dataclass(frozen=True)
class FitTimings:
    """Wall times of the fit's stages (s)."""

    first_estimate: float
    tf_fit: float
    pf_fit: float
    total: float

    @property
    def fit(self) -> float:
        """The bounded optimisation, TF and PF (s)."""
        return self.tf_fit + self.pf_fit


@dataclass
class FitOutcome:
    """A subject's fit: the first estimate and the fitted parameter sets, what the first estimate's steps
    found, the motion fitted, each set's :class:`Validation` against it (``first_errors`` None when the
    first estimate does not assemble over the measured range), against the noise-free truth for a
    synthetic subject (None otherwise), the timings and the warnings."""

    subject: Subject
    first: MechanismParams
    fitted: MechanismParams
    info: FirstEstimateInfo
    motion: Motion
    first_errors: Validation | None
    fitted_errors: Validation
    truth_errors: Validation | None
    truth_first_errors: Validation | None
    seconds: FitTimings
    seed: int = 0
    warnings: list = field(default_factory=list)
    #: Per group ("tf", "pf"), the fit's :class:`~knee.fitting.diagnostics.FitDiagnostics`.
    diagnostics: dict = field(default_factory=dict)
    #: The fitted mechanism's assembly range (deg), against the measured range and :data:`NEEDED_RANGE_DEG`.
    assembly_range_deg: tuple = (math.nan, math.nan)
    #: The bounds the fit used (:class:`~knee.fitting.optimize.FitBounds`).
    bounds: FitBounds | None = None
    #: (motion file, :class:`Validation`) of each trial given to check the fit, not fitted to.
    cross_trial: list = field(default_factory=list)
    #: With ``average_halves``: the fitted model's :class:`Validation` against the trials as measured, every
    #: frame (``fitted_errors`` is against the mean of the flexing and extending phases); None otherwise.
    as_measured_errors: Validation | None = None

    @property
    def range_warning(self) -> str:
        """'' when the fitted model assembles over the range a user is likely to need, else why not."""
        lo, hi = self.assembly_range_deg
        need_lo, need_hi = NEEDED_RANGE_DEG
        if lo <= need_lo and hi >= need_hi:
            return ""
        return (f"the fitted model assembles only from {lo:.1f} to {hi:.1f} deg, not over the {need_lo:g}-{need_hi:g} deg "
                f"a user is likely to need (a FEM case or gait outside it fails)")


#: The flexion range (deg) a fitted knee is likely to be asked about (FEM cases, gait, osteotomy).
NEEDED_RANGE_DEG = (0.0, 120.0)

#: Global-stage effort (differential evolution population factor and generations) per setting.
EFFORT = {"full": {"tf": (12, 15), "pf": (10, 12)}, "quick": {"tf": (5, 4), "pf": (5, 3)}}


def fit_subject(subject: Subject | str | Path, seed: int = 0, global_stage: bool = True,
                progress: Progress | None = None, effort: str = "full", bounds: dict | None = None,
                assemble_over_deg: tuple | None = NEEDED_RANGE_DEG, noise: dict | None = None,
                average_halves: bool = False, extra_trials=(), check_trials=()) -> FitOutcome:
    """Fit a subject-specific mechanism: every step on a subject folder (see the module docstring).

    Parameters
    ----------
    subject : Subject, or the path of a subject folder (read with :func:`load_subject`)
    seed : the global stage's seed; the same seed gives the same parameters
    global_stage : run differential evolution before the local stage; without it the local stage starts
        from the first estimate alone, which must then assemble over the measured range
    progress : ``progress(fraction, text)``, called as the work advances (fraction of the whole fit, 0..1)
    effort : ``"full"`` (the defaults of :func:`fit_tf`/:func:`fit_pf`) or ``"quick"`` (a small global
        stage, for trying a folder out)
    noise : {name: sd} over :data:`~knee.fitting.optimize.NOISE_SD` (the measurement's standard deviations,
        deg and mm): the fit's component weights
    assemble_over_deg : (lo, hi) or None
        a TF candidate must also assemble over this flexion range (deg), beyond the measured one (a short
        measured arc otherwise leaves the model free to stop assembling just past it); default
        :data:`NEEDED_RANGE_DEG`, None for the measured range only
    bounds : {name: value} overriding the subject's ``[fit]`` bounds
        (:class:`~knee.fitting.optimize.FitBounds`); the bounds used are in ``FitOutcome.bounds``
    average_halves : fit the mean of the cycle's flexion and extension halves
        (:func:`~knee.fitting.optimize.average_cycle_halves`), each trial's
    extra_trials : more motion files of the same knee (motion CSV paths) fitted together with the folder's
    check_trials : motion files of the same knee not fitted: the fitted model's error on each is reported
        (``FitOutcome.cross_trial``)

    Returns
    -------
    FitOutcome, with the parameter sets in the subject's anatomical frames (mm, rad)
    """
    if effort not in EFFORT:
        raise KneeInputError(f"effort must be one of {', '.join(EFFORT)}, got {effort!r}")
    say = progress or (lambda f, t: None)
    t_all = time.perf_counter()
    say(0.0, "reading the subject folder")
    subject = subject if isinstance(subject, Subject) else load_subject(Path(subject))
    subject.require_fit_inputs()
    extra = [read_motion_csv(f, subject.side) for f in extra_trials]
    checks = [(str(f), read_motion_csv(f, subject.side)) for f in check_trials]
    warnings = []

    def prepared(m):
        mo = Motion(m.tf, m.pf if subject.has_pf else None)
        if subject.has_pf and m.pf is None:
            raise KneeInputError("a trial without PF motion cannot be fitted or checked with one that has it")
        return average_cycle_halves(mo) if average_halves else mo

    def stacked(parts):
        return Motion(np.vstack([m.tf for m in parts]), np.vstack([m.pf for m in parts]) if subject.has_pf else None)

    motion = stacked([prepared(m) for m in [subject.motion, *extra]])
    if subject.motion.skipped:
        warnings.append(f"{subject.motion.skipped} of {subject.motion.rows} motion rows skipped (missing or "
                        "non-finite values)")
    if subject.motion.pf is not None and not subject.has_pf:
        warnings.append("PF motion given but the patella surface or landmarks are missing: TF-only fit")
    t0 = time.perf_counter()
    say(0.02, "first estimate from imaging")
    fit_bounds = subject.bounds.updated(bounds or {}, "--bounds")
    sd = noise_sd(noise, "--noise")
    first, info = first_estimate(subject, motion, fit_bounds)
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
    diagnostics = {}
    pop, gens = EFFORT[effort]["tf"]
    tf_fit = fit_tf(first, motion, seed=seed, global_stage=global_stage, popsize=pop, maxiter=gens,
                    progress=part(0.05, 0.5 if subject.has_pf else 0.95), weights=noise_weights(sd), bounds=fit_bounds,
                    assemble_over_deg=assemble_over_deg)
    t_tf = time.perf_counter() - t0
    diagnostics["tf"] = tf_fit.diagnostics
    # the fitted geometry's own assembly at the first frame selects its branch from now on
    tf_model, _, ok, _ = quick_tf_sweep(tf_fit.params.to_vector(), tf_fit.params.kinds, motion.tf[0, 1:],
                                        motion.flexion[:1])
    fitted = replace(tf_fit.params, initial=InitialPose(float(motion.tf[0, 0]), tf_model[0, 1:].copy()))
    t_pf = 0.0
    if subject.has_pf:
        t0 = time.perf_counter()
        pop, gens = EFFORT[effort]["pf"]
        pf_res = fit_pf(fitted, motion, seed=seed, global_stage=global_stage, popsize=pop, maxiter=gens,
                        progress=part(0.5, 0.95), bounds=fit_bounds, noise_sd=sd)
        fitted = pf_res.params
        diagnostics["pf"] = pf_res.diagnostics
        t_pf = time.perf_counter() - t0
    fitted = replace(fitted, name=f"{subject.name}-fitted",
                     description=f"Subject {subject.name}: mechanism fitted to the measured motion (knee fit, "
                                 f"seed {seed})")
    say(0.96, "validation")
    fitted_err = validate(fitted, motion)
    fitted = replace(fitted, initial=InitialPose(float(motion.tf[0, 0]), fitted_err.model_tf[0, 1:].copy()))
    truth_err = truth_first = None
    if subject.truth is not None:
        truth = load_model(subject.truth)
        ttf, tpf = model_motion(truth, motion.flexion)
        tm = Motion(ttf, tpf if subject.has_pf else None)
        truth_err = validate(fitted, tm)
        truth_first = validate(first, tm) if first_err is not None else None
    seconds = FitTimings(t_first, t_tf, t_pf, time.perf_counter() - t_all)
    try:
        lo, hi = (math.degrees(v) for v in Mechanism(fitted).assembly_range)
    except AssemblyError:
        lo = hi = math.nan
    outcome = FitOutcome(subject, first, fitted, info, motion, first_err, fitted_err, truth_err, truth_first, seconds,
                         seed, warnings, diagnostics, (lo, hi), fit_bounds)
    if average_halves:
        # the fit's errors are against the phases' mean (seed 002's reference); these against every frame as
        # measured, which no 1-DoF model can match where the phases differ (hysteresis)
        try:
            outcome.as_measured_errors = validate(fitted, stacked([Motion(m.tf, m.pf if subject.has_pf else None)
                                                                   for m in [subject.motion, *extra]]))
        except AssemblyError as e:
            warnings.append(f"the fitted model does not assemble over the trial as measured ({e})")
    for name, m in checks:
        try:
            outcome.cross_trial.append((name, validate(fitted, prepared(m))))
        except AssemblyError as e:
            warnings.append(f"cross-trial check {name}: the fitted model does not assemble over it ({e})")
    if outcome.range_warning:
        warnings.append(outcome.range_warning)
    for g, d in diagnostics.items():
        if d is not None and d.on_bound:
            warnings.append(f"{len(d.on_bound)} of {len(d.names)} {g.upper()} variables end on their bounds (the bounds, "
                            f"not the data, decide them): {', '.join(n for n, _ in d.on_bound[:6])}"
                            + (", ..." if len(d.on_bound) > 6 else ""))
    say(0.97, "fitted")
    return outcome


