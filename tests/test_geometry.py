"""Geometry helpers against closed forms."""

import numpy as np
import pytest

from knee.foundations.conventions import cardan_to_matrix
from knee.foundations.errors import KneeInputError
from knee.foundations.geometry import (
    fit_plane,
    fit_sphere,
    least_varying_pair,
    principal_axes,
    rigid_register,
)


def test_sphere_fit_on_a_noisy_cap():
    """A condyle-like cap (60 degrees around the pole), 0.05 mm noise: centre and radius recovered."""
    rng = np.random.default_rng(0)
    th = np.arccos(rng.uniform(np.cos(np.radians(60)), 1, 2000))
    ph = rng.uniform(0, 2 * np.pi, 2000)
    d = np.column_stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    c0, r0 = np.array([1.75, -1.67, 30.09]), 24.0
    p = c0 + r0 * d + rng.normal(0, 0.05, (2000, 3))
    c, r, rms = fit_sphere(p)
    assert np.linalg.norm(c - c0) < 0.05 and abs(r - r0) < 0.05
    assert rms == pytest.approx(0.05, rel=0.1)
    c_alg, r_alg, _ = fit_sphere(p, refine=False)
    assert np.linalg.norm(c_alg - c0) < 0.5  # the algebraic start is close already


def test_plane_fit_and_principal_axes():
    rng = np.random.default_rng(1)
    n0 = np.array([0.2, 0.9, 0.1])
    n0 /= np.linalg.norm(n0)
    u = np.cross(n0, [1, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n0, u)
    p = np.array([5.0, -3.0, 2.0]) + rng.normal(0, 20, (500, 1)) * u + rng.normal(0, 5, (500, 1)) * v
    c, n, rms = fit_plane(p + rng.normal(0, 0.01, p.shape))
    assert abs(abs(n @ n0) - 1) < 1e-6 and rms < 0.02
    _, axes = principal_axes(p)
    assert abs(abs(axes[0] @ u) - 1) < 1e-3 and abs(abs(axes[2] @ n0) - 1) < 1e-6


def test_rigid_registration_and_fre():
    rng = np.random.default_rng(2)
    src = rng.normal(0, 40, (7, 3))
    R = cardan_to_matrix(0.3, -0.2, 1.0)
    t = np.array([10.0, -5.0, 3.0])
    T, fre = rigid_register(src, src @ R.T + t)
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], t, atol=1e-10)
    assert fre.max() < 1e-10
    noisy = src @ R.T + t + rng.normal(0, 0.5, src.shape)
    _, fre = rigid_register(src, noisy)
    assert 0.1 < fre.mean() < 1.0
    with pytest.raises(KneeInputError, match="collinear"):
        rigid_register(np.outer(np.arange(5.0), [1, 2, 3]), np.outer(np.arange(5.0), [1, 2, 3]))
    with pytest.raises(KneeInputError, match="pair up"):
        rigid_register(src, src[:5])


def test_least_varying_pair_finds_the_planted_link():
    """A general spatial motion built so that one planted pair (a*, b*) keeps length 20 exactly; among
    random candidates the search returns it."""
    rng = np.random.default_rng(3)
    F = 30
    a = rng.normal(0, 10, (50, 3))
    b = rng.normal(0, 10, (60, 3))
    a_s, b_s = a[17], b[41]
    s_ = np.linspace(0, 1, F)
    R = cardan_to_matrix(1.5 * s_, 0.3 * np.sin(3 * s_), 0.4 * s_ ** 2)
    u = np.column_stack([np.cos(2 * s_), np.sin(2 * s_), 0.3 * s_])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    poses = np.tile(np.eye(4), (F, 1, 1))
    poses[:, :3, :3] = R
    poses[:, :3, 3] = a_s + 20.0 * u - np.einsum("fij,j->fi", R, b_s)
    i, j, L, sd = least_varying_pair(a, b, poses, chunk=16)
    assert (i, j) == (17, 41) and sd < 1e-12 and np.allclose(L, 20.0)


def test_bad_point_arrays_are_named():
    with pytest.raises(KneeInputError, match=r"sphere fit: points must be an \(n, 3\) array"):
        fit_sphere(np.zeros((10, 2)))
    with pytest.raises(KneeInputError, match="sphere fit: needs at least 4 points"):
        fit_sphere(np.zeros((3, 3)))
    with pytest.raises(KneeInputError, match="plane fit: points must be finite"):
        fit_plane(np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]))


def test_decimation_keeps_a_closed_volume_or_says_it_cannot():
    """A sphere coarsened to 200 faces stays closed around nearly its volume; taken down to one face (nothing
    closed) or two (two triangles back to back: closed, but empty) it is refused in one line naming what was
    coarsened, rather than handed on as a skin with no inside."""
    import trimesh

    from knee.foundations.surfaces import decimated

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    coarse = decimated(sphere, 200, "skin")
    assert coarse.is_volume and len(coarse.faces) <= 200
    assert coarse.volume == pytest.approx(sphere.volume, rel=0.05)
    assert decimated(sphere, 10 * len(sphere.faces)).faces.shape == sphere.faces.shape  # under the count: as given
    for faces in (1, 2):
        with pytest.raises(KneeInputError, match=r"^the skin could not be coarsened into a closed surface"):
            decimated(sphere, faces, "skin")


def _min_angles(mesh):
    t = mesh.triangles
    e = [t[:, (i + 1) % 3] - t[:, i] for i in range(3)]
    cos = [np.einsum("ij,ij->i", -e[i - 1], e[i]) / (np.linalg.norm(e[i - 1], axis=1) * np.linalg.norm(e[i], axis=1))
           for i in range(3)]
    return np.degrees(np.arccos(np.clip(np.max(cos, axis=0), -1.0, 1.0)))


def test_bisection_to_length_keeps_the_surface_closed_and_its_faces_shaped():
    """A capsule's sides given as long thin faces (a cylinder of 12 sections, 300 mm long: faces 300 mm by 26 mm)
    bisected to 15 mm edges: no edge longer, the same closed surface (every vertex kept, every new one on an old
    edge's midpoint, the volume exact, the Euler characteristic of a sphere, the winding consistent), and no
    angle below half the smallest the mesh had (longest-edge bisection's bound; splitting every edge in four,
    or bisecting any other edge than the longest, makes needles of these faces). An edge already short enough
    is left as it was."""
    import trimesh

    from knee.foundations.surfaces import SurfaceQuery, bisected_to_length

    tube = trimesh.creation.cylinder(radius=50.0, height=300.0, sections=12)
    out = bisected_to_length(tube, 15.0)
    assert out.edges_unique_length.max() <= 15.0
    assert len(out.vertices) > 10 * len(tube.vertices)
    np.testing.assert_array_equal(out.vertices[: len(tube.vertices)], tube.vertices)
    assert out.is_watertight and out.is_winding_consistent and out.euler_number == 2
    assert out.volume == pytest.approx(tube.volume, rel=1e-12)
    assert np.abs(SurfaceQuery.of(tube).signed_distance(out.vertices)).max() < 1e-3  # single precision
    assert _min_angles(out).min() >= 0.5 * _min_angles(tube).min() - 1e-9
    same = bisected_to_length(tube, 1000.0)
    np.testing.assert_array_equal(same.faces, tube.faces)
    for bad in (0.0, -5.0, float("nan"), "15"):  # each round would split every edge: refused in one line
        with pytest.raises(KneeInputError, match=r"^the longest edge to bisect to must be a positive length"):
            bisected_to_length(tube, bad)
