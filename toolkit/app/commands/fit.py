"""``knee fit SUBJECT_DIR --out OUT_DIR``: a subject-specific mechanism from a subject folder, with its
parameter files, report, figure and recording (:mod:`knee.app.reports.fit`)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

from knee.app.console import ProgressBar
from knee.app.reports.fit import check_output_folder, write_outputs
from knee.fitting.optimize import FitBounds, noise_sd
from knee.fitting.pipeline import fit_subject
from knee.foundations.errors import KneeInputError


def key_values(text: str | None, flag: str) -> dict:
    """``KEY=VALUE,...`` as {key: number}; one line naming ``flag`` otherwise."""
    if not text:
        return {}
    out = {}
    for item in str(text).split(","):
        key, sep, value = item.partition("=")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep:
            raise KneeInputError(f"{flag} must be KEY=VALUE pairs separated by commas, got {item!r}")
    return out


def parse_bounds(text: str | None) -> dict:
    """``--bounds KEY=VALUE,...`` as {key: number}, checked (:class:`knee.fitting.optimize.FitBounds`)."""
    out = key_values(text, "--bounds")
    FitBounds().updated(out, "--bounds")  # checked now, before the work
    return out


def parse_range(text: str) -> tuple[float, float] | None:
    """``--assemble-over LO:HI`` (deg, finite, LO < HI, within -90..180) or ``none``."""
    t = str(text).strip().lower()
    if t == "none":
        return None
    try:
        lo, hi = (float(v) for v in t.split(":"))
    except ValueError:
        lo = hi = math.nan
    if not (math.isfinite(lo) and math.isfinite(hi) and -90.0 <= lo < hi <= 180.0):
        raise KneeInputError(f"--assemble-over must be LO:HI in degrees (LO < HI, within -90 to 180) or 'none', "
                             f"got {text!r}")
    return lo, hi


def run(args) -> int:
    subject_dir, out_dir = Path(args.subject_dir), Path(args.out)
    trials = [Path(f) for f in (args.also_trial or []) + (args.check_trial or [])]
    check_output_folder(subject_dir, out_dir, args.force, trials)
    bounds = parse_bounds(args.bounds)
    over = parse_range(args.assemble_over)
    noise = key_values(args.noise, "--noise")
    noise_sd(noise, "--noise")  # checked now, before the work
    bar = ProgressBar() if not args.quiet else None
    o = fit_subject(subject_dir, seed=args.seed, global_stage=not args.no_global, progress=bar,
                    effort="quick" if args.quick else "full", bounds=bounds, assemble_over_deg=over,
                    noise=noise, average_halves=args.average_halves, extra_trials=args.also_trial or (),
                    check_trials=args.check_trial or ())
    if bar:
        bar(0.98, "writing the outputs")
    files = write_outputs(o, out_dir, recording=not args.no_recording)
    if bar:
        bar(1.0, "done")
    fe = o.fitted_errors
    print(f"subject {o.subject.name}: fitted on {len(o.motion.tf)} frames in {o.seconds.fit:.1f} s "
          f"(total {o.seconds.total:.1f} s)")
    names = ("adduction", "int.rot", "anterior", "proximal", "lateral")
    print("TF MAE  " + "  ".join(f"{n} {v:.2f}" for n, v in zip(names, fe.tf.mae[1:])) + "  (deg, mm)")
    if fe.pf is not None:
        pn = ("flexion", "tilt", "rotation", "anterior", "proximal", "lateral")
        print("PF MAE  " + "  ".join(f"{n} {v:.2f}" for n, v in zip(pn, fe.pf.mae)) + "  (deg, mm)")
    if o.as_measured_errors is not None:
        v = o.as_measured_errors
        print("(against the mean of the flexing and extending phases; against every frame as measured: TF MAE "
              + "  ".join(f"{n} {x:.2f}" for n, x in zip(names, v.tf.mae[1:]))
              + ("" if v.pf is None else "; PF flexion %.2f deg" % v.pf.mae[0]) + ")")
    for name, v in o.cross_trial:
        print(f"cross-trial {name}: TF MAE " + "  ".join(f"{n} {x:.2f}" for n, x in zip(names, v.tf.mae[1:]))
              + ("" if v.pf is None else "; PF flexion %.2f deg" % v.pf.mae[0]))
    for w in o.warnings:
        print(f"warning: {w}", file=sys.stderr)
    for k, f in files.items():
        print(f"{k:15s} {f}")
    if "recording" in files:
        print(f"open the recording with: rerun {files['recording']}")
    return 0
