"""Grid, mapping and bone meshes of the association model: exactness checks."""

import numpy as np
import pytest
import trimesh

from knee.foundations.surfaces import SurfaceQuery
from knee.models.fem.bones import tetrahedralize, tetrahedralize_to_count
from knee.models.fem.grid import BOUNDARY, INSIDE, build_grid
from knee.models.fem.mapping import TrilinearMapping


@pytest.fixture(scope="module")
def capsule_grid():
    skin = trimesh.creation.capsule(height=200.0, radius=50.0, count=[32, 32])
    skin.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # along y
    return skin, build_grid(skin, n_across=7, element_size=15.0)


def test_grid_encloses_the_skin(capsule_grid):
    skin, g = capsule_grid
    assert g.shape[0] == g.shape[2] == 7 and g.shape[1] == int(np.ceil((300 + 2) / 15.0))
    assert np.allclose(np.diff(g.axes[1]), 302 / g.shape[1])
    assert set(np.unique(g.status)) <= {INSIDE, BOUNDARY}
    assert np.all((g.weights > 0) & (g.weights <= 1))
    assert np.all(g.weights[g.status == INSIDE] == 1)
    # the kept volume (weighted) approximates the skin's volume
    vol = (g.cell_volumes * g.weights).sum()
    assert vol == pytest.approx(skin.volume, rel=0.05)
    m = TrilinearMapping(g, skin.vertices)
    assert m.outside == 0


