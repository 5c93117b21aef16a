"""External forces and the standard case's target points."""

import numpy as np
import pytest
import scipy.sparse as sp

from knee.models.fem.forces import BoneForces, SurfaceForces


@pytest.fixture(scope="module")
def knee_model(volunteer):
    from knee.models.fem.scene import build_association_model

    return build_association_model(volunteer)


def test_bone_forces_directions_and_magnitudes(knee_model):
    m = knee_model
    bf = BoneForces(m.femur, m.tibia)
    f = bf.forces(m.grid.X)
    # the grid forces carry the applied totals (J^T preserves the resultant: weights sum to 1)
    assert np.linalg.norm(f.sum(axis=0)) == pytest.approx(
        np.linalg.norm(9000 * bf.directions["F1"] + 23000 * bf.directions["F2"] + 3000 * bf.directions["F3"]
                       + 6000 * bf.directions["F4"]), rel=1e-9)
    assert bf.directions["F4"][0] < -0.9      # posterior push on the tibial shaft: flexion
    assert bf.directions["F3"][1] < -0.9      # distal along the femur
    np.testing.assert_allclose(bf.directions["F1"], -bf.directions["F2"])
    held = BoneForces(m.femur, m.tibia, use_femur=False)
    assert np.linalg.norm(held.forces(m.grid.X).sum(axis=0)) == pytest.approx(6000.0, rel=1e-9)


def test_bone_forces_turn_with_the_bones_past_45_degrees(knee_model):
    """The whole knee turned 60 deg about the medio-lateral axis: each force turns with it. Picked against
    the rest axes themselves, the tibia's long axis (now 30 deg from the rest antero-posterior axis) would
    be taken for its antero-posterior one and F4 would push along the shaft."""
    from scipy.spatial.transform import Rotation

    m = knee_model
    bf = BoneForces(m.femur, m.tibia)
    bf.forces(m.grid.X)
    rest = dict(bf.directions)
    R = Rotation.from_euler("z", 60, degrees=True).as_matrix()
    c = m.grid.X.mean(axis=0)
    bf.forces((m.grid.X - c) @ R.T + c)
    for name in ("F1", "F2", "F3", "F4"):
        assert bf.directions[name] @ (R @ rest[name]) > 0.999, name


def test_surface_forces_and_the_adaptive_reference_distance(knee_model):
    m = knee_model
    skin = m.skin_vertices
    # depth points: the front half of the skin moved 3 mm anteriorly
    front = skin[skin[:, 0] > 0]
    sf = SurfaceForces(m.grid, skin, front + [3.0, 0, 0], k=2.0)
    f = sf.forces(m.grid.X)
    assert 0.2 < sf.within_fraction < 0.5                 # one-sided: less than half are within
    assert sf.reference == pytest.approx(10.0)            # so it grows, capped at 10 mm
    assert f.sum(axis=0)[0] > 0                           # pulled towards the points
    assert np.abs(f.sum(axis=0)[0] - 2.0 * 3.0 * sf.active.sum()) < 0.5 * 6.0 * sf.active.sum()
    all_pts = SurfaceForces(m.grid, skin, skin + [0.5, 0, 0], k=2.0)
    for _ in range(5):
        all_pts.forces(m.grid.X)
    assert all_pts.reference == pytest.approx(9.5)        # more than half within: shrinks 0.1 per step
    for _ in range(200):
        all_pts.forces(m.grid.X)
    assert all_pts.reference == pytest.approx(1.0)        # lower limit
    p = np.random.default_rng(0).normal(size=m.grid.X.shape)
    np.testing.assert_allclose(all_pts.matrix() @ p.ravel(), all_pts.apply(p).ravel(), atol=1e-9)


def test_surface_forces_search_only_near_the_cloud_and_find_the_same_springs(knee_model):
    """The forces, the active points and the stiffness with the search left to the points near the cloud
    equal those of a plain bounded search over every skin point, at every reference distance the phase
    passes through (a one-sided cloud: the skin's front, moved and roughened, so that skin points lie at
    every distance from it)."""
    from scipy.spatial import cKDTree

    m = knee_model
    skin = m.skin_vertices
    rng = np.random.default_rng(5)
    cloud = skin[skin[:, 0] > -5.0] + [4.0, 0.0, 0.0] + rng.normal(0.0, 2.0, (int((skin[:, 0] > -5.0).sum()), 3))
    sf = SurfaceForces(m.grid, skin, cloud, k=2.0)
    x = m.grid.X + rng.normal(0.0, 1.0, m.grid.X.shape)
    tree = cKDTree(cloud)
    p = sf.map.apply(x)
    for _ in range(3):
        ref = sf.reference
        d, j = tree.query(p, distance_upper_bound=ref)
        active = d < ref
        f = np.zeros_like(p)
        f[active] = 2.0 * (cloud[j[active]] - p[active])
        np.testing.assert_array_equal(sf.forces(x), sf.map.apply_transpose(f))
        np.testing.assert_array_equal(sf.active, active)
        assert 0 < active.sum() < len(p)
    sf.reference = 3.0
    d = tree.query(p, distance_upper_bound=3.0)[0]
    sf.forces(x)
    np.testing.assert_array_equal(sf.active, d < 3.0)


