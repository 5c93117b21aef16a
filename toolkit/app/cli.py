"""The ``knee`` command line: the parser, and the dispatch to one module per command
(:mod:`knee.app.commands`).

    knee models
    knee sweep MODEL [--from 0] [--to 120] [--step 1] [--out motion.csv] [--rrd sweep.rrd] [--force]
    knee demo [--out DIR] [--flexion 60] [--kinematics-only]
    knee synth-subject OUT_DIR [--model volunteer] [--seed N] [--frames 60] [--depth-frame DEG]
    knee fit SUBJECT_DIR --out OUT_DIR [--seed N] [--quick] [--no-global] [--no-recording] [--force]
             [--bounds KEY=VALUE,...] [--noise KEY=VALUE,...] [--assemble-over 0:120|none] [--average-halves]
             [--also-trial MOTION.csv] [--check-trial MOTION.csv]
    knee gait MODEL [--trial CSV] [--mass 72] [--height 1.75] [--out DIR] [--rrd FILE] [--force]
    knee contact MODEL [--load 700] [--out DIR] [--force]
    knee osteotomy MODEL --bone tibia|femur --angle 8 [--plane px,py,pz,nx,ny,nz] [--hinge hx,hy,hz,ax,ay,az]
                   [--release mcl] [--trial CSV] [--mass 72] [--height 1.75] [--out DIR] [--force]
    knee compare MODEL [--truth MODEL] [--flexion 30:120:15] [--cameras oblique,frontal,lateral] [--out DIR]
    knee compare CASE_SET [--methods links,kinematics,init,paper] [--only ID,...] [--cells-across knee|N|NX,NZ] [--out DIR]
    knee fem MODEL [--flexion 90] [--truth MODEL] [--camera oblique|frontal|lateral|AZ,EL,DIST] [--rrd FILE]
             [--cloud FILE | --depth FILE --intrinsics fx,fy,cx,cy [--depth-scale 1]] [--keep-flying] [--pose FILE]
    knee fem SUBJECT_DIR --prior FITTED.toml (--depth FILE --intrinsics fx,fy,cx,cy | --cloud FILE)
             [--initial-pose FILE] [--method links|init|kinematics|paper] [--cells-across knee|N|NX,NZ] --out DIR

Angles in degrees, lengths in mm. Exit codes: 0 success; 2 bad input or an output that cannot be written
(one line ``knee: error: ...``); 3 a numerical failure on good input (the mechanism does not assemble, a
simulation diverges, a solve does not converge; one line ``knee: error: ...``); 70 an unexpected error (a
bug; one line, ``KNEE_DEBUG=1`` for the traceback); 130 interrupted (Ctrl-C). No existing file is overwritten
unless ``--force`` is given.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from knee.app.console import at_least, error, take_terminations_as_interrupts
from knee.app.threads import set_threads
from knee.foundations.errors import (
    EXIT_BAD_INPUT,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_NUMERICAL,
    KneeInputError,
    KneeNumericalError,
)

#: Each command's module in :mod:`knee.app.commands`, imported when the command runs (so that ``knee
#: models`` does not pay for open3d and matplotlib): it defines ``run(args) -> int``.
COMMANDS = {"models": "models", "sweep": "sweep", "demo": "demo", "synth-subject": "synth_subject", "fit": "fit",
            "gait": "gait", "contact": "contact", "osteotomy": "osteotomy", "compare": "compare", "fem": "fem"}

#: The finest grid ``--cells-across`` takes (cells across the limb; the matrix grows with their square); the
#: same bound as a grid sized by the knee keeps to (:data:`knee.models.fem.scene.KNEE_SIZED_MOST`, not imported
#: here so that the parser stays light).
MAX_CELLS_ACROSS = 24
CELLS_ACROSS_HELP = ("cells across the limb of the association model's grid: 'knee' (the default): x (anteroposterior) "
                     "cells of about a sixth of the femur's width, 7 across z (medio-lateral); or N each way (7: the "
                     "paper's grid), or NX,NZ. 14 halves the paper's cells each way, at about twice the time "
                     "(README, 'The model's grid')")


def cells_across(text: str):
    """``--cells-across``: N (cells each way across the limb) or NX,NZ, each from 3 to :data:`MAX_CELLS_ACROSS`,
    or ``knee`` (sized by the knee: :func:`knee.models.fem.scene.knee_sized_across`) (argparse type): an int, a
    pair or "knee"."""
    if str(text).strip().lower() == "knee":
        return "knee"
    parts = str(text).split(",")
    if len(parts) > 2 or not all(p.strip().lstrip("+-").isdigit() for p in parts):
        raise argparse.ArgumentTypeError(f"must be N, NX,NZ or knee, got {text!r}")
    counts = tuple(at_least(3, int, MAX_CELLS_ACROSS)(p.strip()) for p in parts)
    return counts[0] if len(counts) == 1 else counts


def _gait_options(p) -> None:
    """The gait trial and the subject's anthropometry (knee gait, knee osteotomy)."""
    p.add_argument("--trial", help="gait CSV (README, 'Gait'); default: the bundled normative cycle")
    p.add_argument("--mass", type=float, default=72.0, help="body mass, kg (72)")
    p.add_argument("--height", type=float, default=1.75, help="body height, m (1.75)")


