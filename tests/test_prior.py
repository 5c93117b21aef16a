"""Flexion from depth with the mechanism as a prior, and the kinematics-alone estimate."""

import math

import numpy as np
import pytest

from knee.app.experiments.cases import phantom_targets
from knee.foundations.conventions import invert_poses, joint_to_pose, transform_points
from knee.foundations.errors import KneeInputError
from knee.foundations.pointclouds import backproject, voxel_downsample
from knee.models.evaluation import pose_errors
from knee.models.fem.depth import DepthNoise, default_camera, render_depth
from knee.models.phantom import build_phantom
from knee.models.prior import SkinModel, estimate_flexion, kinematic_estimate

#: The true flexion of the test scene: off the coarse search's 10 deg grid (-5, 5, ..., 65, 75, ...), so
#: that the estimate must come from the refinement, not from a grid point that happens to be the truth.
TRUE_DEG = 71.3


@pytest.fixture(scope="module")
def scene(volunteer):
    ph = build_phantom(volunteer.params)
    cam = default_camera()
    tf, pf, _ = volunteer.solve(math.radians(TRUE_DEG))
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


def test_column_bounds_are_the_columns_least_and_greatest():
    """Column by column, the same as min/max along the rows, for floats, integers and a strided view (a
    slip to the rows' bounds, or a dtype changed on the way, would show)."""
    from knee.foundations.pointclouds import column_bounds

    rng = np.random.default_rng(7)
    for a in (rng.normal(size=(500, 3)) * 50.0, rng.integers(-900, 900, size=(400, 3)),
              rng.normal(size=(600, 5))[::3, 1:4]):
        lo, hi = column_bounds(a)
        np.testing.assert_array_equal(lo, a.min(axis=0))
        np.testing.assert_array_equal(hi, a.max(axis=0))
        assert lo.dtype == a.dtype and hi.dtype == a.dtype


def test_posed_skin_by_parts_matches_the_union_mesh(volunteer, scene):
    """The skin queried part by part (no union built) against the union mesh's own signed distance and
    surface: the same distances away from the creases, and samples on the union's surface only."""
    from knee.foundations.surfaces import SurfaceQuery
    from knee.models.prior import SkinModel

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
    # each part queried only near its box: the same values as every part queried for every point
    posed = sk.at(alpha)
    every = np.min([q.signed_distance((p - T[:3, 3]) @ T[:3, :3]) for q, T in posed.parts], axis=0)
    np.testing.assert_array_equal(got, every)
    np.testing.assert_array_equal(posed.signed_distance(p, margin=0.0), every)
    samples, normals, _ = sk.samples(alpha)
    assert np.abs(SurfaceQuery.of(union).signed_distance(samples)).max() < 0.5
    assert len(samples) > 3000 and np.allclose(np.linalg.norm(normals, axis=1), 1.0)


def test_flexion_from_depth_and_kinematics_alone(volunteer, scene):
    ph, tf, pts = scene
    est = estimate_flexion(SkinModel(volunteer, ph), pts)
    assert abs(math.degrees(est.flexion) - TRUE_DEG) < 2.0 and not est.warnings
    assert est.rms < 2.0 and est.inliers > 0.8
    Tf, Tt = kinematic_estimate(volunteer, est)
    err = pose_errors(phantom_targets(volunteer, ph), np.eye(4), joint_to_pose(tf), Tf, Tt)
    assert err.tibia.footprints.mean < 6.0 and err.femur.epiphysis.mean < 6.0
    # the errors vanish for the true poses (the metric itself)
    zero = pose_errors(phantom_targets(volunteer, ph), np.eye(4), joint_to_pose(tf), np.eye(4), joint_to_pose(tf))
    assert zero.tibia.footprints.mean == 0.0


def test_the_coarse_scan_registers_a_subsample_and_scores_every_point(volunteer, scene, monkeypatch):
    """The flexion estimate's coarse scan registers at most :data:`COARSE_ICP_POINTS` of the thinned points
    (here lowered to a third of them), the same subsample at every candidate, and scores each candidate on
    every thinned point (its trimmed RMS computed here from that ICP's transform, independently); the
    refinement registers all of them. The estimate stays within 0.5 deg of every point's."""
    import knee.models.prior as P
    from knee.foundations.pointclouds import icp

    ph, _, pts = scene
    sk = SkinModel(volunteer, ph)
    every = voxel_downsample(pts, P.VOXEL_MM)
    monkeypatch.setattr(P, "COARSE_ICP_POINTS", len(every))
    whole = estimate_flexion(sk, pts)
    few = len(every) // 3
    monkeypatch.setattr(P, "COARSE_ICP_POINTS", few)
    calls = []
    monkeypatch.setattr(P, "icp", lambda src, *a, **k: calls.append((np.array(src), k["iterations"]))
                        or icp(src, *a, **k))
    est = estimate_flexion(sk, pts)
    coarse = [src for src, it in calls if it == P.COARSE_ICP_ITERATIONS]
    assert len(coarse) >= 10 and all(np.array_equal(src, coarse[0]) for src in coarse)
    assert len(coarse[0]) == few and len({tuple(p) for p in coarse[0]} - {tuple(p) for p in every}) == 0
    assert {len(src) for src, it in calls if it != P.COARSE_ICP_ITERATIONS} == {len(every)}
    assert abs(est.flexion - whole.flexion) < math.radians(0.5)
    a = math.radians(65.0)  # a candidate of the scan (-5, 5, ..., 65, ...)
    samples, normals, tree = sk.samples(a)
    T = icp(coarse[0], samples, init=np.eye(4), max_distance=15.0, iterations=P.COARSE_ICP_ITERATIONS,
            target_normals=normals)[0]
    p = transform_points(T, every)
    _, j = tree.query(p)
    d = np.sort(np.abs(np.sum((p - samples[j]) * normals[j], axis=1)))
    assert est.scores[65.0] == pytest.approx(float(np.sqrt(np.mean(d[: int(0.9 * len(d))] ** 2))), rel=1e-9)


def test_point_clouds_that_cannot_show_the_flexion_are_refused(volunteer, scene):
    ph, tf, pts = scene
    with pytest.raises(KneeInputError, match="at least 500"):
        estimate_flexion(SkinModel(volunteer, ph), pts[:100])
    holed = pts.copy()
    holed[:3, 1] = np.nan
    with pytest.raises(KneeInputError, match=rf"all finite, got {len(pts)} \(3 not finite\)"):
        estimate_flexion(SkinModel(volunteer, ph), holed)
    with pytest.raises(KneeInputError, match=r"must be \(P, 3\) points, got an array of shape \(600, 2\)"):
        estimate_flexion(SkinModel(volunteer, ph), pts[:600, :2])
    with pytest.raises(KneeInputError, match="too little of the shank"):
        estimate_flexion(SkinModel(volunteer, ph), pts[pts[:, 1] > 0.0])


