"""How well the flexion estimate's posed skin fits each view of one or more case sets
(``scripts/build_case_set.py``): the check on the input behind ``knee fem``'s poor-fit warning
(:data:`knee.models.prior.POOR_FIT_RMS_MM`). Runs the mechanism alone (iv), whose flexion estimate and
rough registration are those of (ii) and (iii), on every case, and prints per set, per anatomy and pooled:
the views, the median and the largest trimmed RMS (mm, nearest 90 % of the points), how many fit within
2.5 mm and which exceed the threshold, with their (iv) footprint error beside (a view fitted poorly is one
whose answer should not be trusted).

    .venv/bin/python scripts/estimate_fit.py CASE_SET [CASE_SET ...] [--csv OUT.csv]

About 1.5 s per case on the 2-core machine (60 cases: 2 min).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import statistics
import sys
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+", help="case set folders")
    ap.add_argument("--csv", default=None, help="a row per case: the set, the case and the run's figures")
    args = ap.parse_args()
    from knee.foundations.errors import KneeError

    try:
        return run(args)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def summary(label: str, rows) -> str:
    """One table row: the views, the fit's median and largest, within 2.5 mm, over the threshold."""
    from knee.models.prior import POOR_FIT_RMS_MM

    fit = sorted(r.estimate_rms_mm for r in rows if r.estimate_rms_mm == r.estimate_rms_mm)
    if not fit:
        return f"| {label} | 0 | - | - | - | - |"
    poor = [r for r in rows if r.estimate_rms_mm > POOR_FIT_RMS_MM]
    named = ", ".join(f"{r.case} {r.estimate_rms_mm:.1f} mm ((iv) {r.footprints_mm:.1f} mm)" for r in poor) or "none"
    return (f"| {label} | {len(fit)} | {statistics.median(fit):.2f} | {fit[-1]:.2f} | "
            f"{sum(v <= 2.5 for v in fit)} | {named} |")


def run(args) -> int:
    from knee.app.console import new_files, timed_progress
    from knee.app.experiments.case_set import read_case_set, run_case_set
    from knee.foundations.files import staged_file
    from knee.models.prior import POOR_FIT_RMS_MM

    for folder in args.cases:
        read_case_set(folder)  # every set readable before the first run
    new_files(args.csv)
    progress = timed_progress()
    runs = {}
    for folder in args.cases:
        runs[Path(folder).name] = run_case_set(folder, ["kinematics"], progress)
    print(f"| views | count | median RMS (mm) | largest | within 2.5 mm | over {POOR_FIT_RMS_MM:g} mm |")
    print("|---|---:|---:|---:|---:|---|")
    for name, rows in runs.items():
        for anatomy in sorted({r.anatomy for r in rows}):
            print(summary(f"{name}, {anatomy}", [r for r in rows if r.anatomy == anatomy]))
        print(summary(f"{name}, all", rows))
    if len(runs) > 1:
        print(summary("pooled", [r for rows in runs.values() for r in rows]))
    failed = [(name, r) for name, rows in runs.items() for r in rows if r.failed]
    for name, r in failed:
        print(f"failed: {name} {r.case}: {r.failed}")
    if args.csv:
        allrows = [dict(set=name, **dataclasses.asdict(r)) for name, rows in runs.items() for r in rows]
        with staged_file(args.csv) as tmp, open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(allrows[0]))
            w.writeheader()
            w.writerows(allrows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
