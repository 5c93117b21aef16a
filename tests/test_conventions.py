"""Conventions: Cardan sequence, anatomical meaning of each coordinate, mirroring, SE3."""

import numpy as np
import pinocchio as pin
import pytest

from knee.foundations import conventions as cv


def test_cardan_is_the_stated_product():
    a, b, g = 0.7, -0.2, 0.3
    Rz = np.array([[np.cos(-a), -np.sin(-a), 0], [np.sin(-a), np.cos(-a), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    Ry = np.array([[np.cos(g), 0, np.sin(g)], [0, 1, 0], [-np.sin(g), 0, np.cos(g)]])
    np.testing.assert_allclose(cv.cardan_to_matrix(a, b, g), Rz @ Rx @ Ry, atol=1e-15)


def test_round_trip_vectorised():
    rng = np.random.default_rng(1)
    q = np.column_stack([rng.uniform(-3, 3, 500), rng.uniform(-1.5, 1.5, 500), rng.uniform(-3, 3, 500),
                         rng.normal(0, 30, (500, 3))])
    T = cv.joint_to_pose(q)
    assert T.shape == (500, 4, 4)
    np.testing.assert_allclose(cv.pose_to_joint(T), q, atol=1e-12)
    np.testing.assert_allclose(cv.joint_to_pose(cv.pose_to_joint(T)), T, atol=1e-12)


def test_anatomical_meaning_right_knee():
    # flexion: the tibia's distal direction (-y) swings posteriorly (x < 0) in the femur frame
    R = cv.cardan_to_matrix(np.radians(60), 0, 0)
    assert (R @ [0, -1, 0])[0] < -0.8
    # adduction: the distal tibia moves medially (z < 0 for a right knee)
    R = cv.cardan_to_matrix(0, np.radians(10), 0)
    assert (R @ [0, -1, 0])[2] < -0.1
    # internal rotation: the tibia's anterior axis turns medially
    R = cv.cardan_to_matrix(0, 0, np.radians(10))
    assert (R @ [1, 0, 0])[2] < -0.1


def test_translations_are_the_origin_in_the_femur_frame():
    q = np.array([0.3, 0.1, -0.2, 4.0, -30.0, 2.0])
    T = cv.joint_to_pose(q)
    np.testing.assert_allclose(cv.transform_points(T, np.zeros((1, 3)))[0], q[3:])


def test_left_knee_mirroring_gives_the_same_anatomical_coordinates():
    q_right = np.array([np.radians(40), np.radians(3), np.radians(-8), -5.0, -25.0, 3.0])
    T_right = cv.joint_to_pose(q_right)
    T_left = cv.mirror_poses(T_right)  # the same motion of a left knee (z to the subject's right)
    raw = cv.pose_to_joint(T_left)
    np.testing.assert_allclose(raw[[0, 3, 4]], q_right[[0, 3, 4]], atol=1e-12)
    np.testing.assert_allclose(raw[[1, 2, 5]], -q_right[[1, 2, 5]], atol=1e-12)  # signs flip raw
    np.testing.assert_allclose(cv.joint_coordinates(T_left, side="left"), q_right, atol=1e-12)
    p = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(cv.mirror_points(cv.mirror_points(p)), p)
    with pytest.raises(ValueError):
        cv.joint_coordinates(T_left, side="up")


def test_se3_round_trip_and_composition():
    rng = np.random.default_rng(2)
    T1 = cv.joint_to_pose(rng.normal(size=6))
    T2 = cv.joint_to_pose(rng.normal(size=6))
    M1, M2 = cv.to_se3(T1), cv.to_se3(T2)
    assert isinstance(M1, pin.SE3)
    np.testing.assert_allclose(cv.from_se3(M1), T1, atol=1e-14)
    np.testing.assert_allclose(cv.from_se3(M1 * M2), T1 @ T2, atol=1e-12)
    np.testing.assert_allclose(cv.invert_poses(T1), cv.from_se3(M1.inverse()), atol=1e-12)


def test_bad_shape_is_a_value_error():
    with pytest.raises(ValueError, match="6 components"):
        cv.joint_to_pose(np.zeros(5))
