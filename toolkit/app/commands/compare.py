"""``knee compare MODEL``: the four methods of using the mechanism with the FEM on standard cases, with
the table, the plot and the recording (:mod:`knee.app.experiments.cases`, :mod:`knee.app.reports.compare`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from knee.app.commands.fem_subject import grid_label, model_settings
from knee.app.console import ProgressBar, flexion_list, out_dir, say
from knee.app.experiments.case_set import TRUTH_EDGE_WIDTHS, is_case_set, read_case_set, run_case_set
from knee.app.experiments.cases import compare_cases, prior_floor, truth_phantom
from knee.app.experiments.skin_floor import skin_floor
from knee.app.experiments.subject_cases import compare_subject
from knee.app.reports import case_set as report
from knee.app.reports.compare import (
    CompareRecorder,
    floor_markdown,
    markdown,
    plot,
    summary,
    targets_check,
    write_csv,
)
from knee.fitting.optimize import perturb_endpoints
from knee.fitting.subject import load_subject
from knee.fitting.subject_anatomy import subject_anatomy
from knee.foundations.errors import KneeInputError
from knee.foundations.files import staged_folder
from knee.foundations.imaging import read_motion_csv
from knee.models.fem.depth import CAMERA_PLACEMENTS, DepthNoise, camera_from_spec
from knee.models.fem.methods import METHODS
from knee.models.fem.scene import build_association_model
from knee.models.mechanism import Mechanism
from knee.models.mechanism.params import bundled_models, load_model


def camera_list(text: str) -> list[str]:
    """Camera entries: placement names separated by commas, or any entries (AZ,EL,DIST) separated by ';'."""
    t = str(text).strip()
    parts = t.split(";") if ";" in t else t.split(",")
    parts = [p.strip() for p in parts if p.strip()]
    if ";" not in t and not all(p.lower() in CAMERA_PLACEMENTS for p in parts):
        parts = [t]  # a single AZ,EL,DIST camera
    if not parts:
        raise KneeInputError("--cameras is empty")
    return parts


#: The options each form of ``knee compare`` takes beyond --methods, --out, --force and --quiet (a case set
#: carries its truths, priors, cameras and noise), and their defaults where the form takes them.
FORM_OPTIONS = {"case set": ("only", "no_initial_pose", "cells_across"),
                "subject folder": ("prior", "truth_motion", "frames", "cameras", "seed", "no_noise", "cells_across"),
                "parameter set": ("truth", "flexion", "cameras", "perturb", "seed", "no_noise")}
OPTION_DEFAULTS = {"frames": 4, "flexion": "30:120:15", "cameras": "oblique", "perturb": 2.0, "seed": 3}
_WHERE = {"case set": "a case set (a folder with case-set.toml)", "subject folder": "a subject folder",
          "parameter set": "a parameter set"}


def check_form_options(args, form: str) -> None:
    """An option another form takes, given to this one, is refused in one line naming where it goes (not
    ignored); those this form takes and were not given get their defaults."""
    for flag in sorted({f for opts in FORM_OPTIONS.values() for f in opts}):
        if flag in FORM_OPTIONS[form]:
            if getattr(args, flag, None) is None and flag in OPTION_DEFAULTS:
                setattr(args, flag, OPTION_DEFAULTS[flag])
        elif getattr(args, flag, None) not in (None, False):
            where = " or ".join(_WHERE[f] for f in FORM_OPTIONS if flag in FORM_OPTIONS[f])
            raise KneeInputError(f"--{flag.replace('_', '-')} goes with {where}, not {_WHERE[form].split(' (')[0]}")


def run(args) -> int:
    if Path(args.model).is_dir() and is_case_set(args.model):
        check_form_options(args, "case set")
        return run_cases(args)
    if Path(args.model).is_dir():
        check_form_options(args, "subject folder")
        return run_subject(args)
    if not Path(args.model).exists() and args.model not in bundled_models():
        raise KneeInputError(f"unknown knee {args.model!r}: not a case set, a subject folder, a bundled parameter set "
                             f"({', '.join(sorted(bundled_models()))}) nor an existing TOML file")
    check_form_options(args, "parameter set")
    flexions = flexion_list(args.flexion)
    cams = {c: camera_from_spec(c) for c in camera_list(args.cameras)}
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise KneeInputError(f"--methods must be a comma list of {', '.join(METHODS)}, got {args.methods!r}")
    if not (0.0 <= args.perturb <= 10.0):
        raise KneeInputError(f"--perturb must be 0-10 mm, got {args.perturb}")
    out = out_dir(args.out, args.force, inputs=tuple(Path(m) for m in (args.model, args.truth)
                                                     if m and Path(m).is_file()))
    params = load_model(args.model)
    if args.truth:
        truth, prior = Mechanism.from_name(args.truth), Mechanism(params)
        origin = f"truth {truth.params.name}, prior {params.name}"
    else:
        truth = Mechanism(params)
        prior = Mechanism(perturb_endpoints(params, 0.5 * args.perturb, args.perturb, seed=args.seed))
        origin = (f"truth {params.name}; prior = {params.name} with every TF link endpoint moved "
                  f"{0.5 * args.perturb:g}-{args.perturb:g} mm (seed {args.seed})")
    origin += ("; truth skin: the phantom's envelope, made by the same code as the model's skin (not an independent "
               "truth: a case set's is, scripts/build_case_set.py)")
    say(f"knee compare: {origin}; {len(flexions)} flexion angles x {len(cams)} camera(s) x {len(methods)} methods")
    with staged_folder(out) as tmp:
        recorder = CompareRecorder(tmp / "compare.rrd", truth_phantom(truth), truth_phantom(prior), methods)
        bar = ProgressBar()
        progress = None if args.quiet else (lambda i, n, t: bar(i / n, t))
        try:
            rows = compare_cases(truth, prior, flexions, cams, methods, noise=None if args.no_noise else DepthNoise(),
                                 seed=args.seed, progress=progress, on_result=recorder)
        finally:
            recorder.finish()
        write_csv(rows, tmp / "compare.csv")
        title = f"Kinematic priors for the FEM: {origin}"
        floor = prior_floor(build_association_model(prior), truth, prior, flexions)
        (tmp / "compare.md").write_text(markdown(rows, methods, title) + floor_markdown(floor), encoding="utf-8")
        plot(rows, methods, tmp / "compare.png", title)
    summ = summary(rows, methods)
    print("method      cases  failed  footprints (mm)  epiphysis (mm)  |flexion error| (deg)  wall (s)")
    for m, v in summ.items():
        print(f"{m:11s} {v.cases:5d}  {v.failed:6d}  {v.footprints_mm:15.2f}  {v.epiphysis_mm:14.2f}  "
              f"{v.flexion_error_deg:20.2f}  {v.wall_s:8.1f}")
    for line in targets_check(summ):
        print(line)
    print("the prior's own tibia error (best-matching flexion, femur placed exactly), footprints mm: " +
          ", ".join(f"{r.flexion_deg:g} deg {r.tibia_footprints_mm:.2f}" for r in floor))
    print("of which the axial rotation alone (the phantom's round shank cannot show it; (ii) and (iii) correct the "
          "rest from the shank's points, and that too where the shank is not round), footprints mm: " +
          ", ".join(f"{r.flexion_deg:g} deg {r.tibia_footprints_axial_mm:.2f} ({r.axial_rotation_deg:+.1f} deg)"
                    for r in floor))
    notes = sorted({r.notes for r in rows if r.notes} | {f"failed: {r.failed}" for r in rows if r.failed})
    for n in notes:
        print(f"note: {n}")
    print(f"table: {out / 'compare.csv'}, {out / 'compare.md'}\nplot: {out / 'compare.png'}\n"
          f"recording: {out / 'compare.rrd'}  (open with: rerun {out / 'compare.rrd'})")
    return 0


def run_subject(args) -> int:
    """``knee compare SUBJECT_DIR --prior FITTED.toml --truth-motion MOTION.csv``
    (:mod:`knee.app.experiments.subject_cases`)."""
    if not args.prior or not args.truth_motion:
        raise KneeInputError("a subject's comparison needs --prior FITTED.toml and --truth-motion MOTION.csv")
    if not 1 <= args.frames <= 50:
        raise KneeInputError(f"--frames must be 1-50, got {args.frames}")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not methods or any(m not in METHODS for m in methods):
        raise KneeInputError(f"--methods must be a comma list of {', '.join(METHODS)}, got {args.methods!r}")
    azimuths = []
    for c in camera_list(args.cameras):
        if c.lower() not in CAMERA_PLACEMENTS:
            raise KneeInputError(f"a subject's comparison takes named cameras ({', '.join(CAMERA_PLACEMENTS)}), got {c!r}")
        azimuths.append(CAMERA_PLACEMENTS[c.lower()])
    out = out_dir(args.out, args.force, inputs=(Path(args.model), Path(args.prior), Path(args.truth_motion)))
    subject = load_subject(args.model)
    prior = Mechanism(load_model(args.prior))
    motion = read_motion_csv(args.truth_motion, subject.side)
    rows_idx = np.unique(np.linspace(0, len(motion.tf) - 1, min(args.frames, len(motion.tf))).round().astype(int))
    anatomy = subject_anatomy(subject, prior.params)
    say(f"knee compare: subject {subject.name}, prior {prior.params.name}; {len(rows_idx)} rows of "
        f"{args.truth_motion} x {len(azimuths)} camera(s) x {len(methods)} methods (truth skin: a tetrahedral "
        f"tissue model around the subject's bones, posed with them)")
    bar = ProgressBar()
    rows = compare_subject(anatomy, prior, motion.tf[rows_idx], methods, tuple(azimuths),
                           None if args.no_noise else DepthNoise(), args.seed,
                           None if args.quiet else (lambda i, n, t: bar(i / n, t)), model_settings(args))
    title = f"Subject {subject.name}: truth from {args.truth_motion}, prior {args.prior}"
    with staged_folder(out) as tmp:
        write_csv(rows, tmp / "compare.csv")
        (tmp / "compare.md").write_text(markdown(rows, methods, title), encoding="utf-8")
        plot(rows, methods, tmp / "compare.png", title)
    for m, v in summary(rows, methods).items():
        print(f"{m:11s} cases {v.cases}  failed {v.failed}  footprints {v.footprints_mm:.2f} mm  epiphysis "
              f"{v.epiphysis_mm:.2f} mm  |flexion error| {v.flexion_error_deg:.2f} deg  wall {v.wall_s:.1f} s")
    print(f"table: {out / 'compare.csv'}, {out / 'compare.md'}\nplot: {out / 'compare.png'}")
    return 0


def run_cases(args) -> int:
    """``knee compare CASE_SET``: every method on every case of a case set (``scripts/build_case_set.py``;
    :mod:`knee.app.experiments.case_set`), with the table, the targets and the figure."""
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not methods or any(m not in METHODS for m in methods):
        raise KneeInputError(f"--methods must be a comma list of {', '.join(METHODS)}, got {args.methods!r}")
    index = read_case_set(args.model)
    out = out_dir(args.out, args.force, inputs=(Path(args.model),))
    only = [a.strip() for a in (args.only or "").split(",") if a.strip()]
    select = (lambda c: any(o in c["id"] for o in only)) if only else None
    n = sum(1 for c in index["case"] if select is None or select(c))
    if n == 0:
        raise KneeInputError(f"--only {args.only!r} selects none of the {len(index['case'])} cases")
    truth = ", the truth moving the patella" if index.get("truth_patella") else ""
    if index.get("flying_pixels"):
        truth += f", flying pixels at {100 * float(index['flying_pixels']):g} % of each edge's band"
    if index.get("noise_correlation_px"):
        truth += f", depth errors correlated over {float(index['noise_correlation_px']):g} px"
    if index.get("noise_sigma_mm_at_400_mm", 1.0) != 1.0:
        truth += f", depth noise {float(index['noise_sigma_mm_at_400_mm']):g} mm at 400 mm"
    if index.get("truth_edge_widths", TRUTH_EDGE_WIDTHS) != TRUTH_EDGE_WIDTHS:
        truth += f", the truth's tissue at {float(index['truth_edge_widths']):g} femur widths"
    if index.get("hole_px"):
        truth += f", holes of about {float(index['hole_px']):g} px"
    if args.no_initial_pose:
        truth += ", without the rough poses (the global search)"
    if args.cells_across is not None:
        truth += f", the model's grid {grid_label(args.cells_across)}"
    say(f"knee compare: case set {args.model} (seed {index.get('seed')}{truth}), {n} cases x {len(methods)} methods")
    bar = ProgressBar()
    title = f"Case set {Path(args.model).name} (seed {index.get('seed')}{truth})"
    with staged_folder(out) as tmp:
        recorder = report.CaseSetRecorder(tmp / "compare.rrd", methods)
        try:
            rows = run_case_set(args.model, methods, None if args.quiet else (lambda i, k, t: bar(i / k, t)), select,
                                on_result=recorder, guess=not args.no_initial_pose, settings=model_settings(args))
        finally:
            recorder.finish()
        try:  # what a perfect model reaches at the skin mismatches, where the set has the views to say it
            floors = skin_floor(args.model, select=select)
        except KneeInputError:
            floors = []
        write_csv(rows, tmp / "compare.csv", extra=("case", "anatomy", "family", "mismatch_mm", "registration_inliers",
                                                            "shank_points_true", "cpu_seconds", "estimate_rms_mm"))
        (tmp / "compare.md").write_text(report.markdown(rows, methods, title, floors), encoding="utf-8")
        report.plot(rows, methods, tmp / "compare.png", title)
    for line in report.targets(rows, floors):
        print(line)
    print(f"table: {out / 'compare.csv'}, {out / 'compare.md'}\nplot: {out / 'compare.png'}\n"
          f"recording: {out / 'compare.rrd'}  (open with: rerun {out / 'compare.rrd'})")
    return 0
