"""Isometric fibres (seed 002, 2.4): within a ligament's attachment areas, the pair of points whose
distance varies least over the measured motion; restricted to the bundle the user names.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from knee.foundations.conventions import joint_to_pose
from knee.foundations.errors import KneeInputError
from knee.foundations.geometry import least_varying_pair


@dataclass
class Fibre:
    """An isometric fibre: femoral and tibial points (mm, their bones' frames), its length at each
    frame of the motion (mm), the length at full extension (the frame of least flexion) and the
    standard deviation of the length."""

    femur: np.ndarray
    tibia: np.ndarray
    lengths: np.ndarray
    length_at_extension: float
    sd: float


def isometric_fibre(femur_area, tibia_area, tf_motion, femur_bundle=None, tibia_bundle=None) -> Fibre:
    """Search the isometric fibre of one ligament.

    Parameters
    ----------
    femur_area : (A, 3) float, femur frame; tibia_area : (B, 3) float, tibia frame
        Attachment-area points.
    tf_motion : (F, 6) float or (F, 4, 4) float
        The measured tibia-in-femur motion, joint coordinates (rad, mm) or poses.
    femur_bundle, tibia_bundle : (A,) / (B,) bool, optional
        The named bundle's part of each area (e.g. the ACL's anteromedial bundle); the search is
        restricted to it.
    """
    fa = np.asarray(femur_area, float)
    ta = np.asarray(tibia_area, float)
    if femur_bundle is not None:
        fa = fa[np.asarray(femur_bundle, bool)]
    if tibia_bundle is not None:
        ta = ta[np.asarray(tibia_bundle, bool)]
    if len(fa) == 0 or len(ta) == 0:
        raise KneeInputError("an attachment area (or the named bundle within it) has no points")
    m = np.asarray(tf_motion, float)
    poses = joint_to_pose(m) if m.ndim == 2 else m
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) < 2:
        raise KneeInputError("the motion needs at least two frames of (6,) coordinates or (4, 4) poses")
    i, j, lengths, sd = least_varying_pair(fa, ta, poses)
    flex = m[:, 0] if m.ndim == 2 else np.zeros(len(poses))
    return Fibre(femur=fa[i], tibia=ta[j], lengths=lengths, length_at_extension=float(lengths[np.argmin(flex)]),
                 sd=sd)
