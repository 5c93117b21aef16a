"""Method (iii)'s time with the rough registration's guess refined on a subsample (``ROUGH_ICP_POINTS``,
this build) against every point of the view (the baseline), in one process: the two alternate case by case
(the order swapped every case), so that a shared machine's load falls on both alike. Every ``--every``-th
case of a case set (``scripts/build_case_set.py``). Prints each run, the medians of wall and CPU time, the
median per-case ratio of the two, and the footprint errors' median change.

    .venv/bin/python scripts/bench_rough_points.py CASE_SET [--every 6]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path


def main() -> int:
    from knee.app.console import at_least
    from knee.foundations.errors import KneeError

    ap = argparse.ArgumentParser()
    ap.add_argument("cases")
    ap.add_argument("--every", type=at_least(1), default=6, help="time every n-th case (default 6: 10 of a 60-case "
                    "set)")
    args = ap.parse_args()
    try:
        return run(Path(args.cases), args.every)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def run(folder: Path, every: int) -> int:
    import knee.models.prior as P
    from knee.app.experiments.case_set import iter_cases, run_case

    subsample = P.ROUGH_ICP_POINTS
    rows = {"subsample": [], "every point": []}
    for case, (anatomy, prior, T_ct_model), i, _ in iter_cases(folder):
        if i % every:
            continue
        order = ("subsample", "every point") if (i // every) % 2 == 0 else ("every point", "subsample")
        for which in order:
            P.ROUGH_ICP_POINTS = subsample if which == "subsample" else sys.maxsize
            row, _ = run_case(folder, case, "links", anatomy, prior, T_ct_model)
            rows[which].append(row)
            print(f"{case['id']:45s} {which:12s} {row.wall_seconds:6.2f} s wall {row.cpu_seconds:6.2f} s CPU "
                  f"{row.footprints_mm:5.2f} mm", flush=True)
    P.ROUGH_ICP_POINTS = subsample
    new, old = rows["subsample"], rows["every point"]
    if not new:
        print("error: no case selected", file=sys.stderr)
        return 2
    for name, rs in rows.items():
        print(f"{name}: wall median {statistics.median(r.wall_seconds for r in rs):.2f} s, CPU median "
              f"{statistics.median(r.cpu_seconds for r in rs):.2f} s ({len(rs)} cases)")
    wall = statistics.median(a.wall_seconds / b.wall_seconds for a, b in zip(new, old))
    cpu = statistics.median(a.cpu_seconds / b.cpu_seconds for a, b in zip(new, old))
    change = statistics.median(a.footprints_mm - b.footprints_mm for a, b in zip(new, old))
    print(f"subsample / every point, median per case: wall {wall:.3f}, CPU {cpu:.3f}; footprints' median change "
          f"{change:+.3f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
