"""``knee sweep MODEL``: the mechanism over a flexion range, as CSV (file or standard output) and an
optional Rerun recording."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from knee.app.console import check_new, error
from knee.app.views.sweep import log_sweep, sweep_blueprint
from knee.foundations import recording
from knee.foundations.errors import EXIT_NUMERICAL, KneeInputError
from knee.foundations.files import staged_file
from knee.foundations.motion_io import SWEEP_HEADER, sweep_table, write_sweep_csv
from knee.models.mechanism import Mechanism, SweepResult
from knee.models.phantom import build_phantom


def angles(a_from: float, a_to: float, step: float) -> np.ndarray:
    """The flexion angles (deg) of ``--from``, ``--to`` and ``--step``, checked."""
    for name, v in (("--from", a_from), ("--to", a_to), ("--step", step)):
        if not math.isfinite(v):
            raise KneeInputError(f"{name} must be a finite number of degrees, got {v}")
    if step <= 0:
        raise KneeInputError(f"--step must be positive, got {step}")
    if step > 10:
        raise KneeInputError(f"--step must be at most 10 deg for continuation to follow one branch, got {step}")
    n = int(math.floor(abs(a_to - a_from) / step + 1e-9)) + 1
    if n > 1_000_000:
        raise KneeInputError(f"--from/--to/--step give {n} angles; at most 1000000")
    sign = 1.0 if a_to >= a_from else -1.0
    return a_from + sign * step * np.arange(n)


def run_sweep(model: str, angles_deg: np.ndarray, out: Path | None, rrd: Path | None,
              quiet: bool = False) -> tuple[Mechanism, SweepResult, float]:
    """Solve, write the CSV (or print it) and the recording; returns (mechanism, result, seconds)."""
    mech = Mechanism.from_name(model)
    t0 = time.perf_counter()
    res = mech.sweep(np.radians(angles_deg))
    dt = time.perf_counter() - t0
    phantom = build_phantom(mech.params) if rrd is not None and res.flexion.size else None
    if out is not None:
        with staged_file(out) as tmp:
            write_sweep_csv(tmp, res.tf, res.pf, res.residual, res.condition)
    elif not quiet:
        print(",".join(SWEEP_HEADER))
        for row in sweep_table(res.tf, res.pf, res.residual, res.condition):
            print(",".join("" if not math.isfinite(v) else f"{v:.10g}" for v in row))
    if phantom is not None:
        with staged_file(rrd) as tmp:
            rec = recording.new_recording()
            recording.save(rec, tmp, sweep_blueprint())
            log_sweep(rec, mech, res, phantom)
            recording.close(rec)
    return mech, res, dt


def summary(mech: Mechanism, res: SweepResult, dt: float) -> str:
    """The sweep in a few lines: assembly range, angles solved, time, residual, near-singular angles."""
    lo, hi = (math.degrees(v) for v in mech.assembly_range)
    backend = "compiled" if mech.compiled else "CasADi virtual machine"
    lines = [f"model {mech.params.name}: assembles from {lo:.2f} to {hi:.2f} deg flexion",
             f"solved {res.flexion.size} of {res.requested.size} angles in {dt * 1e3:.2f} ms ({backend})"
             + (f"; max closure residual {res.residual.max():.1e} mm" if res.residual.size else "")]
    if res.flexion.size:
        ns = np.nonzero(res.near_singular)[0]
        if ns.size:
            lines.append(f"near-singular Jacobian (condition > 1e4) at {ns.size} angles, first at "
                         f"{math.degrees(res.flexion[ns[0]]):.2f} deg")
    return "\n".join(lines)


def run(args) -> int:
    out = Path(args.out) if args.out else None
    rrd = Path(args.rrd) if args.rrd else None
    model_file = Path(args.model) if Path(args.model).is_file() else None
    check_new(out, args.force, inputs=(model_file,))
    check_new(rrd, args.force, inputs=(model_file, out), flag="--rrd")
    a = angles(args.a_from, args.a_to, args.step)
    mech, res, dt = run_sweep(args.model, a, out, rrd)
    print(summary(mech, res, dt), file=sys.stderr)
    if out is not None:
        print(f"wrote {res.flexion.size} rows to {out}", file=sys.stderr)
    if rrd is not None and res.flexion.size:
        print(f"recording: {rrd}  (open with: rerun {rrd})", file=sys.stderr)
    if not res.complete:
        return error(f"sweep stopped: {res.message}; {res.flexion.size} rows written", EXIT_NUMERICAL)
    return 0
