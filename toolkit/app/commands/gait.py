"""``knee gait MODEL``: inverse dynamics, member forces and contact pressures over a gait cycle."""

from __future__ import annotations

import contextlib
import csv
from pathlib import Path

import numpy as np

from knee.app.console import check_new, out_dir
from knee.app.views.clinical import gait_blueprint, log_gait, plot_gait
from knee.foundations import recording
from knee.foundations.files import staged_file, staged_folder
from knee.models.gait import (
    Anthropometry,
    GaitResult,
    analyse_gait,
    normative_trial,
    read_gait_csv,
)
from knee.models.mechanism import Mechanism


def write_gait_table(path: Path, res: GaitResult) -> None:
    """One row per frame: time, knee flexion, knee load on the tibia, member forces, contact pressures."""
    st = res.statics
    head = ["time_s", "knee_flexion_deg", "load_force_anterior_N", "load_force_proximal_N", "load_force_lateral_N",
            "load_moment_anterior_Nmm", "load_moment_proximal_Nmm", "load_moment_lateral_Nmm"]
    head += [f"{n}_force_N" for n in st.names]
    cols = [res.trial.time, np.degrees(res.trial.knee), *res.knee_force.T, *res.knee_moment.T, *st.forces.T]
    for name, e in res.contact.items():
        head += [f"{name}_contact_N", f"{name}_hertz_area_mm2", f"{name}_hertz_peak_MPa"]
        cols += [e.force, e.hertz.area, e.hertz.peak]
        if e.foundation is not None:
            head += [f"{name}_foundation_area_mm2", f"{name}_foundation_peak_MPa"]
            cols += [e.foundation.area, e.foundation.peak]
    head += ["valid", "flags"]
    valid = res.valid
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for k, row in enumerate(np.column_stack(cols)):
            w.writerow([f"{v:.6g}" for v in row] + [int(valid[k]), "; ".join(st.flags[k])])


def run(args) -> int:
    model_file = Path(args.model) if Path(args.model).is_file() else None
    trial_file = Path(args.trial) if args.trial else None
    out = out_dir(args.out, args.force, inputs=(model_file, trial_file))
    rrd = Path(args.rrd) if args.rrd else None
    if rrd is not None:
        check_new(rrd, args.force, inputs=(model_file, trial_file, out), flag="--rrd")
    anthro = Anthropometry(args.mass, args.height)
    trial = read_gait_csv(args.trial, args.mass) if args.trial else normative_trial(args.mass)
    mech = Mechanism.from_name(args.model)
    res = analyse_gait(mech, trial, anthro)
    with contextlib.ExitStack() as stack:
        staged = stack.enter_context(staged_folder(out))
        rrd_tmp = stack.enter_context(staged_file(rrd)) if rrd is not None else staged / "gait.rrd"
        write_gait_table(staged / "gait.csv", res)
        plot_gait(res, staged / "gait.png", f"{mech.params.name}: {trial.source}")
        rec = recording.new_recording()
        recording.save(rec, rrd_tmp, gait_blueprint())
        log_gait(rec, mech, res)
        recording.close(rec)
    rrd = rrd or out / "gait.rrd"
    if res.flagged_note:
        print(f"WARNING: {res.flagged_note} (the valid and flags columns of {out / 'gait.csv'})")
    print(f"gait of {mech.params.name} ({trial.source}), {trial.time.size} frames, {args.mass:g} kg, "
          f"{args.height:g} m: analysed in {res.seconds:.2f} s")
    ok = res.valid
    if ok.any():
        for name, e in res.contact.items():
            k = int(np.flatnonzero(ok)[np.argmax(e.force[ok])])
            print(f"contact {name} (valid frames): peak force {e.force[k]:.0f} N at t = {trial.time[k]:.3f} s; Hertz "
                  f"peak pressure {e.hertz.peak[ok].max():.2f} MPa, area {e.hertz.area[k]:.0f} mm2"
                  + (f"; elastic foundation peak {e.foundation.peak[ok].max():.2f} MPa" if e.foundation is not None
                     else ""))
    print(f"table: {out / 'gait.csv'}\nplot:  {out / 'gait.png'}\nrecording: {rrd}  (open with: rerun {rrd})")
    return 0
