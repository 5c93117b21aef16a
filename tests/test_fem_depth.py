"""The depth input: virtual camera, noise, back-projection, files, ICP."""

import numpy as np
import open3d as o3d
import pytest
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from knee.foundations.conventions import cardan_to_matrix
from knee.foundations.errors import KneeInputError
from knee.foundations.pointclouds import (
    PRINCIPAL_POINT_SHARE,
    principal_point_note,
    backproject,
    icp,
    icp_held,
    icp_held_to_surface,
    load_depth_image,
    load_point_cloud,
    mixed_pixels,
)
from knee.foundations.surfaces import SurfaceQuery
from knee.models.fem.depth import Camera, DepthNoise, render_depth


@pytest.fixture(scope="module")
def knee_like():
    m = trimesh.creation.capsule(height=200.0, radius=55.0, count=[48, 48])
    m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    bump = trimesh.creation.icosphere(3, 30.0).apply_translation([45.0, 10.0, 0.0])  # a 'patella'
    return trimesh.boolean.union([m, bump], engine="manifold")


def _camera():
    # 350 mm away, oblique: from anterior, above and lateral
    eye = np.array([300.0, 120.0, 140.0])
    return Camera.looking_at(eye, [0.0, 0.0, 0.0])


def test_plane_depth_is_exact():
    plane = trimesh.creation.box(extents=[2000, 2000, 1]).apply_translation([0, 0, -0.5])
    cam = Camera.looking_at([0, 0, 400.0], [0, 0, 0], up=[0, 1, 0], width=64, height=48)
    d = render_depth(plane.vertices, plane.faces, cam)
    np.testing.assert_allclose(d, 400.0, atol=1e-3)
    pts = backproject(d, cam.K, cam.T_world_cam)
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-3)


def test_backprojected_points_lie_on_the_surface(knee_like):
    cam = _camera()
    assert (cam.width, cam.height) == (1280, 720)
    assert 300 < np.linalg.norm(cam.T_world_cam[:3, 3]) < 400
    d = render_depth(knee_like.vertices, knee_like.faces, cam)
    seen = d > 0
    assert 0.05 < seen.mean() < 0.9
    pts = backproject(d, cam.K, cam.T_world_cam)
    sd = SurfaceQuery.of(knee_like).signed_distance(pts)
    assert np.abs(sd).max() < 0.2  # open3d casts rays in float32
    # one-sided: every point seen lies on a face turned towards the camera
    q = SurfaceQuery.of(knee_like)
    eps = 0.5
    to_cam = cam.T_world_cam[:3, 3] - pts
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    assert np.all(q.signed_distance(pts + eps * to_cam) > 0)  # a step towards the camera is outside
    # and well under the whole surface is seen (the far side is not)
    from scipy.spatial import cKDTree

    surf = knee_like.sample(20000, seed=0)
    seen_fraction = np.mean(cKDTree(pts).query(surf)[0] < 1.5)
    assert 0.2 < seen_fraction < 0.6


def test_band_distances_are_exact_within_the_band_and_ask_little_once_the_points_settle(knee_like):
    """Points moved a little at a time (a rigid drift that slows, as a fit's), asked within a band that
    narrows: wherever the full signed distance is within the band the answer is that distance, wherever it
    is not the answer is outside the band too; points far from the surface are asked once."""
    from knee.foundations.surfaces import BandDistances

    q = SurfaceQuery.of(knee_like)
    rng = np.random.default_rng(7)
    v = np.asarray(knee_like.vertices)
    pts = v[rng.integers(0, len(v), 3000)] + rng.normal(0.0, 30.0, (3000, 3))
    band = BandDistances(q, len(pts))
    for k in range(12):
        R = Rotation.from_rotvec(rng.normal(0.0, 0.02 / (k + 1), 3)).as_matrix()
        pts = (pts - pts.mean(axis=0)) @ R.T + pts.mean(axis=0) + rng.normal(0.0, 1.5 / (k + 1), 3)
        b = 20.0 if k < 4 else 8.0
        got, full = band.within(pts, b), q.signed_distance(pts)
        inside = np.abs(full) < b
        np.testing.assert_allclose(got[inside], full[inside], atol=1e-9)
        assert np.all(np.abs(got[~inside]) >= b - 1e-3)
        assert inside.sum() > 300 and (~inside).sum() > 300
    assert band.asked < 0.5 * 12 * len(pts)  # the far points were not asked again and again


def test_noise_model_statistics():
    rng = np.random.default_rng(0)
    d = np.full((400, 400), 400.0)
    noisy = DepthNoise().apply(d, rng)
    kept = noisy > 0
    assert abs(1 - kept.mean() - 0.02) < 0.003
    assert np.std(noisy[kept] - 400.0) == pytest.approx(1.0, rel=0.02)
    far = DepthNoise().apply(np.full((200, 200), 800.0), rng)
    assert np.std(far[far > 0] - 800.0) == pytest.approx(4.0, rel=0.03)  # quadratic in depth


