"""Gait: a lower-limb chain in Pinocchio driven by a gait trial, inverse dynamics, and the knee's link
forces and contact pressures per frame (issue "contact mechanics, gait and virtual osteotomy", section 3).

The chain (SI units inside Pinocchio: m, kg, N; the toolkit's mm and N*mm outside):

* pelvis: fixed (the universe frame; x anterior, y up, z to the right); its motion is not modelled;
* femur: a spherical joint at the hip centre (ZYX: flexion about z, internal rotation about y, adduction
  about x); the femur's body frame is the knee model's femur frame, the hip centre at (0, L_thigh, 0);
* tibia: a free-flyer joint whose configuration follows the mechanism: its pose in the femur frame is the
  TF pose at the trial's knee flexion, its velocity and acceleration the chain rule of the mechanism's
  motion (derivatives in flexion by central differences, step 1e-4 rad);
* patella: Pinocchio's helical joint (``JointModelHelicalUnaligned``) on the mechanism's helical axis
  with its pitch, at the angle the mechanism gives; a child of the femur, as in the mechanism;
* foot: a revolute joint about z at the ankle, (0, -L_shank, 0) in the tibia frame.

Segment parameters scale with body mass and height: lengths from Winter (2009, thigh 0.245 H, shank
0.246 H, foot 0.152 H, ankle height 0.039 H); masses, centres of mass and radii of gyration from de Leva
(J Biomech 29:1223-1230, 1996, Table 4, males): thigh 14.16 %, CoM 40.95 % from the hip, radii 0.329,
0.329, 0.149; shank 4.33 %, 44.59 % from the knee, 0.255, 0.249, 0.103; foot 1.37 %, 44.15 % of its
length from the heel, 0.257, 0.245, 0.124; the patella 0.05 kg (a point-like body).

The ground reaction force acts on the foot at the centre of pressure on the sole. Inverse dynamics
(RNEA) gives the wrench the femur transmits to the tibia; its negative is the load the knee's five links
and tendon must balance (:func:`knee.models.statics.solve_statics`), and the contact forces give Hertz and
elastic-foundation pressures per frame.

Pinocchio's Python API has no batched RNEA; the per-frame loop calls its C++ RNEA (about 10 us a frame);
everything else is vectorised over frames.
"""

from __future__ import annotations

import csv
import math
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import pinocchio as pin

from knee.foundations.conventions import joint_to_pose
from knee.foundations.errors import AssemblyError, KneeInputError
from knee.foundations.files import read_text
from knee.models.contact import CARTILAGE, Cartilage, contact_loads
from knee.models.mechanism.solver import Mechanism
from knee.models.statics import StaticsResult, solve_statics

G = 9.81
REQUIRED = ("time_s", "hip_flexion_deg", "knee_flexion_deg", "ankle_dorsiflexion_deg")
GRF_COLUMNS = ("grf_anterior", "grf_vertical", "grf_lateral")
#: A gait trial sampled this far apart (median, s) has its time in milliseconds: gait is sampled at 50 Hz
#: or more.
MAX_SAMPLE_INTERVAL_S = 0.5


@dataclass
class GaitTrial:
    """A gait trial: ``time`` (n,) s; ``hip`` (n, 3) rad (flexion, adduction, internal rotation);
    ``knee`` (n,) rad flexion; ``ankle`` (n,) rad dorsiflexion; ``grf`` (n, 3) N on the foot
    (anterior, vertical, lateral, lab frame = pelvis frame); ``cop`` (n,) mm anterior of the ankle along
    the foot (NaN in swing)."""

    time: np.ndarray
    hip: np.ndarray
    knee: np.ndarray
    ankle: np.ndarray
    grf: np.ndarray
    cop: np.ndarray
    source: str = ""


