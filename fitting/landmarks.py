"""Anatomical landmarks found on bone surfaces, for scans that come without them (:mod:`knee.fitting.frames`
names and uses them).

Each landmark is an extreme point or a fitted centre of a region of the bone, the regions scaled by the
bone's own size (its medio-lateral width at the joint), never by millimetre constants: so a long bone and
one cut 60 mm from the joint give the same landmarks near the joint. The scan's rough anatomical
directions must be known (``up``: proximal, ``anterior``; unit vectors in the scan's frame, e.g. from the
scanner's patient orientation); the lateral direction of a right knee is ``anterior x up``.

Femur
    ``LE``, ``ME``: the most lateral and most medial parts of the distal femur (within 0.75 of its
    width above its distal-most point: the epicondyles), each the centroid of the points within 2 % of
    the width of the extreme (a flat side has no single extreme vertex); ``PAL``: the most anterior point of the
    lateral half of that region (the lateral anterior ridge); ``HIP``: the centre of a sphere fitted to
    the femoral head (the medial half of the proximal end) when the femur reaches the hip, else None.
Tibia
    ``LIT``, ``MIT``: the highest points within 0.15 of the plateau's width on either side of its middle
    (the intercondylar tubercles); ``PMP``, ``PLP``: the most posterior points of the medial and lateral
    compartments (beyond 0.15 of the width from the middle, within 0.25 of it below the top); ``MM``:
    the most medial point of the distal end (the medial malleolus) and ``LM`` the most lateral point of
    the fibula's distal end (or the tibia's), when the bones reach the ankle, else None.
Patella
    ``PSUP``, ``PINF``: the most proximal and most distal points; ``PLAT``, ``PMED``: the most lateral
    and most medial.

Shapes: vertices ``(V, 3)`` in mm; every landmark ``(3,)`` in the scan's frame.
"""

from __future__ import annotations

import numpy as np

from knee.foundations.errors import KneeInputError
from knee.foundations.geometry import LONG_BONE, end_width, epicondyles, fit_sphere


def _axes(up, anterior):
    u = np.asarray(up, float)
    u = u / np.linalg.norm(u)
    a = np.asarray(anterior, float)
    a = a - (a @ u) * u
    if np.linalg.norm(a) < 1e-6:
        raise KneeInputError("the anterior direction is parallel to the proximal one")
    a = a / np.linalg.norm(a)
    return u, a, np.cross(a, u)  # proximal, anterior, lateral (right knee)


def femur_landmarks(vertices, up, anterior) -> dict:
    """LE, ME, PAL and HIP (None when the femur does not reach the hip) of a right femur's surface."""
    v = np.asarray(vertices, float)
    u, a, lat = _axes(up, anterior)
    h = v @ u
    W = end_width(v, h, lat, "low")
    le, me = epicondyles(v, h, lat, W)
    distal = v[h < h.min() + 0.75 * W]
    s = distal @ lat
    mid = 0.5 * (s.max() + s.min())
    lateral_half = distal[s > mid]
    pal = lateral_half[(lateral_half @ a).argmax()]
    hip = None
    if h.max() - h.min() > LONG_BONE * W:
        top = v[h > h.max() - 0.6 * W]
        head = top[(top @ lat) < np.median(top @ lat)]  # the head is medial; the greater trochanter lateral
        c, r, _ = fit_sphere(head)
        for _ in range(3):  # drop the neck's points: keep those near the fitted sphere
            d = np.abs(np.linalg.norm(head - c, axis=1) - r)
            keep = d < max(0.05 * r, np.percentile(d, 60))
            c, r, _ = fit_sphere(head[keep])
        hip = c
    return {"LE": le, "ME": me, "PAL": pal, "HIP": hip}


def tibia_landmarks(vertices, up, anterior, fibula=None) -> dict:
    """LIT, MIT, PMP, PLP, LM and MM (the malleoli None when the tibia does not reach the ankle) of a right
    tibia's surface; ``fibula`` (vertices) gives the lateral malleolus when present."""
    v = np.asarray(vertices, float)
    u, a, lat = _axes(up, anterior)
    h = v @ u
    W = end_width(v, h, lat, "high")
    top = v[h > h.max() - 0.25 * W]
    s = top @ lat
    mid = 0.5 * (s.max() + s.min())
    band = 0.15 * W
    lt, mt = top[(s > mid) & (s < mid + band)], top[(s < mid) & (s > mid - band)]
    if not len(lt) or not len(mt):
        raise KneeInputError("the tibial plateau has no points near its middle (intercondylar eminence)")
    lit, mit = lt[(lt @ u).argmax()], mt[(mt @ u).argmax()]
    lc, mc = top[s > mid + band], top[s < mid - band]
    plp, pmp = lc[(lc @ a).argmin()], mc[(mc @ a).argmin()]
    lm = mm = None
    if h.max() - h.min() > LONG_BONE * W:
        bottom = v[h < h.min() + 0.3 * W]
        mm = bottom[(bottom @ lat).argmin()]
        if fibula is not None:
            f = np.asarray(fibula, float)
            fb = f[(f @ u) < (f @ u).min() + 0.3 * W]
            lm = fb[(fb @ lat).argmax()]
        else:
            lm = bottom[(bottom @ lat).argmax()]
    return {"LIT": lit, "MIT": mit, "PMP": pmp, "PLP": plp, "LM": lm, "MM": mm}


def patella_landmarks(vertices, up, anterior) -> dict:
    """PSUP, PINF, PLAT, PMED of a right patella's surface."""
    v = np.asarray(vertices, float)
    u, _, lat = _axes(up, anterior)
    h, s = v @ u, v @ lat
    return {"PSUP": v[h.argmax()], "PINF": v[h.argmin()], "PLAT": v[s.argmax()], "PMED": v[s.argmin()]}
