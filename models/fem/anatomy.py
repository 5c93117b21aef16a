"""What the association model is built from: a knee's bone and skin surfaces in the femur's anatomical
frame, and the regions of them that the model uses, each derived from the anatomy itself.

:class:`KneeAnatomy` holds the femur, the tibia (posed as scanned), the skin (a closed surface: a whole
leg clipped to a band around the joint, or a scan's own band), the tibia's pose in the femur frame, and
the collateral ligaments' insertions. Every region the model needs is scaled by the knee's own size,
``width`` (the femur's medio-lateral width at the condyles), and placed from the joint line, never by
millimetre constants that assume one knee:

- the joint line, ``joint_y``: midway between the femur's distal-most point and the tibia's highest one;
- the contact regions: femur surface within 0.5 ``width`` above the joint line, tibia surface within
  0.4 ``width`` below it (the condyles and the plateau, with their margins);
- the thigh, where the model is held and where a point cloud is registered to it: the skin from
  ``thigh_from`` upwards, 0.8 ``width`` above the joint line, or the upper 40 % of what lies above the
  joint line when the scan is shorter than that (a scan of 60 mm of shaft still has a thigh band);
- the band kept of a longer scan: 2.5 ``width`` above and below the joint line (:func:`clip_anatomy`).

How close the bones are at a pose of the tibia (:func:`bone_clearance`: the least signed distance between
the two surfaces, negative where they overlap) and a tibia slid along its own axis to a given clearance
(:func:`in_contact`): the honest benchmark's truth keeps a measured motion's bones at the scan's clearance
plus the measured knee's own change with them, and the prior's methods keep the bones they place from
sinking into each other
(:func:`knee.models.fem.methods.keep_bones_apart`).

Frames: the femur's anatomical frame (x anterior, y proximal, z lateral, right knee; mm) is the model's
frame; ``tibia_pose`` (4, 4) takes tibia-frame coordinates to it at the scanned pose.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import trimesh
from scipy.optimize import brentq

from knee.foundations.conventions import invert_poses, pose_to_joint, transform_points
from knee.foundations.errors import KneeError, KneeInputError
from knee.foundations.geometry import end_width, epicondyles
from knee.foundations.pointclouds import thinned_evenly
from knee.foundations.surfaces import SurfaceQuery, clip_to_slab, closed_surface, decimated

#: How far (mm) a bone vertex may lie outside the skin before the anatomy is refused.
SKIN_TOLERANCE_MM = 0.5
#: Most surface points of each bone the femur-tibia contact and the bones' clearance use: a denser
#: segmentation (an MRI's bones carry 20,000-30,000 vertices near the joint, where the phantom's and the
#: Visible Human's carry 400-6,000) is thinned evenly to this many, so its cost per step stays that of
#: a coarser one (:func:`knee.foundations.pointclouds.thinned_evenly`).
BONE_POINTS_MOST = 8000
#: :func:`bone_clearance` asks first only the points within this reach (mm) of the other bone's bounding box.
CLEARANCE_REACH_MM = 10.0
#: The band of a longer scan kept around the joint line, in femur widths above and below it.
BAND_WIDTHS = 2.5
#: Most vertices of the skin the model works with (:func:`working_skin`). What the skin costs grows with
#: them: a spring per vertex in the FEM's surface phase, the flexion estimate's posed knee rebuilt at each
#: angle, the tibia's correction's queries. A CT's skin segmented at 1-2 mm carries about 100,000 over
#: such a band; the phantom's, the Visible Human's and lenhart2015's carried skin 1,300, 5,400 and 8,200,
#: and 10,000 vertices over a knee's band still put one every 3-4 mm, against grid cells of 20-30 mm.
SKIN_VERTICES_MOST = 10_000
#: The thigh region (held, registered) starts this many femur widths above the joint line...
THIGH_FROM_WIDTHS = 0.8
#: ... or, on a shorter scan, at this fraction of the height above the joint line from the top.
THIGH_FRACTION = 0.4


@dataclass
class KneeAnatomy:
    """A knee's surfaces for the association model (see the module docstring).

    Attributes
    ----------
    femur, tibia, skin : trimesh.Trimesh
        Closed surfaces in the femur frame (mm); the tibia at its scanned pose.
    tibia_pose : (4, 4) float
        The tibia's frame in the femur frame at the scan.
    mcl, lcl : (2, 3) float or None
        Femoral then tibial insertion of each collateral ligament (femur frame, the tibia's at the scan);
        None when not known (the model then places the spring itself, see
        :func:`knee.models.fem.scene.build_knee_model`).
    name : str
    """

    femur: trimesh.Trimesh
    tibia: trimesh.Trimesh
    skin: trimesh.Trimesh
    tibia_pose: np.ndarray
    mcl: np.ndarray | None = None
    lcl: np.ndarray | None = None
    name: str = "knee"

    @property
    def scan_tf(self) -> np.ndarray:
        """The TF joint coordinates (6,) of the scan (rad, mm)."""
        return pose_to_joint(self.tibia_pose)

    @cached_property
    def joint_y(self) -> float:
        """The joint line's height (femur frame, mm): :func:`joint_line` of the bones."""
        return joint_line(self.femur.vertices, self.tibia.vertices)

    @cached_property
    def width(self) -> float:
        """The femur's medio-lateral width at its distal end (mm): the knee's size."""
        v = np.asarray(self.femur.vertices)
        return end_width(v, v[:, 1], np.array([0.0, 0.0, 1.0]), "low")

    @cached_property
    def thigh_from(self) -> float:
        """Where the thigh region starts (femur frame y, mm; see the module docstring)."""
        top = float(self.skin.vertices[:, 1].max())
        y0 = self.joint_y
        return min(y0 + THIGH_FROM_WIDTHS * self.width, top - THIGH_FRACTION * (top - y0))

    def contact_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Femur and tibia surface points (P, 3) of the contact regions (femur frame)."""
        fv, tv = np.asarray(self.femur.vertices), np.asarray(self.tibia.vertices)
        y0, w = self.joint_y, self.width
        fv, tv = fv[fv[:, 1] < y0 + 0.5 * w], tv[tv[:, 1] > y0 - 0.4 * w]
        return fv[thinned_evenly(fv, BONE_POINTS_MOST)], tv[thinned_evenly(tv, BONE_POINTS_MOST)]

    def check(self, tolerance: float = SKIN_TOLERANCE_MM) -> None:
        """Refuse an anatomy whose bones do not lie inside its skin (with the count of bone vertices more
        than ``tolerance`` mm outside it: a thin soft-tissue layer, such as over the anterior tibia, meets
        the surfaces' discretisation) or whose surfaces are not closed."""
        for name in ("femur", "tibia", "skin"):
            closed_surface(getattr(self, name), name)
        q = SurfaceQuery.of(self.skin)
        for name in ("femur", "tibia"):
            v = np.asarray(getattr(self, name).vertices)
            out = int((q.signed_distance(v) > tolerance).sum())
            if out:
                raise KneeInputError(f"{out} of {len(v)} {name} vertices lie more than {tolerance:g} mm outside the "
                                     f"skin; the skin must enclose the bones (same scan, same frame)")


def default_collaterals(anatomy: KneeAnatomy) -> tuple[np.ndarray, np.ndarray]:
    """Collateral insertions (each (2, 3): femoral then tibial, femur frame) estimated from the bones'
    shapes when a scan gives none: femoral ends at the epicondyles (the centroid of the femur's surface
    within 2 % of its width of its most medial and most lateral points, within 0.75 width of its
    distal end); the MCL's tibial end on the medial tibial surface 0.65 width below the joint line (the
    superficial MCL inserts about 5-6 cm below it in adults), the LCL's on the lateral tibial surface 0.35
    width below the joint line (standing in for the fibular head)."""
    fv, tv = np.asarray(anatomy.femur.vertices), np.asarray(anatomy.tibia.vertices)
    y0, w = anatomy.joint_y, anatomy.width
    le, me = epicondyles(fv, fv[:, 1], np.array([0.0, 0.0, 1.0]), w)

    def side(depth, sign):
        band = tv[np.abs(tv[:, 1] - (y0 - depth * w)) < 0.05 * w]
        if not len(band):
            raise KneeInputError(f"the tibia does not reach {depth:g} femur widths below the joint line for a collateral "
                                 f"insertion; give the insertions")
        return band[(sign * band[:, 2]).argmax()]

    return np.vstack([me, side(0.65, -1.0)]), np.vstack([le, side(0.35, 1.0)])


def clip_anatomy(anatomy: KneeAnatomy, widths: float = BAND_WIDTHS) -> KneeAnatomy:
    """The anatomy within ``widths`` femur widths of the joint line (skin and bones clipped to the band
    and closed at its planes); a shorter scan is returned unchanged. A skin that falls apart in the band
    (a whole body: two legs) keeps the piece around the knee."""
    y0, w = anatomy.joint_y, anatomy.width
    o, up = np.array([0.0, y0, 0.0]), np.array([0.0, 1.0, 0.0])
    skin = clip_to_slab(anatomy.skin, o, up, widths * w, widths * w)
    pieces = skin.split(only_watertight=True) if skin is not anatomy.skin else [skin]
    if len(pieces) > 1:
        knee = np.vstack([anatomy.femur.vertices[anatomy.femur.vertices[:, 1] < y0 + 0.5 * w],
                          anatomy.tibia.vertices[anatomy.tibia.vertices[:, 1] > y0 - 0.5 * w]])
        inside = [int(SurfaceQuery.of(p).inside(knee).sum()) for p in pieces]
        skin = pieces[int(np.argmax(inside))]
    # the bones end a little inside the skin's band, so that their cut faces lie inside it
    femur = clip_to_slab(anatomy.femur, o, up, (widths - 0.05) * w, (widths - 0.05) * w)
    tibia = clip_to_slab(anatomy.tibia, o, up, (widths - 0.05) * w, (widths - 0.05) * w)
    return replace(anatomy, femur=femur, tibia=tibia, skin=skin)


def working_skin(anatomy: KneeAnatomy, most: int = SKIN_VERTICES_MOST) -> KneeAnatomy:
    """The anatomy with its skin coarsened (quadric decimation, kept closed) to about ``most`` vertices
    where it has more (:data:`SKIN_VERTICES_MOST`); unchanged otherwise. A closed surface has about twice
    as many faces as vertices."""
    if len(anatomy.skin.vertices) <= most:
        return anatomy
    return replace(anatomy, skin=decimated(anatomy.skin, 2 * most - 4, "skin"))


def clip_bones_to_skin(anatomy: KneeAnatomy) -> KneeAnatomy:
    """The bones cut to the skin's extent along the femur's axis (5 % of the femur's width inside it): a
    skin scanned as a band around the knee with whole bones beside it."""
    lo, hi = float(anatomy.skin.vertices[:, 1].min()), float(anatomy.skin.vertices[:, 1].max())
    m = 0.05 * anatomy.width
    mid = np.array([0.0, 0.5 * (lo + hi), 0.0])
    up = np.array([0.0, 1.0, 0.0])
    half = 0.5 * (hi - lo) - m
    return replace(anatomy, femur=clip_to_slab(anatomy.femur, mid, up, half, half),
                   tibia=clip_to_slab(anatomy.tibia, mid, up, half, half))


def anatomy_in_femur_frame(femur, tibia, skin, T_scan_femur, T_scan_tibia, mcl=None, lcl=None,
                           name: str = "knee") -> KneeAnatomy:
    """A :class:`KneeAnatomy` from surfaces in a scan's frame and the bones' anatomical frames in it
    (``T_scan_bone`` (4, 4): bone coordinates to the scan). ``mcl``, ``lcl``: (2, 3) insertions in the
    scan's frame (femoral, tibial), or None."""
    Tf_inv = np.linalg.inv(np.asarray(T_scan_femur, float))
    to = [m.copy().apply_transform(Tf_inv) for m in (femur, tibia, skin)]
    ins = [None if p is None else transform_points(Tf_inv, np.asarray(p, float).reshape(2, 3)) for p in (mcl, lcl)]
    return KneeAnatomy(*to, Tf_inv @ np.asarray(T_scan_tibia, float), ins[0], ins[1], name)


def joint_line(femur_vertices, tibia_vertices) -> float:
    """The joint line's height (mm) in the femur frame of the bones' vertices (V, 3) given: midway between
    the femur's distal-most point and the tibia's highest one."""
    return 0.5 * (float(np.min(np.asarray(femur_vertices)[:, 1])) + float(np.max(np.asarray(tibia_vertices)[:, 1])))


def bone_queries(anatomy) -> tuple[list, list, np.ndarray, np.ndarray]:
    """What :func:`bone_clearance` asks, built once for the many poses a slide along the tibia's axis tries:
    the femur's and the tibia's closed shells as signed-distance queries, and each bone's vertices that are
    asked (at most :data:`BONE_POINTS_MOST`, spread evenly)."""
    shells = [[SurfaceQuery.of(m) for m in (mesh.split(only_watertight=True) or [mesh])]
              for mesh in (anatomy.femur, anatomy.tibia)]
    fv, tv = (np.asarray(m.vertices, float) for m in (anatomy.femur, anatomy.tibia))
    return shells[0], shells[1], fv[thinned_evenly(fv, BONE_POINTS_MOST)], tv[thinned_evenly(tv, BONE_POINTS_MOST)]


def bone_clearance(anatomy, T_tibia, queries=None) -> float:
    """The least signed distance (mm) between the femur's and the tibia's surfaces with the tibia at
    ``T_tibia`` (4, 4; its frame in the femur frame): the smallest of each bone's vertices' signed distances
    to the other bone (negative: the bones overlap; at most :data:`BONE_POINTS_MOST` vertices of each, spread
    evenly). A bone made of several closed shells (a cartilage shell
    over the condyles, say) is their union: a point's signed distance is its least over the shells (the
    parity inside two overlapping shells would call it outside). ``queries``: :func:`bone_queries` of the
    anatomy, when already built."""
    femur_q, tibia_q, fv, tv = bone_queries(anatomy) if queries is None else queries
    move = np.asarray(T_tibia, float) @ invert_poses(anatomy.tibia_pose)

    def signed(shells, points):
        # only the points within reach of the other bone's box are asked first (a point outside it lies
        # farther than the reach); all of them when none of those comes within the reach
        lo = np.min([q.lo for q in shells], axis=0) - CLEARANCE_REACH_MM
        hi = np.max([q.hi for q in shells], axis=0) + CLEARANCE_REACH_MM
        near = np.all((points >= lo) & (points <= hi), axis=1)
        if np.any(near):
            d = np.min([q.signed_distance(points[near]) for q in shells], axis=0).min()
            if d < CLEARANCE_REACH_MM:
                return d
        return np.min([q.signed_distance(points) for q in shells], axis=0).min()

    tib = transform_points(move, tv)
    fem = transform_points(invert_poses(move), fv)
    return float(min(signed(femur_q, tib), signed(tibia_q, fem)))


def in_contact(anatomy, T_tibia, clearance: float, reach_mm: float = 30.0, queries=None,
               now: float | None = None) -> np.ndarray:
    """``T_tibia`` (4, 4; the tibia's frame in the femur frame) slid along the tibia's own long axis (its y)
    until the bones are ``clearance`` apart (:func:`bone_clearance`), within 0.01 mm: along that axis the
    joint's contact, not the motion carried from another knee, decides where the tibia is. ``queries``:
    :func:`bone_queries` of the anatomy, when already built. ``now``: the bones' clearance at ``T_tibia``,
    when already known; below ``clearance`` it brackets the slide near the pose (:func:`_parting_bracket`)
    instead of over the whole reach."""
    T = np.asarray(T_tibia, float)
    queries = bone_queries(anatomy) if queries is None else queries

    def slid(s):
        out = T.copy()
        out[:3, 3] += s * T[:3, 1]
        return out

    def f(s):
        return bone_clearance(anatomy, slid(s), queries) - clearance

    bracket = None if now is None or now >= clearance else _parting_bracket(f, clearance - now, reach_mm)
    if bracket is None:
        lo, hi = -reach_mm, reach_mm  # sliding proximally (s > 0) brings the bones together
        if f(lo) < 0.0 or f(hi) > 0.0:
            raise KneeError(f"the tibia cannot be brought to {clearance:.2f} mm from the femur within "
                            f"{reach_mm:.0f} mm along its axis")
        bracket = (lo, hi)
    lo, hi = bracket
    return slid(lo if lo == hi else brentq(f, lo, hi, xtol=0.01))


#: The least first step (mm) of :func:`_parting_bracket`'s search beyond the shortfall: a tiny shortfall
#: doubled from itself would take many clearances to reach a parting slide of a few tenths of a mm.
PARTING_STEP_MM = 0.25


def _parting_bracket(f, short: float, reach_mm: float) -> tuple[float, float] | None:
    """A bracket [lo, hi] (mm, along the tibia's axis, lo <= hi <= 0) of the slide where ``f`` (the clearance
    less the one asked, as a function of the slide) crosses zero, for bones ``short`` mm closer than asked
    at no slide; None when none is found within ``reach_mm``. The least signed distance between two
    surfaces changes by at most the distance one of them moves, so the bones part by the shortfall no
    sooner than after a slide of that length distally: f(-short) <= 0, and the bracket grows from there
    (doubling the step, at least :data:`PARTING_STEP_MM`) until f >= 0."""
    if short >= reach_mm:
        return None
    hi = -short
    if f(hi) >= 0.0:  # exactly parted there (the slide along the clearance's gradient)
        return hi, hi
    step = max(short, PARTING_STEP_MM)
    while hi > -reach_mm:  # ends: each pass moves lo further out, down to the reach
        lo = max(hi - step, -reach_mm)
        if f(lo) >= 0.0:
            return lo, hi
        hi, step = lo, 2.0 * step
    return None