@pytest.mark.parametrize("width", [1.5, 3.0])
def test_correlated_noise_has_the_same_sigma_and_the_smoothing_kernels_correlation(width):
    """A stereo camera's errors are correlated over its matching window. White noise smoothed by a Gaussian
    of width s has, between pixels r apart, the correlation exp(-r^2 / (4 s^2)) (a closed form, not the
    code's); each pixel's sigma stays the uncorrelated model's, and a 10 x 10 patch's mean error (what a
    voxel of a thinned cloud keeps) is far larger than white noise's 1/10 of it."""
    d = np.full((480, 640), 400.0)
    e = DepthNoise(dropout=0.0, correlation_px=width).apply(d, np.random.default_rng(3)) - 400.0
    assert np.std(e) == pytest.approx(1.0, rel=0.05)
    for r in (1, 2, 4, 8):
        rho = np.mean(e[:, r:] * e[:, :-r]) / np.var(e)
        assert rho == pytest.approx(np.exp(-r * r / (4 * width * width)), abs=0.03), r
    patch = e.reshape(48, 10, 64, 10).mean(axis=(1, 3))
    white = DepthNoise(dropout=0.0).apply(d, np.random.default_rng(3)) - 400.0
    assert np.std(white.reshape(48, 10, 64, 10).mean(axis=(1, 3))) < 0.13 < 0.3 < np.std(patch)


def test_holes_lose_the_same_share_in_blobs_and_leave_the_rest_as_it_was():
    """``hole_px``: the dropout's share lost, in blobs of several pixels instead of one by one; the errors of
    the pixels kept are those drawn without holes (the same stream)."""
    d = np.full((300, 400), 400.0)
    d[:, :40] = 0.0  # nothing seen there: a hole cannot be told from it, but the share counts the image
    plain = DepthNoise().apply(d, np.random.default_rng(5))
    holes = DepthNoise(hole_px=6.0).apply(d, np.random.default_rng(5))
    lost = (holes == 0) & (d > 0)
    assert abs(np.mean(holes[:, 40:] == 0) - 0.02) < 0.004
    _, n_single = ndimage.label((plain == 0) & (d > 0))
    _, n_blobs = ndimage.label(lost)
    assert lost.sum() / n_blobs > 10.0 > 1.5 > ((plain == 0) & (d > 0)).sum() / n_single
    both = (holes > 0) & (plain > 0)
    np.testing.assert_array_equal(holes[both], plain[both])


@pytest.mark.parametrize("bad", [{"correlation_px": -1.0}, {"hole_px": float("nan")}, {"dropout": 1.5},
                                 {"sigma_at_ref": float("inf")}, {"ref_depth": 0.0}])
def test_the_noise_model_refuses_impossible_settings(bad):
    with pytest.raises(KneeInputError, match=next(iter(bad))):
        DepthNoise(**bad)