def test_a_shank_behind_the_knee_counts_as_seen(volunteer):
    """Flexed past 90 deg the shank runs behind the knee, not below it: a view with nothing below the knee's
    height still shows the flexion (the shank's skin posed at some flexion explains its points), where
    counting only the points below the knee refused it."""
    ph = build_phantom(volunteer.params)
    sk = SkinModel(volunteer, ph)
    cam = default_camera()
    tf, pf, _ = volunteer.solve(math.radians(97.3))
    skin = ph.skin(joint_to_pose(tf), joint_to_pose(pf))
    pts = backproject(DepthNoise().apply(render_depth(skin.vertices, skin.faces, cam), np.random.default_rng(3)),
                      cam.K, cam.T_world_cam)
    above = pts[pts[:, 1] >= sk.shank_below]
    assert len(above) < len(pts) and not np.any(above[:, 1] < sk.shank_below)
    est = estimate_flexion(sk, above)
    assert abs(math.degrees(est.flexion) - 97.3) < 1.0
    assert not any("shank is hardly seen" in w for w in est.warnings)


def test_a_knee_beyond_the_prior_range_is_flagged(volunteer, scene):
    """A prior that stops assembling before the true flexion: the estimate pegs at its range end and says so."""
    from knee.models.mechanism import Mechanism

    ph, tf, pts = scene
    short = Mechanism(volunteer.params)
    short.assembly_range = (short.assembly_range[0], math.radians(60.0))  # as if the prior stopped at 60 deg
    est = estimate_flexion(SkinModel(short, ph), pts, coarse_step_deg=15.0)
    assert est.at_range_end and "end of the prior's assembly range" in est.warnings[0]


def test_a_view_that_does_not_fit_the_skin_is_flagged(volunteer, scene):
    """The same view read with the intrinsics of half its resolution (focal lengths and principal point
    halved: every ray at the wrong angle, the leg's outline warped): the skin cannot fit it, and the estimate
    says the result is not reliable; the view read with its own intrinsics fits within the threshold and says
    nothing of it."""
    from knee.models.prior import POOR_FIT_RMS_MM

    ph, tf, pts = scene
    est = estimate_flexion(SkinModel(volunteer, ph), pts)
    assert est.rms < POOR_FIT_RMS_MM and not any("fits the points poorly" in w for w in est.warnings)
    cam = default_camera()
    skin = ph.skin(joint_to_pose(tf), joint_to_pose(volunteer.solve(math.radians(TRUE_DEG))[1]))
    depth = DepthNoise().apply(render_depth(skin.vertices, skin.faces, cam), np.random.default_rng(1))
    half = np.diag([0.5, 0.5, 1.0]) @ cam.K
    warped = estimate_flexion(SkinModel(volunteer, ph), backproject(depth, half, cam.T_world_cam))
    assert warped.rms > POOR_FIT_RMS_MM
    assert any("fits the points poorly" in w and "not reliable" in w for w in warped.warnings)


def test_a_view_without_the_shank_is_flagged(volunteer, scene):
    """A camera in front of a knee flexed to 71.3 deg sees the thigh and the knee but not the shank (which
    runs back and down, away from it): the estimate says that the flexion shows only through the knee's
    outline. The counting itself: points on the shank's skin below the knee all count, the thigh's none."""
    from knee.foundations.conventions import transform_points
    from knee.models.prior import MIN_SEEN_SHANK, SkinModel, seen_shank_points

    ph, tf, pts = scene
    est = estimate_flexion(SkinModel(volunteer, ph), pts)  # the default oblique camera sees the shank
    assert est.shank_points >= MIN_SEEN_SHANK
    assert not any("shank is hardly seen" in w for w in est.warnings)
    cam = default_camera(azimuth_deg=0.0)
    skin = ph.skin(joint_to_pose(tf), joint_to_pose(volunteer.solve(math.radians(TRUE_DEG))[1]))
    front = backproject(DepthNoise().apply(render_depth(skin.vertices, skin.faces, cam), np.random.default_rng(2)),
                        cam.K, cam.T_world_cam)
    est = estimate_flexion(SkinModel(volunteer, ph), front)
    assert est.shank_points < MIN_SEEN_SHANK
    [w] = [w for w in est.warnings if "shank is hardly seen" in w]
    assert "8 deg median and up to 18" in w  # how far off such views were measured to be, not "a few degrees"
    alpha = math.radians(TRUE_DEG)
    posed = SkinModel(volunteer, ph).at(alpha)
    on_shank = _shank_points(volunteer, ph, alpha, np.eye(4), n=600, noise=0.0)
    on_shank = on_shank[transform_points(np.linalg.inv(joint_to_pose(tf)), on_shank)[:, 1] < -80.0]
    assert seen_shank_points(posed, on_shank) == len(on_shank) > 100
    from trimesh.sample import sample_surface

    t_pts, _ = sample_surface(ph.skin_parts(np.eye(4))[0][0], 500, seed=1)
    t_pts = t_pts[t_pts[:, 1] > 80.0]
    assert seen_shank_points(posed, t_pts) == 0 and len(t_pts) > 100


def _shank_points(volunteer, ph, alpha, D, n=4000, seed=0, noise=0.3):
    """Points spread over the shank's skin (more than 40 mm below the knee) with the tibia at
    ``T_prior @ D``, in the femur frame."""
    from trimesh.sample import sample_surface

    from knee.foundations.conventions import transform_points

    T = joint_to_pose(volunteer.motion_at(np.array([alpha]))[0][0]) @ D
    shank = ph.skin_parts(np.eye(4))[1][0]
    p, _ = sample_surface(shank, n, seed=seed)
    p = p[p[:, 1] < -40.0]
    p = p + np.random.default_rng(seed).normal(0.0, noise, p.shape)
    return transform_points(T, p)