def read_gait_csv(path, mass: float) -> GaitTrial:
    """Read a gait CSV (``#`` comment lines allowed). Columns: ``time_s``, ``hip_flexion_deg``,
    ``knee_flexion_deg``, ``ankle_dorsiflexion_deg`` (required); ``hip_adduction_deg``,
    ``hip_rotation_deg``; the GRF as ``grf_{anterior,vertical,lateral}_N`` or ``..._bw`` (body weights,
    scaled by ``mass``); ``cop_anterior_mm``. Time must increase strictly."""
    path = Path(path)
    if not (mass > 0 and math.isfinite(mass)):
        raise KneeInputError(f"the body mass must be a positive number of kg, got {mass}")
    lines = [ln for ln in read_text(path, "gait file").splitlines() if ln.strip() and not ln.startswith("#")]
    if not lines:
        raise KneeInputError(f"{path}: empty gait file")
    rows = list(csv.reader(lines))
    header = [h.strip() for h in rows[0]]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise KneeInputError(f"{path}: missing column(s) {', '.join(missing)}")
    try:
        data = np.array([[float(v) if v.strip() else np.nan for v in r] for r in rows[1:]], dtype=float)
    except ValueError as e:
        raise KneeInputError(f"{path}: a value is not a number ({e})") from None
    if data.ndim != 2 or data.shape[0] < 3 or data.shape[1] != len(header):
        raise KneeInputError(f"{path}: needs at least 3 rows of {len(header)} values")

    def col(name, default=None):
        if name in header:
            return data[:, header.index(name)]
        return None if default is None else np.full(len(data), default)

    t = col("time_s")
    for name in REQUIRED:
        if not np.all(np.isfinite(col(name))):
            raise KneeInputError(f"{path}: column {name} has missing or non-finite values")
    if np.any(np.diff(t) <= 0):
        k = int(np.nonzero(np.diff(t) <= 0)[0][0])
        raise KneeInputError(f"{path}: time is not increasing at row {k + 2} ({t[k]:g} then {t[k + 1]:g} s)")
    step = float(np.median(np.diff(t)))
    if step >= MAX_SAMPLE_INTERVAL_S:
        raise KneeInputError(f"{path}: column time_s has samples {step:g} s apart (a {t[-1] - t[0]:g} s trial): it "
                             f"looks like milliseconds; give the time in seconds")
    for name in ("hip_adduction_deg", "hip_rotation_deg") + tuple(f"{b}_{u}" for b in GRF_COLUMNS for u in ("N", "bw")):
        v = col(name)
        if v is not None and not np.all(np.isfinite(v)):
            bad = np.nonzero(~np.isfinite(v))[0] + 2
            raise KneeInputError(f"{path}: column {name} has {bad.size} missing or non-finite values (rows "
                                 f"{bad[0]}-{bad[-1]}); give 0 where there is no ground contact")
    grf = np.zeros((len(t), 3))
    for j, base in enumerate(GRF_COLUMNS):
        if f"{base}_N" in header:
            grf[:, j] = col(f"{base}_N")
        elif f"{base}_bw" in header:
            grf[:, j] = col(f"{base}_bw") * mass * G
        elif base != "grf_lateral":
            raise KneeInputError(f"{path}: missing column {base}_N (or {base}_bw)")
    hip = np.column_stack([col("hip_flexion_deg"), col("hip_adduction_deg", 0.0), col("hip_rotation_deg", 0.0)])
    cop = col("cop_anterior_mm", np.nan)
    return GaitTrial(time=t, hip=np.radians(hip), knee=np.radians(col("knee_flexion_deg")),
                     ankle=np.radians(col("ankle_dorsiflexion_deg")), grf=grf, cop=cop, source=str(path))


def normative_trial(mass: float = 72.0) -> GaitTrial:
    """The bundled normative cycle (``models/data/gait-normative.csv``; see scripts/make_normative_gait.py
    for what it is and its sources) for a subject of ``mass`` kg."""
    with resources.as_file(resources.files("knee.models") / "data" / "gait-normative.csv") as p:
        trial = read_gait_csv(p, mass)
    trial.source = "bundled normative cycle (models/data/gait-normative.csv)"
    return trial