def test_surface_springs_spread_by_area_pull_a_skin_alike_however_finely_it_is_triangulated(knee_model):
    """The phantom's skin and the same surface split into four times as many faces, both 3 mm from a dense
    cloud (the fine skin moved along x): with springs spread by area, the pull on the grid (its resultant)
    is the same for both; with a spring per vertex, the fine skin pulls about four times as hard. The areas add up to the skin's; apply and matrix agree."""
    import trimesh

    from knee.models.fem.forces import SKIN_AREA_PER_SPRING_MM2, skin_point_areas

    m = knee_model
    coarse = trimesh.Trimesh(m.skin_vertices, m.skin_faces, process=False)
    fine = trimesh.Trimesh(*trimesh.remesh.subdivide(coarse.vertices, coarse.faces), process=False)
    cloud = trimesh.Trimesh(*trimesh.remesh.subdivide(fine.vertices, fine.faces)).vertices + [3.0, 0.0, 0.0]
    pulls = {}
    for name, skin in (("coarse", coarse), ("fine", fine)):
        a = skin_point_areas(skin.vertices, skin.faces)
        assert a.sum() == pytest.approx(skin.area, rel=1e-9)
        by_area = SurfaceForces(m.grid, skin.vertices, cloud, k=2.0, weights=a / SKIN_AREA_PER_SPRING_MM2)
        per_vertex = SurfaceForces(m.grid, skin.vertices, cloud, k=2.0)
        pulls[name] = (by_area.forces(m.grid.X).sum(axis=0)[0], per_vertex.forces(m.grid.X).sum(axis=0)[0])
        p = np.random.default_rng(1).normal(size=m.grid.X.shape)
        np.testing.assert_allclose(by_area.matrix() @ p.ravel(), by_area.apply(p).ravel(), atol=1e-9)
    assert pulls["fine"][0] == pytest.approx(pulls["coarse"][0], rel=0.05)
    assert pulls["fine"][1] / pulls["coarse"][1] > 3.5
    with pytest.raises(ValueError, match="weights"):
        SurfaceForces(m.grid, coarse.vertices, cloud, weights=np.ones(3))


def test_target_points_have_footprints(knee_model, volunteer):
    from knee.app.experiments.cases import model_targets

    t = model_targets(knee_model, volunteer)
    assert t.femur_footprints.sum() > 10 and t.tibia_footprints.sum() > 10
    assert len(t.femur) > t.femur_footprints.sum() and len(t.tibia) > t.tibia_footprints.sum()


def test_isometric_lateral_spring(knee_model, volunteer):
    """The LCL spring's attachments keep their distance over the mechanism's motion (within 1 mm)."""
    from knee.foundations.conventions import joint_to_pose, transform_points

    a, b = knee_model.springs.ma.apply(knee_model.grid.X)[1], knee_model.springs.mb.apply(knee_model.grid.X)[1]
    T0 = joint_to_pose(volunteer.solve(0.0)[0])
    res = volunteer.sweep(np.radians(np.arange(0, 121, 10.0)))
    bt = transform_points(res.tf_poses @ np.linalg.inv(T0), b[None, :])[:, 0]
    L = np.linalg.norm(bt - a, axis=1)
    assert L.std() < 1.0 and L.min() > 10.0


def _front_samples(m, n, seed=0):
    """Points on the phantom skin's faces that face +x (what a camera far along +x sees), (n, 3)."""
    import trimesh

    skin = trimesh.Trimesh(m.skin_vertices, m.skin_faces, process=False)
    front = skin.submesh([np.flatnonzero(skin.face_normals[:, 0] > 0.2)], append=True)
    return trimesh.sample.sample_surface(front, n, seed=seed)[0]