def test_the_tibia_correction_recovers_what_the_shank_shows(volunteer):
    """Shank points from a tibia moved off the mechanism's path: with a weak prior the correction finds the
    move (the rotations across the shank and the translation); the rotation about the shank's own axis,
    which the points cannot show, stays the prior's."""
    from knee.models.prior import correct_tibia, small_pose

    ph = build_phantom(volunteer.params)
    alpha = math.radians(60.0)
    xi = np.array([0.03, 0.0, -0.025, 1.5, -1.0, 2.0])  # rad about x, y, z (tibia frame); mm
    pts = _shank_points(volunteer, ph, alpha, small_pose(xi))
    c = correct_tibia(SkinModel(volunteer, ph), pts, alpha, sigma_mm=100.0, sigma_deg=90.0)
    assert c.applied and c.points > 500
    np.testing.assert_allclose(c.rotation_deg, np.degrees(xi[:3]), atol=0.1)
    np.testing.assert_allclose(c.translation_mm, xi[3:], atol=0.15)
    assert c.rms_after < 0.5 < c.rms_before
    # an added axial rotation moves no point of the capsule (a surface of revolution about that axis): the
    # points carry nothing about it, the prior's zero stays (to within 0.3 of the 5.7 deg turned: the
    # capsule's facets show a little of the turn) and the rest of the correction is the same (with the points'
    # assumed sd, the default: given the 0.5 mm their residuals show, the facets' little weighs ten times as much)
    twisted = _shank_points(volunteer, ph, alpha, small_pose(xi) @ small_pose(np.array([0, 0.1, 0, 0, 0, 0])))
    c2 = correct_tibia(SkinModel(volunteer, ph), twisted, alpha, sigma_mm=100.0, sigma_deg=90.0, sigma_axial_deg=3.0)
    assert abs(c2.rotation_deg[1]) < 0.3
    np.testing.assert_allclose(c2.rotation_deg[[0, 2]], c.rotation_deg[[0, 2]], atol=0.1)
    # a confident prior keeps the tibia where the mechanism has it
    stiff = correct_tibia(SkinModel(volunteer, ph), pts, alpha, sigma_mm=0.01, sigma_deg=0.001)
    assert np.linalg.norm(stiff.translation_mm) < 0.1 * np.linalg.norm(c.translation_mm)
    assert np.linalg.norm(stiff.rotation_deg) < 0.1 * np.linalg.norm(c.rotation_deg)


def test_the_tibia_corrections_covariance_is_the_spread_of_its_answers(volunteer):
    """The correction's Laplace covariance (:attr:`TibiaCorrection.cov`) against Monte Carlo: points on a shank
    that is not round (so that all six components show), one per 4 mm voxel and away from the voxels' faces
    (the correction thins to such voxels: points that shared one would average their noise away), each moved
    along the skin's normal by independent noise of 0.3 mm, the correction made with that sd in 40 draws. The
    spread of its six components is the covariance's (each sd within 30 %: an estimate from 40 draws is within
    about 11 % of its own). With a prior far more confident than the points the covariance is the prior's."""
    from trimesh.sample import sample_surface

    from knee.models.prior import VOXEL_MM, correct_tibia, small_pose

    ph = _FlatShank(build_phantom(volunteer.params))
    sk = SkinModel(volunteer, ph)
    alpha = math.radians(60.0)
    T = joint_to_pose(volunteer.motion_at(np.array([alpha]))[0][0])
    shank = ph.skin_parts(np.eye(4))[1][0]
    p, f = sample_surface(shank, 60000, seed=5)
    below = p[:, 1] < -40.0
    p, n = transform_points(T, p[below]), shank.face_normals[f[below]] @ T[:3, :3].T
    frac = p / VOXEL_MM - np.floor(p / VOXEL_MM)
    mid = np.all((frac > 0.3) & (frac < 0.7), axis=1)  # 1.2 mm from every face of its voxel: 4 sd of the noise
    _, first = np.unique(np.floor(p[mid] / VOXEL_MM).astype(int), axis=0, return_index=True)
    p, n = p[mid][first], n[mid][first]
    assert len(p) > 300
    rng = np.random.default_rng(6)
    runs = [correct_tibia(sk, p + n * rng.normal(0.0, 0.3, (len(p), 1)), alpha, sigma_mm=100.0, sigma_deg=90.0,
                          sigma_axial_deg=90.0, point_sd_mm=0.3) for _ in range(40)]
    assert all(c.applied and c.points == runs[0].points for c in runs)
    sd = np.std([c.xi for c in runs], axis=0, ddof=1)
    np.testing.assert_allclose(sd, np.sqrt(np.diag(runs[0].cov)), rtol=0.3)
    stiff = correct_tibia(sk, p, alpha, sigma_mm=0.01, sigma_deg=0.001, sigma_axial_deg=0.001, point_sd_mm=30.0)
    np.testing.assert_allclose(np.sqrt(np.diag(stiff.cov)), [math.radians(0.001)] * 3 + [0.01] * 3, rtol=0.02)
    # no correction, no covariance
    assert correct_tibia(sk, p[:50], alpha).cov is None


class _FlatShank:
    """A phantom whose shank's skin is flattened front to back (its cross-section an ellipse, as a real
    shank's is not a circle): the same phantom otherwise."""

    def __init__(self, ph, flat=0.7):
        self._ph, self._flat = ph, flat

    def __getattr__(self, name):
        return getattr(self._ph, name)

    def skin_parts(self, *a, **kw):
        parts = self._ph.skin_parts(*a, **kw)
        shank = parts[1][0].copy()
        shank.vertices = shank.vertices * np.array([self._flat, 1.0, 1.0])  # the tibia's frame: x antero-posterior
        return [parts[0], (shank, parts[1][1])] + list(parts[2:])


def test_the_tibia_correction_finds_the_axial_rotation_a_non_round_shank_shows(volunteer):
    """A shank whose cross-section is not a circle shows the tibia's rotation about its own axis: points from
    a tibia turned 6 deg about it (and moved across) give the turn back with a weak prior; the prior's sd
    on that rotation weighs it as on the others (a confident one keeps the prior's), and the default's,
    :data:`knee.models.prior.TIBIA_PRIOR_AXIAL_DEG`, wider than about the other axes, lets more of the turn
    through than the others' would."""
    from trimesh.sample import sample_surface

    from knee.models.prior import TIBIA_PRIOR_AXIAL_DEG, TIBIA_PRIOR_DEG, correct_tibia, small_pose

    ph = _FlatShank(build_phantom(volunteer.params))
    sk = SkinModel(volunteer, ph)
    alpha = math.radians(60.0)
    xi = np.array([0.02, math.radians(6.0), -0.015, 1.0, -0.5, 1.5])
    T = joint_to_pose(volunteer.motion_at(np.array([alpha]))[0][0]) @ small_pose(xi)
    p, _ = sample_surface(ph.skin_parts(np.eye(4))[1][0], 4000, seed=3)
    pts = transform_points(T, p[p[:, 1] < -40.0])
    c = correct_tibia(sk, pts, alpha, sigma_mm=100.0, sigma_deg=90.0, sigma_axial_deg=None)  # None: sigma_deg
    np.testing.assert_allclose(c.rotation_deg, np.degrees(xi[:3]), atol=0.15)
    np.testing.assert_allclose(c.translation_mm, xi[3:], atol=0.2)
    default = correct_tibia(sk, pts, alpha).rotation_deg[1]
    as_others = correct_tibia(sk, pts, alpha, sigma_axial_deg=TIBIA_PRIOR_DEG).rotation_deg[1]
    assert TIBIA_PRIOR_AXIAL_DEG > TIBIA_PRIOR_DEG and 0.0 < as_others < default - 0.5 and default < 6.0
    held = correct_tibia(sk, pts, alpha, sigma_mm=100.0, sigma_deg=90.0, sigma_axial_deg=0.01)
    assert abs(held.rotation_deg[1]) < 0.05
    # with the axial rotation held, the points cannot be fitted as well
    assert held.rms_after > 3 * c.rms_after


