"""Building blocks for the kinematic prior in the FEM: bone-attached points, target springs, link springs."""

import numpy as np
import pytest

from models.fem.fields import MappedSprings, MappedTargets, affine_point_map
from models.fem.scene import build_association_model


@pytest.fixture(scope="module")
def model(volunteer):
    return build_association_model(volunteer)


def _rigid(X, deg=25.0):
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    return X @ R.T + [3.0, -7.0, 2.0], R


def test_points_attached_to_a_bone_follow_any_rigid_motion_exactly(model, volunteer):
    pts = np.vstack([volunteer.params.link(n).femur for n in ("acl", "pcl", "lc", "mc")])
    m = affine_point_map(model.femur, pts)
    x, R = _rigid(model.grid.X)  # the whole grid moved rigidly (so is every embedded bone node)
    np.testing.assert_allclose(m.apply(x), pts @ R.T + [3.0, -7.0, 2.0], atol=1e-8)


def test_target_and_link_springs_are_consistent(model, volunteer):
    bone = model.tibia
    tg = MappedTargets(bone.map, bone.el.X + [0.0, 1.0, 0.0], k=50.0)
    x0 = model.grid.X
    f = tg.forces(x0)
    # the nodes are pulled +y by k * 1 mm each, summed through the partition of unity of the embedding
    assert f[:, 1].sum() == pytest.approx(50.0 * len(bone.el.X), rel=1e-9)
    p = np.random.default_rng(0).normal(size=x0.shape)
    np.testing.assert_allclose((tg.matrix() @ p.ravel()).reshape(-1, 3), tg.apply(p), atol=1e-9)
    a = affine_point_map(model.femur, np.array([volunteer.params.link("acl").femur]))
    b = affine_point_map(model.tibia, np.array([[10.0, -5.0, 0.0]]))
    links = MappedSprings(model.grid, a.apply(x0), b.apply(x0), k=1000.0, maps=(a, b))
    assert np.abs(links.forces(x0)).max() < 1e-9  # at rest length: no force
    x1, _ = _rigid(x0, 40.0)
    assert np.abs(links.forces(x1)).max() < 1e-6  # a rigid motion keeps every length


def test_prescribed_nodes_move_exactly_and_rebase_makes_the_state_force_free(volunteer):
    import math

    from models.fem.prior_case import initialise_from_prior
    from models.fem.scene import knee_angles

    model = build_association_model(volunteer)
    s = model.solver
    mask = np.zeros(model.grid.n_nodes, bool)
    mask[:20] = True
    target = model.grid.X.copy()
    target[:20] += [0.0, 0.5, 0.0]
    s.step(prescribed=(mask, target))
    np.testing.assert_allclose(s.x[:20], target[:20], atol=1e-9)  # Dirichlet conditions hold exactly
    model = build_association_model(volunteer)
    initialise_from_prior(model, volunteer, math.radians(60.0))
    assert knee_angles(model)[0] == pytest.approx(60.0, abs=1.0)
    # the initialised state is the new reference: elastic forces vanish there and the knee stays
    assert np.abs(model.soft.forces(model.solver.x)).max() < 1e-6
    for _ in range(3):
        model.solver.step()
    assert knee_angles(model)[0] == pytest.approx(60.0, abs=1.0)


def test_unknown_comparison_method_is_refused(volunteer):
    from models.fem.prior_case import run_method
    from toolkit.errors import KneeInputError

    with pytest.raises(KneeInputError, match="method must be one of paper, init, links, kinematics"):
        run_method("magic", volunteer, volunteer, 60.0)
