"""Method (iii) on a case set (``scripts/build_case_set.py``) with the femur placed three ways: by the
thigh, then again by the knee's and the thigh's points on the skin the FEM posed, the tibia's correction
made again (the default, ``refine_on_posed_skin=True``); by the thigh alone (the paper's way,
``refine_on_posed_skin=False``); and by the whole blended skin of the flexion estimate (the knee's own
shape, ``femur_from="knee"``, not placed again); the mechanism alone (iv) beside them. With
``--fem-skin``, also (iv) and (iii) with the flexion estimate's skin posed by the FEM
(``flexion_skin="fem"``). Medians per anatomy, family and skin mismatch, and the share of cases where
(iii) beats (iv).

    .venv/bin/python scripts/bench_case_set.py CASE_SET [--only ID,...] [--csv OUT.csv] [--fem-skin]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("cases")
    ap.add_argument("--only", default="")
    ap.add_argument("--csv", default=None)
    ap.add_argument("--fem-skin", action="store_true", help="also the rows with the flexion estimate's skin posed by "
                    "the FEM (flexion_skin='fem')")
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
    from knee.foundations.errors import KneeInputError
    from knee.foundations.files import write_records

    index = read_case_set(args.cases)
    new_files(args.csv)
    only = [o for o in args.only.split(",") if o]
    select = (lambda c: any(o in c["id"] for o in only)) if only else None
    if select is not None and not any(select(c) for c in index["case"]):
        raise KneeInputError(f"--only {args.only} selects none of the {len(index['case'])} cases")
    progress = timed_progress()

    rows = {}
    rows["iv"] = run_case_set(args.cases, ["kinematics"], progress, select)
    rows["iii"] = run_case_set(args.cases, ["links"], progress, select)
    rows["iii thigh"] = run_case_set(args.cases, ["links"], progress, select, refine_on_posed_skin=False)
    rows["iii knee"] = run_case_set(args.cases, ["links"], progress, select, femur_from="knee",
                                    refine_on_posed_skin=False)
    if args.fem_skin:  # the flexion estimate's skin posed by the FEM (flexion_skin="fem")
        rows["iv fem skin"] = run_case_set(args.cases, ["kinematics"], progress, select, flexion_skin="fem")
        rows["iii fem skin"] = run_case_set(args.cases, ["links"], progress, select, flexion_skin="fem")
    keys = sorted({(r.anatomy, r.family, r.mismatch_mm) for r in rows["iv"]})
    print("| anatomy | family | mismatch | " + " | ".join(f"{k} fp (femur / tibia)" for k in rows) + " |")
    print("|---|---|---:|" + "---:|" * len(rows))
    for key in keys:
        cells = []
        for k, rs in rows.items():
            ok = [r for r in rs if (r.anatomy, r.family, r.mismatch_mm) == key and not r.failed]
            cells.append(f"{statistics.median(r.footprints_mm for r in ok):.2f} "
                         f"({statistics.median(r.femur_footprints_mm for r in ok):.2f} / "
                         f"{statistics.median(r.tibia_footprints_mm for r in ok):.2f})" if ok else "-")
        print(f"| {key[0]} | {key[1]} | {key[2]:g} mm | " + " | ".join(cells) + " |")
    kin = {r.case: r.footprints_mm for r in rows["iv"] if not r.failed}
    for k in [k for k in rows if k.startswith("iii")]:
        ok = [r for r in rows[k] if not r.failed and r.case in kin]
        if ok:
            print(f"{k}: median {statistics.median(r.footprints_mm for r in ok):.2f} mm over {len(ok)} cases; lower "
                  f"than (iv) in {sum(r.footprints_mm < kin[r.case] for r in ok)} of {len(ok)}; flexion within 2 deg "
                  f"in {sum(abs(r.flexion_estimated_deg - r.flexion_true_deg) <= 2 for r in ok)}; median time "
                  f"{statistics.median(r.wall_seconds for r in ok):.1f} s; failed "
                  f"{sum(r.failed != '' for r in rows[k])}")
    print(f"(iv): median {statistics.median(kin.values()):.2f} mm over {len(kin)} cases")
    if "iv fem skin" in rows:
        ok = [r for r in rows["iv fem skin"] if not r.failed]
        print(f"(iv) fem skin: median {statistics.median(r.footprints_mm for r in ok):.2f} mm over {len(ok)} cases")
    if args.csv:
        write_records(args.csv, (dict(dataclasses.asdict(r), variant=k) for k, rs in rows.items() for r in rs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