def test_the_tibia_priors_weights_are_one_definition_for_the_methods_and_the_floor(volunteer, monkeypatch):
    """The prior's inverse variances by hand (3 deg about x and z, 5 about the tibia's axis, 2 mm), None for
    the axial sd meaning the others'; the methods' correction and the benchmark's floor with the methods'
    prior both take them from :func:`tibia_prior_weights` with the same defaults (a floor that kept 3 deg
    about the tibia's axis after the methods moved to 5 would no longer be the methods' prior)."""
    import inspect

    from knee.app.experiments import skin_floor
    from knee.models.prior import correct_tibia, tibia_prior_weights

    w = tibia_prior_weights(2.0, 3.0, 5.0)
    np.testing.assert_allclose(w, [(180 / math.pi / 3.0) ** 2, (180 / math.pi / 5.0) ** 2, (180 / math.pi / 3.0) ** 2,
                                   0.25, 0.25, 0.25])
    np.testing.assert_allclose(tibia_prior_weights(2.0, 3.0, None)[1], w[0])
    defaults = lambda f: {k: v.default for k, v in inspect.signature(f).parameters.items()
                          if k in ("sigma_mm", "sigma_deg", "sigma_axial_deg")}
    assert defaults(skin_floor.prior_floor_poses) == defaults(correct_tibia) == defaults(tibia_prior_weights)


def test_the_rotation_vectors_right_jacobian_against_finite_differences():
    """R(w + dw) = R(w) exp(J_r(w) dw) to first order: the Jacobian the tibia's correction takes where its
    rotation is, checked column by column against central differences, at a large and a tiny rotation."""
    from scipy.spatial.transform import Rotation

    from knee.models.prior import right_jacobian

    h = 1e-6
    for w in (np.array([0.3, -0.5, 0.2]), np.array([1e-10, 0.0, -2e-10])):
        R = Rotation.from_rotvec(w)
        fd = np.column_stack([(R.inv() * Rotation.from_rotvec(w + h * e)).as_rotvec() / (2 * h)
                              - (R.inv() * Rotation.from_rotvec(w - h * e)).as_rotvec() / (2 * h)
                              for e in np.eye(3)])
        np.testing.assert_allclose(right_jacobian(w), fd, atol=1e-7)
    assert np.abs(right_jacobian(np.array([0.3, -0.5, 0.2])) - np.eye(3)).max() > 0.1  # not the identity there


def test_the_tibia_correction_draws_in_a_shank_beyond_its_narrow_band(volunteer):
    """The front half of a shank swung 17 deg off the mechanism's path (as a camera in front sees it):
    from the narrow band alone too few points lie near the prior's shank to correct it, and the prior's
    pose is kept; starting from the wide band the correction finds the swing."""
    from knee.models.prior import MIN_CORRECTION_POINTS, SHANK, TIBIA_PRIOR_DEG, correct_tibia, small_pose

    ph = build_phantom(volunteer.params)
    sk = SkinModel(volunteer, ph)
    alpha = math.radians(60.0)
    xi = np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0])
    pts = _shank_points(volunteer, ph, alpha, small_pose(xi))
    T_true = sk.at(alpha).parts[SHANK][1] @ small_pose(xi)
    pts = pts[transform_points(invert_poses(T_true), pts)[:, 0] > 0.0]  # the anterior half
    narrow = correct_tibia(sk, pts, alpha, sigma_mm=100.0, sigma_deg=90.0, wide_band_mm=None)
    assert not narrow.applied and narrow.points < MIN_CORRECTION_POINTS
    # (the capsule cannot show the rotation about its axis: the prior's sd holds it, as by default)
    c = correct_tibia(sk, pts, alpha, sigma_mm=100.0, sigma_deg=90.0, sigma_axial_deg=TIBIA_PRIOR_DEG)
    assert c.applied
    np.testing.assert_allclose(c.rotation_deg, np.degrees(xi[:3]), atol=0.2)
    np.testing.assert_allclose(c.translation_mm, xi[3:], atol=0.2)


def test_no_tibia_correction_without_shank_points(volunteer):
    from trimesh.sample import sample_surface

    from knee.models.prior import correct_tibia

    ph = build_phantom(volunteer.params)
    thigh, _ = sample_surface(ph.skin_parts(np.eye(4))[0][0], 3000, seed=0)
    alpha = math.radians(60.0)
    c = correct_tibia(SkinModel(volunteer, ph), thigh[thigh[:, 1] > 60.0], alpha)
    assert not c.applied and "prior's pose is kept" in c.note
    np.testing.assert_array_equal(c.T, c.T_prior)
    # the flexion then rests on the skin's fit alone, which the note says and the benchmark counts as a warning
    from types import SimpleNamespace

    from knee.app.reports.case_set import warned_unseen
    assert warned_unseen(SimpleNamespace(notes=c.note))


@pytest.fixture(scope="module")
def subject_skin(volunteer):
    """The phantom's anatomy taken as a subject's: its extension skin, blended between the bones."""
    from knee.models.fem.methods import skin_model
    from knee.models.fem.scene import build_knee_model, phantom_anatomy
    from knee.models.prior import SubjectSkinModel

    anatomy, _ = phantom_anatomy(volunteer)
    model = build_knee_model(anatomy, prior=volunteer)
    sk = skin_model(model, volunteer)
    assert isinstance(sk, SubjectSkinModel)
    return sk, model


def test_a_subjects_skin_posed_at_its_scan_is_its_skin(subject_skin, volunteer):
    """At the scanned flexion the blended skin is the scanned skin (every vertex of it on the posed skin),
    and the shank part moves rigidly with the tibia along the prior's path."""
    sk, model = subject_skin
    posed = sk.at(model.anatomy.scan_tf[0])
    d = np.abs(posed.signed_distance(model.skin_vertices))
    assert np.percentile(d, 99) < 0.05
    a = math.radians(60.0)
    T_shank = sk.at(a).parts[1][1]
    np.testing.assert_allclose(T_shank, joint_to_pose(volunteer.motion_at(np.array([a]))[0][0]), atol=1e-9)


def test_the_flexion_from_a_subjects_own_skin(subject_skin, volunteer):
    """The phantom's capsule skin posed by the truth, seen obliquely, against the subject's blended skin
    (a different surface near the knee): within 1.5 deg at off-grid angles; a frontal view of a knee
    flexed beyond 50 deg is flagged (the shank unseen)."""
    sk, _ = subject_skin
    for deg in (30.0, TRUE_DEG):
        pts, _ = _case(volunteer, deg, 35.0)
        est = estimate_flexion(sk, pts)
        assert abs(math.degrees(est.flexion) - deg) < 1.5, (deg, math.degrees(est.flexion))
    est = estimate_flexion(sk, _case(volunteer, TRUE_DEG, 0.0)[0])
    assert any("shank is hardly seen" in w for w in est.warnings)


