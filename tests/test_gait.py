"""The Pinocchio lower-limb chain, inverse dynamics and the gait analysis."""

import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest

from knee.foundations.conventions import invert_poses, joint_to_pose
from knee.foundations.errors import AssemblyError, KneeInputError
from knee.models.gait import (
    Anthropometry,
    GaitTrial,
    _quaternions,
    analyse_gait,
    knee_kinematics,
    normative_trial,
    read_gait_csv,
)


def _trial(n=41, dur=0.8, knee=None, grf=None, still=False):
    t = np.linspace(0, dur, n)
    k = np.radians(20 + 15 * np.sin(2 * np.pi * t / dur)) if knee is None else knee
    hip = np.column_stack([np.radians(10 + 5 * np.cos(2 * np.pi * t / dur)), np.zeros(n), np.zeros(n)])
    ank = np.radians(5 * np.sin(2 * np.pi * t / dur))
    if still:
        k, hip, ank = np.full(n, k[0]), np.tile(hip[0], (n, 1)), np.full(n, ank[0])
    return GaitTrial(time=t, hip=hip, knee=k, ankle=ank, grf=np.zeros((n, 3)) if grf is None else grf,
                     cop=np.full(n, 40.0))


def test_quaternions_match_pinocchio():
    rng = np.random.default_rng(0)
    R = np.array([pin.rpy.rpyToMatrix(*rng.uniform(-3, 3, 3)) for _ in range(50)])
    R[0] = np.diag([1.0, -1.0, -1.0])  # 180 deg turns exercise the other branches
    R[1] = np.diag([-1.0, 1.0, -1.0])
    q = _quaternions(R)
    for k in range(len(R)):
        back = pin.Quaternion(q[k, 3], q[k, 0], q[k, 1], q[k, 2]).toRotationMatrix()
        np.testing.assert_allclose(back, R[k], atol=1e-12)


def test_tibia_velocity_and_acceleration_agree_with_pinocchio_lie_group(volunteer):
    """Our chain-rule twist equals Pinocchio's own difference of configurations (SE3 log), and the
    acceleration its derivative: an independent check of the free-flyer convention."""
    dt = 1e-4
    t = np.array([0.3 - dt, 0.3, 0.3 + dt])
    a_of = lambda s: np.radians(40 + 30 * np.sin(3 * s))  # noqa: E731
    al = a_of(t)
    ad = np.radians(90 * np.cos(3 * t))
    add = np.radians(-270 * np.sin(3 * t))
    kin = knee_kinematics(volunteer, al, ad, add)
    M = [pin.SE3(T[:3, :3], T[:3, 3] * 1e-3) for T in kin.T]
    v_fd = pin.log6(M[0].inverse() * M[2]).vector / (2 * dt)
    np.testing.assert_allclose(kin.v[1], v_fd, rtol=1e-5, atol=1e-8)
    a_fd = (kin.v[2] - kin.v[0]) / (2 * dt)
    np.testing.assert_allclose(kin.a[1], a_fd, rtol=1e-3, atol=1e-5)


def test_helical_patella_follows_the_mechanism(volunteer):
    """Pinocchio's helical joint at the mechanism's angle puts the patella where the PF group does."""
    res = analyse_gait(volunteer, _trial(), foundation=False)
    rel = invert_poses(res.poses["femur"]) @ res.poses["patella"]
    rel[:, :3, 3] *= 1e3
    np.testing.assert_allclose(rel, joint_to_pose(res.pf), atol=1e-8)
    tib = invert_poses(res.poses["femur"]) @ res.poses["tibia"]
    tib[:, :3, 3] *= 1e3
    np.testing.assert_allclose(tib, joint_to_pose(res.tf), atol=1e-9)


def test_static_knee_load_equals_gravity_and_grf_by_hand(volunteer):
    """Standing still: the load on the tibia is the weight of shank and foot plus the GRF, and the moment
    about the knee follows from their points of action (computed here from the segment data by hand)."""
    anthro = Anthropometry(80.0, 1.8)
    n = 5
    grf = np.tile([30.0, 400.0, -20.0], (n, 1))
    res = analyse_gait(volunteer, _trial(n=n, still=True, grf=grf), anthro, foundation=False)
    k = 2
    Tt, Tf = res.poses["tibia"][k], res.poses["foot"][k]
    Ls, ms, cs, _ = anthro.shank
    Lf, mf, cf, _ = anthro.foot
    g = np.array([0.0, -9.81, 0.0])
    com_shank = Tt[:3, :3] @ [0.0, -cs * Ls, 0.0] + Tt[:3, 3]
    com_foot = Tf[:3, :3] @ [-0.2 * Lf + cf * Lf, -0.5 * anthro.ankle_height, 0.0] + Tf[:3, 3]
    cop = Tf[:3, :3] @ [0.040, -anthro.ankle_height, 0.0] + Tf[:3, 3]
    # what acts on the tibia subtree besides the femur: gravity and the GRF (world frame, about the knee)
    F_ext = ms * g + mf * g + grf[k]
    o = Tt[:3, 3]
    M_ext = np.cross(com_shank - o, ms * g) + np.cross(com_foot - o, mf * g) + np.cross(cop - o, grf[k])
    R = Tt[:3, :3]
    np.testing.assert_allclose(res.knee_force[k], R.T @ F_ext, atol=1e-6)
    np.testing.assert_allclose(res.knee_moment[k], R.T @ M_ext * 1e3, atol=1e-3)


