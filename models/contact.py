"""Contact pressure at the two condylar contacts (issue "contact mechanics, gait and virtual osteotomy",
section 2).

Hertz (sphere on sphere)
    A femoral condyle of radius R_f on a tibial facet of radius R_t: convex on convex (``"convex"``
    facet, 1/R* = 1/R_f + 1/R_t), convex in concave (``"concave"``, 1/R* = 1/R_f - 1/R_t, R_t > R_f) or
    on a plane (1/R* = 1/R_f). Both surfaces are cartilage: 1/E* = (1 - nu_f^2)/E_f + (1 - nu_t^2)/E_t.
    For a compressive force F: contact radius a = (3 F R* / (4 E*))^(1/3), area pi a^2, mean pressure
    F/(pi a^2), peak pressure 3F/(2 pi a^2), approach delta = a^2/R* (Johnson, Contact Mechanics, 1985,
    section 4.2).
Elastic foundation
    The femoral articular surface as a triangle mesh (a spherical cap of the condyle, or any articular
    mesh in the contact's frame), the tibial surface as its sphere (or plane). A face whose centroid lies
    d > 0 inside the tibial surface carries p = K d with K = (1 - nu) E / ((1 + nu)(1 - 2 nu) h), h the
    total cartilage thickness (the layer model used in musculoskeletal contact, e.g. Bei and Fregly,
    Med Eng Phys 26:777-789, 2004). The approach is solved so that the net force equals the load; the
    map gives the pressure at every face.

Default cartilage (:data:`CARTILAGE`): E = 5 MPa, nu = 0.45, 2 mm per surface (4 mm total), values
commonly used for knee cartilage in contact models (e.g. Blankevoort et al., J Biomech 24:1019-1031,
1991). They are settings; pass your own.

Units: N, mm, MPa (N/mm^2); areas mm^2.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.optimize import brentq

from knee.foundations.errors import KneeInputError
from knee.models.mechanism.params import require_condylar_contacts
from knee.models.mechanism.solver import Mechanism
from knee.models.statics import StaticsResult, solve_statics


@dataclass(frozen=True)
class Cartilage:
    """Cartilage of one contact: modulus (MPa), Poisson's ratio and thickness per surface (mm)."""

    E: float = 5.0
    nu: float = 0.45
    thickness: float = 2.0

    def __post_init__(self):
        if not (self.E > 0 and 0 <= self.nu < 0.5 and self.thickness > 0):
            raise KneeInputError(f"cartilage needs E > 0, 0 <= nu < 0.5 and thickness > 0; got E={self.E}, "
                                 f"nu={self.nu}, thickness={self.thickness}")

    @property
    def foundation_modulus(self) -> float:
        """K (N/mm^3) of the two layers in series (total thickness 2 h)."""
        return (1 - self.nu) * self.E / ((1 + self.nu) * (1 - 2 * self.nu) * 2 * self.thickness)


CARTILAGE = Cartilage()


def effective_radius(r_femur, r_tibia, surface: str) -> float:
    """R* of a femoral sphere on a tibial sphere (``convex``/``concave``) or plane (``plane``)."""
    if r_femur <= 0:
        raise KneeInputError(f"femoral radius must be positive, got {r_femur}")
    if surface == "plane":
        return float(r_femur)
    if surface == "convex":
        return 1.0 / (1.0 / r_femur + 1.0 / r_tibia)
    if surface == "concave":
        if r_tibia <= r_femur:
            raise KneeInputError(f"a concave facet (R {r_tibia:.2f} mm) must be larger than the condyle "
                                 f"(R {r_femur:.2f} mm)")
        return 1.0 / (1.0 / r_femur - 1.0 / r_tibia)
    raise KneeInputError(f"tibial surface must be convex, concave or plane, got {surface!r}")


