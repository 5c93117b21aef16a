"""The subject folder, the fitting pipeline's steps and ``knee fit`` / ``knee synth-subject``."""

import json
import math
import shutil
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from knee.app.reports.fit import check_output_folder, write_outputs
from knee.fitting.frames import SideError, femur_frame, patella_frame, tibia_frame
from knee.fitting.optimize import Motion, fit_tf, noise_weights, synthetic_motion
from knee.fitting.pipeline import (
    Geometry,
    align_mri,
    anatomical_frames,
    contact_spheres,
    first_estimate,
    fit_subject,
    helical_axis,
)
from knee.fitting.subject import load_subject
from knee.fitting.synthetic import BONE_LANDMARKS, make_subject
from knee.foundations.conventions import rot_x, rot_y, rot_z, transform_points
from knee.foundations.errors import KneeInputError
from knee.foundations.imaging import (
    read_markups,
    read_motion_csv,
    read_surface,
    surface_space,
    write_markups,
    write_motion_csv,
    write_surface,
)
from knee.models.mechanism import Mechanism
from knee.models.mechanism.params import load_model


@pytest.fixture(scope="module")
def subject_dir(tmp_path_factory):
    return make_subject(tmp_path_factory.mktemp("subj") / "s", seed=0)


def run_fit(subject_dir, out_dir, recording=True, figure=True, **kw):
    """As ``knee fit``: the output folder checked, the fit, its files; returns (outcome, files)."""
    check_output_folder(subject_dir, out_dir, force=False)
    o = fit_subject(subject_dir, **kw)
    return o, write_outputs(o, out_dir, recording=recording, figure=figure)