def test_depth_point_forces_do_not_pull_a_fitted_skin_towards_the_camera(knee_model):
    """A one-sided cloud lying on the skin (its faces turned towards a camera along +x): the paper's springs,
    skin to cloud, pull the skin behind the silhouette towards the silhouette's points, a net pull towards
    the camera though the skin fits; the depth points' springs, to the nearest point of the skin's surface,
    pull it hardly at all (what is left: the 4 mm voxels average points of a curved skin to just inside it)."""
    from knee.models.fem.forces import SKIN_AREA_PER_SPRING_MM2, DepthPointForces, skin_point_areas

    m = knee_model
    cloud = _front_samples(m, 20000)
    a = skin_point_areas(m.skin_vertices, m.skin_faces)
    skin_to_cloud = SurfaceForces(m.grid, m.skin_vertices, cloud, k=2.0, weights=a / SKIN_AREA_PER_SPRING_MM2)
    cloud_to_skin = DepthPointForces(m.grid, m.skin_vertices, m.skin_faces, cloud, k=2.0)
    old = skin_to_cloud.forces(m.grid.X).sum(axis=0)[0]
    new = cloud_to_skin.forces(m.grid.X).sum(axis=0)[0]
    assert old > 50.0                                    # N: towards the camera
    assert abs(new) < 0.1 * old
    assert cloud_to_skin.within_fraction == pytest.approx(1.0)


def test_depth_point_forces_pull_along_the_normals_by_the_area_each_point_stands_for(knee_model):
    """The front faces' centres moved 1 mm along x: each point pulls its own face (the nearest: faces whose
    inscribed circle's radius is over 2 mm, and turned towards x) along the face's normal by k voxel^2 / 44 mm^2 per mm of the move along it, a third
    on each corner. The grid's resultant carries the springs' (J^T keeps it). A cloud twice as dense pulls
    the same (the 4 mm voxels); apply and matrix agree, and both are the forces' derivative for the pairs
    held."""
    import trimesh

    from knee.models.fem.forces import DEPTH_VOXEL_MM, SKIN_AREA_PER_SPRING_MM2, DepthPointForces

    m = knee_model
    skin = trimesh.Trimesh(m.skin_vertices, m.skin_faces, process=False)
    nrm = skin.face_normals
    perimeter = np.linalg.norm(skin.triangles - np.roll(skin.triangles, 1, axis=1), axis=2).sum(axis=1)
    front = np.flatnonzero((nrm[:, 0] > 0.5) & (2.0 * skin.area_faces / perimeter > 2.0))
    assert len(front) > 100
    t = np.array([1.0, 0.0, 0.0])
    f = DepthPointForces(m.grid, skin.vertices, skin.faces, skin.triangles_center[front] + t, k=2.0, voxel=0.5)
    got = f.forces(m.grid.X).sum(axis=0)
    k_point = 2.0 * 0.5 ** 2 / SKIN_AREA_PER_SPRING_MM2
    want = k_point * (nrm[front] * (nrm[front] @ t)[:, None]).sum(axis=0)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9)
    assert f.active.sum() == len(np.unique(skin.faces[front]))
    # density: the skin's front sampled at two densities, both moved 2 mm, pull alike (within 10 %)
    pulls = [DepthPointForces(m.grid, skin.vertices, skin.faces, _front_samples(m, n) + 2 * t, k=2.0)
             .forces(m.grid.X).sum(axis=0)[0] for n in (30000, 60000)]
    assert DEPTH_VOXEL_MM == 4.0 and pulls[1] == pytest.approx(pulls[0], rel=0.1) and pulls[0] > 0
    # the stiffness: apply == matrix; and, the points on the skin (no pull), minus the forces' change for a
    # small grid motion (the Gauss-Newton stiffness leaves out the normals' turn, which a zero pull does not see)
    rng = np.random.default_rng(3)
    p = rng.normal(size=m.grid.X.shape)
    np.testing.assert_allclose(f.matrix() @ p.ravel(), f.apply(p).ravel(), atol=1e-9)
    on = DepthPointForces(m.grid, skin.vertices, skin.faces, skin.triangles_center[front], k=2.0, voxel=0.5)
    f0 = on.forces(m.grid.X)
    assert np.abs(f0).max() < 1e-9
    dx = 1e-3 * p
    lin = -on.apply(dx)
    assert np.linalg.norm(on.forces(m.grid.X + dx) - lin) < 0.01 * np.linalg.norm(lin)


def test_depth_point_forces_take_a_degenerate_face_without_failing(knee_model):
    """A skin face collapsed to a line (as a segmented surface can hold): the points on it pull nothing (no
    normal) and nothing becomes NaN."""
    from knee.models.fem.forces import DepthPointForces

    m = knee_model
    v = m.skin_vertices.copy()
    f = np.asarray(m.skin_faces)
    a, b, c = f[0]
    v[c] = 0.5 * (v[a] + v[b])  # the first face flattened onto its edge
    cloud = np.vstack([v[f[:50]].mean(axis=1) + [0.5, 0.0, 0.0], 0.5 * (v[a] + v[b])])
    forces = DepthPointForces(m.grid, v, f, cloud, k=2.0, voxel=0.5).forces(m.grid.X)
    assert np.all(np.isfinite(forces))


