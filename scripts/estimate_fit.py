"""How well the flexion estimate's posed skin fits each view of one or more case sets
(``scripts/build_case_set.py``): the check on the input behind ``knee fem``'s poor-fit warning
(:data:`knee.models.prior.POOR_FIT_RMS_MM`). Runs the mechanism alone (iv), whose flexion estimate and
rough registration are those of (ii) and (iii), on every case, and prints per set, per anatomy and pooled the
report's line (:func:`knee.app.reports.case_set.estimate_fit`): the views, the median and the largest
trimmed RMS (mm, nearest 90 % of the points), how many fit within 2.5 mm and which exceed the threshold.

    .venv/bin/python scripts/estimate_fit.py CASE_SET [CASE_SET ...] [--csv OUT.csv]

About 1.5 s per case on the 2-core machine (60 cases: 2 min).
"""

from __future__ import annotations

import argparse
import dataclasses
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


def run(args) -> int:
    from knee.app.console import new_files, timed_progress
    from knee.app.experiments.case_set import read_case_set, run_case_set
    from knee.app.reports.case_set import estimate_fit
    from knee.foundations.files import write_records

    for folder in args.cases:
        read_case_set(folder)  # every set readable before the first run
    new_files(args.csv)
    progress = timed_progress()
    runs = {Path(folder).name: run_case_set(folder, ["kinematics"], progress) for folder in args.cases}
    groups = {}
    for name, rows in runs.items():
        groups.update({f"{name}, {a}:": [r for r in rows if r.anatomy == a] for a in sorted({r.anatomy for r in rows})})
        groups[f"{name}, all:"] = rows
    if len(runs) > 1:
        groups["pooled:"] = [r for rows in runs.values() for r in rows]
    for label, rows in groups.items():
        print(*(estimate_fit(rows, label) or [f"{label} no flexion estimate"]))
    for name, rows in runs.items():
        for r in rows:
            if r.failed:
                print(f"failed: {name} {r.case}: {r.failed}")
    if args.csv:
        write_records(args.csv, (dict(set=name, **dataclasses.asdict(r)) for name, rows in runs.items() for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