@dataclass(frozen=True)
class Anthropometry:
    """Segment parameters from body mass (kg) and height (m); see the module docstring."""

    mass: float = 72.0
    height: float = 1.75

    def __post_init__(self):
        if not (self.mass > 0 and 0.5 < self.height < 2.5):
            raise KneeInputError(f"body mass must be positive and height 0.5-2.5 m, got {self.mass} kg, "
                                 f"{self.height} m")

    @property
    def thigh(self):  # length, mass, CoM fraction from proximal, radii of gyration (sag, trans, long)
        return 0.245 * self.height, 0.1416 * self.mass, 0.4095, (0.329, 0.329, 0.149)

    @property
    def shank(self):
        return 0.246 * self.height, 0.0433 * self.mass, 0.4459, (0.255, 0.249, 0.103)

    @property
    def foot(self):
        return 0.152 * self.height, 0.0137 * self.mass, 0.4415, (0.257, 0.245, 0.124)

    @property
    def ankle_height(self):
        return 0.039 * self.height


def _inertia(m, L, com, radii):
    """Segment inertia: radii (sagittal about z, transverse about x, longitudinal about y) x length."""
    rs, rt, rl = (r * L for r in radii)
    I = np.diag([m * rt ** 2, m * rl ** 2, m * rs ** 2])
    return pin.Inertia(m, np.asarray(com, float), I)


@dataclass
class Limb:
    """The Pinocchio model and what the analysis needs from it."""

    model: object
    joints: dict
    anthropometry: Anthropometry
    ankle_in_tibia: np.ndarray  # (3,) m
    heel: float  # m, heel x in the foot frame
    patella_in_joint: object = None  # pin.SE3: the patella's frame in its helical joint's frame


def build_limb(mech: Mechanism, anthro: Anthropometry, ankle_in_tibia=None, hip_in_femur=None) -> Limb:
    """The chain of the module docstring for a mechanism with a patella. ``ankle_in_tibia`` and
    ``hip_in_femur`` (3,) mm override the ankle centre (tibia frame; default (0, -L_shank, 0)) and the hip
    centre (femur frame; default (0, L_thigh, 0)), e.g. after an osteotomy."""
    p = mech.params
    if p.pf is None:
        raise KneeInputError(f"{p.name}: the gait chain needs a model with a patella")
    model = pin.Model()
    model.gravity = pin.Motion(np.array([0.0, -G, 0.0]), np.zeros(3))
    Lt, mt, ct, rt = anthro.thigh
    Ls, ms, cs, rs = anthro.shank
    Lf, mf, cf, rf = anthro.foot
    hip = model.addJoint(0, pin.JointModelSphericalZYX(), pin.SE3.Identity(), "hip")
    # the femur body frame (knee model's frame) sits L_thigh below the hip centre
    hip_c = np.array([0.0, Lt, 0.0]) if hip_in_femur is None else np.asarray(hip_in_femur, float) * 1e-3
    femur_in_hip = pin.SE3(np.eye(3), -hip_c)
    model.appendBodyToJoint(hip, _inertia(mt, Lt, [0.0, -ct * Lt, 0.0], rt), pin.SE3.Identity())
    knee = model.addJoint(hip, pin.JointModelFreeFlyer(), femur_in_hip, "knee")
    model.appendBodyToJoint(knee, _inertia(ms, Ls, [0.0, -cs * Ls, 0.0], rs), pin.SE3.Identity())
    ankle = np.array([0.0, -Ls, 0.0]) if ankle_in_tibia is None else np.asarray(ankle_in_tibia, float) * 1e-3
    ank = model.addJoint(knee, pin.JointModelRZ(), pin.SE3(np.eye(3), ankle), "ankle")
    heel = -0.2 * Lf
    model.appendBodyToJoint(ank, _inertia(mf, Lf, [heel + cf * Lf, -0.5 * anthro.ankle_height, 0.0], rf),
                            pin.SE3.Identity())
    # patella: helical joint on the mechanism's axis (placement from the reference pose)
    pat, X = _patella_joint(model, hip, femur_in_hip, mech)
    return Limb(model=model, joints={"hip": hip, "knee": knee, "ankle": ank, "patella": pat}, anthropometry=anthro,
                ankle_in_tibia=ankle, heel=heel, patella_in_joint=X)


def _patella_frame(mech):
    """Reference pose (R_ref, P_ref) of the patella (femur frame, mm), helical axis n_f and its point
    a = q_f + lambda0 n_f (mm)."""
    pf = mech.params.pf
    _, pf_ref = mech.motion_at(np.array([pf.reference_flexion]))
    T = joint_to_pose(pf_ref[0])
    n = pf.axis_femur / np.linalg.norm(pf.axis_femur)
    a = pf.point_femur + pf.lambda0 * n
    return T[:3, :3], T[:3, 3], n, a


