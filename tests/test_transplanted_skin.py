"""A second real knee for the association FEM: lenhart2015's MRI bones with a skin carried over from the
Visible Human (fitting/reference_data.py), and the bounded cost of densely meshed bones (models/fem/anatomy.py)."""

from __future__ import annotations

import numpy as np
import pytest

from knee.foundations.pointclouds import seeded_subsample, thinned_evenly
from knee.foundations.surfaces import SurfaceQuery


def test_even_thinning_keeps_input_points_spread_over_them():
    """At most ``most`` of the points, all of them when they are that few, each dropped point near a kept one
    (an even spread, not the first ``most``), the same every call."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(0.0, 100.0, (20000, 3))
    assert np.array_equal(thinned_evenly(pts[:500], 500), np.arange(500))
    keep = thinned_evenly(pts, 2000)
    assert 1000 < keep.size <= 2000 and np.all(np.diff(keep) > 0)
    assert np.array_equal(keep, thinned_evenly(pts, 2000))
    from scipy.spatial import cKDTree

    gap, _ = cKDTree(pts[keep]).query(pts)
    # 2,000 points spread over a 100 mm cube are about 8 mm apart; a voxel of that size holds every point
    # within its diagonal of the one it keeps
    assert gap.max() < 20.0
    assert pts[keep][:, 0].max() > 90.0 and pts[keep][:, 0].min() < 10.0  # the whole extent, not a corner


def test_a_seeded_subsample_is_the_same_ordered_subset_every_call():
    """At most ``most`` of the points, all of them (the array itself) when they are that few; otherwise
    distinct input rows in their input order, the same on every call, and drawn over the whole input rather
    than its first rows."""
    pts = np.random.default_rng(5).uniform(0.0, 100.0, (5000, 3))
    assert np.array_equal(seeded_subsample(pts[:300], 300), pts[:300])
    sub = seeded_subsample(pts, 1000)
    assert sub.shape == (1000, 3) and np.array_equal(sub, seeded_subsample(pts, 1000))
    rows = {tuple(p): i for i, p in enumerate(pts)}
    idx = np.array([rows[tuple(p)] for p in sub])
    assert np.all(np.diff(idx) > 0) and idx.max() > 4000 and idx.min() < 1000


def test_the_bones_clearance_asks_only_the_near_points_and_gives_the_same_answer(volunteer_anatomy):
    """The clearance asks only the points near the other bone's box first; its answer is the least signed
    distance over every vertex of both bones (computed here directly), apart or overlapping."""
    from knee.models.fem.anatomy import bone_clearance

    a = volunteer_anatomy
    fq, tq = SurfaceQuery.of(a.femur), SurfaceQuery.of(a.tibia)
    for lift in (-6.0, 0.0, 3.0, 40.0):  # overlapping, at the scan, apart, far apart
        T = a.tibia_pose.copy()
        T[:3, 3] += lift * T[:3, 1]
        move = T @ np.linalg.inv(a.tibia_pose)
        tib = np.asarray(a.tibia.vertices) @ move[:3, :3].T + move[:3, 3]
        inv = np.linalg.inv(move)
        fem = np.asarray(a.femur.vertices) @ inv[:3, :3].T + inv[:3, 3]
        brute = min(fq.signed_distance(tib).min(), tq.signed_distance(fem).min())
        assert bone_clearance(a, T) == pytest.approx(brute, abs=1e-9)


@pytest.fixture(scope="module")
def volunteer_anatomy():
    from knee.models.fem.scene import phantom_anatomy
    from knee.models.mechanism import Mechanism

    return phantom_anatomy(Mechanism.from_name("volunteer"))[0]


@pytest.fixture(scope="module")
def lenhart_with_skin(visible_human, shared_data, tmp_path_factory):
    from knee.fitting.reference_data import lenhart_subject

    return lenhart_subject(shared_data, tmp_path_factory.mktemp("lenhart") / "lenhart2015", ct_row="least-flexion",
                           skin_from=visible_human)


def test_a_skin_carried_onto_its_own_bones_is_the_skin_itself(visible_human):
    """The Visible Human's skin carried onto the Visible Human's own bones (scale 1, the same frames) lies on
    the Visible Human's skin: the rings, the frames and the blend put it back where it was, except where the
    least tissue over a bone pushes it out. An independent check: the skin read from the data, not made."""
    from knee.fitting.reference_data import transplanted_skin
    from knee.foundations.conventions import invert_poses, transform_points

    vh = visible_human
    lm = vh.landmarks["femur"]
    width = float(np.linalg.norm(lm["LE"] - lm["ME"]))
    skin = transplanted_skin(vh, vh.femur, vh.tibia, vh.frames["femur"], vh.frames["tibia"], width, 100.0, 120.0)
    assert skin.is_watertight and skin.volume > 0
    d = np.abs(SurfaceQuery.of(vh.skin).signed_distance(skin.vertices))
    assert np.median(d) < 0.1 and np.percentile(d, 95) < 1.0  # 2.7 and 4.2 mm with the width 5 % off
    y = transform_points(invert_poses(vh.frames["femur"]), skin.vertices)[:, 1]
    assert np.ptp(y) > 200.0  # it spans what was asked (100 mm below the joint line to 120 above)


def test_lenhart_with_a_carried_skin_builds_the_association_model(lenhart_with_skin):
    """lenhart2015 written with the Visible Human's skin: the skin encloses every bone by at least the least
    tissue (the reader's check passes), the scan is its least flexed row (about 10 deg), and the association
    model builds from it; its densely meshed bones are thinned for the contact to at most
    BONE_POINTS_MOST points each."""
    from knee.fitting.reference_data import SKIN_LEAST_TISSUE_MM
    from knee.fitting.subject import load_subject
    from knee.fitting.subject_anatomy import subject_anatomy
    from knee.models.fem.anatomy import BONE_POINTS_MOST
    from knee.models.fem.scene import build_knee_model

    s = load_subject(lenhart_with_skin)
    assert s.skin is not None and s.skin.is_watertight
    a = subject_anatomy(s)  # refuses bones outside the skin
    flexions = np.degrees(s.motion.tf[:, 0])
    assert np.degrees(a.scan_tf[0]) == pytest.approx(flexions.min(), abs=1.0) and flexions.min() < 15.0
    q = SurfaceQuery.of(a.skin)
    y_lo, y_hi = a.skin.vertices[:, 1].min() + 5.0, a.skin.vertices[:, 1].max() - 5.0
    for bone in (a.femur, a.tibia):
        v = np.asarray(bone.vertices)
        v = v[(v[:, 1] > y_lo) & (v[:, 1] < y_hi)]
        assert -q.signed_distance(v).max() > SKIN_LEAST_TISSUE_MM - 0.5
    fp, tp = a.contact_points()
    assert len(fp) <= BONE_POINTS_MOST and len(tp) <= BONE_POINTS_MOST
    assert len(a.femur.vertices) > BONE_POINTS_MOST  # an MRI's bones: the thinning is exercised
    model = build_knee_model(a)
    assert len(model.grid.cells) > 300


def test_bad_requests_for_a_carried_skin_are_refused_in_one_line(visible_human, shared_data, tmp_path):
    """A knee without a skin to carry over, a skin asked for farther than the source's reaches, and a row
    that is neither a row nor 'least-flexion': each refused with a one-line error naming it, nothing
    written."""
    from dataclasses import replace

    from knee.fitting.reference_data import lenhart_subject, transplanted_skin
    from knee.foundations.errors import KneeInputError

    vh = visible_human
    lm = vh.landmarks["femur"]
    width = float(np.linalg.norm(lm["LE"] - lm["ME"]))
    args = (vh.femur, vh.tibia, vh.frames["femur"], vh.frames["tibia"], width)
    with pytest.raises(KneeInputError, match="visible-human-male has no skin to carry over"):
        transplanted_skin(replace(vh, skin=None), *args, 100.0, 100.0)
    with pytest.raises(KneeInputError, match="skin does not surround its bones' axes from 100 mm below to 5000 mm"):
        transplanted_skin(vh, *args, 100.0, 5000.0)  # past the body's top: the rays meet nothing
    out = tmp_path / "lenhart"
    with pytest.raises(KneeInputError, match="ct_row must be a row of the motion table .* got 'first'"):
        lenhart_subject(shared_data, out, ct_row="first", skin_from=vh)
    assert not out.exists()