def seed(text: str) -> int:
    """A random seed: a whole number from 0 to 2**32 - 1 (argparse type)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None
    if not 0 <= v < 2 ** 32:
        raise argparse.ArgumentTypeError(f"must be from 0 to 4294967295, got {v}")
    return v


class _Parser(argparse.ArgumentParser):
    """argparse with its usage errors as one ``knee: error:`` line and exit code 2."""

    def error(self, message):  # noqa: D401 - argparse's hook
        where = f"{self.prog.split()[-1]}: " if " " in self.prog else ""  # the subcommand, if any
        self.exit(EXIT_BAD_INPUT, f"knee: error: {where}{message}\n")


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="knee", description="Knee kinematics toolkit (mm, degrees at the CLI).")
    sub = ap.add_subparsers(dest="command", required=True, parser_class=_Parser)
    sub.add_parser("models", help="list the bundled parameter sets")
    sp = sub.add_parser("sweep", help="solve the mechanism over a flexion range")
    sp.add_argument("model", help="a bundled parameter set (see 'knee models') or a TOML file")
    sp.add_argument("--from", dest="a_from", type=float, default=0.0, help="first flexion angle, deg (0)")
    sp.add_argument("--to", dest="a_to", type=float, default=120.0, help="last flexion angle, deg (120)")
    sp.add_argument("--step", type=float, default=1.0, help="step, deg (1)")
    sp.add_argument("--out", help="CSV file to write (default: CSV on standard output)")
    sp.add_argument("--rrd", help="Rerun recording to write")
    sp.add_argument("--force", action="store_true", help="replace existing output files")
    dp = sub.add_parser("demo", help="the main job on the bundled default knee, with a Rerun recording")
    dp.add_argument("--out", default="knee-demo", help="output folder (a new one if it exists)")
    dp.add_argument("--flexion", type=float, default=60.0, help="flexion of the virtual depth map, deg (60)")
    dp.add_argument("--kinematics-only", action="store_true", help="only the sweep (no FEM)")
    ss = sub.add_parser("synth-subject", help="write a synthetic subject folder from a parameter set")
    ss.add_argument("out_dir", help="folder to create (must not exist or be empty)")
    ss.add_argument("--model", default="volunteer", help="parameter set with a patella (volunteer)")
    ss.add_argument("--seed", type=seed, default=0, help="random seed (0)")
    ss.add_argument("--frames", type=int, default=60, help="frames of the measured motion, 0-120 deg (60)")
    ss.add_argument("--depth-frame", type=float, metavar="DEG",
                    help="also a depth image of the knee at DEG flexion, as a camera would give it (OUT_DIR/camera/: "
                         "depth.png, intrinsics.txt, a rough CT pose in the camera, the truth): input for knee fem")
    fp = sub.add_parser("fit", help="fit a subject-specific mechanism to a subject folder")
    fp.add_argument("subject_dir", help="the subject folder (README, 'Subject folders'); never written to")
    fp.add_argument("--out", required=True, help="output folder (parameter files, report, figure, recording)")
    fp.add_argument("--seed", type=seed, default=0, help="seed of the global stage (0); same seed, same result")
    fp.add_argument("--no-global", action="store_true", help="skip differential evolution (local stage only)")
    fp.add_argument("--quick", action="store_true", help="a small global stage (a first look; not for results)")
    fp.add_argument("--no-recording", action="store_true", help="do not write the Rerun recording")
    fp.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    fp.add_argument("--quiet", action="store_true", help="no progress bar")
    fp.add_argument("--average-halves", action="store_true", help="fit the mean of the trial's flexing and "
                    "extending phases (split where the flexion turns back by more than 3 deg), as seed 002 did")
    fp.add_argument("--also-trial", action="append", metavar="MOTION.csv", help="another trial of the same knee, "
                    "fitted together with the folder's (repeatable)")
    fp.add_argument("--check-trial", action="append", metavar="MOTION.csv", help="a trial of the same knee not "
                    "fitted: the fitted model's error on it is reported (repeatable)")
    fp.add_argument("--noise", help="the measurement's standard deviations that weigh the fit, KEY=VALUE by commas "
                    "(sagittal_deg 1, sagittal_mm 0.5, out_of_plane_deg 2, out_of_plane_mm 1.5)")
    fp.add_argument("--assemble-over", default="0:120", help="the flexion range LO:HI (deg) the fitted knee must "
                    "assemble over beyond the measured one, or 'none' (0:120)")
    fp.add_argument("--bounds", help="the fit's bounds, KEY=VALUE separated by commas, over the subject's [fit] table "
                    "(tf_endpoint_mm 2, tf_length_mm 5, pf_axis_deg 5, pf_axis_point_mm 5, pf_tendon_mm 2, "
                    "pf_length_mm 5, pf_pitch_mm_per_rad 2)")
    gp = sub.add_parser("gait", help="inverse dynamics, link forces and contact pressures over a gait cycle")
    gp.add_argument("model", help="a bundled parameter set with a patella, or a TOML file")
    _gait_options(gp)
    gp.add_argument("--out", default="knee-gait", help="output folder (knee-gait)")
    gp.add_argument("--rrd", help="recording path (default OUT/gait.rrd)")
    gp.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    cp = sub.add_parser("contact", help="contact area and peak pressure against flexion under a load")
    cp.add_argument("model")
    cp.add_argument("--load", type=float, default=700.0, help="compressive load along the tibia, N (700)")
    cp.add_argument("--out", default="knee-contact", help="output folder (knee-contact)")
    cp.add_argument("--force", action="store_true")
    op = sub.add_parser("osteotomy", help="virtual osteotomy: cut, open/close a wedge, recompute axes, kinematics, gait")
    op.add_argument("model")
    op.add_argument("--bone", choices=("tibia", "femur"), default="tibia")
    op.add_argument("--angle", type=float, required=True, help="wedge angle, deg (+ opens opposite the hinge)")
    op.add_argument("--plane", help="cut plane: point and normal in the bone frame, px,py,pz,nx,ny,nz (mm); "
                                    "default: transverse, 35 mm below (tibia) / 60 mm above (femur) the joint")
    op.add_argument("--hinge", help="hinge: point and axis, hx,hy,hz,ax,ay,az (mm); default: 8 mm inside the "
                                    "lateral cortex, along x")
    op.add_argument("--release", action="append", help="release a ligament whose insertion moves (repeatable)")
    _gait_options(op)
    op.add_argument("--out", default="knee-osteotomy", help="output folder (knee-osteotomy)")
    op.add_argument("--force", action="store_true")
    co = sub.add_parser("compare", help="the four ways to use the mechanism with the FEM: on a case set "
                                         "(scripts/build_case_set.py), a subject's own knee (SUBJECT_DIR --prior "
                                         "--truth-motion) or a parameter set's standard cases")
    co.add_argument("model", help="a case set folder, a subject folder with ct/skin.stl, or the prior: a bundled "
                                  "parameter set or a TOML file")
    co.add_argument("--prior", help="subject: the fitted parameter file, the kinematic prior")
    co.add_argument("--truth-motion", help="subject: a measured motion (the subject folder's motion.csv format) whose "
                                           "rows pose the truth")
    co.add_argument("--only", help="case set: run only the cases whose id contains one of these (comma list)")
    co.add_argument("--no-initial-pose", action="store_true",
                    help="case set: leave each case's rough pose out (the global search finds the knee)")
    co.add_argument("--frames", type=int, help="subject: how many rows of the motion, spread over it (4)")
    co.add_argument("--cells-across", type=cells_across, metavar="N|NX,NZ|knee",
                    help=f"case set, subject: {CELLS_ACROSS_HELP}")
    co.add_argument("--truth", help="parameter set: the parameter set generating the truth (default: MODEL, with "
                                    "the prior = MODEL perturbed by --perturb)")
    co.add_argument("--flexion", help="parameter set: true flexion angles, FROM:TO:STEP or a list (30:120:15)")
    co.add_argument("--cameras", help="subject, parameter set: oblique, frontal, lateral separated by commas, or "
                                      "entries AZ,EL,DIST separated by ';' (oblique)")
    co.add_argument("--methods", default="paper,init,links,kinematics", help="which methods (all four)")
    co.add_argument("--perturb", type=float, help="parameter set: largest endpoint move of the default prior, mm (2)")
    co.add_argument("--seed", type=seed,
                    help="subject, parameter set: seed of the perturbation and the depth noise (3)")
    co.add_argument("--no-noise", action="store_true", help="subject, parameter set: no depth noise")
    co.add_argument("--out", default="knee-compare", help="output folder (knee-compare)")
    co.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    co.add_argument("--quiet", action="store_true", help="no progress bar")
    fe = sub.add_parser("fem", help="the association FEM model deformed toward a depth map: a subject's own knee "
                                     "(SUBJECT_DIR --prior FITTED.toml) or a parameter set's phantom")
    fe.add_argument("model", help="a subject folder with ct/skin.stl, or a parameter set (bundled name or TOML) "
                                  "for the phantom's standard case")
    fe.add_argument("--prior", help="subject: the fitted parameter file (knee fit's fitted.toml), the kinematic prior")
    fe.add_argument("--method", choices=("links", "init", "kinematics", "paper"),
                    help="subject: (iii) links (default), (ii) init, (iv) kinematics, (i) paper")
    fe.add_argument("--cells-across", type=cells_across, metavar="N|NX,NZ|knee", help=CELLS_ACROSS_HELP)
    fe.add_argument("--initial-pose", help="subject: text file with a rough 4x4 pose of the CT frame in the camera's "
                                           "frame (within about 30 deg and 50 mm); default: a global search")
    fe.add_argument("--out", help="subject: output folder (result.json, femur.stl, tibia.stl, fem.rrd, overlay.png)")
    fe.add_argument("--flexion", type=float, help="phantom: flexion of the standard case's truth, deg (90)")
    fe.add_argument("--truth", help="phantom: parameter set generating the truth (default: MODEL)")
    fe.add_argument("--camera", help="phantom: oblique, frontal, lateral or AZ,EL,DIST (oblique)")
    fe.add_argument("--no-noise", action="store_true", help="no depth noise")
    fe.add_argument("--seed", type=seed, help="seed of the depth noise (0)")
    fe.add_argument("--cloud", help="a measured point cloud (.ply/.pcd/.xyz/.pts, mm) instead of the virtual camera")
    fe.add_argument("--depth", help="a measured depth image (16-bit PNG or .npy) instead of the virtual camera")
    fe.add_argument("--intrinsics", help="fx,fy,cx,cy of the depth image (pixels; pixel centres at whole "
                                         "coordinates, as OpenCV and librealsense give them)")
    fe.add_argument("--depth-scale", type=float, default=1.0, help="depth units to mm (1)")
    fe.add_argument("--cloud-scale", type=float, default=1.0, help="the cloud's units to mm (1; 1000 for metres)")
    fe.add_argument("--keep-flying", action="store_true",
                    help="keep the measured points a depth camera returns at depth edges (left out by default: "
                         "flying pixels, blends of the leg and what lies behind it)")
    fe.add_argument("--pose", help="phantom: text file with the 4x4 camera-to-model transform (default identity)")
    fe.add_argument("--max-steps", type=int, help="phantom: step limit (400)")
    fe.add_argument("--bone-stall", type=float, metavar="DEG",
                    help="end the bone forces when the largest flexion reached grows less than DEG over 10 steps "
                         "(0.5; 0: only the paper's femur-tibia angle below 100 deg or a third of --max-steps)")
    fe.add_argument("--rrd", help="phantom: Rerun recording to write")
    fe.add_argument("--force", action="store_true", help="replace an existing recording or output folder")
    fe.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap


def main(argv=None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    try:
        args = build_parser().parse_args(argv)
        command = importlib.import_module(f"knee.app.commands.{COMMANDS[args.command]}")
        return command.run(args)
    except KneeInputError as e:
        return error(str(e), EXIT_BAD_INPUT)
    except KneeNumericalError as e:
        return error(str(e), EXIT_NUMERICAL)
    except KeyboardInterrupt:
        return error("interrupted; no results written", EXIT_INTERRUPTED)
    except BrokenPipeError:
        return 0
    except OSError as e:  # the file system refused: a full disk, a permission changed during the run
        where = f"{e.filename}: " if e.filename else ""
        return error(f"{where}{e.strerror or e}; no results written", EXIT_BAD_INPUT)
    except Exception as e:  # a bug: one line, the traceback only when asked for
        if os.environ.get("KNEE_DEBUG"):
            raise
        return error(f"internal error ({type(e).__name__}: {e}); please report it with the command line "
                     f"(KNEE_DEBUG=1 shows the traceback)", EXIT_INTERNAL)


def entry() -> None:
    """The installed ``knee`` script: :func:`main`, then exit with its code. A termination request
    (SIGTERM: ``kill``, a scheduler's time limit) is taken as Ctrl-C, so that it too removes every partial
    output. After either, when the partial outputs have been removed and the workers stopped, the process
    leaves at once: the interpreter's own teardown of the loaded numeric libraries takes about a second,
    which a user who pressed Ctrl-C should not wait for. The BLAS libraries' threads are set by the
    machine's load before the command imports them (:func:`knee.app.threads.set_threads`; a count the user
    set is kept; the installed script, :func:`knee.app.launch.entry`, sets them before NumPy loads too)."""
    set_threads()
    take_terminations_as_interrupts()
    code = main()
    if code == EXIT_INTERRUPTED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    entry()