def test_mapping_reproduces_affine_fields_and_is_consistent(capsule_grid):
    skin, g = capsule_grid
    rng = np.random.default_rng(0)
    pts = skin.sample(500, seed=1) * 0.9
    m = TrilinearMapping(g, pts)
    np.testing.assert_allclose(np.asarray(m.J.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    A = rng.normal(size=(3, 3))
    t = rng.normal(size=3)
    np.testing.assert_allclose(m.apply(g.X @ A.T + t), pts @ A.T + t, atol=1e-9)  # trilinear is exact
    np.testing.assert_allclose(m.apply(g.X), pts, atol=1e-9)
    f = rng.normal(size=pts.shape)
    x = rng.normal(size=g.X.shape)
    assert np.sum(f * m.apply(x)) == pytest.approx(np.sum(m.apply_transpose(f) * x), rel=1e-12)  # work
    np.testing.assert_allclose(m.J3 @ x.ravel(), m.apply(x).ravel(), atol=1e-12)
    assert np.all((m.natural >= -1 - 1e-9) & (m.natural <= 1 + 1e-9))


def test_graded_grid_along_the_limb():
    from knee.models.fem.grid import graded_axis

    a = graded_axis(-150.0, 120.0, 3.0, 18.0, 0.0, 15.0)
    h = np.diff(a)
    assert a[0] == -150.0 and a[-1] == 120.0 and np.all(h > 0)
    near = np.abs(0.5 * (a[:-1] + a[1:])) < 14.0
    assert np.allclose(h[near], 3.0) and h.max() <= 1.5 * 18.0  # the last cell absorbs a remainder
    skin = trimesh.creation.capsule(height=200.0, radius=50.0, count=[32, 32])
    skin.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    g = build_grid(skin, 7, 18.0, joint_y=0.0, joint_size=3.0)
    assert (g.cell_volumes * g.weights).sum() == pytest.approx(skin.volume, rel=0.05)
    pts = skin.sample(300, seed=2) * 0.9
    m = TrilinearMapping(g, pts)
    A = np.random.default_rng(4).normal(size=(3, 3))
    np.testing.assert_allclose(m.apply(g.X @ A.T), pts @ A.T, atol=1e-9)


def test_grid_offset_moves_the_same_cells():
    """Another placement of the same discretisation: the cells across keep their size and move by the given
    fraction of a cell (one more cell spans the skin), the joint grading's centre by that fraction of a joint
    cell; the kept volume still matches the skin's. Catches an offset that rescales the cells or leaves the
    grid where it was."""
    from knee.foundations.errors import KneeInputError

    skin = trimesh.creation.capsule(height=200.0, radius=50.0, count=[32, 32])
    skin.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    g0 = build_grid(skin, 7, 18.0, joint_y=0.0, joint_size=3.0)
    g1 = build_grid(skin, 7, 18.0, joint_y=0.0, joint_size=3.0, offset=0.25)
    for d in (0, 2):
        h0, h1 = np.diff(g0.axes[d]), np.diff(g1.axes[d])
        assert len(h1) == len(h0) + 1 and np.allclose(h1, h0[0])
        assert g1.axes[d][0] == pytest.approx(g0.axes[d][0] - 0.25 * h0[0])
    assert 0.75 in np.round(g1.axes[1], 9) and 0.0 in g0.axes[1]  # the joint line's node moved by 0.25 x 3 mm
    assert (g1.cell_volumes * g1.weights).sum() == pytest.approx(skin.volume, rel=0.05)
    with pytest.raises(KneeInputError, match="offset"):
        build_grid(skin, 7, 18.0, offset=1.0)


def test_cells_across_x_and_z_apart():
    """A pair (x, z) of cells across: x gets the first count and z the second, each spanning the skin's box
    evenly, with or without an offset; the kept volume still the skin's; a count below 1 or three counts are
    refused. Catches the pair swapped, or one count used for both."""
    from knee.foundations.errors import KneeInputError

    skin = trimesh.creation.capsule(height=200.0, radius=50.0, count=[32, 32])
    skin.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    for offset, extra in ((0.0, 0), (0.5, 1)):
        g = build_grid(skin, (12, 5), 18.0, joint_y=0.0, offset=offset)
        assert (len(g.axes[0]) - 1, len(g.axes[2]) - 1) == (12 + extra, 5 + extra)
        lo, hi = skin.bounds[0] - 1.0, skin.bounds[1] + 1.0
        assert np.allclose(np.diff(g.axes[0]), (hi[0] - lo[0]) / 12) and np.allclose(np.diff(g.axes[2]), (hi[2] - lo[2]) / 5)
        assert (g.cell_volumes * g.weights).sum() == pytest.approx(skin.volume, rel=0.05)
    assert len(build_grid(skin, 6, 18.0).axes[2]) == len(build_grid(skin, (6, 6), 18.0).axes[2]) == 7
    for bad in (0, (7, 0), (7, 7, 7)):
        with pytest.raises(KneeInputError, match="n_across"):
            build_grid(skin, bad, 18.0)


def test_fem_settings_reach_the_grid_and_the_tissue_cells(volunteer):
    """FemSettings' grid_offset and soft_element reach the model built: its grid is the offset one (one more
    cell across, moved by the offset) and its tissue stiffness the named element's, computed independently
    here from the grid; a bad element name is a clear input error, not a KeyError."""
    from knee.foundations.errors import KneeInputError
    from knee.models.fem.elements import hex_stiffness_incompatible
    from knee.models.fem.material import elasticity_matrix
    from knee.models.fem.scene import FemSettings, build_knee_model, phantom_anatomy

    anatomy, ph = phantom_anatomy(volunteer)
    base = build_knee_model(anatomy, prior=volunteer, phantom=ph)
    m = build_knee_model(anatomy, FemSettings(grid_offset=0.5, soft_element="incompatible"), prior=volunteer,
                         phantom=ph)
    h = np.diff(base.grid.axes[0])[0]
    assert len(m.grid.axes[0]) == len(base.grid.axes[0]) + 1
    assert m.grid.axes[0][0] == pytest.approx(base.grid.axes[0][0] - 0.5 * h)
    K = hex_stiffness_incompatible(m.grid.X, m.grid.cells, elasticity_matrix(1.0, 0.3)) * m.grid.weights[:, None, None]
    np.testing.assert_allclose(m.soft.el.K, K, rtol=1e-12, atol=1e-12 * np.abs(K).max())
    with pytest.raises(KneeInputError, match="hexahedra's element"):
        build_knee_model(anatomy, FemSettings(soft_element="serendipity"), prior=volunteer, phantom=ph)


def test_grid_sized_by_the_knee(volunteer):
    """``n_across="knee"``: cells along x of about a sixth of the femur's width over the grid's box (the skin's
    widened by the grid's margin each side), at least the paper's 7, and 7 along z; the model built with it
    carries the pair it used and its grid has those cells. Catches the axes swapped, the floor of 7, the cap
    of 24 or the grid's margin left out, and an unknown word taken silently."""
    from knee.foundations.errors import KneeInputError
    from knee.models.fem.scene import FemSettings, build_knee_model, knee_sized_across, phantom_anatomy

    # a box 216 mm across x (218 with the margins) and a 90 mm femur: cells of 15 mm, 218 / 15 = 14.5 -> 15
    # (216 / 15 = 14.4 would give 14); a narrow box keeps the paper's 7
    assert knee_sized_across([[0.0, 0.0, 0.0], [216.0, 400.0, 300.0]], 90.0) == (15, 7)
    assert knee_sized_across([[0.0, 0.0, 0.0], [60.0, 400.0, 300.0]], 90.0) == (7, 7)
    assert knee_sized_across([[0.0, 0.0, 0.0], [900.0, 400.0, 300.0]], 90.0) == (24, 7)  # capped, not 60
    with pytest.raises(KneeInputError, match="width"):
        knee_sized_across([[0.0, 0.0, 0.0], [216.0, 400.0, 300.0]], 0.0)
    anatomy, ph = phantom_anatomy(volunteer)
    m = build_knee_model(anatomy, FemSettings(n_across="knee"), prior=volunteer, phantom=ph)
    ext = np.ptp(np.asarray(anatomy.skin.vertices)[:, 0]) + 2.0
    nx = max(7, int(round(ext / (anatomy.width / 6.0))))
    assert m.settings.n_across == (nx, 7)
    assert (len(m.grid.axes[0]) - 1, len(m.grid.axes[2]) - 1) == (nx, 7)
    with pytest.raises(KneeInputError, match="knee"):
        build_knee_model(anatomy, FemSettings(n_across="limb"), prior=volunteer, phantom=ph)


def test_tetrahedralize_a_sphere():
    s = trimesh.creation.icosphere(4, 60.0)
    X, T = tetrahedralize(s, 20.0)
    p = X[T]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6
    assert np.all(vol > 0)
    assert vol.sum() == pytest.approx(s.volume, rel=0.12)
    assert np.all(SurfaceQuery.of(s).signed_distance(p.mean(axis=1)) < 0)
    assert len(np.unique(T)) == len(X)


def test_phantom_bones_reach_the_papers_element_count(volunteer):
    from knee.models.phantom import build_phantom

    ph = build_phantom(volunteer.params)
    for bone in (ph.femur, ph.tibia):
        X, T, edge = tetrahedralize_to_count(bone, (400, 700))
        assert 400 <= len(T) <= 900, (len(T), edge)


def test_mapped_bone_field_matches_embedding_then_elements(capsule_grid):
    """The bone field gathers its element positions straight from the grid and scatters straight back (one
    sparse map each, the embedding composed in): the same forces and products as embedding the nodes
    (J x), computing the tetrahedra's co-rotational forces there, and returning them through J^T."""
    from knee.models.fem.elements import CorotationalElements
    from knee.models.fem.fields import MappedBoneElasticity

    skin, g = capsule_grid
    bone = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    Xb, tets = tetrahedralize(bone, 12.0)
    field = MappedBoneElasticity(g, Xb, tets, E=1500.0, nu=0.3)
    rng = np.random.default_rng(3)
    x = g.X + rng.normal(scale=0.4, size=g.X.shape)
    m = TrilinearMapping(g, Xb)
    ref = CorotationalElements(Xb, tets, 1500.0, 0.3)
    xb = m.apply(x)
    expected = m.apply_transpose(ref.forces(xb))  # np.add.at gather of the element forces, then J^T
    np.testing.assert_allclose(field.forces(x), expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    # the tangent's product at those rotations: R K R^T on the embedded displacement, returned by J^T
    p = rng.normal(size=g.X.shape)
    pe = m.apply(p)[ref.cells]
    Kr = ref.rotated_stiffness()
    fe = (Kr @ pe.reshape(len(tets), 12, 1)).reshape(-1, 4, 3)
    out = np.zeros_like(Xb)
    np.add.at(out, ref.cells, fe)
    np.testing.assert_allclose(field.apply(p), m.apply_transpose(out), atol=1e-9 * np.abs(out).max())
    # the cached transposed rotations follow the rotations when they are replaced
    field.el.R = np.broadcast_to(np.eye(3), field.el.R.shape)
    np.testing.assert_allclose(field.el.Rt, np.broadcast_to(np.eye(3), field.el.R.shape))


def test_a_bone_fields_reserved_pattern_holds_its_matrix_however_the_bone_turns(capsule_grid):
    """J^T K J at the scan (no rotation) has entries that cancel to exactly zero, which a turned bone's
    matrix holds: the reserved pattern holds both, so the solver's pattern does not change mid-motion."""
    from scipy.spatial.transform import Rotation

    from knee.models.fem.fields import MappedBoneElasticity

    skin, g = capsule_grid
    bone = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    Xb, tets = tetrahedralize(bone, 12.0)
    field = MappedBoneElasticity(g, Xb, tets, E=1500.0, nu=0.3)
    reserve = field.pattern_reserve().tocoo()
    reserved = set(zip(reserve.row.tolist(), reserve.col.tolist()))

    def keys(M):
        M = M.tocoo()
        return set(zip(M.row[M.data != 0].tolist(), M.col[M.data != 0].tolist()))

    field.forces(g.X)
    at_scan = keys(field.matrix())
    R = Rotation.from_rotvec([0.3, -0.5, 0.4]).as_matrix()
    field.forces(g.X @ R.T)  # the whole grid turned: the bone's elements take its rotation
    turned = keys(field.matrix())
    assert turned - at_scan  # the turned bone's matrix holds entries the scan's lacks
    assert at_scan <= reserved and turned <= reserved
    # and no more than the bone reaches: every reserved coupling joins nodes of cells holding one tetrahedron
    cells_of = field.map.nodes  # (P, 8) the grid nodes each bone node is embedded with
    reach = {(int(a), int(b)) for t in tets for a in cells_of[t].ravel() for b in cells_of[t].ravel()}
    assert {(r // 3, c // 3) for r, c in reserved} == reach


def test_signed_distance_signs_agree_with_the_half_spaces_of_a_convex_hull():
    """Inside and outside of a closed mesh as the convex hull's half-spaces say, for a million points at random
    around it (those within 1e-3 mm of a face plane left out): one ray per point (open3d's default) miscounts
    where it grazes an edge, and got one of these points wrong; the majority of three gets none."""
    from knee.foundations.surfaces import SIGN_RAYS

    rng = np.random.default_rng(0)
    v = rng.normal(size=(300, 3))
    hull = trimesh.convex.convex_hull(20.0 * v / np.linalg.norm(v, axis=1)[:, None])
    rng.uniform(-22.0, 22.0, (1_000_000, 3))  # the first million drawn hold no point a single ray gets wrong
    p = rng.uniform(-22.0, 22.0, (1_000_000, 3)).astype(np.float32)
    offset = np.sum(hull.face_normals * hull.triangles[:, 0], axis=1)
    # the largest distance beyond a face plane, in chunks (a million points by 600 faces at once is 5 GB)
    beyond = np.concatenate([np.max(c.astype(float) @ hull.face_normals.T - offset, axis=1)
                             for c in np.array_split(p, 20)])
    inside, outside = beyond < -1e-3, beyond > 1e-3
    q = SurfaceQuery.of(hull)
    d = q.signed_distance(p)
    assert SIGN_RAYS > 1 and SIGN_RAYS % 2 == 1
    assert np.count_nonzero(inside & (d > 0)) + np.count_nonzero(outside & (d < 0)) == 0
    occupied = q.inside(p)
    assert np.count_nonzero(inside & ~occupied) + np.count_nonzero(outside & occupied) == 0