def test_depth_image_and_point_cloud_files(tmp_path, knee_like):
    cam = _camera()
    d = render_depth(knee_like.vertices, knee_like.faces, cam)
    png = tmp_path / "depth.png"
    o3d.io.write_image(str(png), o3d.geometry.Image(np.round(d).astype(np.uint16)))
    pts = load_depth_image(png, cam.K, cam.T_world_cam)
    assert np.abs(SurfaceQuery.of(knee_like).signed_distance(pts)).max() < 1.0  # mm rounding
    np.save(tmp_path / "depth.npy", d)
    assert len(load_depth_image(tmp_path / "depth.npy", cam.K, drop_mixed=False)) == (d > 0).sum()
    assert len(load_depth_image(tmp_path / "depth.npy", cam.K)) == (d > 0).sum() - mixed_pixels(d, cam.K).sum()
    ply = tmp_path / "cloud.ply"
    o3d.io.write_point_cloud(str(ply), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    np.testing.assert_allclose(load_point_cloud(ply), pts, atol=1e-3)
    # a camera's pixels without a return (NaN, or depth 0 back-projected to the origin) are dropped, the
    # rest kept in order; a cloud of nothing else is refused
    holes = np.insert(pts, [0, 5, 5], [[np.nan, np.nan, np.nan], [0.0, 0.0, 0.0], [np.inf, 1.0, 2.0]], axis=0)
    xyz = tmp_path / "holes.xyz"
    np.savetxt(xyz, holes)
    np.testing.assert_allclose(load_point_cloud(xyz), pts, atol=1e-6)
    np.savetxt(xyz, np.array([[np.nan, 0.0, 1.0], [0.0, 0.0, 0.0]]))
    with pytest.raises(KneeInputError, match="none of its 2 points is valid"):
        load_point_cloud(xyz)
    with pytest.raises(KneeInputError, match="no such"):
        load_point_cloud(tmp_path / "missing.ply")
    with pytest.raises(KneeInputError, match="intrinsics"):
        backproject(d, np.eye(2))
    with pytest.raises(KneeInputError, match="2-D"):
        backproject(d.ravel(), cam.K)
    with pytest.raises(KneeInputError, match="no such depth image"):
        load_depth_image(tmp_path / "missing.png", cam.K)
    gray = tmp_path / "gray.png"
    o3d.io.write_image(str(gray), o3d.geometry.Image(np.full(d.shape, 200, np.uint8)))
    with pytest.raises(KneeInputError, match="gray.png: a depth image must be a 16-bit PNG, got 8-bit"):
        load_depth_image(gray, cam.K)
    np.save(tmp_path / "none.npy", np.where(d > 0, np.nan, -1.0))
    with pytest.raises(KneeInputError, match="none.npy: no pixel holds a depth"):
        load_depth_image(tmp_path / "none.npy", cam.K)
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n")
    with pytest.raises(KneeInputError, match="no points"):
        load_point_cloud(empty)
    stl = tmp_path / "knee.stl"
    knee_like.export(stl)
    with pytest.raises(KneeInputError, match=r"knee.stl: not a point-cloud format .*\.ply, \.pcd, \.xyz, \.pts"):
        load_point_cloud(stl)
    two = tmp_path / "two.xyz"
    two.write_text("1 2\n3 4\n")
    with pytest.raises(KneeInputError, match="not three numbers x y z per line"):
        load_point_cloud(two)
    with pytest.raises(KneeInputError, match="coincide"):
        Camera.looking_at([1, 2, 3], [1, 2, 3])
    with pytest.raises(KneeInputError, match="parallel"):
        Camera.looking_at([0, 0, 0], [0, 10, 0], up=[0, 1, 0])


def test_truncated_point_cloud_files_are_refused_not_read_in_part(tmp_path, capfd):
    """A cloud file cut short (an interrupted copy or write) is refused with the count it declared, and
    nothing the reader printed reaches the terminal: open3d returns the points it had from a short binary
    or ASCII PLY (printing its complaint on stderr), and from a short ASCII PCD the declared number of
    points with the missing ones undefined, either of which would otherwise run as a measured view."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-50.0, 50.0, (1000, 3)) + [0.0, 0.0, 400.0]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    for name, ascii_ in [("b.ply", False), ("a.ply", True), ("a.pcd", True), ("b.pcd", False)]:
        whole = tmp_path / name
        o3d.io.write_point_cloud(str(whole), cloud, write_ascii=ascii_)
        np.testing.assert_allclose(load_point_cloud(whole), pts, atol=1e-3)  # the whole file reads back
        data = whole.read_bytes()
        cut = tmp_path / f"cut-{name}"
        cut.write_bytes(data[:len(data) // 2])
        with pytest.raises(KneeInputError, match=f"cut-{name}: truncated"):
            load_point_cloud(cut)
    assert "RPly" not in capfd.readouterr().err


def _box_faces(rng, half=(30.0, 90.0, 45.0), n=400):
    """Points on five faces of a box (all but the bottom), their faces' outward normals and the faces'
    offsets (n . x = d)."""
    half = np.asarray(half)
    pts, nrm = [], []
    for axis, sign in [(0, 1), (0, -1), (1, 1), (2, 1), (2, -1)]:
        p = rng.uniform(-half, half, size=(n, 3))
        p[:, axis] = sign * half[axis]
        e = np.zeros(3)
        e[axis] = sign
        pts.append(p)
        nrm.append(np.tile(e, (n, 1)))
    pts, nrm = np.vstack(pts), np.vstack(nrm)
    return pts, nrm, np.einsum("ij,ij->i", pts, nrm)


def _motion(rotvec_deg, t, c):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = np.asarray(t) + c - T[:3, :3] @ c
    return T


def test_icp_held_takes_back_the_free_motion_and_holds_the_rest():
    """Points of a box moved by a turn about y and a shift are registered back with every component free;
    with the turn about z held, a motion without one is taken back and the held turn stays exactly as it
    came."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    target, normals, _ = _box_faces(rng, n=3000)
    src, _, _ = _box_faces(np.random.default_rng(4), n=300)
    c = np.array([0.0, -60.0, 0.0])
    off = _motion([1.0, 3.0, 0.0], [2.0, -3.0, 1.5], c)
    moved = src @ off[:3, :3].T + off[:3, 3]
    T, fitness = icp_held(moved, target, normals, pivot=c, max_distance=10.0)
    back = moved @ T[:3, :3].T + T[:3, 3]
    assert fitness == 1.0 and np.abs(back - src).max() < 0.05
    T, _ = icp_held(moved, target, normals, free=(True, True, False, True, True, True), pivot=c, max_distance=10.0)
    back = moved @ T[:3, :3].T + T[:3, 3]
    assert np.abs(back - src).max() < 0.05
    # a turn about z in the motion: held, it stays in the result whole
    off = _motion([0.0, 2.0, 1.5], [1.0, 1.0, 0.0], c)
    moved = src @ off[:3, :3].T + off[:3, 3]
    T, _ = icp_held(moved, target, normals, free=(True, True, False, True, True, True), pivot=c, max_distance=10.0)
    assert abs(Rotation.from_matrix(T[:3, :3]).as_rotvec()[2]) < 1e-4  # held to second order (composed steps)
    with pytest.raises(KneeInputError, match="six"):
        icp_held(moved, target, normals, free=(True, False))


def test_icp_held_is_the_best_fit_with_the_held_rotation_fixed():
    """The held fit against an independent solve: the box's points turned 1.5 deg about z (held) and
    shifted; scipy's least squares on the exact distances to each point's own face, over the five free
    components, gives the translation the held ICP must reach. Fitting all six and dropping the turn
    about z afterwards (about the pivot) leaves a different one, which this catches."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    target, normals, _ = _box_faces(rng, n=4000)
    src, src_n, src_d = _box_faces(np.random.default_rng(6), n=300)
    c = np.array([0.0, -80.0, 0.0])  # the pivot below the box, as the knee's centre below the thigh
    off = _motion([0.5, -1.0, 1.5], [1.0, 2.0, -1.0], c)
    moved = src @ off[:3, :3].T + off[:3, 3]

    def residual(x):
        T = _motion(np.r_[x[:2], 0.0], x[2:], c)
        p = moved @ T[:3, :3].T + T[:3, 3]
        return np.einsum("ij,ij->i", p, src_n) - src_d

    x = least_squares(residual, np.zeros(5), xtol=1e-12, ftol=1e-12).x
    T, _ = icp_held(moved, target, normals, free=(True, True, False, True, True, True), pivot=c, max_distance=10.0)
    np.testing.assert_allclose(np.degrees(Rotation.from_matrix(T[:3, :3]).as_rotvec()[:2]), x[:2], atol=0.05)
    np.testing.assert_allclose(T[:3, :3] @ c + T[:3, 3] - c, x[2:], atol=0.05)
    # fitted free and the turn dropped afterwards: the knee's centre is elsewhere
    T_all, _ = icp_held(moved, target, normals, pivot=c, max_distance=10.0)
    assert np.linalg.norm((T_all[:3, :3] @ c + T_all[:3, 3] - c) - x[2:]) > 0.5


def test_closest_on_faces_gives_the_distances_gradient_and_changes_continuously():
    """A cube of side 20: above a face's inside, the closest point is the point's foot and the normal the
    face's; beyond an edge, the closest point is on the edge and the normal points from it to the point (the
    distance's gradient, the same whichever of the edge's two faces is taken as nearest); crossing from one
    region to the other, the normal turns continuously (closed forms)."""
    cube = trimesh.creation.box(extents=[20.0, 20.0, 20.0])
    q = SurfaceQuery.of(cube)
    c, n = q.closest_on_faces(np.array([[3.0, -2.0, 14.0]]))  # above the top face
    np.testing.assert_allclose(c, [[3.0, -2.0, 10.0]], atol=1e-12)
    np.testing.assert_allclose(n, [[0.0, 0.0, 1.0]], atol=1e-12)
    c, n = q.closest_on_faces(np.array([[14.0, 1.0, 13.0]]))  # beyond the edge x = z = 10
    np.testing.assert_allclose(c, [[10.0, 1.0, 10.0]], atol=1e-12)
    np.testing.assert_allclose(n, [[0.8, 0.0, 0.6]], atol=1e-12)
    # a point on the bisector of that edge, equally near both faces: the bisector's direction
    c, n = q.closest_on_faces(np.array([[13.0, 4.0, 13.0]]))
    np.testing.assert_allclose(n, [[np.sqrt(0.5), 0.0, np.sqrt(0.5)]], atol=1e-12)
    # from above the top face's inside to beyond its edge: the normal turns by about as much as the point moves
    x = np.linspace(9.9, 10.1, 41)
    _, n = q.closest_on_faces(np.column_stack([x, np.zeros_like(x), np.full_like(x, 15.0)]))
    assert np.all(np.linalg.norm(np.diff(n, axis=0), axis=1) < 0.01)
    np.testing.assert_allclose(n[0], [0.0, 0.0, 1.0], atol=1e-12)
    assert n[-1][0] > 0.0
    # what the springs of the surface phase pair with: the nearest face, the closest point on it, the face's own
    # normal (beyond the edge too) and weights that rebuild the closest point from the face's corners
    p = np.array([[3.0, -2.0, 14.0], [14.0, 1.0, 13.0]])
    face, c, n, w = q.on_nearest_faces(p)
    np.testing.assert_allclose(c, [[3.0, -2.0, 10.0], [10.0, 1.0, 10.0]], atol=1e-12)
    np.testing.assert_allclose(np.einsum("pi,pij->pj", w, cube.vertices[cube.faces[face]]), c, atol=1e-12)
    np.testing.assert_allclose(n, cube.face_normals[face], atol=1e-12)
    assert np.all(w >= -1e-12) and np.allclose(w.sum(axis=1), 1.0)
    np.testing.assert_allclose(n[0], [0.0, 0.0, 1.0], atol=1e-12)


def test_icp_held_to_surface_places_one_side_of_a_curved_surface_back_exactly():
    """Points on the side of an ellipsoid a camera sees, moved by a turn of 2.7 deg and a shift of 1 mm: paired
    with the surface's own closest points they come back to the surface's own places (1e-4 mm), every
    component free and with a rotation held. Paired with the nearest of 1,000 samples of the same surface
    (about 3.5 mm apart), the planes lean the same way over one side and leave them over 0.1 mm off, which
    is what the pairing on the surface is for."""
    from scipy.spatial.transform import Rotation

    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    m.apply_scale([40.0, 25.0, 20.0])
    src, f = trimesh.sample.sample_surface(m, 3000, seed=1)
    src = src[m.face_normals[f] @ np.array([0.3, 0.2, 1.0]) > 0.2]
    c = np.array([0.0, -10.0, 0.0])
    off = _motion([2.0, -1.0, 1.5], [0.5, -0.3, 0.8], c)
    moved = src @ off[:3, :3].T + off[:3, 3]
    surface = SurfaceQuery.of(m)
    T, fitness = icp_held_to_surface(moved, surface, pivot=c, max_distance=5.0)
    assert fitness == 1.0
    assert np.abs(moved @ T[:3, :3].T + T[:3, 3] - src).max() < 1e-4
    # the turn about z held where the motion has none: the rest is taken back, exactly
    off = _motion([2.0, -1.0, 0.0], [0.5, -0.3, 0.8], c)
    moved = src @ off[:3, :3].T + off[:3, 3]
    T, _ = icp_held_to_surface(moved, surface, free=(True, True, False, True, True, True), pivot=c, max_distance=5.0)
    assert np.abs(moved @ T[:3, :3].T + T[:3, 3] - src).max() < 1e-3
    samples, face = trimesh.sample.sample_surface(m, 1000, seed=0)
    T, _ = icp_held(moved, samples, m.face_normals[face], pivot=c, max_distance=5.0)
    assert np.abs(moved @ T[:3, :3].T + T[:3, 3] - src).max() > 0.1
    with pytest.raises(KneeInputError, match="six"):
        icp_held_to_surface(moved, surface, free=(True, False))


def _pose_about(T, c) -> np.ndarray:
    """A small transform (4, 4) as a rotation vector about ``c`` (rad) and the translation that goes with it."""
    return np.r_[Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3] + T[:3, :3] @ c - c]


def test_a_surface_fits_covariance_is_the_spread_of_fits_to_noisy_points():
    """The Laplace covariance of a point-to-plane fit against Monte Carlo: points on the side of an ellipsoid a
    camera sees, each moved along the surface's normal by independent noise of 0.5 mm, fitted back (every
    component free, about a pivot off the centre) in 60 draws. The spread of the six components is the
    covariance's (each sd within 30 %: an estimate from 60 draws is within about 9 % of its own, and a covariance
    off by the points' variance or the pivot is off by far more), and the slide along a cylinder's axis, which
    its points cannot fix, comes out unbounded (and the turn about it, which only its facets show, ten thousand
    times as uncertain as the turns across it)."""
    from knee.foundations.pointclouds import surface_fit_covariance

    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    m.apply_scale([40.0, 25.0, 20.0])
    pts, f = trimesh.sample.sample_surface(m, 1500, seed=2)
    keep = m.face_normals[f] @ np.array([0.3, 0.2, 1.0]) > 0.2
    pts, nrm = pts[keep], m.face_normals[f][keep]
    c = np.array([5.0, -10.0, 3.0])
    surface = SurfaceQuery.of(m)
    cov, n = surface_fit_covariance(pts, surface, 0.5, pivot=c, max_distance=5.0)
    assert n == len(pts) and np.allclose(cov, cov.T)
    rng = np.random.default_rng(3)
    fits = []
    for _ in range(60):
        noisy = pts + nrm * rng.normal(0.0, 0.5, (len(pts), 1))
        T, _ = icp_held_to_surface(noisy, surface, pivot=c, max_distance=5.0, iterations=10)
        fits.append(_pose_about(T, c))
    sd = np.std(fits, axis=0, ddof=1)
    np.testing.assert_allclose(sd, np.sqrt(np.diag(cov)), rtol=0.3)
    # twice the noise, twice the sd
    np.testing.assert_allclose(surface_fit_covariance(pts, surface, 1.0, pivot=c, max_distance=5.0)[0], 4 * cov)
    # a cylinder along y: the turn about its axis moves no point's distance
    cyl = trimesh.creation.cylinder(radius=20.0, height=120.0, sections=256)
    cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1.0, 0.0, 0.0]))
    p, f = trimesh.sample.sample_surface(cyl, 2000, seed=4)
    side = np.abs(cyl.face_normals[f][:, 1]) < 0.5
    cov, _ = surface_fit_covariance(p[side], SurfaceQuery.of(cyl), 0.5, max_distance=5.0)
    assert cov[4, 4] >= 1e12 and cov[3, 3] < 1e-2 and cov[5, 5] < 1e-2
    assert cov[1, 1] > 1e4 * max(cov[0, 0], cov[2, 2])


def test_icp_recovers_a_rigid_offset(volunteer):
    """A flexed phantom skin seen by the oblique camera with noise; the same surface displaced by a
    known rigid motion is registered back."""
    from knee.foundations.conventions import joint_to_pose
    from knee.models.phantom import build_phantom

    ph = build_phantom(volunteer.params, shaft_length=100.0)
    tf, pf, _ = volunteer.solve(np.radians(30))
    skin = ph.skin(joint_to_pose(tf), joint_to_pose(pf))
    cam = _camera()
    rng = np.random.default_rng(1)
    clean = backproject(render_depth(skin.vertices, skin.faces, cam), cam.K, cam.T_world_cam)
    d = DepthNoise().apply(render_depth(skin.vertices, skin.faces, cam), rng)
    target = backproject(d, cam.K, cam.T_world_cam)[::7]
    Q = cardan_to_matrix(np.radians(4), np.radians(-3), np.radians(5))
    t = np.array([6.0, -4.0, 3.0])
    truth = clean[::11]  # the part of the model's surface the camera sees
    src = truth @ Q.T + t
    assert np.linalg.norm(src - truth, axis=1).mean() > 10.0
    T, fitness, rmse = icp(src, target)
    reg = src @ T[:3, :3].T + T[:3, 3]
    assert np.linalg.norm(reg - truth, axis=1).mean() < 0.5
    assert np.sqrt((SurfaceQuery.of(skin).signed_distance(reg) ** 2).mean()) < 0.3
    assert rmse < 1.5 and fitness > 0.9  # rmse: the depth noise (about 0.8 mm here)


def test_pixel_centres_lie_at_whole_pixel_coordinates_as_measured_intrinsics_state_them():
    """Intrinsics as OpenCV and librealsense give them: pixel (u, v)'s centre is at (u, v), so a point is
    seen at u = fx x / z + cx. Closed forms: a depth image's pixel back-projects to ((u - cx) z / fx,
    (v - cy) z / fy, z); a virtual camera's depth of the tilted plane z = a + b x at pixel (u, v) is
    a / (1 - b (u - cx) / fx), which a half-pixel shift of the principal point (the ray caster's own
    convention) would miss by about b a (z / fx) / 2 per pixel."""
    K = np.array([[500.0, 0.0, 31.5], [0.0, 480.0, 20.25], [0.0, 0.0, 1.0]])
    depth = np.zeros((40, 64))
    depth[7, 50] = 400.0
    np.testing.assert_allclose(backproject(depth, K), [[(50 - 31.5) * 400.0 / 500.0, (7 - 20.25) * 400.0 / 480.0,
                                                        400.0]])
    a, b = 400.0, 1.5  # the plane z = a + b x, steep enough that half a pixel changes the depth by ~0.5 mm
    plane = trimesh.Trimesh(vertices=[[-300.0, -300.0, a - 300 * b], [300.0, -300.0, a + 300 * b],
                                      [300.0, 300.0, a + 300 * b], [-300.0, 300.0, a - 300 * b]],
                            faces=[[0, 1, 2], [0, 2, 3]])
    cam = Camera(K=K, width=64, height=40, T_world_cam=np.eye(4))
    d = render_depth(plane.vertices, plane.faces, cam)
    u = np.arange(64)[None, :].repeat(40, axis=0)
    expected = a / (1.0 - b * (u - K[0, 2]) / K[0, 0])
    np.testing.assert_allclose(d, expected, rtol=1e-5)
    # and the rendered image back-projects onto the plane
    p = backproject(d, K)
    np.testing.assert_allclose(p[:, 2], a + b * p[:, 0], atol=1e-3)


def test_dominant_planes_are_a_tables_not_a_legs():
    """A cylinder (a leg, 60 mm radius) in front of a large plane (a table) holding most of the points: the
    plane's points are found (and only they, bar the few of the cylinder within 5 mm of it); the cylinder
    alone has no dominant plane."""
    from knee.foundations.pointclouds import dominant_planes

    rng = np.random.default_rng(0)
    t, y = rng.uniform(0, 2 * np.pi, 20000), rng.uniform(-150, 150, 20000)
    leg = np.column_stack([60.0 * np.cos(t), y, 400.0 + 60.0 * np.sin(t)])
    g = rng.uniform(-400, 400, size=(60000, 2))
    table = np.column_stack([g[:, 0], g[:, 1], np.full(len(g), 470.0)]) + rng.normal(0, 1.0, (len(g), 3))
    on = dominant_planes(np.vstack([leg, table]))
    assert on[len(leg):].mean() > 0.99
    assert on[:len(leg)].mean() < 0.02  # the cylinder's points within 5 mm of the table's plane
    assert not dominant_planes(leg).any()
    assert dominant_planes(table).all() and not dominant_planes(table[:2]).any()  # a plane alone; too few points


def test_connected_parts_split_a_cloud_where_it_has_gaps():
    """Two cylinders (legs) 60 mm apart between surfaces, one with more points: two pieces, the larger
    labelled 0; a line of points bridging them, each within the gap of the next, joins them into one; a
    point off on its own is a piece of its own. Labels checked against the points' known origin."""
    from knee.foundations.pointclouds import connected_parts

    def leg(length, x):  # points 5 mm apart on a cylinder of 60 mm radius
        t, y = np.meshgrid(np.linspace(0, 2 * np.pi, 76)[:-1], np.arange(0.0, length + 1e-9, 5.0))
        return np.column_stack([x + 60.0 * np.cos(t.ravel()), y.ravel(), 400.0 + 60.0 * np.sin(t.ravel())])

    a, b = leg(200.0, 0.0), leg(300.0, 180.0)
    lab = connected_parts(np.vstack([a, b]), 10.0)
    assert set(lab[:len(a)]) == {1} and set(lab[len(a):]) == {0}
    bridge = np.column_stack([np.linspace(60.0, 120.0, 13), np.zeros(13), np.full(13, 400.0)])  # 5 mm apart
    lone = np.array([[0.0, 500.0, 400.0]])
    lab = connected_parts(np.vstack([a, b, bridge, lone]), 10.0)
    assert set(lab[:-1]) == {0} and lab[-1] == 1

