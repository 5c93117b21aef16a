"""Virtual osteotomy on the mechanism (issue "contact mechanics, gait and virtual osteotomy", section 4).

A plane (point, normal; the bone's frame, mm) cuts the tibia or the femur. The fragment on the side of the
plane away from the knee (the bone frame's origin) is the moved one: it turns about the hinge axis (a
point inside the bone and a direction, roughly in the cut plane) by ``angle`` degrees: a positive angle
opens a wedge on the side of the cut opposite the hinge, a negative one closes it (for a right tibia
with a lateral hinge, +8 is a medial opening-wedge high tibial osteotomy: the ankle moves laterally and
the weight-bearing line toward the lateral compartment). Link insertions, tendon insertions and the
limb's joint centre (ankle or hip) on the moved fragment move with it; the mechanism is rebuilt and
everything is recomputed:

* mechanical axes at full extension: hip centre -> knee centre (femur), knee centre -> ankle centre
  (tibia), and the hip-knee-ankle deviation in the frontal plane of the femur (positive varus);
* the weight-bearing line (hip centre to ankle centre) where it crosses the tibial plateau (the tibia
  frame's y = 0 plane), as a percentage of the plateau width from its medial (0 %) to lateral (100 %)
  edge; the commonly targeted point is 62.5 % (Fujisawa et al., Orthop Clin North Am 10:585-608, 1979);
* the kinematics over flexion and the contact pressures in gait, before and after.

The hip and ankle centres default to the femoral and tibial long axes at the lengths of
:class:`knee.models.gait.Anthropometry` (thigh 0.245 H, shank 0.246 H); pass measured ones when you have them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import trimesh

from knee.foundations.conventions import joint_to_pose
from knee.foundations.errors import AssemblyError, KneeInputError
from knee.foundations.surfaces import SurfaceQuery
from knee.models.gait import Anthropometry, GaitResult, GaitTrial, analyse_gait
from knee.models.mechanism.params import InitialPose, MechanismParams
from knee.models.mechanism.solver import Mechanism, quick_tf_sweep
from knee.models.phantom import Phantom, build_phantom

FUJISAWA = 62.5


@dataclass(frozen=True)
class Cut:
    """An osteotomy: ``bone`` ('tibia' or 'femur'); plane point and normal, hinge point and axis (mm, the
    bone's frame); ``angle`` in degrees."""

    bone: str
    plane_point: np.ndarray
    plane_normal: np.ndarray
    hinge_point: np.ndarray
    hinge_axis: np.ndarray
    angle: float


def default_cut(bone: str, mesh: trimesh.Trimesh, angle: float) -> Cut:
    """A transverse cut 35 mm below the joint line (tibia; 60 mm above it for the femur) with the hinge
    8 mm inside the lateral cortex of that cross-section, along x (anterior)."""
    y = -35.0 if bone == "tibia" else 60.0
    g = np.arange(-60.0, 60.0 + 1e-9, 1.0)
    X, Z = np.meshgrid(g, g, indexing="ij")
    pts = np.column_stack([X.ravel(), np.full(X.size, y), Z.ravel()])
    inside = pts[SurfaceQuery.of(mesh).signed_distance(pts) < 0]
    if len(inside) == 0:
        raise KneeInputError(f"the {bone} has no bone {abs(y):.0f} mm from the joint line for the default cut")
    z_lat = inside[:, 2].max()
    row = inside[inside[:, 2] > z_lat - 9.0]
    hinge = np.array([float(np.median(row[:, 0])), y, z_lat - 8.0])
    return Cut(bone, np.array([0.0, y, 0.0]), np.array([0.0, 1.0, 0.0]), hinge, np.array([1.0, 0.0, 0.0]),
               float(angle))


def wedge_transform(cut: Cut) -> np.ndarray:
    """The rigid motion (4, 4) of the moved fragment: rotation by ``angle`` about the hinge axis, turning
    so that a positive angle opens the cut on the side opposite the hinge."""
    k = np.asarray(cut.hinge_axis, float)
    k = k / np.linalg.norm(k)
    n = cut.plane_normal / np.linalg.norm(cut.plane_normal)
    into_moved = -np.sign((np.zeros(3) - cut.plane_point) @ n) * n
    v = np.asarray(cut.plane_point, float) - cut.hinge_point
    v -= (v @ k) * k
    if np.cross(k, v) @ into_moved < 0:
        k = -k
    th = math.radians(cut.angle)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cut.hinge_point - R @ cut.hinge_point
    return T


def validate_cut(cut: Cut, mesh: trimesh.Trimesh) -> None:
    """Clear errors for a plane that misses the bone, a hinge outside it, or a bad angle."""
    if cut.bone not in ("tibia", "femur"):
        raise KneeInputError(f"the cut bone must be tibia or femur, got {cut.bone!r}")
    for name, v in (("plane normal", cut.plane_normal), ("hinge axis", cut.hinge_axis)):
        if not (np.all(np.isfinite(v)) and np.linalg.norm(v) > 1e-9):
            raise KneeInputError(f"the {name} must be a finite non-zero vector")
    if not (math.isfinite(cut.angle) and abs(cut.angle) <= 30.0):
        raise KneeInputError(f"the wedge angle must be within +-30 deg, got {cut.angle}")
    n = cut.plane_normal / np.linalg.norm(cut.plane_normal)
    s = (mesh.vertices - cut.plane_point) @ n
    if s.min() >= 0 or s.max() <= 0:
        raise KneeInputError(f"the cutting plane misses the {cut.bone} (all of the bone lies on one side)")
    if (np.zeros(3) - cut.plane_point) @ n == 0:
        raise KneeInputError("the cutting plane passes through the knee centre; no fragment to move")
    outside = float(SurfaceQuery.of(mesh).signed_distance(np.asarray(cut.hinge_point, float)[None])[0])
    if outside > 1.0:
        raise KneeInputError(f"the hinge point lies {outside:.1f} mm outside the {cut.bone}")
    if abs(np.dot(cut.hinge_axis / np.linalg.norm(cut.hinge_axis), n)) > 0.5:
        raise KneeInputError("the hinge axis must lie roughly in the cutting plane (it is more than 30 deg out of it)")


def moved_side(cut: Cut, points) -> np.ndarray:
    """(n,) bool: points on the fragment that moves (the side of the plane away from the knee centre)."""
    n = cut.plane_normal / np.linalg.norm(cut.plane_normal)
    knee_side = np.sign((np.zeros(3) - cut.plane_point) @ n)
    return np.sign((np.atleast_2d(points) - cut.plane_point) @ n) == -knee_side


def apply_cut(params: MechanismParams, cut: Cut, release=()) -> tuple[MechanismParams, list[str]]:
    """The parameter set after the osteotomy, and the names of the insertions that moved.

    ``release``: names of ligament links to release: a released ligament whose insertion moved gets the
    length between its (moved) endpoints at the pre-operative full-extension pose, as after a surgical
    release and re-tensioning; an unreleased one keeps its length (it is isometric), which may stop the
    knee from assembling."""
    W = wedge_transform(cut)
    names = [lk.name for lk in params.links]
    for r in release:
        if r not in names or params.link(r).role != "ligament":
            raise KneeInputError(f"release {r}: not a ligament link of {params.name} ({', '.join(names)})")
    T0 = None
    if release:
        T0 = joint_to_pose(Mechanism(params).motion_at(np.array([0.0]))[0][0])

    def mv(p):
        return W[:3, :3] @ p + W[:3, 3]

    moved = []
    links = []
    up = np.array([0.0, 1.0, 0.0])
    for lk in params.links:
        pt = lk.tibia if cut.bone == "tibia" else lk.femur
        if lk.role == "contact" and cut.bone == "tibia" and lk.kind == "distance":
            # the articular facet, not the (deep) sphere centre, decides which fragment carries a contact
            rf = lk.femur_radius or 24.0
            pt = lk.tibia + ((lk.length - rf) if lk.tibia_surface == "convex" else -(lk.length + rf)) * up
        if moved_side(cut, pt)[0]:
            moved.append(f"{lk.name} {cut.bone} point")
            if cut.bone == "tibia":
                nrm = None if lk.normal is None else W[:3, :3] @ lk.normal
                lk = replace(lk, tibia=mv(lk.tibia), normal=nrm)
            else:
                lk = replace(lk, femur=mv(lk.femur))
            if lk.name in release:
                ln = float(np.linalg.norm(lk.femur - (T0[:3, :3] @ lk.tibia + T0[:3, 3])))
                moved.append(f"{lk.name} released: length {lk.length:.2f} -> {ln:.2f} mm")
                lk = replace(lk, length=ln)
        links.append(lk)
    pf = params.pf
    if pf is not None:
        if cut.bone == "tibia" and moved_side(cut, pf.tendon_tibia)[0]:
            moved.append("patellar tendon tibial point")
            pf = replace(pf, tendon_tibia=mv(pf.tendon_tibia))
        if cut.bone == "femur" and moved_side(cut, pf.point_femur)[0]:
            moved.append("helical axis (femur)")
            ax = W[:3, :3] @ pf.axis_femur
            q = mv(pf.point_femur)
            q = q - q[2] / ax[2] * ax  # back to the sagittal plane
            pf = replace(pf, axis_femur=ax, point_femur=q)
    new = replace(params, links=tuple(links), pf=pf, initial=_track_initial(params, links, pf),
                  name=f"{params.name}-{cut.bone}-osteotomy-{cut.angle:+g}deg",
                  description=f"{params.name} after a {cut.angle:+g} deg {cut.bone} osteotomy (knee osteotomy)")
    return new, moved


def _track_initial(params: MechanismParams, links, pf):
    """The stored assembly carried to the new geometry by a homotopy in 20 steps (Newton from the previous
    step's solution), so the osteotomised knee keeps its branch."""
    if params.initial is None:
        return None
    v0 = params.to_vector()
    v1 = replace(params, links=tuple(links), pf=pf).to_vector()
    x = params.initial.unknowns.copy()
    a = np.array([params.initial.flexion])
    for s in np.linspace(0.0, 1.0, 21)[1:]:
        tf, _, ok, _ = quick_tf_sweep((1 - s) * v0 + s * v1, params.kinds, x, a)
        if not ok:
            return None  # the geometry stops assembling at the stored flexion: let the solver search
        x = tf[0, 1:]
    return InitialPose(params.initial.flexion, x)


@dataclass
class Alignment:
    """Limb alignment at full extension: ``hka_deg`` (deviation from straight, positive varus),
    ``wbl_percent`` (weight-bearing line across the plateau, medial 0 % to lateral 100 %), and the
    points (femur frame, mm) for drawing: hip, knee (femur origin), tibia origin, ankle, WBL crossing."""

    hka_deg: float
    wbl_percent: float
    hip: np.ndarray
    knee: np.ndarray
    tibia_origin: np.ndarray
    ankle: np.ndarray
    crossing: np.ndarray


def alignment(mech: Mechanism, hip_in_femur, ankle_in_tibia, plateau_z: tuple[float, float],
              flexion: float = 0.0) -> Alignment:
    """Mechanical axes and weight-bearing line with the tibia at ``flexion`` (rad, default full extension)."""
    tf, _ = mech.motion_at(np.array([flexion]))
    T = joint_to_pose(tf[0])
    H = np.asarray(hip_in_femur, float)
    K = np.zeros(3)
    To = T[:3, 3]
    A = T[:3, :3] @ np.asarray(ankle_in_tibia, float) + To
    d1, d2 = K - H, A - To
    d1[0] = d2[0] = 0.0  # frontal plane of the femur (y-z)
    hka = math.degrees(math.atan2(np.cross(d1, d2)[0], d1 @ d2))
    # WBL crossing with the plateau plane (tibia y = 0) in the tibia frame
    Ti = np.linalg.inv(T)
    h = Ti[:3, :3] @ H + Ti[:3, 3]
    a = Ti[:3, :3] @ A + Ti[:3, 3]
    s = h[1] / (h[1] - a[1])
    c = h + s * (a - h)
    z_med, z_lat = plateau_z
    pct = 100.0 * (c[2] - z_med) / (z_lat - z_med)
    return Alignment(hka_deg=hka, wbl_percent=pct, hip=H, knee=K, tibia_origin=To, ankle=A,
                     crossing=T[:3, :3] @ c + To)


def plateau_width(tibia: trimesh.Trimesh, depth: float = 20.0) -> tuple[float, float]:
    """Medial and lateral edges (z, mm) of the tibial plateau: the bone within ``depth`` of the top."""
    v = tibia.vertices
    top = v[v[:, 1] > v[:, 1].max() - depth]
    return float(top[:, 2].min()), float(top[:, 2].max())


@dataclass
class OsteotomyResult:
    """An osteotomy applied: the mechanisms before and after, the parameter set after, what moved with the
    fragment (one line each), the fragment's motion ``W`` (4, 4, bone frame), the phantom cut, the
    alignments at full extension before and after, the hip and ankle centres (femur and tibia frames, mm)
    before and after, and the plateau's medial and lateral edges (z, mm)."""

    before: Mechanism
    after: Mechanism
    params: MechanismParams
    moved: list
    W: np.ndarray
    phantom: Phantom
    align_before: Alignment
    align_after: Alignment
    hip: tuple
    ankle: tuple
    plateau_z: tuple


def osteotomy(params: MechanismParams, cut: Cut, height: float = 1.75, hip_in_femur=None, ankle_in_tibia=None,
              release=()) -> OsteotomyResult:
    """Apply ``cut`` to ``params`` and recompute the alignment (see the module docstring). The hip and
    ankle centres default to the long axes at the anthropometric segment lengths of a subject of
    ``height`` (m). Raises :class:`AssemblyError` when the knee no longer assembles at full extension."""
    anthro = Anthropometry(72.0, height)
    H = np.array([0.0, anthro.thigh[0] * 1e3, 0.0]) if hip_in_femur is None else np.asarray(hip_in_femur, float)
    A = np.array([0.0, -anthro.shank[0] * 1e3, 0.0]) if ankle_in_tibia is None else np.asarray(ankle_in_tibia, float)
    ph = build_phantom(params)
    mesh = ph.tibia if cut.bone == "tibia" else ph.femur
    validate_cut(cut, mesh)
    before = Mechanism(params)
    new, moved = apply_cut(params, cut, release)
    W = wedge_transform(cut)
    H2, A2 = H.copy(), A.copy()
    if cut.bone == "tibia" and moved_side(cut, A)[0]:
        A2 = W[:3, :3] @ A + W[:3, 3]
        moved.append("ankle centre")
    if cut.bone == "femur" and moved_side(cut, H)[0]:
        H2 = W[:3, :3] @ H + W[:3, 3]
        moved.append("hip centre")
    try:
        after = Mechanism(new)
        if not after.in_range(0.0):
            raise AssemblyError(f"assembles only from {math.degrees(after.assembly_range[0]):.1f} to "
                                f"{math.degrees(after.assembly_range[1]):.1f} deg, not at full extension")
    except AssemblyError as e:
        hint = [lk.name for lk in params.links if lk.role == "ligament" and f"{lk.name} {cut.bone} point" in moved
                and lk.name not in release]
        extra = (f"; the insertion of {', '.join(hint)} moved with the fragment: release {hint[0]} to re-tension "
                 f"it") if hint else ""
        raise AssemblyError(f"after a {cut.angle:+g} deg {cut.bone} osteotomy the mechanism does not assemble "
                            f"({str(e).split(': ', 1)[-1]}){extra}") from None
    pz = plateau_width(ph.tibia)
    return OsteotomyResult(before, after, new, moved, W, ph, alignment(before, H, A, pz), alignment(after, H2, A2, pz),
                           (H, H2), (A, A2), pz)


@dataclass
class OsteotomyComparison:
    """Before against after: the TF motion (n, 6) (rad, mm) at the angles ``flexion_deg`` (n,) both
    assemble over (0-120 deg, every 2), and the gait analyses of one trial."""

    flexion_deg: np.ndarray
    tf_before: np.ndarray
    tf_after: np.ndarray
    gait_before: GaitResult
    gait_after: GaitResult


def compare(res: OsteotomyResult, trial: GaitTrial, height: float = 1.75, mass: float = 72.0) -> OsteotomyComparison:
    """Kinematics over flexion and contact in gait, before and after (the numbers of the report)."""
    b, a = res.before, res.after
    lo = max(b.assembly_range[0], a.assembly_range[0], 0.0)
    hi = min(b.assembly_range[1], a.assembly_range[1], math.radians(120.0))
    fl = np.arange(math.degrees(lo), math.degrees(hi) + 1e-9, 2.0)
    tb, _ = b.motion_at(np.radians(fl))
    ta, _ = a.motion_at(np.radians(fl))
    anthro = Anthropometry(mass, height)
    gb = analyse_gait(b, trial, anthro, ankle_in_tibia=res.ankle[0], hip_in_femur=res.hip[0])
    ga = analyse_gait(a, trial, anthro, ankle_in_tibia=res.ankle[1], hip_in_femur=res.hip[1])
    return OsteotomyComparison(fl, tb, ta, gb, ga)


@dataclass(frozen=True)
class ContactSummary:
    """One contact over a gait cycle's valid frames (no statics flag, :attr:`GaitResult.valid`): its peak
    force (N), Hertz and elastic-foundation peak pressures (MPa; the latter None when not computed), its
    mean share of the total contact force in stance, and how many frames these come from (``frames``, of
    ``of``). With no valid frame every figure is NaN: nothing is presented from flagged frames."""

    peak_force_N: float
    hertz_peak_MPa: float
    foundation_peak_MPa: float | None
    mean_share: float
    frames: int = 0
    of: int = 0


def gait_contact_summary(g: GaitResult) -> dict[str, ContactSummary]:
    """Per contact, its :class:`ContactSummary` over the valid frames of the gait cycle ``g``."""
    out = {}
    ok = g.valid
    total = sum(e.force for e in g.contact.values())
    stance = (total > 0) & ok
    nan = float("nan")

    def peak(v):
        return float(v[ok].max()) if ok.any() else nan

    for name, e in g.contact.items():
        share = float(np.mean(e.force[stance] / total[stance])) if stance.any() else nan
        out[name] = ContactSummary(peak(e.force), peak(e.hertz.peak),
                                   peak(e.foundation.peak) if e.foundation is not None else None, share,
                                   int(ok.sum()), int(ok.size))
    return out
