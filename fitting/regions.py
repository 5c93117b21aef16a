"""Articular regions computed from the surfaces, for subject folders that do not give them.

Defined in the bones' anatomical frames (:mod:`knee.fitting.frames`: x anterior, y proximal, z lateral of
a right knee; the femur's origin midway between the epicondyles, the tibia's midway between the
intercondylar tubercles), on the articular surface (the cartilage surface when there is one, else the
bone's), with no millimetre constants (fractions of the femur's epicondylar width W):

``femur_lateral_condyle``, ``femur_medial_condyle`` (the posterior condyles)
    the femoral articular points posterior to the epicondylar plane (x < 0) and below the origin
    (y < 0), lateral (z > 0.1 W) and medial (z < -0.1 W) of the intercondylar notch;
``femur_intercondylar`` (the trochlear groove)
    on the anterior articular surface (x > 0), in slices of height 0.02 W, the deepest (least anterior)
    point of the slice's middle half (between its 25th and 75th percentiles of z): the groove line;
``femur_lateral_trochlea``, ``femur_medial_trochlea`` (the anterior condyles)
    the anterior articular points (x > 0) lateral and medial of the groove (z above and below the groove
    line's median z);
``tibia_lateral_facet``, ``tibia_medial_facet``
    the tibial articular points lateral (z > 0.05 W) and medial (z < -0.05 W) of the tubercles' midpoint.

Every region needs at least :data:`MIN_POINTS` points (the groove line :data:`MIN_GROOVE_POINTS`); the user's own regions (``mri/areas``) win when
given.
"""

from __future__ import annotations

import numpy as np

from knee.foundations.conventions import invert_poses, transform_points
from knee.foundations.errors import KneeInputError

MIN_POINTS = 20
#: The groove line has one point per slice: fewer are needed for its plane.
MIN_GROOVE_POINTS = 10
REGION_NAMES = ("femur_lateral_condyle", "femur_medial_condyle", "femur_lateral_trochlea", "femur_medial_trochlea",
                "femur_intercondylar", "tibia_lateral_facet", "tibia_medial_facet")


def articular_regions(femur_surface, tibia_surface, T_femur, T_tibia, width: float) -> dict[str, np.ndarray]:
    """The regions (module docstring) as point sets in the surfaces' own coordinates.

    ``femur_surface``, ``tibia_surface``: articular vertices (V, 3); ``T_femur``, ``T_tibia``: the
    anatomical frames (4, 4) in the same coordinates; ``width``: the femur's epicondylar width (mm)."""
    W = float(width)
    if not W > 0:
        raise KneeInputError(f"the femur's epicondylar width must be positive, got {W}")
    f_world = np.asarray(femur_surface, float)
    t_world = np.asarray(tibia_surface, float)
    f = transform_points(invert_poses(T_femur), f_world)
    t = transform_points(invert_poses(T_tibia), t_world)
    out = {}
    post = (f[:, 0] < 0.0) & (f[:, 1] < 0.0)
    out["femur_lateral_condyle"] = f_world[post & (f[:, 2] > 0.1 * W)]
    out["femur_medial_condyle"] = f_world[post & (f[:, 2] < -0.1 * W)]
    ant = f[:, 0] > 0.0
    a, a_world = f[ant], f_world[ant]
    groove = []
    if len(a):
        h = a[:, 1]
        edges = np.arange(h.min(), h.max() + 0.02 * W, 0.02 * W)
        slot = np.digitize(h, edges)
        for k in np.unique(slot):
            idx = np.flatnonzero(slot == k)
            z = a[idx, 2]
            lo, hi = np.percentile(z, [25, 75])
            mid = idx[(z >= lo) & (z <= hi)]
            if len(mid):
                groove.append(mid[np.argmin(a[mid, 0])])
    groove = np.asarray(groove, int)
    out["femur_intercondylar"] = a_world[groove]
    zg = float(np.median(a[groove, 2])) if len(groove) else 0.0
    out["femur_lateral_trochlea"] = a_world[a[:, 2] > zg]
    out["femur_medial_trochlea"] = a_world[a[:, 2] < zg]
    out["tibia_lateral_facet"] = t_world[t[:, 2] > 0.05 * W]
    out["tibia_medial_facet"] = t_world[t[:, 2] < -0.05 * W]
    few = [f"{k} ({len(v)})" for k, v in out.items()
           if len(v) < (MIN_GROOVE_POINTS if k == "femur_intercondylar" else MIN_POINTS)]
    if few:
        raise KneeInputError(f"articular regions with fewer than {MIN_POINTS} points: {', '.join(few)}; check the "
                             "surfaces and the landmarks' frames")
    return out


__all__ = ["articular_regions", "REGION_NAMES", "MIN_POINTS"]