def test_near_cloud_passes_every_point_within_its_reach_and_few_beyond():
    """A one-sided cloud (half a cylinder of 60 mm radius, 1 mm apart) with a far outlier, and query points
    around the whole cylinder, on the cells' faces too (the cloud's own coordinates shifted by whole reaches):
    every query with a cloud point within the reach (brute force) passes; those beyond twice the reach's
    diagonal cannot; the unseen side (over 100 mm off) is left out. Bad reach or cloud: one-line errors."""
    from knee.foundations.pointclouds import NearCloud

    t, y = np.meshgrid(np.linspace(0.0, np.pi, 190), np.arange(0.0, 100.0, 1.0))
    cloud = np.column_stack([60.0 * np.cos(t.ravel()), y.ravel(), 60.0 * np.sin(t.ravel())])
    cloud = np.vstack([cloud, [[5000.0, -3000.0, 8000.0]]])  # an outlier far off costs no cells between
    rng = np.random.default_rng(2)
    q = np.vstack([rng.uniform([-90, -30, -90], [90, 130, 90], (20000, 3)),
                   cloud[rng.choice(len(cloud), 2000)] + 10.0 * rng.integers(-2, 3, (2000, 3))])
    near = NearCloud(cloud, 10.0)
    mask = near(q)
    d = cKDTree(cloud).query(q)[0]
    assert mask[d < 10.0].all()
    assert not mask[d > 2.0 * np.sqrt(3.0) * 10.0 + 1e-6].any()
    assert not mask[(q[:, 2] < -40.0) & (d > 40.0)].any()
    assert mask[d < 10.0].size > 2000 and (~mask).sum() > 5000
    with pytest.raises(KneeInputError, match="reach must be positive"):
        NearCloud(cloud, 0.0)
    with pytest.raises(KneeInputError, match="non-empty"):
        NearCloud(np.zeros((0, 3)), 10.0)


