"""Whether a case set's truth is converged (``scripts/build_case_set.py``): every 0 mm view's flexed skin made
again by the truth's tissue on finer spacings (``--truth-edges``, femur widths; the set's own is 0.1 unless it
was built with ``--truth-edge``), rendered noise-free from the view's placement, and the femur's tissue floor
measured on those points under each model grid of ``--cells-across`` cells across (the association model posed
with the true bones, the femur placed on its skin with every other step exact, as methods (ii)/(iii) place it;
the footprint error, mm; :func:`knee.app.experiments.skin_floor.truth_edge_floor`).

    .venv/bin/python scripts/truth_convergence.py CASE_SET [--truth-edges 0.1,0.07,0.05] [--cells-across 7,14]
        [--cameras paper] [--only ANATOMY] [--csv OUT.csv]

Prints, per anatomy and grid, the median floor at each spacing and how far each spacing's skin lies from the
finest's over the knee. Where the floor moves as the truth is refined, the set's figures carry that much of the
truth's own discretisation. Slow: the truth's tissue at 0.05 femur widths takes 1-2 min a pose, and 10-15 min
for a knee flexed to 90 deg (seed 0's six 0 mm paper views of one anatomy at 0.1, 0.07 and 0.05: about 30 min).
"""

from __future__ import annotations

import argparse
import sys


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", help="a case set folder (scripts/build_case_set.py)")
    ap.add_argument("--truth-edges", default="0.1,0.07,0.05",
                    help="the truth tissue's node spacings, femur widths, comma-separated (0.1,0.07,0.05)")
    ap.add_argument("--cells-across", default="7", help="the model grids: cells across the limb, comma-separated (7)")
    ap.add_argument("--cameras", default="paper", help="the camera placements of the views measured (paper)")
    ap.add_argument("--only", default="", help="only the cases whose id contains this (e.g. an anatomy)")
    ap.add_argument("--csv", default=None, help="write a row per view, spacing and grid here")
    args = ap.parse_args()
    from knee.app.console import new_files, numbers, timed_progress, write_rows_csv
    from knee.app.experiments.skin_floor import truth_edge_floor, truth_edge_table
    from knee.foundations.errors import KneeError, KneeInputError

    try:
        edges = numbers(args.truth_edges, None, "--truth-edges")
        cells = numbers(args.cells_across, None, "--cells-across")
        cameras = {c.strip() for c in args.cameras.split(",") if c.strip()}
        if not cameras:
            raise KneeInputError(f"--cameras must name camera placements, got {args.cameras!r}")
        new_files(args.csv)
        rows = truth_edge_floor(args.cases, edges, cells, timed_progress(),
                                lambda c: c["camera"] in cameras and args.only in c["id"])
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.csv:
        write_rows_csv(args.csv, rows)
    print("\n".join(truth_edge_table(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
