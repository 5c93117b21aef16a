"""Virtual osteotomy: the wedge, moved insertions, alignment, the recomputed knee, and bad cuts."""

import math
import subprocess
import sys

import numpy as np
import pytest

from knee.foundations.errors import AssemblyError, KneeInputError
from knee.models.mechanism.params import load_model
from knee.models.osteotomy import (
    FUJISAWA,
    Cut,
    alignment,
    apply_cut,
    default_cut,
    moved_side,
    osteotomy,
    wedge_transform,
)
from knee.models.phantom import build_phantom


@pytest.fixture(scope="module")
def vol():
    p = load_model("volunteer")
    return p, build_phantom(p)


def test_wedge_is_a_rotation_about_the_hinge_that_opens_opposite_it(vol):
    p, ph = vol
    cut = default_cut("tibia", ph.tibia, 8.0)
    W = wedge_transform(cut)
    np.testing.assert_allclose(W[:3, :3] @ cut.hinge_point + W[:3, 3], cut.hinge_point, atol=1e-12)  # hinge fixed
    np.testing.assert_allclose(W[:3, :3].T @ W[:3, :3], np.eye(3), atol=1e-12)
    assert math.degrees(math.acos((np.trace(W[:3, :3]) - 1) / 2)) == pytest.approx(8.0)
    # the medial edge of the distal fragment (opposite the lateral hinge) moves away from the knee: opening
    medial = np.array([cut.hinge_point[0], cut.plane_point[1], -20.0])
    assert (W[:3, :3] @ medial + W[:3, 3])[1] < medial[1] - 2.0
    assert moved_side(cut, [[0, -100, 0], [0, 10, 0]]).tolist() == [True, False]


def test_alignment_closed_form_for_a_straight_limb(vol):
    """Hip and ankle on the long axes and a tibia at zero adduction: HKA equals the knee's own frontal
    angle, and the weight-bearing line crosses the plateau where the geometry says."""
    from knee.foundations.conventions import joint_to_pose
    from knee.models.mechanism import Mechanism

    p, ph = vol
    mech = Mechanism(p)
    H, A = np.array([0.0, 430.0, 0.0]), np.array([0.0, -430.0, 0.0])
    al = alignment(mech, H, A, (-50.0, 50.0))
    T = joint_to_pose(mech.motion_at(np.array([0.0]))[0][0])
    d1 = -H
    d2 = T[:3, :3] @ A
    d1[0] = d2[0] = 0
    ref = math.degrees(math.atan2(np.cross(d1, d2)[0], d1 @ d2))
    assert al.hka_deg == pytest.approx(ref, abs=1e-9)
    assert np.isclose((np.linalg.inv(T) @ np.r_[al.crossing, 1])[1], 0.0, atol=1e-9)  # on the plateau plane
    assert al.wbl_percent == pytest.approx(50.0 + (np.linalg.inv(T) @ np.r_[al.crossing, 1])[2], abs=1e-9)


def test_opening_wedge_moves_the_weight_bearing_line_laterally(vol):
    p, ph = vol
    res = osteotomy(p, default_cut("tibia", ph.tibia, 5.0), release=("mcl",))
    b, a = res.align_before, res.align_after
    assert a.wbl_percent > b.wbl_percent + 10 and a.hka_deg < b.hka_deg  # toward valgus
    assert "mcl tibia point" in res.moved and "ankle centre" in res.moved
    assert abs(a.wbl_percent - FUJISAWA) < abs(b.wbl_percent - FUJISAWA)
    # the unmoved links are untouched; the knee still assembles through 0..120 deg
    for lb, la in zip(p.links, res.params.links):
        if lb.name in ("acl", "pcl", "lc", "mc"):
            np.testing.assert_array_equal(lb.tibia, la.tibia)
    assert res.after.in_range(0.0) and res.after.in_range(math.radians(120))
    # the README's example, pinned: the weight-bearing line from 42 % to 66 % of the plateau
    assert (b.wbl_percent, a.wbl_percent) == (pytest.approx(42.15, abs=0.05), pytest.approx(66.29, abs=0.05))
    zero = osteotomy(p, default_cut("tibia", ph.tibia, 0.0))  # a zero wedge changes nothing
    assert zero.align_after.wbl_percent == pytest.approx(zero.align_before.wbl_percent, abs=1e-9)