def test_segment_parameters_are_de_leva_and_winter():
    """Segment lengths (Winter 2009: thigh 0.245 H, shank 0.246 H, foot 0.152 H, ankle height 0.039 H) and
    masses, centres of mass and radii of gyration (de Leva 1996, Table 4, males; % of body mass, % of the
    segment's length from its proximal end; radii sagittal, transverse, longitudinal)."""
    a = Anthropometry(80.0, 1.8)
    published = {"thigh": (0.245, 14.16, 40.95, (32.9, 32.9, 14.9)),
                 "shank": (0.246, 4.33, 44.59, (25.5, 24.9, 10.3)),
                 "foot": (0.152, 1.37, 44.15, (25.7, 24.5, 12.4))}
    for seg, (length, mass_pct, com_pct, radii_pct) in published.items():
        L, m, com, radii = getattr(a, seg)
        assert L == pytest.approx(length * 1.8) and m == pytest.approx(mass_pct / 100 * 80.0)
        assert com == pytest.approx(com_pct / 100)
        np.testing.assert_allclose(radii, np.array(radii_pct) / 100)
    assert a.ankle_height == pytest.approx(0.039 * 1.8)


def test_a_hanging_shank_loads_the_knee_with_its_weight(volunteer):
    """Standing still with the foot off the ground: the femur holds up shank and foot, 5.70 % of body mass
    (de Leva 1996: 4.33 % + 1.37 %): 44.73 N for 80 kg, along gravity, whatever the segment model inside."""
    res = analyse_gait(volunteer, _trial(n=5, still=True), Anthropometry(80.0, 1.8), foundation=False)
    R = res.poses["tibia"][2][:3, :3]
    np.testing.assert_allclose(R @ res.knee_force[2], [0.0, -0.0570 * 80.0 * 9.81, 0.0], atol=1e-6)


def test_normative_gait_runs_and_flags_honestly(volunteer):
    trial = normative_trial(72.0)
    assert trial.time.size == 101 and np.degrees(trial.knee).max() == pytest.approx(60, abs=1)
    assert trial.grf[:, 1].max() == pytest.approx(1.1 * 72 * 9.81, rel=0.01)
    res = analyse_gait(volunteer, trial)
    for name, e in res.contact.items():
        assert np.all(e.force >= 0) and np.all(np.isfinite(e.hertz.peak))
        assert e.foundation.peak.max() > e.hertz.peak.max()  # thin layers concentrate pressure
    # members loaded the wrong way are reported per frame, never hidden: a frame is flagged exactly when a
    # ligament or the tendon pushes, or a contact pulls, or no ligament carries tension (checked here on
    # the member forces themselves)
    st = res.statics
    roles = np.array(st.roles)
    lig, con, ten = roles == "ligament", roles == "contact", roles == "tendon"
    wrong = ((st.forces[:, lig | ten] < -1e-6).any(axis=1) | (st.forces[:, con] > 1e-6).any(axis=1)
             | (st.forces[:, lig] <= 1e-6).all(axis=1))
    flagged = np.array([bool(f) and any("push" in x or "pull" in x or "slack" in x for x in f) for f in st.flags])
    np.testing.assert_array_equal(flagged, wrong)
    assert wrong.any()  # walking needs muscles (the hamstrings) that this model does not have
    assert len(res.flags) == sum(1 for f in st.flags if f)


def test_gait_csv_errors(tmp_path):
    f = tmp_path / "g.csv"
    f.write_text("time_s,hip_flexion_deg,knee_flexion_deg\n0,1,2\n0.1,1,2\n0.2,1,2\n")
    with pytest.raises(KneeInputError, match="missing column.*ankle_dorsiflexion_deg"):
        read_gait_csv(f, 70)
    f.write_text("time_s,hip_flexion_deg,knee_flexion_deg,ankle_dorsiflexion_deg,grf_vertical_N,grf_anterior_N\n"
                 "0,1,2,0,0,0\n0.2,1,2,0,0,0\n0.1,1,2,0,0,0\n")
    with pytest.raises(KneeInputError, match="time is not increasing at row 3"):
        read_gait_csv(f, 70)
    f.write_text("time_s,hip_flexion_deg,knee_flexion_deg,ankle_dorsiflexion_deg\n0,1,2,0\n0.1,1,2,0\n0.2,1,2,0\n")
    with pytest.raises(KneeInputError, match="grf_anterior_N"):
        read_gait_csv(f, 70)