@pytest.fixture(scope="module")
def fitted(subject_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "out"
    return run_fit(subject_dir, out, seed=0)


def _copy(subject_dir, tmp_path):
    d = tmp_path / "copy"
    shutil.copytree(subject_dir, d)
    return d


# ---------------------------------------------------------------------------------------------- file I/O

@pytest.mark.parametrize("suffix", [".stl", ".ply", ".obj"])
@pytest.mark.parametrize("space", ["LPS", "RAS"])
def test_surface_space_comment_round_trip(tmp_path, suffix, space):
    m = trimesh.creation.icosphere(2, 20.0).apply_translation([10.0, -30.0, 55.0])
    f = write_surface(tmp_path / f"bone{suffix}", m, space)
    assert surface_space(f) == space
    back = read_surface(f)
    # LPS in and out whatever the file's space; a RAS file really holds negated x and y
    assert np.allclose(np.sort(back.vertices, axis=0), np.sort(m.vertices, axis=0), atol=1e-4)
    raw = trimesh.load(f, force="mesh")
    sign = -1.0 if space == "RAS" else 1.0
    assert np.isclose(raw.vertices[:, 0].mean(), sign * m.vertices[:, 0].mean(), atol=1e-3)
    assert back.volume > 0  # outward normals kept


def test_surface_without_comment_is_lps_and_metres_are_refused(tmp_path):
    m = trimesh.creation.icosphere(2, 20.0)
    f = tmp_path / "plain.stl"
    m.export(f)
    assert surface_space(f) == "LPS"
    small = tmp_path / "metres.stl"
    m.copy().apply_scale(0.001).export(small)
    with pytest.raises(KneeInputError, match="metres"):
        read_surface(small)
    with pytest.raises(KneeInputError, match="not found"):
        read_surface(tmp_path / "nope.stl")


def test_markups_ras_lps_and_undefined_points(tmp_path):
    pts = np.array([[1.0, 2.0, 3.0], [-4.0, 5.0, -6.0]])
    f = write_markups(tmp_path / "a.mrk.json", ["A", "B"], pts, "RAS")
    doc = json.loads(f.read_text())
    assert doc["markups"][0]["coordinateSystem"] == "RAS"
    assert doc["markups"][0]["controlPoints"][0]["position"] == [-1.0, -2.0, 3.0]
    mk = read_markups(f)
    assert np.allclose(mk.require(["A", "B"]), pts)
    doc["markups"][0]["controlPoints"][1]["positionStatus"] = "undefined"
    f.write_text(json.dumps(doc))
    mk = read_markups(f)
    assert mk.missing == ["B"]
    with pytest.raises(KneeInputError, match="B .*not defined"):
        mk.get("B")
    with pytest.raises(KneeInputError, match="missing landmark C"):
        mk.get("C")


def test_motion_csv_coordinates_and_matrices_agree_and_nan_rows_are_counted(tmp_path):
    meas, _ = synthetic_motion(load_model("volunteer"), np.linspace(0, 90, 12), seed=1)
    a = read_motion_csv(write_motion_csv(tmp_path / "q.csv", meas.tf, meas.pf))
    b = read_motion_csv(write_motion_csv(tmp_path / "T.csv", meas.tf, meas.pf, form="matrix"))
    np.testing.assert_allclose(a.tf, meas.tf, atol=1e-7)
    np.testing.assert_allclose(b.tf, meas.tf, atol=1e-7)
    np.testing.assert_allclose(b.pf, meas.pf, atol=1e-7)
    lines = (tmp_path / "q.csv").read_text().splitlines()
    cells = lines[3].split(",")
    cells[4] = "nan"
    lines[3] = ",".join(cells)
    lines[5] = lines[5].rsplit(",", 1)[0] + ","  # an empty PF cell
    (tmp_path / "q.csv").write_text("\n".join(lines) + "\n")
    c = read_motion_csv(tmp_path / "q.csv")
    assert (c.skipped, c.rows, len(c.tf)) == (2, 12, 10)
    (tmp_path / "bad.csv").write_text("frame,tf_flexion_deg\n0,1\n")
    with pytest.raises(KneeInputError, match="missing TF column"):
        read_motion_csv(tmp_path / "bad.csv")


# ---------------------------------------------------------------------------------------------- frames

def test_frames_recover_a_known_pose_and_catch_a_mirrored_knee():
    T = np.eye(4)
    T[:3, :3] = rot_x(0.3) @ rot_y(-1.1) @ rot_z(2.0)
    T[:3, 3] = [12.0, -40.0, 300.0]
    lm = {b: {k: transform_points(T, np.array(v, float)[None])[0] for k, v in d.items()}
          for b, d in BONE_LANDMARKS.items()}
    lm["femur"]["PAL"] = transform_points(T, np.array([[30.0, 20.0, 20.0]]))[0]
    np.testing.assert_allclose(femur_frame(lm["femur"]), T, atol=1e-12)
    np.testing.assert_allclose(tibia_frame(lm["tibia"]), T, atol=1e-12)
    np.testing.assert_allclose(patella_frame(lm["patella"]), T, atol=1e-12)
    M = np.diag([-1.0, 1.0, 1.0])  # a left knee's landmarks in the same scanner
    with pytest.raises(SideError, match="left knee"):
        femur_frame({k: M @ v for k, v in lm["femur"].items()})
    with pytest.raises(SideError, match="left knee"):
        tibia_frame({k: M @ v for k, v in lm["tibia"].items()})
    bad = dict(lm["femur"], ME=lm["femur"]["LE"])
    with pytest.raises(KneeInputError):
        femur_frame(bad)


# ---------------------------------------------------------------------------------------------- steps

def test_steps_recover_the_synthetic_geometry(subject_dir):
    s = load_subject(subject_dir)
    truth = load_model(subject_dir / "truth.toml")
    geo = Geometry(anatomical_frames(s), align_mri(s))
    # the frames are the phantom's: a CT landmark maps back to its bone-frame position exactly
    le = geo.to_bone(s.ct_landmarks.get("LE")[None], "femur", "ct")[0]
    np.testing.assert_allclose(le, BONE_LANDMARKS["femur"]["LE"], atol=1e-9)
    for b, a in align_mri(s).items():  # 0.3 mm identification noise on the MRI fiducials
        assert 0.0 < max(a.fre.values()) < 1.0
    c = contact_spheres(s, geo)
    for side, name in (("lateral", "lc"), ("medial", "mc")):
        lk = truth.link(name)
        assert c[side].surface == lk.tibia_surface
        assert c[side].femur.radius == pytest.approx(lk.femur_radius, abs=0.02)
        assert c[side].length == pytest.approx(lk.length, abs=0.3)
        assert np.linalg.norm(c[side].femur.centre - lk.femur) < 0.8  # alignment noise only
        assert np.linalg.norm(c[side].tibia.centre - lk.tibia) < 0.8
    ax = helical_axis(s, geo)
    n_true = truth.pf.axis_femur / np.linalg.norm(truth.pf.axis_femur)
    assert math.degrees(math.acos(min(1.0, ax.n @ n_true))) < 1.0
    assert np.linalg.norm(ax.q - truth.pf.point_femur) < 1.0


def test_first_estimate_is_within_reach_and_assembles_near_extension(subject_dir):
    s = load_subject(subject_dir)
    first, info = first_estimate(s)
    truth = load_model(subject_dir / "truth.toml")
    for lk in first.links:  # isometric fibres under 1.5 mm / 2 deg noise: a few mm (why the paper optimises)
        t = truth.link(lk.name)
        assert np.linalg.norm(lk.femur - t.femur) < 4.5 and np.linalg.norm(lk.tibia - t.tibia) < 4.5
    assert abs(first.pf.tendon_length - truth.pf.tendon_length) < 2.0
    assert abs(first.pf.lambda1 - truth.pf.lambda1) < 1.0
    lo, hi = Mechanism(first).assembly_range
    assert lo < 0.0 < hi


def test_tendon_centroids_are_projected_onto_the_ct_surfaces(subject_dir, tmp_path):
    d = _copy(subject_dir, tmp_path)
    toml = (d / "subject.toml").read_text().replace("project_tendon = false", "project_tendon = true")
    (d / "subject.toml").write_text(toml)
    s = load_subject(d)
    first, info = first_estimate(s)
    from knee.foundations.surfaces import SurfaceQuery

    for bone, p in (("tibia", first.pf.tendon_tibia), ("patella", first.pf.tendon_patella)):
        mesh = s.ct[bone].copy().apply_transform(np.linalg.inv(info.frames[bone]))
        assert abs(SurfaceQuery.of(mesh).signed_distance(p[None])[0]) < 1e-3


def test_fit_same_seed_same_result(subject_dir):
    s = load_subject(subject_dir)
    first, _ = first_estimate(s)
    m = Motion(s.motion.tf, None)
    runs = [fit_tf(first, m, seed=5, popsize=4, maxiter=2, local_starts=1, weights=noise_weights()) for _ in range(2)]
    np.testing.assert_array_equal(runs[0].params.to_vector(), runs[1].params.to_vector())


# ---------------------------------------------------------------------------------------------- whole fit

def test_pipeline_outputs_and_accuracy(fitted, subject_dir):
    o, files = fitted
    for key in ("first_estimate", "fitted", "report_json", "report_md", "figure", "recording"):
        assert files[key].is_file() and files[key].stat().st_size > 0
    p = load_model(files["fitted"])  # loadable by `knee sweep`
    assert p.has_pf and Mechanism(p).in_range(math.radians(120))
    rep = json.loads(files["report_json"].read_text())
    # the fit improves on the measured motion over the first estimate
    fe, ff = o.first_errors, o.fitted_errors
    if fe is not None:
        assert np.mean(ff.tf.mae[1:]) < np.mean(fe.tf.mae[1:])
    # against the noise-free truth (measured with seed 0: TF 0.52/0.45 deg, 0.12/0.20/0.22 mm; PF <= 0.6)
    t = o.truth_errors
    assert np.all(t.tf.mae[1:3] < 0.8) and np.all(t.tf.mae[3:] < 0.5), t.tf.mae
    assert np.all(t.pf.mae[:3] < 1.0) and np.all(t.pf.mae[3:] < 0.5), t.pf.mae
    assert rep["fitted_vs_truth"]["tf"]["adduction"]["mae"] == pytest.approx(t.tf.mae[1])
    md = files["report_md"].read_text()
    assert "| TF | MAE | input |" in md
    # the report states the assembly range against the measured and the needed ranges, and what the fit
    # determines: the same figures as the fit's own diagnostics
    lo, hi = (math.degrees(v) for v in Mechanism(p).assembly_range)
    assert rep["assembly_range_deg"]["fitted"] == pytest.approx([lo, hi], abs=1e-6)
    assert rep["assembly_range_deg"]["needed"] == [0.0, 120.0] and "## Assembly range" in md
    for g in ("tf", "pf"):
        d = o.diagnostics[g]
        assert rep["identifiability"][g]["condition_number"] == pytest.approx(d.condition)
        assert len(rep["identifiability"][g]["ci95"]) == len(d.names) == (35 if g == "tf" else 17)
        assert f"## What the fit determines: {g.upper()} group" in md
        on = [n for n, _ in d.on_bound]
        assert all(n in md for n in on)
        assert not on or any(f"{len(on)} of {len(d.names)} {g.upper()} variables end on their bounds" in w
                             for w in o.warnings)
    # the input folder is untouched
    assert not any(f.name in ("fitted.toml", "report.json") for f in subject_dir.rglob("*"))


# ---------------------------------------------------------------------------------------------- bad input

def _mirror_folder(src, dst, side):
    """A mirrored copy of a subject folder (LPS x negated): what a left knee's scans look like."""
    shutil.copytree(src, dst)
    for f in list(dst.rglob("*.stl")) + list(dst.rglob("*.ply")):
        m = read_surface(f)
        m.vertices[:, 0] *= -1
        m.invert()
        write_surface(f, m, surface_space(f))
    for f in dst.rglob("*.mrk.json"):
        mk = read_markups(f)
        write_markups(f, mk.labels, mk.points * [-1, 1, 1], json.loads(f.read_text())["markups"][0]["coordinateSystem"])
    toml = (dst / "subject.toml").read_text().replace('side = "right"', f'side = "{side}"')
    (dst / "subject.toml").write_text(toml)
    return dst


def test_left_knee_is_mirrored_and_a_mislabelled_one_is_refused(subject_dir, tmp_path):
    right, _ = first_estimate(load_subject(subject_dir))
    left_dir = _mirror_folder(subject_dir, tmp_path / "left", "left")
    left, _ = first_estimate(load_subject(left_dir))
    np.testing.assert_allclose(left.to_vector(), right.to_vector(), atol=1e-6)
    wrong = _mirror_folder(subject_dir, tmp_path / "wrong", "right")
    with pytest.raises(SideError, match="left knee"):
        first_estimate(load_subject(wrong))


def test_missing_and_degenerate_inputs_name_what_is_wrong(subject_dir, tmp_path):
    d = _copy(subject_dir, tmp_path)
    mk = read_markups(d / "ct/landmarks.mrk.json")
    keep = [i for i, lb in enumerate(mk.labels) if lb != "PAL"]
    write_markups(d / "ct/landmarks.mrk.json", [mk.labels[i] for i in keep], mk.points[keep])
    with pytest.raises(KneeInputError, match="missing landmark PAL"):
        load_subject(d)
    shutil.rmtree(d)
    d = _copy(subject_dir, tmp_path)
    (d / "mri/areas/pcl_tibia.mrk.json").unlink()
    with pytest.raises(KneeInputError, match="missing area pcl_tibia"):
        first_estimate(load_subject(d))
    shutil.rmtree(d)
    d = _copy(subject_dir, tmp_path)
    area = read_markups(d / "mri/areas/femur_lateral_condyle.mrk.json")
    write_markups(d / "mri/areas/femur_lateral_condyle.mrk.json", area.labels[:3], area.points[:3])
    with pytest.raises(KneeInputError, match="femur_lateral_condyle.*at least 4 points, got 3"):
        first_estimate(load_subject(d))
    flat = np.column_stack([np.linspace(0, 10, 20), np.linspace(5, -5, 20) ** 2 * 0, np.zeros(20)])
    flat[:, 1] = np.tile([0.0, 3.0], 10)
    write_markups(d / "mri/areas/femur_lateral_condyle.mrk.json", ["p"] * 20, flat)
    with pytest.raises(KneeInputError, match="20 points are .*coplanar"):
        first_estimate(load_subject(d))
    shutil.rmtree(d)
    d = _copy(subject_dir, tmp_path)
    m = read_surface(d / "ct/tibia.stl")
    write_surface(d / "ct/tibia.stl", m.apply_scale(0.001))
    with pytest.raises(KneeInputError, match="metres"):
        load_subject(d)


def test_areas_as_per_vertex_labels_give_the_same_fit(subject_dir, tmp_path):
    """A region given as vertex indices into the MRI surface (mri/labels/<bone>.json) instead of a point list."""
    d = _copy(subject_dir, tmp_path)
    s = load_subject(d)
    region = s.area("femur_lateral_condyle").points
    verts = s.mri["femur"].vertices
    idx = [int(np.argmin(np.linalg.norm(verts - p, axis=1))) for p in region]
    (d / "mri/labels").mkdir()
    (d / "mri/labels/femur.json").write_text(json.dumps({"femur_lateral_condyle": idx}))
    (d / "mri/areas/femur_lateral_condyle.mrk.json").unlink()
    s2 = load_subject(d)
    geo = Geometry(anatomical_frames(s2), align_mri(s2))
    c1 = contact_spheres(s, Geometry(anatomical_frames(s), align_mri(s)))["lateral"].femur
    c2 = contact_spheres(s2, geo)["lateral"].femur
    assert s2.area("femur_lateral_condyle").source.endswith(":femur_lateral_condyle")
    np.testing.assert_allclose(c2.centre, c1.centre, atol=1e-4)
    (d / "mri/labels/femur.json").write_text(json.dumps({"femur_lateral_condyle": [0, 1, 10 ** 7]}))
    with pytest.raises(KneeInputError, match="vertex indices outside"):
        load_subject(d).area("femur_lateral_condyle")


def test_nan_rows_are_skipped_and_counted_in_the_report(subject_dir, tmp_path):
    d = _copy(subject_dir, tmp_path)
    lines = (d / "motion.csv").read_text().splitlines()
    lines[7] = lines[7].replace(lines[7].split(",")[3], "nan", 1)
    (d / "motion.csv").write_text("\n".join(lines) + "\n")
    o, _ = run_fit(d, tmp_path / "out", effort="quick", recording=False, figure=False)
    rep = json.loads((tmp_path / "out/report.json").read_text())
    assert rep["motion"]["rows_skipped"] == 1 and rep["motion"]["frames_used"] == 59
    assert any("1 of 60 motion rows skipped" in w for w in o.warnings)
    with pytest.raises(KneeInputError, match="not empty"):
        run_fit(d, tmp_path / "out")
    with pytest.raises(KneeInputError, match="lies inside the input folder"):
        run_fit(d, d / "results")
    with pytest.raises(KneeInputError, match="holds an input"):
        run_fit(d, d.parent)
    with pytest.raises(KneeInputError, match="is also an input"):
        run_fit(d, d)


def test_cli_synth_subject_and_fit(tmp_path):
    knee = [sys.executable, "-m", "knee.app.cli"]
    r = subprocess.run(knee + ["synth-subject", str(tmp_path / "s"), "--seed", "4", "--frames", "30"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    r = subprocess.run(knee + ["fit", str(tmp_path / "s"), "--out", str(tmp_path / "o"), "--quick",
                               "--no-recording"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "TF MAE" in r.stdout and "100%" in r.stderr  # the progress bar ran to the end
    assert load_model(tmp_path / "o/fitted.toml").has_pf
    again = subprocess.run(knee + ["fit", str(tmp_path / "s"), "--out", str(tmp_path / "o")],
                           capture_output=True, text=True)
    assert again.returncode == 2 and again.stderr.count("\n") == 1 and "not empty" in again.stderr
    r = subprocess.run(knee + ["synth-subject", str(tmp_path / "s")], capture_output=True, text=True)
    assert r.returncode == 2 and "not empty" in r.stderr
    r = subprocess.run(knee + ["fit", str(tmp_path / "missing"), "--out", str(tmp_path / "o2")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "not found" in r.stderr
