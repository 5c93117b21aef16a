"""The isometric-fibre search on the mechanism's own motion."""

import numpy as np
import pytest

from knee.fitting.isometric import isometric_fibre
from knee.fitting.optimize import synthetic_motion
from knee.foundations.errors import KneeInputError
from knee.models.mechanism import load_model


def _area(centre, n, radius, rng):
    d = rng.normal(size=(n, 3))
    d *= (radius * rng.uniform(0, 1, n) ** (1 / 3) / np.linalg.norm(d, axis=1))[:, None]
    pts = centre + d
    pts[0] = centre  # the true attachment is among the candidates
    return pts


@pytest.mark.parametrize("name", ["acl", "pcl", "mcl"])
def test_the_mechanism_links_are_the_isometric_fibres(name):
    p = load_model("volunteer")
    _, truth = synthetic_motion(p, np.linspace(0, 120, 40), noise=False)
    rng = np.random.default_rng(4)
    lk = p.link(name)
    fa, ta = _area(lk.femur, 300, 5.0, rng), _area(lk.tibia, 300, 5.0, rng)
    fib = isometric_fibre(fa, ta, truth.tf)
    np.testing.assert_allclose(fib.femur, lk.femur, atol=1e-12)
    np.testing.assert_allclose(fib.tibia, lk.tibia, atol=1e-12)
    assert fib.sd < 1e-9 and fib.length_at_extension == pytest.approx(lk.length, abs=1e-9)


def test_noisy_motion_and_bundle_restriction():
    p = load_model("volunteer")
    meas, truth = synthetic_motion(p, np.linspace(0, 120, 60), seed=2)
    rng = np.random.default_rng(5)
    lk = p.link("acl")
    fa, ta = _area(lk.femur, 250, 5.0, rng), _area(lk.tibia, 250, 5.0, rng)
    fib = isometric_fibre(fa, ta, meas.tf)
    # with fluoroscopy-like noise the point found is not the true one, but over the true motion the
    # fibre found is nearly isometric, far more than a typical pair of the areas
    from knee.foundations.conventions import joint_to_pose

    T = joint_to_pose(truth.tf)
    L = np.linalg.norm(fib.femur - (T[:, :3, :3] @ fib.tibia + T[:, :3, 3]), axis=1)
    pairs = rng.integers(0, 250, (200, 2))
    typical = np.median([np.linalg.norm(fa[i] - (T[:, :3, :3] @ ta[j] + T[:, :3, 3]), axis=1).std()
                         for i, j in pairs])
    assert L.std() < 0.5 and L.std() < typical / 4, (L.std(), typical)
    # restricted to a bundle that excludes the true points: the result lies in that bundle
    fb = fa[:, 0] > lk.femur[0] + 1.0
    fib2 = isometric_fibre(fa, ta, meas.tf, femur_bundle=fb)
    assert fib2.femur[0] > lk.femur[0] + 1.0
    with pytest.raises(KneeInputError, match="no points"):
        isometric_fibre(fa, ta, meas.tf, femur_bundle=np.zeros(len(fa), bool))
