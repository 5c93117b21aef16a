"""The association model from any knee's surfaces: the anatomy's regions (closed forms on simple shapes)
and the model of a real knee (the Visible Human's, where the data is present)."""

import math

import numpy as np
import pytest
import trimesh

from knee.foundations.errors import KneeInputError
from knee.models.fem.anatomy import KneeAnatomy, anatomy_in_femur_frame, clip_anatomy, default_collaterals


def _cylinder(r, y0, y1, sections=48):
    m = trimesh.creation.cylinder(radius=r, height=y1 - y0, sections=sections)
    m.apply_transform(trimesh.transformations.rotation_matrix(-math.pi / 2, [1, 0, 0]))  # axis z -> y
    m.apply_translation([0.0, 0.5 * (y0 + y1), 0.0])
    return m


def _leg(skin_r=70.0, top=300.0, bottom=-300.0, gap=4.0):
    """A femur rod above a tibia rod (radius 40 mm, a 4 mm joint space centred on y = -20), in a skin rod."""
    femur, tibia = _cylinder(40.0, -20.0 + gap / 2, top - 20.0), _cylinder(40.0, bottom + 20.0, -20.0 - gap / 2)
    return KneeAnatomy(femur, tibia, _cylinder(skin_r, bottom, top), np.eye(4), mcl=np.array([[0, 0, -40.0], [0, -60, -40.0]]),
                       lcl=np.array([[0, 0, 40.0], [0, -60, 40.0]]))


def test_regions_of_a_simple_leg_follow_its_size():
    a = _leg()
    assert a.joint_y == pytest.approx(-20.0)
    w = a.width
    assert w == pytest.approx(80.0, rel=0.01)  # the rod's diameter (a 48-gon's width across vertices)
    assert a.thigh_from == pytest.approx(-20.0 + 0.8 * w)
    fc, tc = a.contact_points()
    assert fc[:, 1].max() < -20.0 + 0.5 * w and tc[:, 1].min() > -20.0 - 0.4 * w and len(fc) and len(tc)
    # a scan with only 60 mm of shaft above the joint line: the thigh band is its upper 40 %
    short = clip_anatomy(a, widths=60.0 / w)
    assert short.skin.vertices[:, 1].max() == pytest.approx(40.0, abs=1e-6)
    assert short.thigh_from == pytest.approx(40.0 - 0.4 * 60.0, abs=1e-6)
    short.check()


def test_clipping_keeps_the_band_and_the_piece_around_the_knee():
    a = _leg()
    other_leg = _cylinder(70.0, -300.0, 280.0).apply_translation([0.0, 0.0, 300.0])
    two = KneeAnatomy(a.femur, a.tibia, trimesh.util.concatenate([a.skin, other_leg]), np.eye(4))
    c = clip_anatomy(two, widths=2.0)
    w = a.width
    assert c.skin.is_watertight and c.skin.bounds[1, 2] < 100.0  # the other leg is gone
    np.testing.assert_allclose(c.skin.bounds[:, 1], [-20.0 - 2 * w, -20.0 + 2 * w], atol=1e-6)
    assert c.femur.vertices[:, 1].max() < -20.0 + 2 * w and c.tibia.vertices[:, 1].min() > -20.0 - 2 * w
    c.check()


def test_bones_outside_the_skin_are_refused_with_their_count():
    a = _leg(skin_r=30.0)  # thinner than the bones
    with pytest.raises(KneeInputError, match=r"\d+ of \d+ femur vertices lie more than 0.5 mm outside the skin"):
        a.check()


def test_frames_move_the_surfaces_into_the_femur_frame():
    a = _leg()
    T = trimesh.transformations.rotation_matrix(0.3, [0, 0, 1])
    T[:3, 3] = [10.0, -5.0, 2.0]
    moved = [m.copy().apply_transform(T) for m in (a.femur, a.tibia, a.skin)]
    b = anatomy_in_femur_frame(*moved, T, T, mcl=(T[:3, :3] @ a.mcl.T).T + T[:3, 3])
    np.testing.assert_allclose(b.femur.vertices, a.femur.vertices, atol=1e-9)
    np.testing.assert_allclose(b.tibia_pose, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(b.mcl, a.mcl, atol=1e-9)


def _vh_anatomy(visible_human, widths=None):
    vh = visible_human
    a = anatomy_in_femur_frame(vh.femur, vh.tibia, vh.skin, vh.frames["femur"], vh.frames["tibia"], name=vh.name)
    return clip_anatomy(a) if widths is None else clip_anatomy(a, widths=widths)


def test_a_real_leg_gives_a_closed_band_around_its_knee(visible_human):
    a = _vh_anatomy(visible_human)
    a.check()
    # one leg kept of the whole-body skin: its medio-lateral extent is a thigh's, not a pelvis's
    assert a.skin.is_watertight and np.ptp(a.skin.vertices[:, 2]) < 250.0
    assert 70.0 < a.width < 110.0  # an adult distal femur
    # the scan's pose: near extension
    assert abs(math.degrees(a.scan_tf[0])) < 20.0


def test_collateral_insertions_found_on_a_real_femur_lie_at_its_annotated_entheses(visible_human):
    """The femoral ends of the estimated collaterals against the data's own epicondylar entheses (an
    annotation the estimate does not use): within 12 mm (measured 6.2 medial, 9.7 lateral)."""
    a = _vh_anatomy(visible_human)
    mcl, lcl = default_collaterals(a)
    Ti = np.linalg.inv(visible_human.frames["femur"])
    for ends, name in ((mcl, "medial_epicondylar_enthesis"), (lcl, "lateral_epicondylar_enthesis")):
        c = (Ti[:3, :3] @ visible_human.annotations[name].mean(axis=0)) + Ti[:3, 3]
        assert np.linalg.norm(ends[0] - c) < 12.0, name
    assert 40.0 < np.linalg.norm(mcl[0] - mcl[1]) < 120.0 and 30.0 < np.linalg.norm(lcl[0] - lcl[1]) < 90.0


def test_the_model_of_a_real_knee_scanned_with_60_mm_of_shaft(visible_human):
    """A scan of 60 mm of shaft above and below the joint line still gives a model: a grid, bones in it,
    a thigh band to hold and register, and a knee that flexes under a posterior push on the tibia."""
    from dataclasses import replace

    from knee.models.fem.scene import build_knee_model, knee_angles

    a = _vh_anatomy(visible_human)
    a = clip_anatomy(a, widths=60.0 / a.width + 0.05)
    mcl, lcl = default_collaterals(a)
    model = build_knee_model(replace(a, mcl=mcl, lcl=lcl))
    assert 300 <= len(model.femur.el.cells) and 300 <= len(model.tibia.el.cells)
    top = model.skin_vertices[:, 1].max()
    assert model.joint_y < model.thigh_from < top and len(model.thigh_samples()[0]) > 1000
    assert model.solver.fixed.any()
    flex0, _ = knee_angles(model)
    assert flex0 == pytest.approx(math.degrees(a.scan_tf[0]), abs=1e-9)
    s, tib = model.solver, model.tibia
    end = np.argsort(tib.el.X[:, 1])[:5]

    def push(x):
        f = np.zeros((len(tib.el.X), 3))
        f[end, 0] = -200.0  # 1000 N in all
        return tib.map.apply_transpose(f)

    for _ in range(20):
        s.step(push)
    flex, _ = knee_angles(model)
    assert np.all(np.isfinite(s.x)) and flex > flex0 + 1.0, (flex0, flex)
