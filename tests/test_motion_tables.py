"""OpenSim body-transform tables (.sto/.mot) as a subject's measured motion: a round trip through a table
built from known joint coordinates, the CT-at-a-row convention, and the real lenhart2015 passive trial."""

import shutil

import numpy as np
import pytest

from knee.fitting.frames import femur_frame, patella_frame, tibia_frame
from knee.fitting.subject import load_subject
from knee.fitting.synthetic import make_subject
from knee.foundations.conventions import joint_coordinates, joint_to_pose, rot_x, rot_y, rot_z
from knee.foundations.errors import KneeInputError
from knee.foundations.imaging import motion_from_body_transforms, read_body_transforms


@pytest.fixture(scope="module")
def subject(tmp_path_factory):
    return make_subject(tmp_path_factory.mktemp("sto") / "s", seed=2, frames=15)


def _write_sto(path, time, poses, unit_scale=1e-3):
    names = list(poses)
    head = ["time"] + [f"{b}_T{i}{j}" for b in names for i in range(1, 5) for j in range(1, 5)]
    lines = ["body transforms", "version=1", f"nRows={len(time)}", f"nColumns={len(head)}", "endheader",
             "\t".join(head)]
    for k, t in enumerate(time):
        vals = [t]
        for b in names:
            T = poses[b][k].copy()
            T[:3, 3] *= unit_scale
            vals += list(T.ravel())
        lines.append("\t".join(f"{v:.17g}" for v in vals))
    path.write_text("\n".join(lines) + "\n")


def _table_from_motion(s, rng, reference_row=None):
    """Bone poses (CT coordinates to a moving ground) that realise the subject's measured motion."""
    lm = s.ct_landmarks
    F = {"femur": femur_frame(lm), "tibia": tibia_frame(lm), "patella": patella_frame(lm)}
    n = len(s.motion.tf)
    poses = {b: np.zeros((n, 4, 4)) for b in ("femur_b", "tibia_b", "patella_b")}
    for k in range(n):
        G = np.eye(4)
        G[:3, :3] = rot_z(rng.normal(0, 0.3)) @ rot_x(rng.normal(0, 0.3)) @ rot_y(rng.normal(0, 0.3))
        G[:3, 3] = rng.normal(0, 200, 3)
        if reference_row is not None and k == reference_row:  # the CT's own pose: CT = ground at this row
            G = F["femur"]
        poses["femur_b"][k] = G @ np.linalg.inv(F["femur"])
        tf = s.motion.tf[k] if reference_row is None or k != reference_row else joint_coordinates(
            np.linalg.inv(F["femur"]) @ F["tibia"])
        pf = s.motion.pf[k] if reference_row is None or k != reference_row else joint_coordinates(
            np.linalg.inv(F["femur"]) @ F["patella"])
        poses["tibia_b"][k] = G @ joint_to_pose(tf) @ np.linalg.inv(F["tibia"])
        poses["patella_b"][k] = G @ joint_to_pose(pf) @ np.linalg.inv(F["patella"])
    return poses, F


def test_a_body_transform_table_gives_back_the_joint_coordinates(subject, tmp_path):
    d = tmp_path / "s"
    shutil.copytree(subject, d)
    s = load_subject(d)
    poses, _ = _table_from_motion(s, np.random.default_rng(0))
    _write_sto(d / "trial.sto", np.arange(len(s.motion.tf)) * 0.1, poses)
    (d / "motion.csv").unlink()
    toml = (d / "subject.toml").read_text()
    (d / "subject.toml").write_text(toml + '\n[motion]\nfile = "trial.sto"\nfemur = "femur_b"\ntibia = "tibia_b"\n'
                                    'patella = "patella_b"\n')
    m = load_subject(d).motion
    np.testing.assert_allclose(m.tf, s.motion.tf, atol=1e-9)
    np.testing.assert_allclose(m.pf, s.motion.pf, atol=1e-9)
    # both given: refused
    shutil.copy(subject / "motion.csv", d / "motion.csv")
    with pytest.raises(KneeInputError, match="not both"):
        load_subject(d)


def test_a_ct_taken_at_a_row_of_the_table(subject):
    """With reference_row k the CT shows the bones at row k: each bone moves by T(i) T(k)^-1. A table whose
    poses carry an arbitrary fixed body-to-CT offset per bone gives the same motion as the CT-to-ground one."""
    s = load_subject(subject)
    r = 4
    poses, F = _table_from_motion(s, np.random.default_rng(1), reference_row=r)
    rng = np.random.default_rng(2)
    offset = {}
    for b in poses:
        C = np.eye(4)
        C[:3, :3] = rot_x(rng.normal()) @ rot_y(rng.normal())
        C[:3, 3] = rng.normal(0, 50, 3)
        offset[b] = np.linalg.inv(C)
    from knee.foundations.imaging import BodyTransforms

    direct = BodyTransforms(np.arange(len(s.motion.tf)), poses)
    shifted = BodyTransforms(direct.time, {b: T @ offset[b] for b, T in poses.items()})
    bodies = {"femur": "femur_b", "tibia": "tibia_b", "patella": "patella_b"}
    tf0, pf0 = motion_from_body_transforms(direct, bodies, F)
    tf1, pf1 = motion_from_body_transforms(shifted, bodies, F, reference_row=r)
    np.testing.assert_allclose(tf1, tf0, atol=1e-9)
    np.testing.assert_allclose(pf1, pf0, atol=1e-9)
    keep = np.arange(len(tf0)) != r
    np.testing.assert_allclose(tf0[keep], s.motion.tf[keep], atol=1e-9)


def test_the_lenhart2015_passive_trial(shared_data):
    """The real dynamic-MRI table: 60 rows (its header says 48), three bodies, metres; in the bodies' own
    frames (x anterior, y proximal, z to the right, a right knee) the flexion spans about 10-47 deg, as the
    data's README measured."""
    t = read_body_transforms(shared_data / "lenhart2015/dynamic_mri/passive_body_transformations.sto")
    assert set(t.poses) == {"femur_distal_r", "tibia_proximal_r", "patella_r"} and len(t.time) == 60
    eye = {"femur": np.eye(4), "tibia": np.eye(4), "patella": np.eye(4)}
    tf, pf = motion_from_body_transforms(t, {"femur": "femur_distal_r", "tibia": "tibia_proximal_r",
                                             "patella": "patella_r"}, eye)
    flex = np.degrees(tf[:, 0])
    assert 5.0 < flex.min() < 15.0 and 42.0 < flex.max() < 52.0, (flex.min(), flex.max())
    assert np.abs(np.diff(flex)).max() < 10.0  # a continuous cycle, not jumps between branches
    # translations converted to mm: both knee frames sit near the joint centre, a few mm apart (in metres
    # this would read 0.003)
    assert 1.0 < np.linalg.norm(tf[:, 3:], axis=1).mean() < 20.0


def test_bad_tables_are_one_line(tmp_path):
    f = tmp_path / "t.sto"
    f.write_text("no header\n")
    with pytest.raises(KneeInputError, match="endheader"):
        read_body_transforms(f)
    f.write_text("endheader\ntime\tb_T11\n0\t1\n1\t1\n")
    with pytest.raises(KneeInputError, match="lacks column"):
        read_body_transforms(f)
    T = np.tile(np.eye(4), (3, 1, 1))
    T[1, 0, 0] = 2.0
    _write_sto(f, [0.0, 0.1, 0.2], {"b": T})
    with pytest.raises(KneeInputError, match="not rotations"):
        read_body_transforms(f)