@pytest.fixture(scope="module")
def flying_scene(knee_like):
    """The knee seen by a depth camera with its noise and dropout, a wall 300 mm behind it, and flying pixels:
    blends of the two (a depth drawn evenly between them) on half the pixels of a band two pixels wide on
    either side of the knee's outline. (camera, the clean render, the noisy knee alone, the image, the
    flying pixels (those over 2 mm from both surfaces), the knee's silhouette)."""
    cam = _camera()
    clean = render_depth(knee_like.vertices, knee_like.faces, cam)
    rng = np.random.default_rng(4)
    knee = DepthNoise().apply(clean, rng)
    on = knee > 0
    leg = ndimage.binary_closing(on, np.ones((3, 3), bool), iterations=2) & ndimage.binary_fill_holes(on)
    ring = ndimage.binary_dilation(leg, iterations=2) & ~ndimage.binary_erosion(leg, iterations=2)
    front = ndimage.grey_dilation(np.where(on, knee, 0.0), size=7)  # the knee's depth near each ring pixel
    blend = ring & (rng.random(knee.shape) < 0.5) & (front > 0)
    d = np.where(leg, knee, 700.0)
    d[blend] = front[blend] + rng.random(blend.sum()) * (700.0 - front[blend])
    flying = blend & (np.abs(d - front) > 2.0) & (np.abs(d - 700.0) > 2.0)
    assert flying.sum() > 1000
    return cam, clean, knee, d, flying, leg


