"""Target point errors (seed 000's evaluation) against closed forms: the footprint's area, the epiphysis's
extent, and the error of a rotated bone."""

import math

import numpy as np
import pytest

from knee.models.evaluation import (
    EPIPHYSIS_LENGTH_MM,
    FOOTPRINT_RADIUS_MM,
    pose_errors,
    target_errors,
    target_points,
)


def _plate(level: float, spacing: float = 0.25, half: float = 30.0) -> np.ndarray:
    """A flat square of points (the x-z plane at y = level), ``spacing`` mm apart."""
    g = np.arange(-half, half + 1e-9, spacing)
    X, Z = np.meshgrid(g, g, indexing="ij")
    return np.column_stack([X.ravel(), np.full(X.size, level), Z.ravel()])


def test_a_footprint_is_a_disc_of_10_mm_radius():
    """On a flat surface the footprint around an attachment is a disc of radius 10 mm (314 mm²): its points
    times the area each stands for give pi r^2 (a doubled radius gives four times that)."""
    assert FOOTPRINT_RADIUS_MM == 10.0
    spacing = 0.25
    femur, tibia = _plate(-5.0, spacing), _plate(5.0, spacing)
    # attachments 3 mm off the surfaces: the footprint is centred on the nearest surface point
    t = target_points(femur, tibia, [[4.0, -8.0, -6.0]], [[-2.0, 8.0, 1.0]])
    for mask in (t.femur_footprints, t.tibia_footprints):
        assert mask.sum() * spacing ** 2 == pytest.approx(math.pi * 10.0 ** 2, rel=0.01)
    centre = t.femur[t.femur_footprints].mean(axis=0)
    np.testing.assert_allclose(centre, [4.0, -5.0, -6.0], atol=0.05)
    # two attachments 30 mm apart: two discs
    t2 = target_points(femur, tibia, [[-15.0, -5.0, 0.0], [15.0, -5.0, 0.0]], [[0.0, 5.0, 0.0]])
    assert t2.femur_footprints.sum() * spacing ** 2 == pytest.approx(2 * math.pi * 100.0, rel=0.01)


def test_the_epiphysis_is_40_mm_from_the_joint_line():
    """Points along each bone's axis: the femur's epiphysis is below the joint line plus 40 mm, the tibia's
    above it minus 40 mm."""
    assert EPIPHYSIS_LENGTH_MM == 40.0
    y = np.arange(-100.0, 100.0 + 1e-9, 1.0)
    column = np.column_stack([np.zeros_like(y), y, np.zeros_like(y)])
    t = target_points(column, column, [[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]], femur_joint_level=10.0,
                      tibia_joint_level=-5.0)
    assert t.femur[:, 1].max() == 49.0 and t.femur[:, 1].min() == -100.0
    assert t.tibia[:, 1].min() == -44.0 and t.tibia[:, 1].max() == 100.0


def test_a_rotated_bone_is_off_by_the_chord():
    """A bone turned by theta about an axis through the origin moves a point at distance r from the axis by
    the chord 2 r sin(theta / 2): the error of every target point, and their mean."""
    pts = _plate(-5.0, 1.0, 20.0)
    t = target_points(pts, pts, [[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    th = math.radians(7.0)
    R = np.eye(4)
    R[:3, :3] = [[1, 0, 0], [0, math.cos(th), -math.sin(th)], [0, math.sin(th), math.cos(th)]]  # about x
    e = pose_errors(t, np.eye(4), np.eye(4), R, np.eye(4))
    r = np.hypot(t.femur[:, 1], t.femur[:, 2])
    np.testing.assert_allclose(e.femur.distances, 2 * r * math.sin(th / 2), atol=1e-9)
    assert e.femur.epiphysis.mean == pytest.approx(np.mean(2 * r * math.sin(th / 2)))
    assert e.tibia.epiphysis.mean == pytest.approx(0.0, abs=1e-12)
    assert e.footprints_mm == pytest.approx(0.5 * e.femur.footprints.mean)


def test_errors_of_a_translation_are_its_length():
    pts = _plate(0.0, 2.0, 20.0)
    t = target_points(pts, pts, [[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    d = np.array([1.0, 2.0, 2.0])
    e = target_errors(t, t.femur + d, t.tibia - d, t.femur, t.tibia)
    for bone in ("femur", "tibia"):
        assert e.bone(bone).footprints.mean == pytest.approx(3.0) and e.bone(bone).epiphysis.sd == pytest.approx(0.0)
