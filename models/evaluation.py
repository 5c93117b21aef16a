"""Target point errors: how far estimated bones lie from the true ones where a surgeon drills (seed 000, 3).

The target points are bone surface points of the epiphysis: the surface within
:data:`EPIPHYSIS_LENGTH_MM` of the joint line along the bone's proximal axis (y). Among them the ACL and
PCL footprints are the points within :data:`FOOTPRINT_RADIUS_MM` of each ligament attachment's nearest
epiphysis point: a disc of 10 mm radius, 314 mm² on a flat surface, about twice the measured mean
ACL and PCL insertion areas (113-153 mm², Harner et al. 1999), so that it covers the drill's entry
around the attachment's centre.

An error is the distance between a target point carried by the estimated bone and the same point
carried by the true bone; per bone its mean and standard deviation over the footprints and over the
whole epiphysis are reported (seed 000 Table 1: footprints 3.81 / 3.89 mm, epiphysis 4.88 / 5.12 mm,
femur / tibia).

Frames: every array of points is ``(P, 3)`` in mm, in whatever frame the caller uses consistently;
poses are ``(4, 4)`` taking the frame of the target points to the world.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from knee.foundations.conventions import transform_points

#: Radius (mm) of the ACL and PCL footprints around each attachment's nearest surface point.
FOOTPRINT_RADIUS_MM = 10.0
#: Length (mm) of the epiphysis from the joint line along the bone's axis.
EPIPHYSIS_LENGTH_MM = 40.0
#: The paper's errors (seed 000 Table 1), mm: footprints femur/tibia, epiphysis femur/tibia.
PAPER_ERRORS_MM = {"footprints": (3.81, 3.89), "epiphysis": (4.88, 5.12)}


@dataclass(frozen=True)
class TargetPoints:
    """Target points of femur and tibia and which of them are ACL/PCL footprints.

    Attributes
    ----------
    femur, tibia : (F, 3), (T, 3) float
        Epiphysis surface points (mm), in the frame they were given in.
    femur_footprints, tibia_footprints : (F,), (T,) bool
        The footprint points among them.
    """

    femur: np.ndarray
    tibia: np.ndarray
    femur_footprints: np.ndarray
    tibia_footprints: np.ndarray


def _epiphysis(vertices, level: float, sign: float, length: float) -> np.ndarray:
    v = np.asarray(vertices, float)
    return v[sign * (v[:, 1] - level) < length]


def _footprints(points: np.ndarray, attachments, radius: float) -> np.ndarray:
    a = np.asarray(attachments, float).reshape(-1, 3)
    # an attachment can lie off a simplified bone: its footprint is around its nearest surface point
    centre = points[np.linalg.norm(points[:, None] - a[None], axis=2).argmin(axis=0)]
    return (np.linalg.norm(points[:, None] - centre[None], axis=2) < radius).any(axis=1)


def target_points(femur_vertices, tibia_vertices, femur_attachments, tibia_attachments,
                  femur_joint_level: float = 0.0, tibia_joint_level: float = 0.0,
                  footprint_radius: float = FOOTPRINT_RADIUS_MM,
                  epiphysis_length: float = EPIPHYSIS_LENGTH_MM) -> TargetPoints:
    """The target points of two bone surfaces.

    Parameters
    ----------
    femur_vertices, tibia_vertices : (Vf, 3), (Vt, 3) float
        Surface points of each bone (mm), in frames whose y axis is the bone's proximal axis.
    femur_attachments, tibia_attachments : (k, 3) float
        The ACL and PCL attachment points in the same frames.
    femur_joint_level, tibia_joint_level : float
        The joint line's y in each frame: the femur's epiphysis lies below it plus ``epiphysis_length``,
        the tibia's above it minus ``epiphysis_length``.
    """
    fe = _epiphysis(femur_vertices, femur_joint_level, 1.0, epiphysis_length)
    te = _epiphysis(tibia_vertices, tibia_joint_level, -1.0, epiphysis_length)
    return TargetPoints(fe, te, _footprints(fe, femur_attachments, footprint_radius),
                        _footprints(te, tibia_attachments, footprint_radius))


@dataclass(frozen=True)
class ErrorStats:
    """Mean and standard deviation (mm) of distances."""

    mean: float
    sd: float

    @classmethod
    def of(cls, d) -> "ErrorStats":
        d = np.asarray(d, float)
        return cls(float(d.mean()), float(d.std())) if d.size else cls(float("nan"), float("nan"))


@dataclass(frozen=True)
class BoneErrors:
    """One bone's errors: over its footprints and over its whole epiphysis (mm), and the per-point
    distances ``distances`` (P,) (for distance maps)."""

    footprints: ErrorStats
    epiphysis: ErrorStats
    distances: np.ndarray


@dataclass(frozen=True)
class TargetErrors:
    """Target point errors of both bones."""

    femur: BoneErrors
    tibia: BoneErrors

    @property
    def footprints_mm(self) -> float:
        """The mean of the two bones' mean footprint errors (mm)."""
        return 0.5 * (self.femur.footprints.mean + self.tibia.footprints.mean)

    @property
    def epiphysis_mm(self) -> float:
        """The mean of the two bones' mean epiphysis errors (mm)."""
        return 0.5 * (self.femur.epiphysis.mean + self.tibia.epiphysis.mean)

    def bone(self, name: str) -> BoneErrors:
        return {"femur": self.femur, "tibia": self.tibia}[name]


def _bone_errors(est, true, footprints) -> BoneErrors:
    d = np.linalg.norm(np.asarray(est, float) - np.asarray(true, float), axis=1)
    return BoneErrors(ErrorStats.of(d[footprints]), ErrorStats.of(d), d)


def target_errors(targets: TargetPoints, est_femur, est_tibia, true_femur, true_tibia) -> TargetErrors:
    """Errors between estimated and true positions of the target points, each ``(P, 3)`` in one frame
    (the points of ``targets.femur`` and ``targets.tibia``, moved by the estimate and by the truth)."""
    return TargetErrors(_bone_errors(est_femur, true_femur, targets.femur_footprints),
                        _bone_errors(est_tibia, true_tibia, targets.tibia_footprints))


def pose_errors(targets: TargetPoints, T_femur_true, T_tibia_true, T_femur_est, T_tibia_est) -> TargetErrors:
    """Errors of estimated rigid bone poses: the target points (in each bone's frame) carried by the
    true and by the estimated poses ``(4, 4)`` (bone frame to world)."""
    return target_errors(targets, transform_points(T_femur_est, targets.femur),
                         transform_points(T_tibia_est, targets.tibia),
                         transform_points(T_femur_true, targets.femur), transform_points(T_tibia_true, targets.tibia))
