"""Flexion from depth with the mechanism as a prior, and the kinematics-alone estimate."""

import math

import numpy as np
import pytest

from models.fem.case import default_camera
from models.fem.depth import DepthNoise, backproject, render_depth
from models.phantom import build_phantom
from models.prior import (estimate_flexion, kinematic_estimate, pose_errors, target_set, voxel_downsample)
from toolkit.conventions import joint_to_pose
from toolkit.errors import KneeInputError


@pytest.fixture(scope="module")
def scene(volunteer):
    ph = build_phantom(volunteer.params)
    cam = default_camera()
    tf, pf, _ = volunteer.solve(math.radians(75.0))
    skin = ph.skin(joint_to_pose(tf), joint_to_pose(pf))
    pts = backproject(DepthNoise().apply(render_depth(skin.vertices, skin.faces, cam), np.random.default_rng(1)),
                      cam.K, cam.T_world_cam)
    return ph, tf, pts


def test_voxel_downsample_means_per_voxel():
    p = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [5.0, 5.0, 5.0]])
    out = voxel_downsample(p, 1.0)
    assert len(out) == 2 and np.allclose(sorted(out[:, 0]), [0.2, 5.0])


def test_voxel_downsample_against_a_per_point_grouping():
    """The packed-key grouping gives the voxel means of a plain dictionary grouping (negative coordinates
    included)."""
    p = np.random.default_rng(4).normal(size=(3000, 3)) * 20.0
    groups = {}
    for q in p:
        groups.setdefault(tuple(np.floor(q / 4.0).astype(int)), []).append(q)
    ref = np.array(sorted(tuple(np.mean(g, axis=0)) for g in groups.values()))
    out = np.array(sorted(map(tuple, voxel_downsample(p, 4.0))))
    np.testing.assert_allclose(out, ref, atol=1e-9)


def test_posed_skin_by_parts_matches_the_union_mesh(volunteer, scene):
    """The skin queried part by part (no union built) against the union mesh's own signed distance and
    surface: the same distances away from the creases, and samples on the union's surface only."""
    from models.fem.geometry import SurfaceQuery
    from models.prior import SkinModel

    ph, _, _ = scene
    alpha = math.radians(60.0)
    tf, pf, _ = volunteer.solve(alpha)
    union = ph.skin(joint_to_pose(tf), joint_to_pose(pf))
    sk = SkinModel(volunteer, ph)
    rng = np.random.default_rng(2)
    p = union.bounds[0] + rng.random((4000, 3)) * np.ptp(union.bounds, axis=0)
    ref = SurfaceQuery.of(union).signed_distance(p)
    got = sk.at(alpha).signed_distance(p)
    outside = ref > 1.0
    assert np.median(np.abs(got[outside] - ref[outside])) < 0.05
    assert np.mean(np.abs(got[outside] - ref[outside]) < 0.5) > 0.95  # all but points facing a crease
    np.testing.assert_array_equal(got < 0, ref < 0)  # inside the union exactly when inside a part
    samples, normals, _ = sk.samples(alpha)
    assert np.abs(SurfaceQuery.of(union).signed_distance(samples)).max() < 0.5
    assert len(samples) > 3000 and np.allclose(np.linalg.norm(normals, axis=1), 1.0)


def test_flexion_from_depth_and_kinematics_alone(volunteer, scene):
    ph, tf, pts = scene
    est = estimate_flexion(volunteer, ph, pts)
    assert abs(math.degrees(est.flexion) - 75.0) < 2.0 and not est.warnings
    assert est.rms < 2.0 and est.inliers > 0.8
    Tf, Tt = kinematic_estimate(volunteer, est)
    err = pose_errors(target_set(volunteer, ph), np.eye(4), joint_to_pose(tf), Tf, Tt)
    assert err["tibia"]["footprints"][0] < 6.0 and err["femur"]["epiphysis"][0] < 6.0
    # the errors vanish for the true poses (the metric itself)
    zero = pose_errors(target_set(volunteer, ph), np.eye(4), joint_to_pose(tf), np.eye(4), joint_to_pose(tf))
    assert zero["tibia"]["footprints"][0] == 0.0


def test_point_clouds_that_cannot_show_the_flexion_are_refused(volunteer, scene):
    ph, tf, pts = scene
    with pytest.raises(KneeInputError, match="at least 500"):
        estimate_flexion(volunteer, ph, pts[:100])
    with pytest.raises(KneeInputError, match="too little of the shank"):
        estimate_flexion(volunteer, ph, pts[pts[:, 1] > 0.0])


def test_a_knee_beyond_the_prior_range_is_flagged(volunteer, scene):
    """A prior that stops assembling before the true flexion: the estimate pegs at its range end and says so."""
    from models.mechanism import Mechanism

    ph, tf, pts = scene
    short = Mechanism(volunteer.params)
    short.assembly_range = (short.assembly_range[0], math.radians(60.0))  # as if the prior stopped at 60 deg
    est = estimate_flexion(short, ph, pts, coarse_step_deg=15.0)
    assert est.at_range_end and "end of the prior's assembly range" in est.warnings[0]