def _mixed_pixels_pixel_by_pixel(d, K, footprints, support):
    """The definition of a flying pixel, pixel by pixel: seen, stepping from a seen neighbour by more than
    ``footprints`` footprints of the nearer, and continued by fewer than ``support`` seen neighbours."""
    f = 0.5 * (K[0, 0] + K[1, 1])
    h, w = d.shape
    out = np.zeros(d.shape, bool)
    for v in range(h):
        for u in range(w):
            if not d[v, u] > 0:
                continue
            worst, fine = 0.0, 0
            for dv in (-1, 0, 1):
                for du in (-1, 0, 1):
                    y, x = v + dv, u + du
                    if (dv or du) and 0 <= y < h and 0 <= x < w and d[y, x] > 0:
                        step = abs(d[y, x] - d[v, u]) / (min(d[y, x], d[v, u]) / f)
                        worst, fine = max(worst, step), fine + (step <= footprints)
            out[v, u] = worst > footprints and fine < support
    return out


@pytest.mark.parametrize("footprints, support", [(25.0, 3), (3.0, 2), (25.0, 9)])
def test_mixed_pixels_as_defined_pixel_by_pixel(footprints, support):
    """The whole-image shifts (each neighbour pair once, within the seen pixels' box) give what the definition
    gives pixel by pixel, at the image's borders, beside holes and across steps of either sign: a wrong
    shift, a pair counted for one pixel only or a box cut one pixel short would differ."""
    rng = np.random.default_rng(3)
    K = np.array([[500.0, 0.0, 12.0], [0.0, 480.0, 9.0], [0.0, 0.0, 1.0]])
    d = 400.0 + 40.0 * rng.random((18, 23))
    d[:, 11:] += 300.0                                   # a depth edge down the middle
    d[rng.random(d.shape) < 0.15] = 0.0                 # dropout
    d[:2] = 0.0                                          # unseen rows and a column: the seen box is smaller
    d[:, -1] = 0.0
    d[7, 11] = 550.0                                     # a blend on the edge
    expected = _mixed_pixels_pixel_by_pixel(d, K, footprints, support)
    assert expected.any() and not expected.all()
    assert np.array_equal(mixed_pixels(d, K, footprints, support), expected)
    assert np.array_equal(mixed_pixels(d[:, ::-1], K, footprints, support), expected[:, ::-1])
    assert not mixed_pixels(np.zeros((4, 5)), K).any()


