"""The Pinocchio lower-limb chain, inverse dynamics and the gait analysis."""

import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest

from models.gait import (Anthropometry, GaitTrial, _quaternions, analyse_gait, knee_kinematics, normative_trial,
                         read_gait_csv)
from toolkit.conventions import invert_poses, joint_to_pose
from toolkit.errors import AssemblyError, KneeInputError


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
    M = [pin.SE3(T[:3, :3], T[:3, 3] * 1e-3) for T in kin["T"]]
    v_fd = pin.log6(M[0].inverse() * M[2]).vector / (2 * dt)
    np.testing.assert_allclose(kin["v"][1], v_fd, rtol=1e-5, atol=1e-8)
    a_fd = (kin["v"][2] - kin["v"][0]) / (2 * dt)
    np.testing.assert_allclose(kin["a"][1], a_fd, rtol=1e-3, atol=1e-5)


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


def test_normative_gait_runs_and_flags_honestly(volunteer):
    trial = normative_trial(72.0)
    assert trial.time.size == 101 and np.degrees(trial.knee).max() == pytest.approx(60, abs=1)
    assert trial.grf[:, 1].max() == pytest.approx(1.1 * 72 * 9.81, rel=0.01)
    res = analyse_gait(volunteer, trial)
    for name, e in res.contact.items():
        assert np.all(e["force"] >= 0) and np.all(np.isfinite(e["hertz"].peak))
        assert e["foundation_peak"].max() > e["hertz"].peak.max()  # thin layers concentrate pressure
    # members loaded the wrong way are reported per frame, never hidden
    assert len(res.flags) == sum(1 for f in res.statics.flags if f)


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
    r = subprocess.run([sys.executable, "-m", "toolkit.cli", "gait", "volunteer", "--out", str(tmp_path / "g")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "g/gait.rrd").stat().st_size > 0 and (tmp_path / "g/gait.png").is_file()
    rows = (tmp_path / "g/gait.csv").read_text().splitlines()
    assert len(rows) == 102 and "lc_hertz_peak_MPa" in rows[0]
    r = subprocess.run([sys.executable, "-m", "toolkit.cli", "gait", "volunteer", "--out", str(tmp_path / "g")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "not empty" in r.stderr
    r = subprocess.run([sys.executable, "-m", "toolkit.cli", "gait", "generic-sancisi2017", "--out",
                        str(tmp_path / "h")], capture_output=True, text=True)
    assert r.returncode == 2 and "patella" in r.stderr


def test_cli_contact_against_flexion(tmp_path):
    r = subprocess.run([sys.executable, "-m", "toolkit.cli", "contact", "volunteer", "--load", "700", "--out",
                        str(tmp_path / "c")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rows = (tmp_path / "c/contact.csv").read_text().splitlines()
    head = rows[0].split(",")
    table = np.array([[float(v) for v in row.split(",")] for row in rows[1:]])
    assert table[0, 0] == 0.0 and table[-1, 0] == 120.0
    # with Hertz, area and peak pressure follow from the force by the closed form (independent recomputation)
    from models.contact import hertz
    from models.mechanism.params import load_model

    lc = load_model("volunteer").link("lc")
    f = table[:, head.index("lc_force_N")]
    np.testing.assert_allclose(table[:, head.index("lc_hertz_peak_MPa")],
                               hertz(f, lc.femur_radius, lc.tibia_radius, "convex").peak, rtol=1e-5, atol=1e-6)
    r = subprocess.run([sys.executable, "-m", "toolkit.cli", "contact", "volunteer", "--load", "-5", "--out",
                        str(tmp_path / "d")], capture_output=True, text=True)
    assert r.returncode == 2 and "--load" in r.stderr
