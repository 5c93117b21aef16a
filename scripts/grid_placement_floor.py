"""How much the association model's grid placement moves its answer, on a case set (``scripts/build_case_set.py``):
the femur's tissue floor (the association model posed with the true bones, the femur placed on its skin from the
depth points with every other step exact, as methods (ii)/(iii) place it; the footprint error, mm) under each grid
of ``--cells-across`` cells across the limb, moved by each of ``--offsets`` (fractions of a cell; the model's own
grid is 7 across at offset 0), on the views of ``--cameras`` at ``--mismatches``
(:func:`knee.app.experiments.skin_floor.placement_floor`).

    .venv/bin/python scripts/grid_placement_floor.py CASE_SET [--cells-across 7,14] [--offsets 0,0.25,0.5,0.75]
        [--mismatches 0,1] [--cameras paper] [--only ANATOMY] [--csv OUT.csv] [--plot OUT.png]

Prints, per anatomy, grid and mismatch, the median floor at each offset and each view's standard deviation over
the offsets (averaged over the views): where it is large, a figure measured under one placement carries that
much of where the cells fall on the leg. ``--plot`` draws every view's floor against the offset
(:func:`knee.app.reports.case_set.plot_placement_floor`).

About 1 s per view and placement with the model's 7 cells across, about 4 s with 14 (seed 0's 24 paper views at
0 and 1 mm, four placements of both grids: 13 minutes on the 2-core machine beside another run).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", help="a case set folder (scripts/build_case_set.py)")
    ap.add_argument("--cells-across", default="7", help="the grids: cells across the limb, comma-separated (7)")
    ap.add_argument("--offsets", default="0,0.25,0.5,0.75",
                    help="the placements: each grid moved by these fractions of a cell, in [0, 1) (0,0.25,0.5,0.75)")
    ap.add_argument("--mismatches", default="0,1", help="the skin mismatches (mm) of the views measured (0,1)")
    ap.add_argument("--cameras", default="paper", help="the camera placements of the views measured (paper)")
    ap.add_argument("--only", default="", help="only the cases whose id contains this (e.g. an anatomy)")
    ap.add_argument("--csv", default=None, help="write a row per view and grid placement here")
    ap.add_argument("--plot", default=None, help="draw every view's floor against the placement here (PNG)")
    args = ap.parse_args()
    from knee.app.console import new_files, numbers, timed_progress, write_rows_csv
    from knee.app.experiments.case_set import read_case_set
    from knee.app.experiments.skin_floor import placement_floor, placement_spread
    from knee.foundations.errors import KneeError, KneeInputError
    from knee.foundations.files import staged_file

    try:
        # (the counts and the offsets are checked by placement_floor, before any model is built)
        cells = numbers(args.cells_across, None, "--cells-across")
        offsets = numbers(args.offsets, None, "--offsets")
        mismatches = numbers(args.mismatches, None, "--mismatches")
        if any(not m >= 0.0 for m in mismatches):
            raise KneeInputError(f"--mismatches must be skin mismatches in mm (0 or more), got {args.mismatches!r}")
        cameras = {c.strip() for c in args.cameras.split(",") if c.strip()}
        if not cameras:
            raise KneeInputError(f"--cameras must name camera placements, got {args.cameras!r}")
        if args.plot and Path(args.plot).suffix.lower() != ".png":
            raise KneeInputError(f"--plot {args.plot}: the figure is a PNG; give a .png file")
        new_files(args.csv, args.plot)
        index = read_case_set(args.cases)

        def chosen(c: dict) -> bool:
            return c["camera"] in cameras and args.only in c["id"]

        if not any(chosen(c) and float(c["mismatch_mm"]) in mismatches for c in index["case"]):
            raise KneeInputError(f"{args.cases}: no case from the {', '.join(sorted(cameras))} placement(s) at "
                                 f"{', '.join(f'{m:g}' for m in mismatches)} mm"
                                 + (f" whose id contains {args.only!r}" if args.only else ""))
        rows = placement_floor(args.cases, cells, offsets, mismatches, timed_progress(), chosen)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.csv:
        write_rows_csv(args.csv, rows)
    if args.plot:
        from knee.app.reports.case_set import plot_placement_floor

        with staged_file(args.plot) as tmp:
            plot_placement_floor(rows, tmp)
    summary = placement_spread(rows)
    offsets = sorted({o for d in summary.values() for o in d["offsets"]})
    print("| anatomy | cells across | skin mismatch | views | " + " | ".join(f"offset {o:g}" for o in offsets)
          + " | spread over the placements |")
    print("|---|---:|---:|---:|" + "---:|" * (len(offsets) + 1))
    for (anatomy, n, mm), d in summary.items():
        at = dict(zip(d["offsets"], d["median"]))
        print(f"| {anatomy} | {n} | {mm:g} mm | {d['cases']} | "
              + " | ".join(f"{at[o]:.2f}" if o in at else "" for o in offsets) + f" | {d['spread']:.2f} |")
    print("(the femur's tissue floor, median footprint error in mm at each placement; the spread: each view's "
          "standard deviation over the placements, averaged)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