def test_knee_outside_the_assembly_range_is_refused(volunteer):
    with pytest.raises(AssemblyError, match="outside the assembly range"):
        analyse_gait(volunteer, _trial(knee=np.radians(np.linspace(100, 140, 41))), foundation=False)


def test_cli_gait(tmp_path):
    r = subprocess.run([sys.executable, "-m", "knee.app.cli", "gait", "volunteer", "--out", str(tmp_path / "g")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "g/gait.rrd").stat().st_size > 0 and (tmp_path / "g/gait.png").is_file()
    rows = (tmp_path / "g/gait.csv").read_text().splitlines()
    assert len(rows) == 102 and "lc_hertz_peak_MPa" in rows[0]
    r = subprocess.run([sys.executable, "-m", "knee.app.cli", "gait", "volunteer", "--out", str(tmp_path / "g")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "not empty" in r.stderr
    r = subprocess.run([sys.executable, "-m", "knee.app.cli", "gait", "generic-sancisi2017", "--out",
                        str(tmp_path / "h")], capture_output=True, text=True)
    assert r.returncode == 2 and "patella" in r.stderr


def test_cli_contact_against_flexion(tmp_path):
    r = subprocess.run([sys.executable, "-m", "knee.app.cli", "contact", "volunteer", "--load", "700", "--out",
                        str(tmp_path / "c")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rows = (tmp_path / "c/contact.csv").read_text().splitlines()
    head = rows[0].split(",")
    table = np.array([[float(v) for v in row.split(",")] for row in rows[1:]])
    assert table[0, 0] == 0.0 and table[-1, 0] == 120.0
    # with Hertz, area and peak pressure follow from the force by the closed form (Johnson 1985, written out
    # here): E* = E / (2 (1 - nu^2)) for two equal layers, R* = 1 / (1/R_f + 1/R_t) on a convex facet,
    # a = (3 F R* / (4 E*))^(1/3), p0 = 3 F / (2 pi a^2)
    from knee.models.mechanism.params import load_model

    lc = load_model("volunteer").link("lc")
    f = table[:, head.index("lc_force_N")]
    E_star = 5.0 / (2 * (1 - 0.45 ** 2))
    R_star = 1.0 / (1.0 / lc.femur_radius + 1.0 / lc.tibia_radius)
    a = (3 * f * R_star / (4 * E_star)) ** (1 / 3)
    np.testing.assert_allclose(table[:, head.index("lc_hertz_area_mm2")], np.pi * a ** 2, rtol=1e-5)
    loaded = f > 0  # an unloaded contact has no area and no pressure
    assert loaded.sum() >= 20
    np.testing.assert_allclose(table[loaded, head.index("lc_hertz_peak_MPa")],
                               3 * f[loaded] / (2 * np.pi * a[loaded] ** 2), rtol=1e-5)
    assert np.all(table[~loaded, head.index("lc_hertz_peak_MPa")] == 0.0)
    r = subprocess.run([sys.executable, "-m", "knee.app.cli", "contact", "volunteer", "--load", "-5", "--out",
                        str(tmp_path / "d")], capture_output=True, text=True)
    assert r.returncode == 2 and "--load" in r.stderr


def test_the_bundled_normative_cycle_is_what_its_script_generates():
    """models/data/gait-normative.csv is reproducible: scripts/make_normative_gait.py generates it byte for
    byte (a hand edit of the file, or of the script's key values without regenerating it, fails here), and
    it passes through the textbook key values it is drawn through (knee 5 deg at heel strike and 60 deg in
    swing at 73 %, the vertical force zero in swing)."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("make_normative_gait", root / "scripts" / "make_normative_gait.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    bundled = (root / "models" / "data" / "gait-normative.csv").read_text(encoding="utf-8")
    assert script.text() == bundled
    header, t = script.table()
    col = {h: t[:, i] for i, h in enumerate(header)}
    assert col["knee_flexion_deg"][0] == pytest.approx(5.0) and col["knee_flexion_deg"][73] == pytest.approx(60.0)
    assert np.all(col["grf_vertical_bw"][63:] == 0.0) and np.all(np.isnan(col["cop_anterior_mm"][63:]))