def _patella_joint(model, hip, femur_in_hip, mech):
    R_ref, P_ref, n, a = _patella_frame(mech)
    axis_local = R_ref.T @ n
    placement = femur_in_hip * pin.SE3(R_ref, a * 1e-3)
    j = model.addJoint(hip, pin.JointModelHelicalUnaligned(axis_local, mech.params.pf.lambda1 * 1e-3), placement,
                       "patella")
    X = pin.SE3(np.eye(3), R_ref.T @ (P_ref - a) * 1e-3)  # patella origin in the joint frame
    model.appendBodyToJoint(j, pin.Inertia(0.05, np.zeros(3), np.eye(3) * 1e-6), X)
    return j, X


def _vee(W):
    return np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], axis=-1)


@dataclass(frozen=True)
class KneeKinematics:
    """The knee's motion at n frames: the tibia's pose ``T`` (n, 4, 4) in the femur frame (mm), its twist
    velocity ``v`` and acceleration ``a`` (n, 6) (linear m/s, m/s^2 then angular rad/s, rad/s^2, in the tibia
    frame), the TF and PF joint coordinates (n, 6), and the patella's helical angle ``theta`` (n,) (rad)
    with its rates."""

    T: np.ndarray
    v: np.ndarray
    a: np.ndarray
    tf: np.ndarray
    pf: np.ndarray
    theta: np.ndarray
    theta_d: np.ndarray
    theta_dd: np.ndarray


def knee_kinematics(mech: Mechanism, alpha, alpha_d, alpha_dd, h: float = 1e-4) -> KneeKinematics:
    """Tibia pose (n, 4, 4) in the femur frame, body velocity (n, 6) and its time derivative (n, 6)
    (linear m/s, angular rad/s, in the tibia frame), and the patella's helical angle with its rates."""
    al = np.asarray(alpha, float)
    n = al.size
    path = np.column_stack([al - h, al, al + h]).ravel()
    tf, pf = mech.motion_at(path)
    T = joint_to_pose(tf).reshape(n, 3, 4, 4)
    Tm, T0, Tp = T[:, 0], T[:, 1], T[:, 2]
    d1 = (Tp - Tm) / (2 * h)
    d2 = (Tp - 2 * T0 + Tm) / h ** 2
    R, dR, ddR = T0[:, :3, :3], d1[:, :3, :3], d2[:, :3, :3]
    dP, ddP = d1[:, :3, 3] * 1e-3, d2[:, :3, 3] * 1e-3
    Rt = np.swapaxes(R, 1, 2)
    dRt = np.swapaxes(dR, 1, 2)
    Jv = np.einsum("nij,nj->ni", Rt, dP)
    Jw = _vee(Rt @ dR)
    dJv = np.einsum("nij,nj->ni", dRt, dP) + np.einsum("nij,nj->ni", Rt, ddP)
    dJw = _vee(dRt @ dR + Rt @ ddR)
    J = np.column_stack([Jv, Jw])
    dJ = np.column_stack([dJv, dJw])
    ad, add = np.asarray(alpha_d, float), np.asarray(alpha_dd, float)
    v = J * ad[:, None]
    a = J * add[:, None] + dJ * (ad ** 2)[:, None]
    # patella: angle about the helical axis from the reference orientation
    R_ref, _, nax, _ = _patella_frame(mech)
    Pp = joint_to_pose(pf).reshape(n, 3, 4, 4)[:, :, :3, :3]
    Q = Pp @ R_ref.T
    s = np.einsum("nkj,j->nk", _vee(Q - np.swapaxes(Q, -1, -2)) / 2, nax)
    c = (np.trace(Q, axis1=-2, axis2=-1) - 1) / 2
    th = np.unwrap(np.arctan2(s, c), axis=1)
    dth = (th[:, 2] - th[:, 0]) / (2 * h)
    ddth = (th[:, 2] - 2 * th[:, 1] + th[:, 0]) / h ** 2
    return KneeKinematics(T0, v, a, tf.reshape(n, 3, 6)[:, 1], pf.reshape(n, 3, 6)[:, 1], th[:, 1], dth * ad,
                          ddth * ad ** 2 + dth * add)