def effective_modulus(femur: Cartilage = CARTILAGE, tibia: Cartilage = CARTILAGE) -> float:
    """E* (MPa) of the two cartilage surfaces."""
    return 1.0 / ((1 - femur.nu ** 2) / femur.E + (1 - tibia.nu ** 2) / tibia.E)


@dataclass
class HertzResult:
    """Per load: ``radius`` a (mm), ``area`` (mm^2), ``mean`` and ``peak`` pressure (MPa), ``approach``
    (mm); zero where the contact is unloaded (force <= 0 compression)."""

    radius: np.ndarray
    area: np.ndarray
    mean: np.ndarray
    peak: np.ndarray
    approach: np.ndarray


def hertz(force, r_femur, r_tibia, surface, femur: Cartilage = CARTILAGE, tibia: Cartilage = CARTILAGE) -> HertzResult:
    """Hertz contact of a femoral condyle on a tibial facet, vectorised over loads.

    Parameters
    ----------
    force : (n,) or scalar float
        Compressive contact force, N (negative values count as 0).
    r_femur, r_tibia : float
        Condyle and facet sphere radii, mm (``r_tibia`` ignored on a plane).
    surface : str
        The facet: ``"convex"``, ``"concave"`` or ``"plane"``.
    femur, tibia : Cartilage
        Each surface's cartilage (MPa, mm).

    Returns
    -------
    HertzResult: contact radius and approach (mm), area (mm²), mean and peak pressure (MPa), each like
    ``force``.
    """
    F = np.maximum(np.asarray(force, float), 0.0)
    Rs = effective_radius(r_femur, r_tibia, surface)
    Es = effective_modulus(femur, tibia)
    a = np.cbrt(3.0 * F * Rs / (4.0 * Es))
    area = math.pi * a ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(area > 0, F / area, 0.0)
    return HertzResult(radius=a, area=area, mean=mean, peak=1.5 * mean, approach=a ** 2 / Rs)


# ----------------------------------------------------------------------------------------------
# Elastic foundation


@functools.lru_cache(maxsize=16)
def condyle_cap(r_femur: float, half_angle_deg: float = 40.0, subdivisions: int = 6) -> trimesh.Trimesh:
    """The femoral articular surface of a contact in its local frame: the cap of a sphere of radius
    ``r_femur`` centred at the origin facing -z (toward the tibia, which lies along -z). Cached: treat the
    returned mesh as read-only."""
    s = trimesh.creation.icosphere(subdivisions, r_femur)
    c = s.triangles_center
    keep = -c[:, 2] / np.linalg.norm(c, axis=1) > math.cos(math.radians(half_angle_deg))
    cap = trimesh.Trimesh(s.vertices, s.faces[keep], process=False)
    cap.remove_unreferenced_vertices()
    return cap


@dataclass
class FoundationResult:
    """Elastic-foundation solution: ``approach`` (mm), face ``pressure`` (MPa) on the mesh, ``area`` in
    contact (mm^2), ``peak`` and ``mean`` pressure (MPa), ``net_force`` (3,) N on the femur surface in the
    contact frame (the tibia pushes along +z)."""

    approach: float
    pressure: np.ndarray
    area: float
    peak: float
    mean: float
    net_force: np.ndarray


def _tibial_depth(centres, r_femur, r_tibia, surface, approach):
    """Depth (mm) of points of the femoral cap (centre at the origin, tibia along -z) inside the tibial
    surface, and the unit normal of the tibial surface at each (pointing toward the femur).

    ``centres`` (F, 3); ``approach`` a scalar or (k,) array: the results are (F,) and (F, 3), or (k, F) and
    (k, F, 3), vectorised over approaches and points."""
    ap = np.asarray(approach, float)
    a = ap.reshape(-1, 1, 1)  # (k, 1, 1)
    c = np.asarray(centres, float)[None]  # (1, F, 3)
    if surface == "plane":
        d = (-r_femur + a[..., 0]) - c[..., 2]
        nrm = np.broadcast_to([0.0, 0.0, 1.0], d.shape + (3,))
    else:
        zc = -(r_femur + r_tibia - a) if surface == "convex" else (r_tibia - r_femur + a)  # tibial centre z
        v = c - np.concatenate([np.zeros(a.shape[:1] + (1, 2)), zc], axis=2)
        dist = np.linalg.norm(v, axis=2)
        if surface == "convex":
            d, nrm = r_tibia - dist, v / dist[..., None]
        else:  # concave: the femur sits inside the tibial sphere
            d, nrm = dist - r_tibia, -v / dist[..., None]
    if ap.ndim == 0:
        return d[0], nrm[0]
    return d, nrm