def test_the_lateral_share_of_stance_contact_follows_the_weight_bearing_line(vol):
    """The 5 deg opening wedge moves the lateral share of the stance contact force in the normative gait
    from 0.45 to 0.64 (pinned), the two shares summing to one - counted over every frame. But every frame of
    that gait is flagged on the volunteer (a member loaded the wrong way), so the summary presents none of
    it: no figure from flagged frames."""
    import dataclasses

    from knee.models.gait import normative_trial
    from knee.models.osteotomy import compare, gait_contact_summary

    p, ph = vol
    res = osteotomy(p, default_cut("tibia", ph.tibia, 5.0), release=("mcl",))
    cmp = compare(res, normative_trial(72.0))
    before, after = gait_contact_summary(cmp.gait_before), gait_contact_summary(cmp.gait_after)
    assert not cmp.gait_before.valid.any() and "every frame is flagged" in cmp.gait_before.flagged_note
    assert before["lc"].frames == 0 and before["lc"].of == 101
    assert all(math.isnan(v) for v in (before["lc"].mean_share, before["lc"].peak_force_N, after["mc"].mean_share))

    def unflagged(g):
        return dataclasses.replace(g, statics=dataclasses.replace(g.statics, flags=[[] for _ in g.statics.flags]))

    before = gait_contact_summary(unflagged(cmp.gait_before))
    after = gait_contact_summary(unflagged(cmp.gait_after))
    assert before["lc"].mean_share == pytest.approx(0.450, abs=0.005)
    assert after["lc"].mean_share == pytest.approx(0.638, abs=0.005)
    assert before["lc"].mean_share + before["mc"].mean_share == pytest.approx(1.0)
    # half the frames flagged: the summary is over the other half only
    g = cmp.gait_before
    half = dataclasses.replace(g, statics=dataclasses.replace(g.statics, flags=[
        (["x"] if k % 2 else []) for k in range(len(g.statics.flags))]))
    s = gait_contact_summary(half)["lc"]
    ok = np.arange(len(g.statics.flags)) % 2 == 0
    assert s.frames == ok.sum() and s.peak_force_N == pytest.approx(g.contact["lc"].force[ok].max())


def test_bad_cuts_are_clear_errors(vol):
    p, ph = vol
    good = default_cut("tibia", ph.tibia, 8.0)
    with pytest.raises(KneeInputError, match="misses the tibia"):
        osteotomy(p, Cut("tibia", np.array([0, -400.0, 0]), np.array([0, 1.0, 0]), good.hinge_point,
                         good.hinge_axis, 8.0))
    with pytest.raises(KneeInputError, match="outside the tibia"):
        osteotomy(p, Cut("tibia", good.plane_point, good.plane_normal, np.array([0, -35.0, 70.0]),
                         good.hinge_axis, 8.0))
    with pytest.raises(KneeInputError, match="within"):
        osteotomy(p, Cut("tibia", good.plane_point, good.plane_normal, good.hinge_point, good.hinge_axis, 45.0))
    with pytest.raises(AssemblyError, match="does not assemble.*release mcl"):
        osteotomy(p, good)  # the MCL insertion moves 4 mm: an isometric link cannot follow
    with pytest.raises(KneeInputError, match="not a ligament"):
        apply_cut(p, good, release=("lc",))


def test_cli_osteotomy(tmp_path):
    knee = [sys.executable, "-m", "knee.app.cli", "osteotomy", "volunteer"]
    r = subprocess.run(knee + ["--angle", "5", "--release", "mcl", "--out", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for f in ("report.md", "osteotomy.png", "osteotomy.rrd", "after.toml"):
        assert (tmp_path / "o" / f).stat().st_size > 0
    assert "weight-bearing line" in (tmp_path / "o/report.md").read_text()
    assert load_model(tmp_path / "o/after.toml").link("mcl").length > 100.79
    r = subprocess.run(knee + ["--angle", "5", "--plane", "0,-400,0,0,1", "--out", str(tmp_path / "p")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "six comma-separated" in r.stderr and not (tmp_path / "p").exists()


@pytest.mark.parametrize("angle", [8.0, 15.0])
def test_clinical_wedges_are_covered_by_the_contact_model(vol, angle):
    """Clinical opening wedges are 5-15 deg: with the MCL released, the 8 and 15 deg wedges load a condyle
    with 3.4-4.9 kN in the normative gait (the elastic foundation's table used to stop at 3.2 kN and the
    whole osteotomy failed). The foundation's net force at each frame's approach equals its load."""
    from knee.models.contact import foundation_force
    from knee.models.gait import normative_trial
    from knee.models.osteotomy import compare

    p, ph = vol
    res = osteotomy(p, default_cut("tibia", ph.tibia, angle), release=("mcl",))
    cmp = compare(res, normative_trial(72.0))
    lk = res.after.params.link("lc")
    e = cmp.gait_after.contact["lc"]
    k = int(np.argmax(e.force))
    assert e.force[k] > 3300.0
    net, _ = foundation_force(e.foundation.cap, lk.femur_radius, lk.tibia_radius, lk.tibia_surface,
                              e.foundation.approach[k])
    assert net[2] == pytest.approx(e.force[k], rel=2e-3)