@dataclass
class GaitResult:
    """Per frame: the knee load on the tibia (``force`` N and ``moment`` N*mm, tibia frame), the member
    forces (:class:`StaticsResult`), Hertz and elastic-foundation results per contact, and the world
    poses of the segments (for the recording)."""

    trial: GaitTrial
    knee_force: np.ndarray
    knee_moment: np.ndarray
    statics: StaticsResult
    contact: dict
    poses: dict
    tau: np.ndarray
    tf: np.ndarray = None
    pf: np.ndarray = None
    flags: list = field(default_factory=list)
    seconds: float = 0.0

    @property
    def valid(self) -> np.ndarray:
        """(n,) bool: the frames whose member forces all have their physical sign (no statics flag). In a
        flagged frame a ligament would push or a contact pull: its forces and pressures are not valid."""
        return np.array([not f for f in self.statics.flags], dtype=bool)

    @property
    def flagged_note(self) -> str:
        """One line for the top of a report: how many frames are flagged and what that means ('' if none)."""
        n, k = self.valid.size, int((~self.valid).sum())
        if k == 0:
            return ""
        return (f"{k} of {n} frames are flagged: a ligament would have to push or a contact to pull (the 1-DoF "
                f"mechanism's statics is determinate, so it cannot share the load otherwise); the forces and "
                f"pressures of those frames are not physically valid" + (
                    " - every frame is flagged, so no contact figure of this run is valid" if k == n else
                    "; summaries use the other frames only"))


def _rates(t, x):
    return np.gradient(x, t, axis=0), np.gradient(np.gradient(x, t, axis=0), t, axis=0)


