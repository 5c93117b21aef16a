"""Where method (iii)'s error comes from, stage by stage, on a case set (``scripts/build_case_set.py``): after
the flexion estimate (the tibia on the prior's path), after the femur's placement by the thigh with the
tibia's first correction, after its placement again on the skin the FEM posed with the second correction,
after the bones were slid apart where they overlapped, and at the end of the FEM's surface phase (the bones'
rigid poses, what ``knee compare`` measures). Per stage: the median footprint error (mm; femur / tibia) at 0-1
mm and at 2 mm skin mismatch and over all cases, the flexions within 2 deg of the truth among the cases that
see the shank, and the medians of the femur's error (rotation, deg; translation at the knee's centre, mm; in
the true femur's frame: x anterior, y proximal, z the medio-lateral axis) and of the tibia's rotation relative
to the femur (deg, the true tibia's frame; its z is the flexion's error with the sign reversed).

    .venv/bin/python scripts/diagnose_case_set.py CASE_SET [--only ID,...] [--method links|init]
        [--csv OUT.csv]

The CSV has a row per case and stage. About 5 s per case on the 2-core machine (60 cases: 5 min).
"""

from __future__ import annotations

import argparse
import statistics
import sys

import numpy as np


def _median(values) -> float:
    v = [x for x in values if np.isfinite(x)]
    return statistics.median(v) if v else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", help="a case set folder (scripts/build_case_set.py)")
    ap.add_argument("--only", default="", help="comma-separated parts of case ids to run")
    ap.add_argument("--method", default="links", choices=("links", "init"))
    ap.add_argument("--csv", default=None, help="write a row per case and stage here")
    args = ap.parse_args()
    from knee.app.console import new_files, timed_progress
    from knee.app.experiments.case_set import diagnose_case_set, read_case_set
    from knee.foundations.errors import KneeError
    from knee.foundations.files import write_records
    from knee.models.fem.methods import STAGES
    from knee.models.prior import MIN_SEEN_SHANK  # the cases that see the shank, as knee compare counts them

    try:
        new_files(args.csv)
        read_case_set(args.cases)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    only = [o for o in args.only.split(",") if o]
    select = (lambda c: any(o in c["id"] for o in only)) if only else None
    progress = timed_progress()

    runs = diagnose_case_set(args.cases, args.method, progress, select)
    if not runs:
        print(f"error: no case of {args.cases} matches --only {args.only}", file=sys.stderr)
        return 2
    records = []
    for row, stages in runs:
        if row.failed:
            print(f"{row.case}: failed ({row.failed})", file=sys.stderr)
            continue
        for s in stages:
            records.append({"case": row.case, "anatomy": row.anatomy, "family": row.family,
                            "mismatch_mm": row.mismatch_mm, "shank_points_true": row.shank_points_true,
                            "flexion_true_deg": row.flexion_true_deg, "stage": s.stage,
                            "femur_footprints_mm": s.femur_footprints_mm, "tibia_footprints_mm": s.tibia_footprints_mm,
                            "footprints_mm": s.footprints_mm, "flexion_deg": s.flexion_deg,
                            **{f"femur_rotation_{a}_deg": v for a, v in zip("xyz", s.femur_rotation_deg)},
                            **{f"femur_translation_{a}_mm": v for a, v in zip("xyz", s.femur_translation_mm)},
                            **{f"relative_rotation_{a}_deg": v for a, v in zip("xyz", s.relative_rotation_deg)}})
    if args.csv:
        write_records(args.csv, records)
    groups = {"0-1 mm": lambda r: r["mismatch_mm"] <= 1, "2 mm": lambda r: r["mismatch_mm"] > 1, "all": lambda r: True}
    print("| stage | " + " | ".join(f"footprints {g} (femur / tibia)" for g in groups)
          + " | flexion within 2 deg | femur rotation (deg) | femur at the knee (mm) | tibia rotation (deg) |")
    print("|---|" + "---:|" * (len(groups) + 4))
    for stage in (*STAGES, "final"):
        rs = [r for r in records if r["stage"] == stage]
        if not rs:
            continue
        cells = []
        for sel in groups.values():
            g = [r for r in rs if sel(r)]
            if not g:
                cells.append("-")
                continue
            cells.append(f"{_median(r['footprints_mm'] for r in g):.2f} ({_median(r['femur_footprints_mm'] for r in g):.2f}"
                         f" / {_median(r['tibia_footprints_mm'] for r in g):.2f})")
        seen = [r for r in rs if r["shank_points_true"] >= MIN_SEEN_SHANK]
        within = sum(abs(r["flexion_deg"] - r["flexion_true_deg"]) <= 2.0 for r in seen)
        vec = [" / ".join(f"{_median(r[f'{k}_{a}_{u}'] for r in rs):+.2f}" for a in "xyz")
               for k, u in (("femur_rotation", "deg"), ("femur_translation", "mm"), ("relative_rotation", "deg"))]
        print(f"| {stage} | " + " | ".join(cells) + f" | {within} of {len(seen)} | " + " | ".join(vec) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