def test_depth_point_forces_pair_each_point_with_the_exact_nearest_point_of_the_skin(knee_model):
    """Each depth point within reach is paired with the nearest point of the whole skin surface: its pair
    (the corners weighed by its barycentric weights) lies as far from it as trimesh's exhaustive closest
    point on the mesh, to single precision's tie-breaking (1e-3 mm); and exactly the points within the reach pull."""
    import trimesh

    from knee.models.fem.forces import DepthPointForces

    m = knee_model
    skin = trimesh.Trimesh(m.skin_vertices, m.skin_faces, process=False)
    rng = np.random.default_rng(5)
    cloud = _front_samples(m, 6000) + rng.normal(scale=4.0, size=(6000, 3))  # some beyond the 10 mm reach
    f = DepthPointForces(m.grid, skin.vertices, skin.faces, cloud, k=2.0, voxel=4.0)
    f.forces(m.grid.X)
    corners, w, _ = f._pairs
    paired = np.einsum("ij,ijk->ik", w, skin.vertices[corners])
    # exhaustively: every point against every face (in chunks)
    exact = np.concatenate([
        np.linalg.norm(trimesh.triangles.closest_point(np.tile(skin.triangles, (len(q), 1, 1)),
                                                        np.repeat(q, len(skin.faces), axis=0))
                       .reshape(len(q), -1, 3) - q[:, None, :], axis=2).min(axis=1)
        for q in np.array_split(f.thinned, max(1, len(f.thinned) // 20))])
    near = exact < f.reference
    assert 0 < near.sum() < len(near) and len(corners) == near.sum()
    np.testing.assert_allclose(np.linalg.norm(f.thinned[near] - paired, axis=1), exact[near], atol=1e-3)


def test_depth_point_forces_factorise_each_vertex_block_within_its_cell(knee_model):
    """What the solver factorises for the depth points' springs: the whole stiffness's per-vertex 3 x 3
    blocks (taken here from C^T C built pair by corner, independently of the field's sums) carried to the
    grid, with no coupling between a face's corners. Its entries couple only nodes of one cell (within the
    tissue's pattern), and where every point sits on a face's corner it is the whole stiffness."""
    import trimesh

    from knee.models.fem.forces import DepthPointForces

    m = knee_model
    skin = trimesh.Trimesh(m.skin_vertices, m.skin_faces, process=False)
    f = DepthPointForces(m.grid, skin.vertices, skin.faces, _front_samples(m, 3000) + [1.5, 0.0, 0.0], k=2.0)
    f.forces(m.grid.X)
    corners, w, n = f._pairs
    S, P = len(skin.vertices), len(corners)
    rows = np.repeat(np.arange(P), 9)
    cols = (3 * corners[:, :, None] + np.arange(3)).ravel()
    C = sp.csr_matrix(((w[:, :, None] * n[:, None, :]).ravel(), (rows, cols)), shape=(P, 3 * S))
    whole = (C.T @ C).tocoo()
    own = whole.row // 3 == whole.col // 3  # a vertex with itself
    blocks = sp.csr_matrix((whole.data[own], (whole.row[own], whole.col[own])), shape=whole.shape)
    want = f.k_point * (f.map.J3.T @ blocks @ f.map.J3)
    F = f.factor_matrix()
    assert abs(F - want).max() <= 1e-12 * abs(want).max()
    assert abs(f.matrix() - F).max() > 1e-3 * abs(want).max()  # the corners' couplings are what it leaves out
    # only nodes of one cell coupled
    r, c = F.nonzero()
    in_cell = sp.csr_matrix((np.ones(m.grid.cells.size), (np.repeat(np.arange(len(m.grid.cells)), 8),
                                                           m.grid.cells.ravel())))
    share = (in_cell.T @ in_cell).tocsr()
    assert np.all(np.asarray(share[r // 3, c // 3]).ravel() > 0)
    # every point on a corner of its face (weights 1, 0, 0): nothing left out
    on_corner = DepthPointForces(m.grid, skin.vertices, skin.faces, skin.vertices[np.unique(corners[:, 0])], k=2.0,
                                 voxel=0.5)
    on_corner.forces(m.grid.X)
    assert abs(on_corner.factor_matrix() - on_corner.matrix()).max() <= 1e-12 * abs(on_corner.matrix()).max()