def analyse_gait(mech: Mechanism, trial: GaitTrial, anthro: Anthropometry | None = None,
                 cartilage: Cartilage = CARTILAGE, ankle_in_tibia=None, foundation: bool = True,
                 hip_in_femur=None) -> GaitResult:
    """Kinematics, inverse dynamics, statics and contact pressures for every frame of ``trial``.

    ``trial``: the joint angles (rad), ground reaction force (N, world frame: x anterior, y up, z lateral)
    and centre of pressure (mm along the foot) over time (s); ``anthro``: body mass (kg) and height (m);
    ``ankle_in_tibia``, ``hip_in_femur`` (3,) mm: joint centres in the bone frames, when measured.
    Returns a :class:`GaitResult` (the knee load on the tibia in the tibia frame, N and N*mm, per frame;
    member forces, N; contact pressures, MPa). Raises :class:`AssemblyError` when the knee's flexion leaves
    the mechanism's assembly range."""

    t0 = time.perf_counter()
    anthro = anthro or Anthropometry()
    lo, hi = mech.assembly_range
    bad = np.nonzero((trial.knee < lo) | (trial.knee > hi))[0]
    if bad.size:
        k = int(bad[0])
        raise AssemblyError(f"{mech.params.name}: knee flexion {math.degrees(trial.knee[k]):.1f} deg at t = "
                            f"{trial.time[k]:.3f} s is outside the assembly range {math.degrees(lo):.1f} to "
                            f"{math.degrees(hi):.1f} deg")
    limb = build_limb(mech, anthro, ankle_in_tibia, hip_in_femur)
    model = limb.model
    data = model.createData()
    t = trial.time
    kd, kdd = _rates(t, trial.knee)
    hd, hdd = _rates(t, trial.hip)
    ad, add = _rates(t, trial.ankle)
    kin = knee_kinematics(mech, trial.knee, kd, kdd)
    n = t.size
    # configuration, velocity, acceleration (pinocchio ordering: hip ZYX = (flex z, rot y, add x))
    q = np.zeros((n, model.nq))
    v = np.zeros((n, model.nv))
    a = np.zeros((n, model.nv))
    hip_zyx = trial.hip[:, [0, 2, 1]]
    q[:, 0:3], v[:, 0:3], a[:, 0:3] = hip_zyx, hd[:, [0, 2, 1]], hdd[:, [0, 2, 1]]
    T = kin.T
    quat = _quaternions(T[:, :3, :3])
    q[:, 3:6] = T[:, :3, 3] * 1e-3
    q[:, 6:10] = quat
    v[:, 3:9], a[:, 3:9] = kin.v, kin.a
    iq_a, iv_a = model.joints[limb.joints["ankle"]].idx_q, model.joints[limb.joints["ankle"]].idx_v
    iq_p, iv_p = model.joints[limb.joints["patella"]].idx_q, model.joints[limb.joints["patella"]].idx_v
    q[:, iq_a], v[:, iv_a], a[:, iv_a] = trial.ankle, ad, add
    q[:, iq_p], v[:, iv_p], a[:, iv_p] = kin.theta, kin.theta_d, kin.theta_dd
    # centre of pressure on the sole (foot frame, m); default heel-to-forefoot over stance
    Lf = anthro.foot[0]
    cop = np.where(np.isfinite(trial.cop), trial.cop * 1e-3, limb.heel + 0.5 * Lf)
    sole = -anthro.ankle_height
    fk = np.zeros((n, 6))
    tau = np.zeros((n, model.nv))
    poses = {k: np.zeros((n, 4, 4)) for k in ("femur", "tibia", "foot", "patella")}
    j_hip, j_knee, j_ank, j_pat = (limb.joints[k] for k in ("hip", "knee", "ankle", "patella"))
    femur_in_hip = model.jointPlacements[j_knee]
    zero = pin.Force.Zero()
    for k in range(n):  # Pinocchio's C++ RNEA per frame (no batched Python API)
        pin.forwardKinematics(model, data, q[k])
        oMf = data.oMi[j_ank]
        p_cop = oMf.act(np.array([cop[k], sole, 0.0]))
        f_world = pin.Force(trial.grf[k], np.cross(p_cop, trial.grf[k]))
        fext = [zero] * model.njoints
        fext[j_ank] = oMf.actInv(f_world)
        tau[k] = pin.rnea(model, data, q[k], v[k], a[k], fext)
        fk[k] = data.f[j_knee].vector
        poses["femur"][k] = (data.oMi[j_hip] * femur_in_hip).homogeneous
        poses["tibia"][k] = data.oMi[j_knee].homogeneous
        poses["foot"][k] = oMf.homogeneous
        poses["patella"][k] = (data.oMi[j_pat] * limb.patella_in_joint).homogeneous
    # the load on the tibia that the links and tendon balance: minus what the femur transmits
    F = -fk[:, :3]
    M = -fk[:, 3:] * 1e3
    st = solve_statics(mech, trial.knee, F, M)
    contact = contact_loads(mech.params, st, cartilage, foundation)
    flags = [f"t = {t[k]:.3f} s: {'; '.join(st.flags[k])}" for k in range(n) if st.flags[k]]
    return GaitResult(trial=trial, knee_force=F, knee_moment=M, statics=st, contact=contact, poses=poses, tau=tau,
                      tf=kin.tf, pf=kin.pf, flags=flags, seconds=time.perf_counter() - t0)


def _quaternions(R):
    """Unit quaternions (x, y, z, w) of rotation matrices (n, 3, 3), vectorised (Shepperd's method)."""
    n = R.shape[0]
    q = np.zeros((n, 4))
    tr = np.trace(R, axis1=1, axis2=2)
    cases = np.column_stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]]).argmax(axis=1)
    for c in range(4):
        m = cases == c
        if not m.any():
            continue
        r = R[m]
        if c == 0:
            s = np.sqrt(1 + tr[m]) * 2
            q[m] = np.column_stack([(r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s,
                                    (r[:, 1, 0] - r[:, 0, 1]) / s, 0.25 * s])
        else:
            i = c - 1
            j, k = (i + 1) % 3, (i + 2) % 3
            s = np.sqrt(1 + r[:, i, i] - r[:, j, j] - r[:, k, k]) * 2
            qq = np.zeros((m.sum(), 4))
            qq[:, i] = 0.25 * s
            qq[:, j] = (r[:, j, i] + r[:, i, j]) / s
            qq[:, k] = (r[:, k, i] + r[:, i, k]) / s
            qq[:, 3] = (r[:, k, j] - r[:, j, k]) / s
            q[m] = qq
    return q / np.linalg.norm(q, axis=1, keepdims=True)
