"""``knee demo``: the whole pipeline on the bundled volunteer: the sweep and its recording, then the
association FEM with the kinematic prior against the paper's method and the mechanism alone on a
virtual depth map (:mod:`knee.app.demo`).

This module imports nothing heavy: the FEM's worker processes start first
(:mod:`knee.app.demo_workers`), then the sweep's and the comparison's modules are imported here while the
workers start up (``importlib``, at those points on purpose: the overlap is the demo's wall time).
"""

from __future__ import annotations

import importlib
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from knee.app.console import say
from knee.app.demo_workers import call, start_workers, stop_workers
from knee.foundations.errors import AssemblyError, KneeInputError
from knee.foundations.files import check_output, staged_folder


def new_folder(base: Path) -> Path:
    """``base``, or ``base-2``, ``base-3``, ... : the first that does not exist (not created; checked to be
    writable)."""
    out, k = base, 2
    while out.exists() or out.is_symlink():  # never overwrite an earlier demo
        out = base.with_name(f"{base.name}-{k}")
        k += 1
    return check_output(out, "folder", force=False)


def run(args) -> int:
    if not (math.isfinite(args.flexion) and 15.0 <= args.flexion <= 110.0):
        raise KneeInputError(f"--flexion must be 15-110 deg (within the prior's range), got {args.flexion}")
    out = new_folder(Path(args.out))
    with staged_folder(out) as tmp:  # the demo's files appear together, when complete
        _run_into(args, tmp, out)
    return 0


def _run_into(args, tmp: Path, out: Path) -> None:
    fem = pool = None
    try:
        if not args.kinematics_only:
            # the FEM comparison (two worker processes) starts first and runs while the sweep is solved and
            # recorded: the workers' start-up overlaps it; a thread collects their results
            t0 = time.perf_counter()
            pool, futures = start_workers(args.flexion, 3, 2.0)
            say(f"knee demo: virtual depth map at {args.flexion:g} deg; the association FEM with the kinematic "
                f"prior and with the paper's forcing, two processes (started) ...")
            runner = ThreadPoolExecutor(max_workers=1)
            fem = runner.submit(call, "knee.app.demo", "collect_demo_comparison", tmp, futures, args.flexion, 3,
                                2.0, t0, say)
            runner.shutdown(wait=False)
        _sweep_and_report(args, tmp, out, fem)
    except BaseException:
        if pool is not None:
            stop_workers(pool)  # Ctrl-C or a failure: the workers stop now, not when their cases end
        raise
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


def _sweep_and_report(args, out_dir: Path, shown: Path, fem) -> None:
    """The sweep and the report: files written to ``out_dir``, their final place ``shown`` printed."""
    # imported now, after the workers started (see the module docstring)
    sweep = importlib.import_module("knee.app.commands.sweep")
    mech = importlib.import_module("knee.models.mechanism").Mechanism.from_name("volunteer")
    hi = math.floor(math.degrees(mech.assembly_range[1]))
    a = np.arange(0.0, hi + 1.0, 1.0)
    csv_path, rrd_path = shown / "volunteer-sweep.csv", shown / "volunteer-sweep.rrd"
    say(f"knee demo: sweeping the bundled 'volunteer' knee over 0..{hi} deg ...")
    mech, res, dt = sweep.run_sweep("volunteer", a, out_dir / csv_path.name, out_dir / rrd_path.name)
    print(sweep.summary(mech, res, dt))
    i = np.searchsorted(res.flexion, math.radians(90.0))
    if i < res.flexion.size:
        tf, pf = res.tf[i], res.pf[i]
        print(f"at {math.degrees(tf[0]):.0f} deg: TF adduction {math.degrees(tf[1]):+.2f} deg, internal rotation "
              f"{math.degrees(tf[2]):+.2f} deg, translation ({tf[3]:+.1f}, {tf[4]:+.1f}, {tf[5]:+.1f}) mm; "
              f"PF flexion {math.degrees(pf[0]):.1f} deg")
    print(f"motion table: {csv_path}")
    print(f"recording:    {rrd_path}")
    print(f"open it with: rerun {rrd_path}")
    if not res.complete:
        raise AssemblyError(res.message)
    if fem is None:
        return
    out = fem.result()
    labels = importlib.import_module("knee.app.reports.compare").METHOD_LABELS
    print(f"\nFEM at {args.flexion:g} deg flexion (truth: volunteer, its skin made by a tetrahedral "
          f"tissue model; prior: volunteer with TF endpoints moved 1-2 mm; oblique camera, depth noise):")
    print(f"{'method':44s} {'flexion':>8s} {'footprints':>11s} {'epiphysis':>10s} {'steps':>6s} {'wall (s)':>9s}")
    for r in out.rows:
        print(f"{labels[r.method]:44s} {r.flexion_estimated_deg:7.1f}° {r.footprints_mm:8.2f} mm "
              f"{r.epiphysis_mm:7.2f} mm {r.steps:6d} {r.wall_seconds:9.1f}")
        if math.isfinite(r.flexion_sd_deg):
            print(f"  the flexion's standard error from the method's fits: {r.flexion_sd_deg:.1f} deg")
        if math.isfinite(r.tibia_correction_deg):
            print(f"  the tibia's pose corrected from the shank's depth points: {r.tibia_correction_deg:.1f} deg, "
                  f"{r.tibia_correction_mm:.1f} mm off the prior's path")
        if r.notes:
            print(f"  note: {r.notes}")
    print(f"comparison: {shown / 'compare.md'}, {shown / 'compare.png'}")
    print(f"open it with: rerun {shown / 'compare.rrd'}")
    print(f"(the FEM part took {out.seconds:.0f} s)", file=sys.stderr)