def test_mixed_pixels_are_the_blends_at_depth_edges_not_a_steep_surface_noise_or_holes(flying_scene):
    """A depth camera's flying pixels, blends of the knee in front and a wall 300 mm behind it in a band two
    pixels wide around the knee's outline, are found (all but a few) and left out, so hardly a point lies
    between the knee and the wall; the knee's own pixels stay, its outline's too (next to the blends, but
    continued by the knee's own), and so does its own occluding edge (the bump over the capsule), even with
    the noise model's depth noise and dropout holes (a stereo camera's too: correlated, in blobs), and so do
    those of a plane seen 80 deg from face-on, whose neighbouring pixels step tan 80 deg = 5.7 pixel
    footprints apart (a steep surface, not an edge)."""
    cam, clean, knee, d, flying, leg = flying_scene
    on = knee > 0
    own = ndimage.binary_dilation(mixed_pixels(clean, cam.K), iterations=2)  # the bump's occluding edge
    assert own.sum() < 0.01 * (clean > 0).sum()
    m = mixed_pixels(d, cam.K)
    assert m[flying].mean() > 0.95
    assert not (m & ndimage.binary_erosion(leg, iterations=4) & on & ~own).any()  # the knee away from edges
    outline = on & leg & ~flying & ~ndimage.binary_erosion(leg, iterations=3)
    # its outline, beside the blends (inside the band, half its pixels blends): mostly kept, where leaving
    # out every pixel at a step (no support asked) would lose nearly all of it
    assert outline.sum() > 2000 and m[outline].mean() < 0.2
    assert mixed_pixels(d, cam.K, support=9)[outline].mean() > 0.8
    assert not m[ndimage.binary_erosion(~leg, iterations=4)].any()  # the wall
    # nothing between the knee and the wall in what the loader gives
    pts = backproject(d, cam.K, drop_mixed=True)
    kept_between = (pts[:, 2] > knee[on].max() + 5.0) & (pts[:, 2] < 695.0)
    assert kept_between.sum() < 0.05 * flying.sum()
    assert len(backproject(d, cam.K)) == int((d > 0).sum())  # kept where not asked
    # the knee alone, with its noise and holes: nothing but its own occluding edge and, where the noise meets
    # the outline's grazing rays, a few of its outermost pixels
    alone = mixed_pixels(knee, cam.K) & ~own
    assert alone.sum() < 20 and not (alone & ndimage.binary_erosion(clean > 0, iterations=2)).any()
    # and with a stereo camera's errors, correlated over 3 pixels at a D435's rated 1.6 mm at 400 mm, its lost
    # pixels in blobs (a blob's rim steps to no seen neighbour: not an edge to blend across)
    stereo = DepthNoise(sigma_at_ref=1.6, correlation_px=3.0, hole_px=4.0).apply(clean, np.random.default_rng(6))
    alone = mixed_pixels(stereo, cam.K) & ~own
    assert (stereo[clean > 0] == 0).sum() > 1000
    assert alone.sum() < 20 and not (alone & ndimage.binary_erosion(clean > 0, iterations=2)).any()
    # a plane turned 80 deg from the camera's axis: a steep surface, every pixel kept
    plane = trimesh.creation.box(extents=[400, 400, 1]).apply_transform(
        trimesh.transformations.rotation_matrix(np.radians(80.0), [0, 1, 0]))
    pc = Camera.looking_at([0, 0, 400.0], [0, 0, 0], up=[0, 1, 0], width=160, height=120)
    dp = render_depth(plane.vertices, plane.faces, pc)
    inside = ndimage.binary_erosion(dp > 0, iterations=2)
    assert inside.sum() > 100 and not mixed_pixels(dp, pc.K)[inside].any()