def foundation_force(mesh: trimesh.Trimesh, r_femur, r_tibia, surface, approach, cartilage: Cartilage = CARTILAGE):
    """Net force (3,) and face pressures of the elastic foundation at a given approach (mm)."""
    c = mesh.triangles_center
    d, nrm = _tibial_depth(c, r_femur, r_tibia, surface, approach)
    p = cartilage.foundation_modulus * np.maximum(d, 0.0)
    f = (p * mesh.area_faces)[:, None] * nrm
    return f.sum(axis=0), p


def foundation(force: float, r_femur, r_tibia, surface, mesh: trimesh.Trimesh | None = None,
               cartilage: Cartilage = CARTILAGE) -> FoundationResult:
    """Solve the elastic foundation for a compressive ``force`` (N): the approach at which the net normal
    force equals the load, by Brent's method (relative tolerance 1e-10)."""
    effective_radius(r_femur, r_tibia, surface)  # validates
    mesh = mesh if mesh is not None else condyle_cap(r_femur)
    F = float(force)
    if not F > 0:
        return FoundationResult(0.0, np.zeros(len(mesh.faces)), 0.0, 0.0, 0.0, np.zeros(3))

    def g(dl):
        return foundation_force(mesh, r_femur, r_tibia, surface, dl, cartilage)[0][2] - F

    hi = 0.05
    while g(hi) < 0:
        hi *= 2
        if hi > 0.5 * r_femur:
            raise KneeInputError(f"elastic foundation: the articular mesh is too small to carry {F:.0f} N")
    dl = brentq(g, 0.0, hi, xtol=1e-14, rtol=1e-10)
    net, p = foundation_force(mesh, r_femur, r_tibia, surface, dl, cartilage)
    loaded = p > 0
    area = float(mesh.area_faces[loaded].sum())
    return FoundationResult(approach=dl, pressure=p, area=area, peak=float(p.max()),
                            mean=F / area if area > 0 else 0.0, net_force=net)


def foundation_closed_form_approach(force, r_femur, r_tibia, surface, cartilage: Cartilage = CARTILAGE):
    """Approach of the elastic foundation on a paraboloid (small contact): F = pi K R* delta^2."""
    Rs = effective_radius(r_femur, r_tibia, surface)
    return np.sqrt(np.maximum(np.asarray(force, float), 0.0) / (math.pi * cartilage.foundation_modulus * Rs))


@dataclass(frozen=True)
class FoundationMaps:
    """The elastic foundation under n loads: ``approach`` (n,) mm, face ``pressure`` (n, faces) MPa on the
    articular ``cap`` mesh, contact ``area`` (n,) mm² and ``peak`` pressure (n,) MPa."""

    approach: np.ndarray
    pressure: np.ndarray
    area: np.ndarray
    peak: np.ndarray
    cap: trimesh.Trimesh


