"""Anatomical frames of femur, tibia and patella from landmarks (seed 002, section 2.2).

Each frame follows the toolkit's convention (x anterior, y proximal, z lateral, right knee; origin at
the joint). Landmark labels (3D Slicer markups, LPS, mm):

Femur (``FEMUR_LANDMARKS``)
    ``LE``, ``ME`` lateral and medial epicondyles; ``PAL`` peak of the lateral anterior ridge;
    ``HIP`` hip (femoral head) centre.
    Origin: midpoint of LE and ME. y: from the origin to HIP. z: ME -> LE, made orthogonal to y.
    x = y x z. Check: PAL lies anterior (x > 0).
Tibia (``TIBIA_LANDMARKS``)
    ``LIT``, ``MIT`` lateral and medial intercondylar tubercles; ``PMP`` most posterior point of the
    medial compartment; ``PLP`` most lateral point of the posterior aspect of the lateral compartment;
    ``LM``, ``MM`` lateral and medial malleoli.
    Origin: midpoint of LIT and MIT. y: from the malleoli's midpoint to the origin. z: PMP -> PLP, made
    orthogonal to y. x = y x z. Check: PMP and PLP lie posterior (x < 0).
Patella (``PATELLA_LANDMARKS``)
    ``PSUP`` superior pole (base), ``PINF`` inferior pole (apex), ``PLAT`` and ``PMED`` lateral and
    medial borders. Origin: mean of the four. y: PINF -> PSUP. z: PMED -> PLAT, made orthogonal to y.

The alignment fiducials (MRI to CT, seed 002 Fig. 1b) are LE, ME, PAL on the femur, LIT, MIT, PMP, PLP
on the tibia, and the four patellar points.

A frame is returned as its pose in image space, ``T_image_bone`` (4, 4): bone coordinates -> image.
"""

from __future__ import annotations

import numpy as np

from knee.foundations.errors import KneeInputError

FEMUR_LANDMARKS = ("LE", "ME", "PAL", "HIP")
TIBIA_LANDMARKS = ("LIT", "MIT", "PMP", "PLP", "LM", "MM")
PATELLA_LANDMARKS = ("PSUP", "PINF", "PLAT", "PMED")
LANDMARKS = {"femur": FEMUR_LANDMARKS, "tibia": TIBIA_LANDMARKS, "patella": PATELLA_LANDMARKS}
FIDUCIALS = {"femur": ("LE", "ME", "PAL"), "tibia": ("LIT", "MIT", "PMP", "PLP"), "patella": PATELLA_LANDMARKS}


class SideError(KneeInputError):
    """The landmarks describe the other knee than the one declared."""


def _frame(origin, y_dir, z_hint, what):
    y_n = np.linalg.norm(y_dir)
    if y_n < 1e-6:
        raise KneeInputError(f"{what} frame: the landmarks that give the y axis coincide")
    y = y_dir / y_n
    z = z_hint - (z_hint @ y) * y
    z_n = np.linalg.norm(z)
    if z_n < 1e-3 * max(np.linalg.norm(z_hint), 1e-12) or z_n < 1e-6:
        raise KneeInputError(f"{what} frame: the medio-lateral landmarks are parallel to the long axis")
    z = z / z_n
    x = np.cross(y, z)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = origin
    return T


def femur_frame(lm) -> np.ndarray:
    """``T_image_femur`` from a :class:`knee.foundations.imaging.Markups` (or a dict of label -> (3,))."""
    le, me, pal, hip = (_get(lm, k) for k in FEMUR_LANDMARKS)
    o = 0.5 * (le + me)
    T = _frame(o, hip - o, le - me, "femur")
    if (pal - o) @ T[:3, 0] <= 0:
        raise SideError("femur landmarks describe a left knee (PAL lies posterior in a right-knee frame); "
                        "check 'side' in subject.toml or the LE/ME labels")
    return T


def tibia_frame(lm) -> np.ndarray:
    """``T_image_tibia`` (see the module docstring)."""
    lit, mit, pmp, plp, lmal, mmal = (_get(lm, k) for k in TIBIA_LANDMARKS)
    o = 0.5 * (lit + mit)
    T = _frame(o, o - 0.5 * (lmal + mmal), plp - pmp, "tibia")
    if (0.5 * (pmp + plp) - o) @ T[:3, 0] >= 0:
        raise SideError("tibia landmarks describe a left knee (PMP/PLP lie anterior in a right-knee frame); "
                        "check 'side' in subject.toml or the PMP/PLP labels")
    return T


def patella_frame(lm) -> np.ndarray:
    """``T_image_patella`` (see the module docstring)."""
    sup, inf, lat, med = (_get(lm, k) for k in PATELLA_LANDMARKS)
    return _frame(0.25 * (sup + inf + lat + med), sup - inf, lat - med, "patella")


FRAME_FUNCTIONS = {"femur": femur_frame, "tibia": tibia_frame, "patella": patella_frame}


def check_consistent(frames: dict) -> None:
    """The bones' lateral axes must roughly agree (the scan holds one knee, near extension): a
    patella or tibia frame whose z points medially relative to the femur's means swapped labels."""
    zf = frames["femur"][:3, 2]
    for b in ("tibia", "patella"):
        if b in frames and frames[b][:3, 2] @ zf < 0:
            raise SideError(f"the {b} frame's lateral axis points medially relative to the femur's; check the "
                            f"{b} landmarks' lateral/medial labels")


def _get(lm, key):
    if isinstance(lm, dict):
        if key not in lm:
            raise KneeInputError(f"missing landmark {key}")
        return np.asarray(lm[key], float)
    return np.asarray(lm.get(key), float)