def _case(volunteer, deg, azimuth):
    from knee.app.experiments.cases import case_points

    return case_points(volunteer, deg, default_camera(azimuth_deg=azimuth), DepthNoise(), 3)


def test_rough_registration_keeps_the_better_of_its_reach_schedules(volunteer, scene):
    """From a guess 25 deg and 40 mm off, the rough registration keeps the best match over its reach
    schedules, in whichever order they come: a schedule that cannot move the cloud (a 1 mm reach: no
    pairs) beside the default wide one gives the wide one's answer, which lands near the truth (the
    scene's world is the model frame); the default tries more than one schedule."""
    from scipy.spatial.transform import Rotation

    from knee.models.prior import ROUGH_REACHES_MM, register_roughly

    ph, _, pts = scene
    sk = SkinModel(volunteer, ph)
    guess = np.eye(4)
    guess[:3, :3] = Rotation.from_rotvec(math.radians(25.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
    guess[:3, 3] = [24.0, -32.0, 0.0]
    assert len(ROUGH_REACHES_MM) >= 2
    wide, stuck = ROUGH_REACHES_MM[0], (1.0,)
    alone = register_roughly(sk, pts, guess, reaches_mm=(wide,))
    idle = register_roughly(sk, pts, guess, reaches_mm=(stuck,))
    assert idle.inliers < alone.inliers - 0.2
    for order in ((stuck, wide), (wide, stuck)):
        r = register_roughly(sk, pts, guess, reaches_mm=order)
        assert r.inliers == pytest.approx(alone.inliers) and r.rms == pytest.approx(alone.rms)
        np.testing.assert_allclose(r.T_model_world, alone.T_model_world, atol=1e-6)
    T = alone.T_model_world
    rot = math.degrees(math.acos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    shift = float(np.linalg.norm(transform_points(T, pts) - pts, axis=1).mean())
    assert rot < 10.0 and shift < 15.0, (rot, shift)


def test_rough_registration_tries_the_global_starts_where_the_guess_led_it_astray(volunteer, scene, monkeypatch):
    """A guess within its bounds (25 deg, 40 mm) is refined alone; a guess 90 deg and 100 mm off, beyond
    them, leads the ICP to the leg turned upside down (177 deg off the truth, fewer points on the skin),
    so the global search's starts are tried as well and the better match kept, near the truth (the
    scene's world is the model frame)."""
    from scipy.spatial.transform import Rotation

    import knee.models.prior as P

    ph, _, pts = scene
    sk = SkinModel(volunteer, ph)
    eye = default_camera().T_world_cam[:3, 3]  # the scene's points are in the model frame: the camera's there
    calls = []
    original = P.view_starts
    monkeypatch.setattr(P, "view_starts", lambda *a, **k: calls.append(1) or original(*a, **k))

    def guess(deg, mm):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(math.radians(deg) * np.array([0.6, 0.0, 0.8])).as_matrix()
        T[:3, 3] = mm * np.array([0.6, -0.8, 0.0])
        return T

    def off(r):
        T = r.T_model_world
        rot = math.degrees(math.acos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
        return rot, float(np.linalg.norm(transform_points(T, pts) - pts, axis=1).mean())

    P.register_roughly(sk, pts, guess(25.0, 40.0), viewpoint=eye)
    assert not calls
    alone = P.register_roughly(sk, pts, guess(90.0, 100.0), guess_within=(1e9, 1e9))  # the guess trusted
    assert not calls and off(alone)[0] > 90.0
    r = P.register_roughly(sk, pts, guess(90.0, 100.0), viewpoint=eye)
    assert calls and r.inliers > alone.inliers + 0.1
    rot, shift = off(r)
    assert rot < 10.0 and shift < 15.0, (rot, shift)
    # a caller that leaves out the background first (a whole camera frame) asks for the guess's own match
    # where it holds fewer points than it needs: returned as the guess alone gives it, no global starts
    calls.clear()
    poor = P.register_roughly(sk, pts, guess(90.0, 100.0), local_below=alone.inliers + 0.01)
    assert not calls and poor.inliers == pytest.approx(alone.inliers) and off(poor)[0] > 90.0
    P.register_roughly(sk, pts, guess(90.0, 100.0), local_below=alone.inliers - 0.01, viewpoint=eye)
    assert calls


def _phantom_view(volunteer, flexion_deg: float, seed: int, azimuth_deg: float = 0.0):
    """The phantom's skin posed by the volunteer at ``flexion_deg`` seen by the default camera (at
    ``azimuth_deg``) with its noise: (the skin model, the points in the model frame, the camera)."""
    ph = build_phantom(volunteer.params)
    tf, pf, _ = volunteer.solve(math.radians(flexion_deg))
    skin = ph.skin(joint_to_pose(tf), joint_to_pose(pf))
    cam = default_camera(azimuth_deg=azimuth_deg)
    pts = backproject(DepthNoise().apply(render_depth(skin.vertices, skin.faces, cam), np.random.default_rng(seed)),
                      cam.K, cam.T_world_cam)
    return SkinModel(volunteer, ph), pts, cam


def test_the_global_search_finds_the_knee_from_any_side(volunteer):
    """Without a guess, the rough registration searches rotations spread over all of them, each as the camera
    (at ``viewpoint``, here not the points' origin: their frame is the model's) would see the skin: the
    phantom at 40 deg seen from the front and from behind lands near the truth each time (the skin is the
    truth's own). A case set's views, whose skin is not the model's, are tested in test_benchmark_cases."""
    import knee.models.prior as P

    for az in (0.0, 180.0):
        sk, pts, cam = _phantom_view(volunteer, 40.0, seed=1, azimuth_deg=az)
        r = P.register_roughly(sk, pts, viewpoint=cam.T_world_cam[:3, 3])
        T = r.T_model_world
        rot = math.degrees(math.acos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
        shift = float(np.linalg.norm(transform_points(T, pts) - pts, axis=1).mean())
        assert rot < 10.0 and shift < 15.0, (az, rot, shift)
        # its next best matches, for a caller that can judge them better: apart from it and from each other
        # (over 30 deg or 40 mm at the knee), holding no more of the points
        assert 0 < len(r.alternatives) <= P.GLOBAL_ALTERNATIVES
        for i, m in enumerate(r.alternatives):
            assert m.inliers <= r.inliers
            for o in [r] + r.alternatives[:i]:
                assert max(np.subtract(P.placements_apart(sk, m.T_model_world, o.T_model_world), P.DISTINCT_MATCHES)) > 0


def test_the_global_searchs_starts_keep_their_best_when_pruned(volunteer, monkeypatch):
    """The starts' rotations are pruned to the share nearest the skin after their first mean shift
    (:data:`GLOBAL_PRUNED`): on a view of the phantom at 40 deg the best start at each candidate flexion is the
    one all the rotations give (the same rotation and score)."""
    import knee.models.prior as P

    sk, pts, cam = _phantom_view(volunteer, 40.0, seed=3)
    flexions = [math.radians(d) for d in P.ROUGH_FLEXIONS_DEG]
    pruned = P.view_starts(sk, pts, flexions, cam.T_world_cam[:3, 3])
    monkeypatch.setattr(P, "GLOBAL_PRUNED", 1.0)
    every = P.view_starts(sk, pts, flexions, cam.T_world_cam[:3, 3])
    for a in flexions:
        (s1, _, T1), (s2, _, T2) = [next(c for c in starts if c[1] == a) for starts in (pruned, every)]
        assert s1 == s2 and np.allclose(T1[:3, :3], T2[:3, :3]), math.degrees(a)


def test_the_global_search_looks_again_between_its_candidate_flexions(volunteer):
    """A knee flexed halfway between two of the search's candidate flexions (30 deg, between 15 and 45): the
    global search's best matches are looked at again halfway to the neighbouring candidates, so its match
    is the skin at 30 deg, holding more of the points than the best match at either candidate (there a view
    can hold as many points turned over as the right way round)."""
    import knee.models.prior as P

    sk, pts, cam = _phantom_view(volunteer, 30.0, seed=2)
    r = P.register_roughly(sk, pts, viewpoint=cam.T_world_cam[:3, 3])
    assert math.degrees(r.flexion) == pytest.approx(30.0, abs=1e-6)
    at_candidates = P.register_roughly(sk, pts, r.T_model_world, flexions_deg=(15.0, 45.0))
    assert r.inliers > at_candidates.inliers + 0.05, (r.inliers, at_candidates.inliers)
    T = r.T_model_world
    rot = math.degrees(math.acos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    assert rot < 5.0 and float(np.linalg.norm(transform_points(T, pts) - pts, axis=1).mean()) < 5.0


def test_rough_registration_searches_a_large_cloud_with_a_subsample(volunteer, scene, monkeypatch):
    """A cloud over the search's point budget (here lowered to a third of the scene's thinned points, as a
    frame with a table is over the default) is searched with a subsample of that many: the
    match lands near the truth as the whole cloud's does, and the share of points on the skin it reports is
    that of all the thinned points at the match (counted here independently), not the subsample's."""
    from scipy.spatial.transform import Rotation

    import knee.models.prior as P
    from knee.foundations.pointclouds import voxel_downsample

    ph, _, pts = scene
    sk = SkinModel(volunteer, ph)
    guess = np.eye(4)
    guess[:3, :3] = Rotation.from_rotvec(math.radians(20.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
    guess[:3, 3] = [20.0, -25.0, 0.0]
    whole = P.register_roughly(sk, pts, guess)
    every = voxel_downsample(pts, P.VOXEL_MM)
    assert len(every) > 3000
    searched = []
    original = P.icp
    monkeypatch.setattr(P, "icp", lambda src, *a, **k: searched.append(len(src)) or original(src, *a, **k))
    monkeypatch.setattr(P, "ROUGH_MAX_POINTS", len(every) // 3)
    monkeypatch.setattr(P, "ROUGH_ICP_POINTS", len(every))  # the ICPs' own subsample apart (next test)
    r = P.register_roughly(sk, pts, guess)
    assert set(searched) == {len(every) // 3}
    d, _ = sk.samples(r.flexion)[2].query(transform_points(r.T_model_world, every))
    assert r.inliers == pytest.approx(float(np.mean(d < 5.0)))
    assert r.flexion == whole.flexion and r.inliers > whole.inliers - 0.05
    T = r.T_model_world
    rot = math.degrees(math.acos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    shift = float(np.linalg.norm(transform_points(T, pts) - pts, axis=1).mean())
    assert rot < 10.0 and shift < 15.0, (rot, shift)


def test_the_guess_is_refined_with_a_subsample_and_scored_on_every_point(volunteer, scene, monkeypatch):
    """From a guess, every ICP of the rough registration takes at most :data:`ROUGH_ICP_POINTS` of the
    thinned points (here lowered to a third of them): the match lands where every point's does (the same
    candidate flexion, within 1 deg and 1 mm), and the share of points on the skin it reports is that of all
    the thinned points at the match (counted here independently), not the subsample's."""
    from scipy.spatial.transform import Rotation

    import knee.models.prior as P
    from knee.foundations.pointclouds import voxel_downsample

    ph, _, pts = scene
    sk = SkinModel(volunteer, ph)
    guess = np.eye(4)
    guess[:3, :3] = Rotation.from_rotvec(math.radians(20.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
    guess[:3, 3] = [20.0, -25.0, 0.0]
    every = voxel_downsample(pts, P.VOXEL_MM)
    monkeypatch.setattr(P, "ROUGH_ICP_POINTS", len(every))
    whole = P.register_roughly(sk, pts, guess)
    few = len(every) // 3
    monkeypatch.setattr(P, "ROUGH_ICP_POINTS", few)
    searched = []
    original = P.icp
    monkeypatch.setattr(P, "icp", lambda src, *a, **k: searched.append(len(src)) or original(src, *a, **k))
    r = P.register_roughly(sk, pts, guess)
    assert set(searched) == {few}
    d, _ = sk.samples(r.flexion)[2].query(transform_points(r.T_model_world, every))
    assert r.inliers == pytest.approx(float(np.mean(d < 5.0)))
    assert r.flexion == whole.flexion
    turned, moved = P.placements_apart(sk, r.T_model_world, whole.T_model_world)
    assert turned < 1.0 and moved < 1.0, (turned, moved)


def test_the_global_search_refines_its_starts_with_a_subsample(volunteer, monkeypatch):
    """The global search's starts are refined with at most :data:`GLOBAL_ICP_POINTS` of the thinned points
    (here lowered to a third of them), its best matches followed in flexion with all of them: the match still
    lands near the truth, and the share of points on the skin it reports is that of all the thinned points."""
    import knee.models.prior as P
    from knee.foundations.pointclouds import voxel_downsample

    sk, pts, cam = _phantom_view(volunteer, 40.0, seed=1)
    every = voxel_downsample(pts, P.VOXEL_MM)
    few = len(every) // 3
    monkeypatch.setattr(P, "GLOBAL_ICP_POINTS", few)
    searched = []
    original = P.icp
    monkeypatch.setattr(P, "icp", lambda src, *a, **k: searched.append((len(src), k["max_distance"]))
                        or original(src, *a, **k))
    r = P.register_roughly(sk, pts, viewpoint=cam.T_world_cam[:3, 3])
    wide, narrow = P.ROUGH_REACHES_MM
    assert {n for n, reach in searched if reach == wide[0]} == {few}  # every start's first, widest ICP
    assert len(every) in {n for n, _ in searched}                      # the matches followed with all points
    d, _ = sk.samples(r.flexion)[2].query(transform_points(r.T_model_world, every))
    assert r.inliers == pytest.approx(float(np.mean(d < 5.0)))
    T = r.T_model_world
    rot = math.degrees(math.acos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    assert rot < 10.0 and float(np.linalg.norm(transform_points(T, pts) - pts, axis=1).mean()) < 15.0


def test_the_fem_posed_skin_is_the_fems_skin(volunteer):
    """The flexion estimate's knee band posed by the association model (``skin_model(..., "fem")``) is
    where the FEM puts the skin: at an angle between the sweep's, a separate FEM solve there (8 increments
    from the scan instead of one step per 10 deg) agrees within 1 mm for half the band's points and 3 mm for
    three quarters, where the blend of the bones' motions is 5-6 mm off for half of them; the sweep leaves the model's grid as it found it, and a second model of the same
    anatomy and prior gets the cached sweep."""
    from knee.models.fem.mapping import TrilinearMapping
    from knee.models.fem.methods import (FemPosedSkinModel, move_tibia, prior_method, quasi_static, skin_model,
                                         tibia_path)
    from knee.models.fem.scene import build_knee_model, phantom_anatomy
    from knee.models.prior import SubjectSkinModel

    anatomy, _ = phantom_anatomy(volunteer)
    model = build_knee_model(anatomy, prior=volunteer)
    sk = skin_model(model, volunteer, "fem")
    assert isinstance(sk, FemPosedSkinModel)
    s = model.solver
    np.testing.assert_array_equal(s.x, model.grid.X)  # restored after the sweep
    assert skin_model(build_knee_model(anatomy, prior=volunteer), volunteer, "fem") is sk
    with pytest.raises(KneeInputError, match="one of blend, fem"):
        skin_model(model, volunteer, "lbs")
    with pytest.raises(KneeInputError, match="one of blend, fem"):  # not a fallback to the paper's method
        prior_method("links", model, volunteer, np.zeros((600, 3)), flexion_skin="lbs")
    a = math.radians(47.0)
    assert np.min(np.abs(sk.angles - a)) > math.radians(2.0)
    a_scan = model.anatomy.scan_tf[0]
    with quasi_static(s):
        move_tibia(model, tibia_path(volunteer, model, a_scan + (a - a_scan) * np.arange(1, 9) / 8), settle=2,
                   rebase=False)
    fem = TrilinearMapping(model.grid, sk._knee_rest).apply(s.x)
    blend = SubjectSkinModel._knee_vertices(sk, a)
    assert np.median(np.linalg.norm(blend - fem, axis=1)) > 3.0
    # the crease behind the knee (crushed tissue, its cells inverted) depends on the increments by tens of mm
    # between any two solves; the rest of the band does not
    np.testing.assert_array_less(np.percentile(np.linalg.norm(sk._knee_vertices(a) - fem, axis=1), [50, 75]), [1.0, 3.0])


def test_the_shank_as_the_fem_posed_it_is_carried_by_the_tibia_and_corrects_it(volunteer):
    """``fem_posed_shank``: at the scan (nothing moved) its shank is the scanned one in the tibia's frame. With
    the tibia moved to 60 deg (and a known correction) by the prior's initialisation, its shank in the tibia's
    frame is the scanned one far below the knee (the tibia carries the tissue there, within 0.5 mm) and
    departs from it near the knee (the tissue follows the thigh); a frame left uninverted would put it tens of
    mm off everywhere. Points on that posed shank, given to the tibia's correction from the prior's path with
    the points weighed as exact, bring the tibia back to the pose the model was moved to; the scanned shank
    moved rigidly, given the same points, does not. A skin asked at another flexion than it was replaced at is
    refused."""
    import trimesh
    from trimesh.sample import sample_surface

    from knee.models.fem.mapping import TrilinearMapping
    from knee.models.fem.methods import (fem_posed_shank, initialise_from_prior, prior_method, quasi_static, skin_model,
                                         tibia_path)
    from knee.models.fem.scene import build_knee_model, phantom_anatomy
    from knee.models.prior import SHANK, correct_tibia, small_pose

    anatomy, _ = phantom_anatomy(volunteer)
    model = build_knee_model(anatomy, prior=volunteer)
    sk = skin_model(model, volunteer)
    rest = sk.shank_at_scan
    a_scan = anatomy.scan_tf[0]
    scan = fem_posed_shank(model, sk, a_scan, anatomy.tibia_pose)
    q_scan = scan.at(a_scan).parts[SHANK][0]
    p, _ = sample_surface(rest, 3000, seed=1)
    # (the ray-casting scene's single precision: 0.01 mm on the scanned shank's own samples)
    assert np.abs(q_scan.signed_distance(transform_points(invert_poses(anatomy.tibia_pose), p))).max() < 0.05
    a = math.radians(60.0)
    xi = np.array([0.02, -0.03, 0.015, 1.0, -0.8, 1.2])
    T = tibia_path(volunteer, model, a)[0] @ small_pose(xi)
    with quasi_static(model.solver):
        initialise_from_prior(model, volunteer, a, correction_xi=xi)
    posed = fem_posed_shank(model, sk, a, T)
    q = posed.at(a).parts[SHANK][0]
    local = transform_points(invert_poses(anatomy.tibia_pose), p)  # the scanned shank in the tibia's frame
    far = p[:, 1] < anatomy.joint_y - 1.5 * anatomy.width
    d = np.abs(q.signed_distance(local))
    assert far.sum() > 100 and np.percentile(d[far], 90) < 0.5
    assert d[~far].max() > 1.0
    # the points: on the posed shank's skin as the model has it (its vertices carried by the grid), not the
    # solid's cut across the leg; the part near the knee included: a shank far below it is a near-cylinder,
    # which leaves the slide along and the turn about its axis to the prior
    mesh = trimesh.Trimesh(TrilinearMapping(model.grid, np.asarray(rest.vertices)).apply(model.solver.x), rest.faces,
                           process=False)
    on, face = sample_surface(mesh, 6000, seed=2)
    cut = anatomy.joint_y - (sk.BLEND - sk.OVERLAP) * anatomy.width
    pts = on[rest.vertices[rest.faces[face]][:, :, 1].max(axis=1) < cut - 1.0]
    found = correct_tibia(posed, pts, a, point_sd_mm=0.05)
    rigid = correct_tibia(sk, pts, a, point_sd_mm=0.05)
    knee_centre = np.array([[0.0, anatomy.joint_y, 0.0]])
    off = [float(np.linalg.norm(transform_points(c.T, knee_centre) - transform_points(T, knee_centre))) for c in (found, rigid)]
    assert off[0] < 0.1 and off[1] > 3 * off[0]
    with pytest.raises(ValueError, match="replaced at 60.00 deg"):
        posed.at(math.radians(30.0))
    with pytest.raises(KneeInputError, match="one of fem, blend"):  # refused, not a fallback to the paper's method
        prior_method("links", model, volunteer, np.zeros((600, 3)), shank_skin="rigid")
    with pytest.raises(KneeInputError, match="surface springs must be one of from_points, from_skin"):
        prior_method("links", model, volunteer, np.zeros((600, 3)), surface_springs="both")


def test_the_tibia_correction_weighs_points_that_err_together_as_few(volunteer):
    """The front of a shank that has not moved, its skin displaced by a smooth field of 2 mm RMS (bumps a
    quarter of the knee's width across, as a skin model errs): treated as independent points (sd 2 mm) the
    correction chases the bumps and moves the tibia millimetres; weighed as the few patches they are
    (:func:`effective_point_sd`), it stays near the prior, and a true move of the shank is still found."""
    from trimesh.sample import sample_surface

    from knee.foundations.conventions import transform_points
    from knee.models.fem.tissue import smooth_surface_field
    from knee.models.prior import correct_tibia, effective_point_sd, small_pose

    ph = build_phantom(volunteer.params)
    sk = SkinModel(volunteer, ph)
    alpha = math.radians(60.0)
    T = joint_to_pose(volunteer.motion_at(np.array([alpha]))[0][0])
    shank = ph.skin_parts(np.eye(4))[1][0]
    assert effective_point_sd(sk.width) == pytest.approx(2.0 * math.sqrt(math.pi) * 0.25 * sk.width / 4.0)
    spurious = {"independent": [], "patches": []}
    for seed in range(4):
        p, f = sample_surface(shank, 6000, seed=seed)
        front = (p[:, 1] < -40.0) & (p[:, 0] > 0.0)
        p = smooth_surface_field(p[front], shank.face_normals[f][front], 2.0, 0.25 * sk.width,
                                 np.random.default_rng(seed))
        pts = transform_points(T, p)
        spurious["independent"].append(np.linalg.norm(correct_tibia(sk, pts, alpha, point_sd_mm=2.0).translation_mm))
        spurious["patches"].append(np.linalg.norm(correct_tibia(sk, pts, alpha).translation_mm))
    assert np.mean(spurious["patches"]) < 0.6 * np.mean(spurious["independent"])
    assert np.mean(spurious["independent"]) > 2.0
    # a shank truly moved (swung 1.7 and 1.4 deg, shifted 2.7 mm) is still followed where it is seen: the
    # points fit it and its skin a hand's breadth below the knee lands within a millimetre; what the shank
    # cannot separate (a swing about the knee from a shift) is left nearer the prior
    xi = np.array([0.03, 0.0, -0.025, 1.5, -1.0, 2.0])
    moved = correct_tibia(sk, _shank_points(volunteer, ph, alpha, small_pose(xi)), alpha)
    assert moved.rms_after < 0.5 < moved.rms_before
    below = np.array([[0.0, -100.0, 0.0]])
    assert np.linalg.norm(transform_points(moved.T, below) - transform_points(moved.T_prior @ small_pose(xi), below)) < 1.0


def test_the_tibia_correction_can_take_the_points_sd_from_its_residuals_below_the_bound(volunteer):
    """With ``adapt_point_sd`` (an option), where the shank's skin fits its points closely the correction gives
    them the sd their residuals show (not below MIN_POINT_SD_MM, inflated for the error's correlation as
    before): its answer is the MAP estimate with that sd, asked for directly, and nearer the tibia's true move
    than with the assumed 2 mm (the default's answer). Where the residuals exceed the assumed sd, the answer is
    the assumed sd's. Catches an adaptation that does nothing, that drops the inflation or the bound, or that
    raises the sd above POINT_SD_MM, and a default that adapts."""
    from knee.models.prior import MIN_POINT_SD_MM, correct_tibia, effective_point_sd, small_pose

    ph = build_phantom(volunteer.params)
    sk = SkinModel(volunteer, ph)
    alpha = math.radians(60.0)
    xi = np.array([0.03, 0.0, -0.025, 1.5, -1.0, 2.0])
    exact = _shank_points(volunteer, ph, alpha, small_pose(xi))
    adapted = correct_tibia(sk, exact, alpha, adapt_point_sd=True)
    fixed = correct_tibia(sk, exact, alpha)
    np.testing.assert_array_equal(fixed.xi, correct_tibia(sk, exact, alpha, adapt_point_sd=False).xi)
    direct = correct_tibia(sk, exact, alpha, point_sd_mm=effective_point_sd(sk.width, MIN_POINT_SD_MM))
    assert adapted.rms_after < MIN_POINT_SD_MM  # exact points: the bound is what sets the sd
    np.testing.assert_allclose(adapted.xi, direct.xi, atol=2e-4)
    err = lambda c: np.linalg.norm(c.xi[3:] - xi[3:]) + np.linalg.norm(np.degrees(c.xi[:3] - xi[:3]))
    assert err(adapted) < 0.7 * err(fixed)
    # points noisier than the assumed sd: the assumed sd stays
    noisy = _shank_points(volunteer, ph, alpha, small_pose(xi), noise=3.0)
    a, f = correct_tibia(sk, noisy, alpha, adapt_point_sd=True), correct_tibia(sk, noisy, alpha)
    assert a.rms_after > 2.0
    np.testing.assert_array_equal(a.xi, f.xi)


def test_the_prior_cases_script_runs_the_cases_asked_and_refuses_bad_input(tmp_path, capsys, run_script):
    """scripts/prior_cases.py (the fixed benchmark of the flexion estimate and of method (iv)) on two of its
    cases: a row per camera and flexion asked, the oblique view's flexion within 2 deg and the shank seen, the
    frontal view of a 90 deg knee flagged as not seeing it; bad choices and an existing output refused in one
    line with nothing written. Catches a script that stops at its first case (as it once did, when the truth's
    skin shadowed the skin model) or that writes rows for other cases than those asked."""
    import csv

    out = tmp_path / "cases.csv"
    assert run_script("prior_cases", ["--flexions", "90", "--azimuths", "35,0", "--out", out]) == 0
    rows = list(csv.DictReader(out.open()))
    assert [(float(r["camera_azimuth_deg"]), float(r["flexion_true_deg"])) for r in rows] == [(35.0, 90.0), (0.0, 90.0)]
    oblique, frontal = rows
    assert abs(float(oblique["flexion_est_deg"]) - 90.0) <= 2.0 and int(oblique["shank_points"]) > 500
    assert math.isclose(float(oblique["error_deg"]), float(oblique["flexion_est_deg"]) - 90.0)
    assert not oblique["warning"] and "shank is hardly seen" in frontal["warning"]
    assert all(0.0 < float(r[k]) < 20.0 for r in rows for k in ("femur_footprints_mm", "tibia_footprints_mm"))
    capsys.readouterr()
    for argv, says in ((["--flexions", "30,200"], "--flexions must give 1-50 angles"),
                       (["--azimuths", "35,x"], "--azimuths must be a comma list"),
                       (["--out", out], "exists; not overwritten")):
        before = out.read_bytes()
        assert run_script("prior_cases", argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error:") and says in err[0], err
        assert out.read_bytes() == before
