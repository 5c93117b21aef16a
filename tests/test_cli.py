"""The knee command as a user runs it: real files, the command line's own entry point (in-process: a
subprocess costs seconds of imports; one test runs the installed ``knee`` script itself)."""

import contextlib
import io
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from knee.app.cli import main
from knee.foundations.motion_io import SWEEP_HEADER, read_sweep_csv
from knee.models.mechanism import load_model

KNEE = [sys.executable, "-m", "knee.app.cli"]
HEADER = ("tf_flexion_deg,tf_adduction_deg,tf_internal_rotation_deg,tf_anterior_mm,tf_proximal_mm,"
          "tf_lateral_mm,pf_flexion_deg,pf_adduction_deg,pf_internal_rotation_deg,pf_anterior_mm,"
          "pf_proximal_mm,pf_lateral_mm,max_residual_mm,jacobian_condition")


@dataclass
class Completed:
    """What a run of the command line gave: exit code, standard output and standard error."""

    returncode: int
    stdout: str
    stderr: str


def run(*args) -> Completed:
    """``knee ARGS`` in this process, as the installed script runs it (its exit code, its output)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in args])
        except SystemExit as e:  # argparse's own exits (usage errors, --help)
            code = e.code if isinstance(e.code, int) else 1
    return Completed(code, out.getvalue(), err.getvalue())


def run_subprocess(*args, cwd=None):
    env = dict(os.environ, CI="1")
    return subprocess.run(KNEE + [str(a) for a in args], capture_output=True, text=True, cwd=cwd, env=env,
                          timeout=300)


def assert_clean_error(p, *fragments, code=2):
    assert p.returncode == code, p.stderr
    assert "Traceback" not in p.stderr
    last = p.stderr.strip().splitlines()[-1]
    assert last.startswith("knee: error: ")
    for f in fragments:
        assert f in last, last


def test_models_lists_bundled_sets():
    p = run("models")
    assert p.returncode == 0
    for name in ("volunteer", "volunteer-initial", "generic-sancisi2017"):
        assert name in p.stdout


def test_sweep_csv_and_recording(tmp_path, volunteer):
    out, rrd = tmp_path / "motion.csv", tmp_path / "sweep.rrd"
    p = run("sweep", "volunteer", "--from", 0, "--to", 120, "--step", 2, "--out", out, "--rrd", rrd)
    assert p.returncode == 0, p.stderr
    lines = out.read_text().splitlines()
    assert lines[0] == HEADER == ",".join(SWEEP_HEADER)
    assert len(lines) == 62
    table = read_sweep_csv(out)
    np.testing.assert_allclose(table[:, 0], np.arange(0, 121, 2.0))
    res = volunteer.sweep(np.radians(np.arange(0, 121, 2.0)))
    np.testing.assert_allclose(table[:, 1], np.degrees(res.tf[:, 1]), atol=1e-7)
    np.testing.assert_allclose(table[:, 9], res.pf[:, 3], atol=1e-7)
    assert np.all(table[:, 12] < 1e-9) and np.all(table[:, 13] >= 1)
    assert "rerun" in p.stderr and rrd.is_file()
    rerun_bin = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    v = subprocess.run([rerun_bin, "rrd", "verify", str(rrd)], capture_output=True, text=True,
                       env=dict(os.environ, CI="1"), timeout=120)
    assert v.returncode == 0, v.stderr
    pr = subprocess.run([rerun_bin, "rrd", "print", str(rrd)], capture_output=True, text=True,
                        env=dict(os.environ, CI="1"), timeout=120)
    for entity in ("/knee/femur", "/knee/tibia", "/knee/patella", "/knee/links/acl", "/knee/links/mc",
                   "/knee/links/patellar_tendon", "/metrics/tf/adduction_deg", "/metrics/pf/flexion_deg",
                   "/metrics/tf/flexion_deg", "/metrics/solver/log10_jacobian_condition"):
        assert entity in pr.stdout, entity


def test_sweep_to_stdout_and_sphere_plane_model():
    p = run("sweep", "generic-sancisi2017", "--to", 10, "--step", 5)
    assert p.returncode == 0, p.stderr
    rows = p.stdout.strip().splitlines()
    assert rows[0] == HEADER and len(rows) == 4
    assert rows[1].split(",")[6] == ""  # no patella: PF columns empty


def test_sweep_from_a_toml_path(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text(load_model("volunteer").to_toml())
    p = run("sweep", f, "--from", 10, "--to", 20, "--step", 5, "--out", tmp_path / "m.csv")
    assert p.returncode == 0, p.stderr
    assert len((tmp_path / "m.csv").read_text().splitlines()) == 4


def test_unknown_model():
    assert_clean_error(run("sweep", "no-such-knee"), "unknown model 'no-such-knee'")


@pytest.mark.parametrize("edit, field", [
    (("length = 33.05\n", ""), "missing field 'length'"),
    (("lambda0 = 1.48", "lambda0 = nan"), "field 'lambda0' is not finite"),
    (('length = "mm"', 'length = "cm"'), 'length must be "mm"'),
])
def test_bad_toml(tmp_path, edit, field):
    text = load_model("volunteer").to_toml()
    assert edit[0] in text
    f = tmp_path / "bad.toml"
    f.write_text(text.replace(edit[0], edit[1], 1))
    assert_clean_error(run("sweep", f), field, "bad.toml")


def test_unreachable_range_writes_the_rows_it_solved(tmp_path, volunteer):
    out = tmp_path / "part.csv"
    p = run("sweep", "volunteer", "--from", 120, "--to", 140, "--out", out)
    hi = np.degrees(volunteer.assembly_range[1])
    assert_clean_error(p, "sweep stopped", f"stops assembling at {hi:.2f} deg", "last angle solved: 129.00", code=3)
    table = read_sweep_csv(out)
    np.testing.assert_allclose(table[:, 0], np.arange(120, 130.0))


def test_range_outside_assembly(tmp_path):
    p = run("sweep", "volunteer-initial", "--from", 0, "--to", 30, "--out", tmp_path / "x.csv")
    assert_clean_error(p, "outside the assembly range 7.32 to 60.04 deg", code=3)


def test_existing_files_are_not_overwritten(tmp_path):
    out = tmp_path / "keep.csv"
    out.write_text("precious")
    assert_clean_error(run("sweep", "volunteer", "--to", 5, "--out", out), "exists; not overwritten")
    assert out.read_text() == "precious"
    assert run("sweep", "volunteer", "--to", 5, "--out", out, "--force").returncode == 0
    assert out.read_text().startswith("tf_flexion_deg")


@pytest.mark.parametrize("args, msg", [
    (["--step", "0"], "--step must be positive"),
    (["--step", "-1"], "--step must be positive"),
    (["--to", "nan"], "--to must be a finite number"),
    (["--step", "45"], "--step must be at most 10"),
])
def test_bad_ranges(args, msg):
    assert_clean_error(run("sweep", "volunteer", *args), msg)


def test_argparse_errors_exit_2():
    p = run("sweep")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert p.stderr.count("\n") == 1 and p.stderr.startswith("knee: error: sweep: ")
    # an unknown option after a command is parsed by the top-level parser: its line names no command twice
    p = run("sweep", "volunteer", "--start", 0)
    assert p.returncode == 2 and p.stderr == "knee: error: unrecognized arguments: --start 0\n"


def test_the_installed_script_runs():
    """The ``knee`` console script of the installation (not this process's import of it)."""
    exe = shutil.which("knee") or str(Path(sys.executable).with_name("knee"))
    p = subprocess.run([exe, "models"], capture_output=True, text=True, env=dict(os.environ, CI="1"), timeout=120)
    assert p.returncode == 0 and "volunteer" in p.stdout, p.stderr
    p = subprocess.run([exe, "sweep", "volunteer", "--step", "0"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and p.stderr == "knee: error: --step must be positive, got 0.0\n"


def test_demo(tmp_path):
    p = run("demo", "--out", tmp_path / "demo")
    assert p.returncode == 0, p.stderr
    assert "rerun " in p.stdout and "assembles from" in p.stdout
    for f in ("volunteer-sweep.rrd", "volunteer-sweep.csv", "compare.rrd", "compare.md", "compare.csv", "compare.png"):
        assert (tmp_path / "demo" / f).is_file(), f
    rows = {ln.split()[0]: ln for ln in p.stdout.splitlines() if ln.startswith("(")}
    assert set(rows) == {"(i)", "(iii)", "(iv)"}
    # the prior-constrained FEM ends near the true 60 deg (measured 58.9); its footprint error is printed in
    # mm. On the truth's skin made by the tetrahedral tissue, it beats the mechanism alone (measured 1.53
    # against 5.05 mm), which beats the paper's method at its best reading (6.11 mm at 54.6 deg; read
    # literally it ended near extension, 9.72 mm)
    flex = float(rows["(iii)"].split("°")[0].split()[-1])
    assert abs(flex - 60.0) < 2.0
    fp = {k: float(v.split("°")[1].split()[0]) for k, v in rows.items()}
    assert fp["(iii)"] < fp["(iv)"] < fp["(i)"]
    p2 = run("demo", "--out", tmp_path / "demo", "--kinematics-only")  # a second run does not touch the first
    assert p2.returncode == 0 and (tmp_path / "demo-2" / "volunteer-sweep.rrd").is_file()
    assert not (tmp_path / "demo-2" / "compare.md").exists()
    assert_clean_error(run("demo", "--flexion", 130, "--out", tmp_path / "d3"), "--flexion must be 15-110")


def test_compare_kinematics_only(tmp_path):
    out = tmp_path / "cmp"
    p = run("compare", "volunteer", "--flexion", "45,75", "--methods", "kinematics", "--out", out, "--quiet")
    assert p.returncode == 0, p.stderr
    for f in ("compare.csv", "compare.md", "compare.png", "compare.rrd"):
        assert (out / f).is_file(), f
    import csv

    rows = list(csv.DictReader((out / "compare.csv").open()))
    assert [float(r["flexion_true_deg"]) for r in rows] == [45.0, 75.0]
    for r in rows:  # the mechanism-only estimate: within a few degrees, errors of a few mm
        assert abs(float(r["flexion_estimated_deg"]) - float(r["flexion_true_deg"])) < 3.0
        assert 0.2 < float(r["femur_footprints_mm"]) < 8.0
    assert "kinematics" in p.stdout and "prior = volunteer with every TF link endpoint moved" in p.stderr
    assert "the prior's own tibia error" in p.stdout and "The prior's own tibia error" in (out / "compare.md").read_text()
    assert_clean_error(run("compare", "volunteer", "--out", out), "not empty")


@pytest.mark.parametrize("args,msg", [
    (["--flexion", "30:20:5"], "--flexion must be FROM:TO:STEP"),
    (["--flexion", "200"], "within 0-150"),
    (["--methods", "paper,magic"], "--methods must be"),
    (["--cameras", "above"], "camera must be one of"),
    (["--perturb", "50"], "--perturb must be 0-10"),
])
def test_compare_bad_input(tmp_path, args, msg):
    assert_clean_error(run("compare", "volunteer", "--out", tmp_path / "c", *args), msg)
    assert not (tmp_path / "c").exists()


def test_compare_names_a_knee_it_cannot_find(tmp_path):
    """A path that is neither a case set, a subject folder, a parameter file nor a bundled set is named as such,
    whatever the options given with it (not an option refused as if it were a parameter set's)."""
    for extra in ([], ["--prior", "p.toml", "--truth-motion", "m.csv"]):
        assert_clean_error(run("compare", tmp_path / "nowhere", "--out", tmp_path / "c", *extra),
                           "not a case set, a subject folder, a bundled parameter set")
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("command", [["synth-subject", "x"], ["fit", "x", "--out", "y"], ["fem", "volunteer"],
                                     ["compare", "volunteer"]])
def test_a_negative_seed_is_one_line(command, tmp_path):
    p = run(*command, "--seed", "-1")
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "--seed" in p.stderr and "4294967295" in p.stderr
    assert "Traceback" not in p.stderr


def test_at_least_refuses_counts_and_numbers_out_of_range():
    import argparse

    from knee.app.console import at_least

    ap = argparse.ArgumentParser(prog="x")
    ap.add_argument("--runs", type=at_least(1))
    ap.add_argument("--flexion", type=at_least(0.0, float, 150.0))
    ok = ap.parse_args(["--runs", "1", "--flexion", "150"])
    assert ok.runs == 1 and isinstance(ok.runs, int) and ok.flexion == 150.0
    for argv, says in ((["--runs", "0"], "--runs: must be at least 1, got 0"),
                       (["--runs", "2.5"], "--runs: must be an integer, got '2.5'"),
                       (["--flexion", "150.5"], "--flexion: must be from 0 to 150, got 150.5"),
                       (["--flexion", "nan"], "--flexion: must be from 0 to 150, got nan"),
                       (["--flexion", "-1"], "--flexion: must be from 0 to 150, got -1")):
        err = io.StringIO()
        with contextlib.redirect_stderr(err), pytest.raises(SystemExit) as e:
            ap.parse_args(argv)
        assert e.value.code == 2 and err.getvalue().strip().splitlines()[-1] == f"x: error: argument {says}"


@pytest.mark.parametrize("script, argv", [("bench_mechanism", ["--repeat", "0"]), ("bench_demo", ["--runs", "-1"]),
                                          ("bench_prior", ["--repeat", "0"]),
                                          ("fem_stability", ["--steps", "0"]),
                                          ("fem_standard_case", ["--flexion", "500"]),
                                          ("bench_fem", ["--steps", "0"]), ("bench_fit", ["--repeat", "0"]),
                                          ("bench_gait", ["--repeat", "0"]), ("real_knee_fit", ["--seed", "-1"]),
                                          ("bench_subsamples", ["--every", "0"]),
                                          ("bench_subsamples", ["--subsample", "rough,hip"]),
                                          ("bench_bone_slide", ["--pushes", "0"]),
                                          ("bench_depth_edges", ["--repeats", "0"]),
                                          ("bench_loaded", ["--cases", "0"]), ("bench_loaded", ["--rounds", "0"]),
                                          ("bench_loaded", ["--loads", "-1"]), ("bench_loaded", ["--threads", "0"]),
                                          ("bench_loaded", ["--grids", "2"]),
                                          ("bench_loaded", ["--grids", "x"])])
def test_scripts_refuse_counts_out_of_range_in_one_line(script, argv):
    """A benchmark script given a count or an angle out of range stops at its arguments, one line, before
    any work (a zero repeat count had ended in a median of nothing)."""
    path = Path(__file__).resolve().parents[1] / "scripts" / f"{script}.py"
    r = subprocess.run([sys.executable, str(path), *argv], capture_output=True, text=True, timeout=120)
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert last.startswith(f"{script}.py: error: argument {argv[0]}: must be") and last.endswith(f"got {argv[1]}")


def test_an_interrupt_dropped_where_it_landed_stops_at_the_next_progress_report(monkeypatch, capsys):
    """A signal whose KeyboardInterrupt Python drops (raised in a finaliser or a callback from compiled code)
    is remembered: the next status line or progress bar raises it again, so the run does not carry on to
    write results as if nothing had happened."""
    import knee.app.console as console

    monkeypatch.setattr(console, "_stop_requested", False)
    console.say("working")
    console.ProgressBar()(0.5, "half")
    with contextlib.suppress(KeyboardInterrupt):  # where the exception is dropped
        console._interrupted(15, None)
    with pytest.raises(KeyboardInterrupt):
        console.say("still working")
    with pytest.raises(KeyboardInterrupt):
        console.ProgressBar()(0.75, "three quarters")
    assert "still working" not in capsys.readouterr().err


def test_a_librarys_log_of_a_caught_interrupt_is_not_printed(monkeypatch):
    """A library that catches the interrupt logs it with its traceback (trimesh's vertex normals do, then
    fall back): that record is dropped once interrupts are taken, other warnings are kept."""
    import logging
    import signal as signal_module

    import knee.app.console as console

    monkeypatch.setattr(signal_module, "signal", lambda *a: None)  # the test process's handlers left alone
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        console.take_terminations_as_interrupts()
        log = logging.getLogger("some.library")
        try:
            raise KeyboardInterrupt
        except BaseException:
            log.warning("unable to use sparse matrix, falling back!", exc_info=True)
        log.warning("a warning of its own")
    finally:
        root.removeHandler(handler)
    assert stream.getvalue() == "a warning of its own\n"
    assert console._not_an_interrupt in logging.lastResort.filters


def test_real_data_and_standard_case_scripts_refuse_bad_input_in_one_line(tmp_path):
    """scripts/real_knee_cases.py checks --methods and its output before reading any data,
    scripts/fem_standard_case.py says in one line that a flexion lies outside the mechanism's assembly range
    (129.3 deg for volunteer), scripts/real_knee_fit.py names the data file it misses and
    scripts/compare_priors.py refuses an output that holds a run already or is a file: exit code 2, no
    traceback, an existing output untouched."""
    scripts = Path(__file__).resolve().parents[1] / "scripts"

    def last_error(*argv):
        r = subprocess.run([sys.executable, *map(str, argv)], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and "Traceback" not in r.stderr
        return r.stderr.strip().splitlines()[-1]

    none = tmp_path / "no-data"
    assert last_error(scripts / "real_knee_cases.py", "--data", none, "--methods", "links,walk") == (
        "error: --methods must be a comma list of paper, init, links, kinematics, got 'links,walk'")
    kept = tmp_path / "kept.csv"
    kept.write_text("kept\n")
    assert last_error(scripts / "real_knee_cases.py", "--data", none, "--out", kept) == (
        f"error: {kept} exists; not overwritten (give a new file)")
    assert kept.read_text() == "kept\n"
    assert last_error(scripts / "real_knee_cases.py", "--data", none).startswith(f"error: {none}")
    line = last_error(scripts / "fem_standard_case.py", "--flexion", "140")
    assert line.startswith("error: flexion 140.00 deg is outside the assembly range") and "volunteer" in line
    assert last_error(scripts / "real_knee_fit.py", "--data", none).startswith(f"error: body-transform table {none}")
    taken = tmp_path / "runs"
    (taken / "oblique").mkdir(parents=True)
    assert last_error(scripts / "compare_priors.py", "--out", taken) == (
        f"error: {taken / 'oblique'} exists; not overwritten (give a new --out)")
    assert last_error(scripts / "compare_priors.py", "--out", kept) == (
        f"error: {kept} exists; not overwritten (give a new --out)")
    assert kept.read_text() == "kept\n" and list(taken.iterdir()) == [taken / "oblique"]
