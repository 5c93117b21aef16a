"""The depth input: virtual camera, noise, back-projection, files, ICP."""

import numpy as np
import open3d as o3d
import pytest
import trimesh

from knee.foundations.conventions import cardan_to_matrix
from knee.foundations.errors import KneeInputError
from knee.foundations.pointclouds import (
    backproject,
    icp,
    load_depth_image,
    load_point_cloud,
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


def test_noise_model_statistics():
    rng = np.random.default_rng(0)
    d = np.full((400, 400), 400.0)
    noisy = DepthNoise().apply(d, rng)
    kept = noisy > 0
    assert abs(1 - kept.mean() - 0.02) < 0.003
    assert np.std(noisy[kept] - 400.0) == pytest.approx(1.0, rel=0.02)
    far = DepthNoise().apply(np.full((200, 200), 800.0), rng)
    assert np.std(far[far > 0] - 800.0) == pytest.approx(4.0, rel=0.03)  # quadratic in depth


def test_depth_image_and_point_cloud_files(tmp_path, knee_like):
    cam = _camera()
    d = render_depth(knee_like.vertices, knee_like.faces, cam)
    png = tmp_path / "depth.png"
    o3d.io.write_image(str(png), o3d.geometry.Image(np.round(d).astype(np.uint16)))
    pts = load_depth_image(png, cam.K, cam.T_world_cam)
    assert np.abs(SurfaceQuery.of(knee_like).signed_distance(pts)).max() < 1.0  # mm rounding
    np.save(tmp_path / "depth.npy", d)
    assert len(load_depth_image(tmp_path / "depth.npy", cam.K)) == (d > 0).sum()
    ply = tmp_path / "cloud.ply"
    o3d.io.write_point_cloud(str(ply), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    np.testing.assert_allclose(load_point_cloud(ply), pts, atol=1e-3)
    with pytest.raises(KneeInputError, match="no such"):
        load_point_cloud(tmp_path / "missing.ply")
    with pytest.raises(KneeInputError, match="intrinsics"):
        backproject(d, np.eye(2))
    with pytest.raises(KneeInputError, match="2-D"):
        backproject(d.ravel(), cam.K)
    with pytest.raises(KneeInputError, match="no such depth image"):
        load_depth_image(tmp_path / "missing.png", cam.K)
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n")
    with pytest.raises(KneeInputError, match="no points"):
        load_point_cloud(empty)
    with pytest.raises(KneeInputError, match="coincide"):
        Camera.looking_at([1, 2, 3], [1, 2, 3])
    with pytest.raises(KneeInputError, match="parallel"):
        Camera.looking_at([0, 0, 0], [0, 10, 0], up=[0, 1, 0])


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