def test_sparse_points_are_a_clouds_flying_pixels_whatever_its_density_or_unit(flying_scene):
    """The same flying pixels in a cloud (no pixel grid to tell neighbours): nearly all are found by their
    distance to their 8th nearest neighbour, under 1 % of the knee's and the wall's points with them; the
    cloud in metres or thinned to 3 mm voxels is judged against itself alike (its knee kept)."""
    from knee.foundations.pointclouds import sparse_points, voxel_downsample

    cam, clean, knee, d, flying, leg = flying_scene
    pts = backproject(d, cam.K)
    fly = flying[d > 0]  # back-projection keeps the seen pixels in row order
    s = sparse_points(pts)
    assert s[fly].mean() > 0.97
    assert s[~fly & ~(ndimage.binary_dilation(flying, iterations=2)[d > 0])].mean() < 0.01
    np.testing.assert_array_equal(sparse_points(pts / 1000.0), s)
    thin = voxel_downsample(backproject(knee, cam.K), 3.0)
    assert sparse_points(thin).mean() < 0.01


def test_the_noise_models_flying_pixels_blend_the_surfaces_at_each_outline(knee_like):
    """``DepthNoise(flying=p)``: the noise and the dropout are those drawn without it; about p of the pixels
    within two of the knee's outline or its own occluding edge (on either side) return a blend, a depth
    between the nearer surface's and the one behind (300 mm behind where the render has none), none
    elsewhere; the loader's filter finds most of those that are far from both surfaces."""
    cam = _camera()
    clean = render_depth(knee_like.vertices, knee_like.faces, cam)
    plain = DepthNoise().apply(clean, np.random.default_rng(2))
    d = DepthNoise(flying=0.5).apply(clean, np.random.default_rng(2))
    blend = d != plain
    on = clean > 0
    outline = on & ~ndimage.binary_erosion(on, np.ones((3, 3), bool))  # next to an unseen pixel, diagonals too
    steps = on & (ndimage.maximum_filter(clean, size=3) - ndimage.minimum_filter(np.where(on, clean, np.inf),
                                                                                 size=3) > 20.0)
    near_edges = ndimage.binary_dilation(outline | steps, iterations=2)  # the outline, the bump's edge
    assert blend.sum() > 1000 and not blend[~near_edges].any()
    assert 0.4 < blend[near_edges].mean() < 0.55
    front = ndimage.minimum_filter(np.where(on, clean, np.inf), size=5)
    assert np.all(d[blend] >= front[blend] - 1e-9) and np.all(d[blend] <= front[blend] + 300.0 + 1e-9)
    assert np.median(d[blend & ~ndimage.binary_dilation(steps, iterations=4)] - front[blend & ~ndimage.binary_dilation(
        steps, iterations=4)]) == pytest.approx(150.0, abs=15.0)  # even over the 300 mm behind the outline
    far = blend & (d - front > 10.0) & (front + 300.0 - d > 10.0)
    assert mixed_pixels(d, cam.K)[far].mean() > 0.9


def test_intrinsics_for_another_resolution_are_questioned_and_a_centred_principal_point_is_not():
    """A depth camera's principal point lies near its image's centre: intrinsics stated for 640x480 on a
    1280x720 image (the principal point a quarter of the width off) are questioned, with how far off; the
    image's own, or ones off centre within the allowed share, are not."""
    def K(cx, cy, f=600.0):
        return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])

    assert principal_point_note(K(639.5, 359.5), (720, 1280)) is None  # the exact centre (pixel centres whole)
    assert principal_point_note(K(655.0, 350.0), (720, 1280)) is None  # a real camera's few pixels off
    note = principal_point_note(K(319.5, 239.5), (720, 1280))
    assert note is not None and "(319.5, 239.5)" in note and "25 % of the width" in note and "17 % of the height" in note
    # the share is measured each way from the centre, on each axis apart
    share = PRINCIPAL_POINT_SHARE
    assert principal_point_note(K(639.5 + (share - 0.01) * 1280, 359.5), (720, 1280)) is None
    assert principal_point_note(K(639.5, 359.5 - (share + 0.01) * 720), (720, 1280)) is not None
    assert principal_point_note(K(639.5 - (share + 0.01) * 1280, 359.5), (720, 1280)) is not None
