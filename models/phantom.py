"""Procedural phantom geometry of a knee, consistent with a mechanism parameter set.

Each bone is a watertight triangle mesh in its own frame (mm; x anterior, y proximal, z lateral):

* femur: a sphere for each condylar contact (centre = the contact link's femoral point, radius =
  ``femur_radius``), a bar joining the condyles, a shaft, and, with a patella, a trochlear cylinder on
  the helical axis;
* tibia: for each sphere-sphere contact a facet cut from the tibial sphere (centre = the link's tibial
  point, radius = length + R_femur for a concave facet, length - R_femur for a convex one), for each
  sphere-plane contact a facet whose top is the tibial plane; a plateau slab, a shaft and the tibial
  tuberosity;
* patella: an ellipsoid on the far side of the helical axis from the trochlea, at the reference pose;
* skin: a soft-tissue envelope around the posed bones (thigh and shank capsules and a knee sphere).

By construction the femoral condyle spheres touch the tibial facets whenever the mechanism is closed:
that is what the contact links mean. Booleans use trimesh's ``manifold`` engine (manifold3d).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from knee.foundations.conventions import joint_to_pose
from knee.models.mechanism.params import MechanismParams, require_condylar_contacts

DEFAULT_CONDYLE_RADIUS = 22.0
FACET_RADIUS = 17.0  # horizontal radius of a tibial facet (mm)
TROCHLEA_OFFSET = 12.0  # distance of the trochlear spheres from the axis point (mm), trochlea="spheres"


def trochlea_radius(params: MechanismParams) -> float:
    """Radius of the phantom's trochlea (cylinder or spheres) about the helical axis (mm)."""
    return max(float(np.linalg.norm(params.pf.point_patella[:2])) - 20.0, 10.0)


@dataclass
class Phantom:
    """Bone meshes of a phantom knee, each in its own bone frame (trimesh.Trimesh, mm)."""

    femur: trimesh.Trimesh
    tibia: trimesh.Trimesh
    patella: trimesh.Trimesh | None
    params: MechanismParams
    skin_radius: float
    shaft_length: float = 160.0

    def skin(self, tf_pose: np.ndarray, pf_pose: np.ndarray | None = None,
             length: float | None = None) -> trimesh.Trimesh:
        """The soft-tissue envelope, in the femur frame, with the tibia at ``tf_pose`` (4, 4).

        A thigh capsule along the femoral shaft, a shank capsule along the tibial shaft (posed) and a
        sphere at the knee, joined; the radius clears every bone by at least 8 mm at extension. The
        capsules run ``length`` mm from the knee (default: 10 mm beyond the bone shafts). The union of
        :meth:`skin_parts`.
        """
        return _union([m.copy().apply_transform(T) for m, T in self.skin_parts(tf_pose, pf_pose, length)])

    def skin_parts(self, tf_pose: np.ndarray, pf_pose: np.ndarray | None = None,
                   length: float | None = None) -> list[tuple[trimesh.Trimesh, np.ndarray]]:
        """The envelope's solid parts before their union: (mesh in the part's own frame, pose (4, 4) that
        places it in the femur frame). The meshes do not depend on the pose (built once per length), so a
        posed envelope can be queried part by part without building the union (:class:`knee.models.prior.SkinModel`)."""
        L = self.shaft_length + 10.0 if length is None else float(length)
        thigh, shank, knee, patella = self._skin_meshes(L)
        tf_pose = np.asarray(tf_pose, float)
        knee_T = np.eye(4)
        knee_T[:3, 3] = 0.5 * tf_pose[:3, 3]
        parts = [(thigh, np.eye(4)), (shank, tf_pose), (knee, knee_T)]
        if pf_pose is not None and self.patella is not None:
            pat_T = np.eye(4)
            pat_T[:3, 3] = pf_pose[:3, :3] @ self.patella.centroid + pf_pose[:3, 3]
            parts.append((patella, pat_T))
        return parts

    def _skin_meshes(self, L: float):
        cache = self.__dict__.setdefault("_skin_mesh_cache", {})
        if L not in cache:
            r = self.skin_radius
            cache[L] = (_capsule(np.array([0.0, 10.0, 0.0]), np.array([0.0, L, 0.0]), r),
                        _capsule(np.array([0.0, -10.0, 0.0]), np.array([0.0, -L, 0.0]), r * 0.92),
                        trimesh.creation.icosphere(3, r * 1.02), trimesh.creation.icosphere(3, 24.0))
        return cache[L]


