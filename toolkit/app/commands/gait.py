"""``knee gait MODEL``: inverse dynamics, member forces and contact pressures over a gait cycle."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from knee.app.console import check_new, out_dir
from knee.app.views.clinical import gait_blueprint, log_gait, plot_gait
from knee.foundations import recording
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
    head.append("flags")
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for k, row in enumerate(np.column_stack(cols)):
            w.writerow([f"{v:.6g}" for v in row] + ["; ".join(st.flags[k])])


def run(args) -> int:
    out = out_dir(args.out, args.force)
    rrd = Path(args.rrd) if args.rrd else out / "gait.rrd"
    if args.rrd:
        check_new(rrd, args.force)
    anthro = Anthropometry(args.mass, args.height)
    trial = read_gait_csv(args.trial, args.mass) if args.trial else normative_trial(args.mass)
    mech = Mechanism.from_name(args.model)
    res = analyse_gait(mech, trial, anthro)
    out.mkdir(parents=True, exist_ok=True)
    write_gait_table(out / "gait.csv", res)
    plot_gait(res, out / "gait.png", f"{mech.params.name}: {trial.source}")
    rec = recording.new_recording()
    recording.save(rec, rrd, gait_blueprint())
    log_gait(rec, mech, res)
    rec.flush()
    print(f"gait of {mech.params.name} ({trial.source}), {trial.time.size} frames, {args.mass:g} kg, "
          f"{args.height:g} m: analysed in {res.seconds:.2f} s")
    for name, e in res.contact.items():
        k = int(np.argmax(e.force))
        print(f"contact {name}: peak force {e.force[k]:.0f} N at t = {trial.time[k]:.3f} s; Hertz peak pressure "
              f"{e.hertz.peak.max():.2f} MPa, area {e.hertz.area[k]:.0f} mm2"
              + (f"; elastic foundation peak {e.foundation.peak.max():.2f} MPa" if e.foundation is not None else ""))
    nflag = sum(1 for f in res.statics.flags if f)
    if nflag:
        print(f"flagged frames: {nflag} of {trial.time.size} (a member would have to push or pull the wrong way; "
              f"see the flags column of {out / 'gait.csv'})")
    print(f"table: {out / 'gait.csv'}\nplot:  {out / 'gait.png'}\nrecording: {rrd}  (open with: rerun {rrd})")
    return 0