def foundation_maps(forces, r_femur, r_tibia, surface, cartilage: Cartilage = CARTILAGE, mesh=None,
                    n_table: int = 160) -> FoundationMaps:
    """The elastic foundation for many compressive loads (N, (n,)) at once: the net force is tabulated
    against the approach once (vectorised over approaches and faces), the approach of each load
    interpolated, and the face pressures computed for every load together."""
    effective_radius(r_femur, r_tibia, surface)  # validates
    mesh = mesh if mesh is not None else condyle_cap(r_femur, subdivisions=5)
    F = np.maximum(np.asarray(forces, float), 0.0)
    c, A = mesh.triangles_center, mesh.area_faces
    reach = 0.15 * r_femur
    while True:  # the table reaches the largest load (deeper approaches for larger loads, as foundation())
        dl = np.linspace(0.0, reach, n_table)
        d, nrm = _tibial_depth(c, r_femur, r_tibia, surface, dl)
        table = ((cartilage.foundation_modulus * np.maximum(d, 0.0) * A) * nrm[..., 2]).sum(axis=1)
        if not F.size or F.max() <= table[-1] or reach >= 0.5 * r_femur:
            break
        reach = min(2.0 * reach, 0.5 * r_femur)
    if F.size and F.max() > table[-1]:
        raise KneeInputError(f"elastic foundation: {F.max():.0f} N exceeds what the articular mesh carries "
                             f"({table[-1]:.0f} N)")
    appr = np.interp(F, table, dl)
    p = cartilage.foundation_modulus * np.maximum(_tibial_depth(c, r_femur, r_tibia, surface, appr)[0], 0.0)
    return FoundationMaps(appr, p, (p > 0) @ A, p.max(axis=1), mesh)


@dataclass(frozen=True)
class ContactSeries:
    """One condylar contact over n frames or angles: the compressive ``force`` (n,) N, its Hertz result,
    and (when computed) the elastic foundation's maps, else None."""

    force: np.ndarray
    hertz: HertzResult
    foundation: FoundationMaps | None = None


def contact_loads(params, statics, cartilage: Cartilage = CARTILAGE, foundation: bool = True) -> dict[str, ContactSeries]:
    """Per condylar contact of ``params`` (by link name), its :class:`ContactSeries` from a statics result:
    the compressive force, Hertz, and (with ``foundation``) :func:`foundation_maps`."""
    require_condylar_contacts(params, "contact mechanics")
    out = {}
    for lk in params.links:
        if lk.role != "contact":
            continue
        if lk.femur_radius is None:
            raise KneeInputError(f"contact {lk.name} of {params.name} has no femur_radius; contact mechanics needs "
                                 "the condyle radius")
        comp = np.maximum(-statics.force(lk.name), 0.0)
        surf = "plane" if lk.kind == "sphere-plane" else lk.tibia_surface
        maps = foundation_maps(comp, lk.femur_radius, lk.tibia_radius, surf, cartilage) if foundation else None
        out[lk.name] = ContactSeries(comp, hertz(comp, lk.femur_radius, lk.tibia_radius, surf, cartilage, cartilage),
                                     maps)
    return out


@dataclass(frozen=True)
class ContactAlongFlexion:
    """The contacts under a constant load over flexion: the angles ``flexion_deg`` (n,), the statics and
    each contact's :class:`ContactSeries` (with the elastic foundation)."""

    flexion_deg: np.ndarray
    load: float
    statics: StaticsResult
    contacts: dict


def contact_along_flexion(mech: Mechanism, load: float = 700.0, flexion_deg=None,
                          cartilage: Cartilage = CARTILAGE) -> ContactAlongFlexion:
    """Contact force, Hertz and elastic-foundation area and peak pressure at each contact against flexion,
    under a compressive ``load`` (N) along the tibia's long axis (seed 001 Fig. 3d); by default every 5 deg
    from 0 (or the assembly range's start) to 120 deg (or its end)."""
    lo, hi = (math.degrees(v) for v in mech.assembly_range)
    if flexion_deg is None:
        flexion_deg = np.arange(max(0.0, math.ceil(lo)), min(120.0, math.floor(hi)) + 1e-9, 5.0)
    fl = np.asarray(flexion_deg, float)
    st = solve_statics(mech, np.radians(fl), [0.0, load, 0.0])
    return ContactAlongFlexion(fl, float(load), st, contact_loads(mech.params, st, cartilage))