def _union(meshes) -> trimesh.Trimesh:
    return trimesh.boolean.union(meshes, engine="manifold")


def _capsule(a, b, r) -> trimesh.Trimesh:
    """A capsule of radius r between points a and b."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    h = float(np.linalg.norm(b - a))
    cap = trimesh.creation.capsule(height=h, radius=r, count=[24, 24])  # along z, centred
    T = trimesh.geometry.align_vectors([0, 0, 1], (b - a) / h)
    cap.apply_transform(T)
    cap.apply_translation(0.5 * (a + b))
    return cap


def _cylinder(a, b, r, sections=40) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=r, segment=np.array([a, b], float), sections=sections)


def _sphere(c, r, subdivisions=4) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions, r).apply_translation(np.asarray(c, float))


def build_phantom(params: MechanismParams, shaft_length: float = 160.0, cartilage: float = 0.0,
                  trochlea: str = "cylinder") -> Phantom:
    """Build the phantom of a parameter set (about 0.2 s); bone shafts reach ``shaft_length`` mm from
    the knee (a knee CT covers about 100-150 mm each way).

    With ``cartilage`` > 0 the bones are the subchondral bone: both articular surfaces are set back by
    that thickness (mm), so the posed bones leave a soft joint space of twice that width where the
    mechanism's contacts touch (the spheres of the contact links describe the cartilage surfaces).

    ``trochlea``: ``"cylinder"`` (a cylinder on the helical axis) or ``"spheres"`` (two spheres centred on
    the helical axis, 12 mm either side of its sagittal point: anterior condyles whose sphere fits give
    the axis back exactly, as the synthetic subject needs)."""
    c = float(cartilage)
    if not 0.0 <= c < 10.0:
        raise ValueError(f"cartilage thickness must be in [0, 10) mm, got {cartilage}")
    require_condylar_contacts(params, "the bone phantom")
    contacts = [lk for lk in params.links if lk.role == "contact"]
    up = np.array([0.0, 1.0, 0.0])

    # ---- femur
    fparts = []
    centres = []
    for lk in contacts:
        rf = (lk.femur_radius or DEFAULT_CONDYLE_RADIUS) - c
        fparts.append(_sphere(lk.femur, rf))
        centres.append((lk.femur, rf))
    (c1, r1), (c2, r2) = centres
    fparts.append(_cylinder(c1, c2, 0.8 * min(r1, r2)))
    mid = 0.5 * (c1 + c2)
    shaft_top = mid + np.array([0.0, shaft_length, 0.0])
    fparts.append(_cylinder(mid + np.array([0, 0.3 * r1, 0]), shaft_top, 14.0))
    fparts.append(_cylinder(mid + np.array([-4.0, 0.0, 0.0]), mid + np.array([-4.0, 45.0, 0.0]), 0.9 * min(r1, r2)))
    patella = None
    pf = params.pf
    if pf is not None:
        n = pf.axis_femur / np.linalg.norm(pf.axis_femur)
        # trochlea: a cylinder on the helical axis reaching to the patella's posterior surface
        tro_r = trochlea_radius(params)
        if trochlea == "spheres":
            fparts += [_sphere(pf.point_femur + s_ * TROCHLEA_OFFSET * n, max(tro_r, 10.0)) for s_ in (-1, 1)]
        elif trochlea == "cylinder":
            fparts.append(_cylinder(pf.point_femur - 22 * n, pf.point_femur + 22 * n, max(tro_r, 10.0)))
        else:
            raise ValueError(f"trochlea must be 'cylinder' or 'spheres', got {trochlea!r}")
        # patella: ellipsoid, semi-axes 10 (AP) x 22 (PD) x 20 (ML), between origin and axis
        pat = trimesh.creation.icosphere(4, 1.0)
        pat.apply_scale([10.0, 22.0, 20.0])
        ax_p = pf.point_patella
        centre = ax_p - (tro_r + 10.0) * np.r_[ax_p[:2], 0.0] / np.linalg.norm(ax_p[:2])
        pat.apply_translation(centre)
        patella = pat
    femur = _union(fparts)

    # ---- tibia
    tparts = []
    tops = []
    for lk in contacts:
        rf = lk.femur_radius or DEFAULT_CONDYLE_RADIUS
        if lk.kind == "distance":
            if lk.tibia_surface == "convex":
                rt = lk.length - rf - c
                top = lk.tibia + rt * up
                block = _cylinder(top - 14 * up, top + 2 * up, FACET_RADIUS)
                facet = trimesh.boolean.intersection([block, _sphere(lk.tibia, rt, 5)], engine="manifold")
                base_y = top[1] - 14
            else:
                rt = lk.length + rf + c
                bottom = lk.tibia - rt * up
                block = _cylinder(bottom - 12 * up, bottom + 6 * up, FACET_RADIUS)
                facet = trimesh.boolean.difference([block, _sphere(lk.tibia, rt, 5)], engine="manifold")
                top = bottom
                base_y = bottom[1] - 12
            tparts.append(facet)
        else:  # sphere-plane: the facet's top face is the tibial plane
            nrm = lk.normal / np.linalg.norm(lk.normal)
            top = lk.tibia - c * nrm
            tparts.append(_cylinder(top - 14 * nrm, top, FACET_RADIUS))
            base_y = top[1] - 14
        tops.append((top, base_y))
    (t1, b1), (t2, b2) = tops
    slab_top = min(b1, b2) + 4.0
    cx, cz = 0.5 * (t1[0] + t2[0]), 0.5 * (t1[2] + t2[2])
    half_w = 0.5 * abs(t1[2] - t2[2]) + FACET_RADIUS
    slab = trimesh.creation.box(extents=[2 * FACET_RADIUS + 8, 16.0, 2 * half_w])
    slab.apply_translation([cx, slab_top - 8.0, cz])
    tparts.append(slab)
    shaft_top = np.array([cx, slab_top - 10, cz])
    tparts.append(_cylinder(shaft_top, np.array([cx, -shaft_length, cz]), 15.0))
    if pf is not None:
        tparts.append(_sphere(pf.tendon_tibia - np.array([6.0, 0, 0]), 9.0, 3))
        tparts.append(_cylinder(pf.tendon_tibia - np.array([6.0, 0, 0]), shaft_top - np.array([0, 30, 0]), 9.0))
    tibia = _union(tparts)

    # ---- skin radius: clear every bone by 8 mm at extension (lateral and AP extent near the knee)
    ext = np.vstack([femur.vertices[femur.vertices[:, 1] < 60], tibia.vertices[tibia.vertices[:, 1] > -60]])
    rad = np.sqrt(ext[:, 0] ** 2 + ext[:, 2] ** 2).max()
    return Phantom(femur=femur, tibia=tibia, patella=patella, params=params, skin_radius=float(rad + 8.0),
                   shaft_length=float(shaft_length))


def posed_bones(phantom: Phantom, tf: np.ndarray, pf: np.ndarray | None = None) -> dict[str, trimesh.Trimesh]:
    """Copies of the bones posed in the femur frame for joint coordinates ``tf`` (and ``pf``), (6,)."""
    out = {"femur": phantom.femur.copy(), "tibia": phantom.tibia.copy().apply_transform(joint_to_pose(tf))}
    if phantom.patella is not None and pf is not None and np.all(np.isfinite(pf)):
        out["patella"] = phantom.patella.copy().apply_transform(joint_to_pose(pf))
    return out
