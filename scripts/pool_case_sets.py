"""The honest benchmark's targets over several case sets: each ``knee compare CASE_SET`` table (``compare.csv``)
given, its targets for method (iii) as ``knee compare`` prints them, then the same targets over all of them
pooled (each set's cases kept apart, so that (iii) is compared with (iv) on its own case). Case sets built
from different seeds (``scripts/build_case_set.py --seed N``) draw other skin fields, deviations, noise,
camera guesses and synthetic phantom subjects: one seed's medians alone can be a lucky draw.

    .venv/bin/python scripts/pool_case_sets.py SEED0/compare.csv SEED1/compare.csv [...] [--plot POOLED.png]

Reads tables only (instant). ``--plot``: every pooled case's footprint error per method, a panel per anatomy
and family, grouped by skin mismatch (the figure ``knee compare`` draws for one set).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tables", nargs="+", help="knee compare CSVs, one per case set")
    ap.add_argument("--plot", help="a PNG of every pooled case's footprint error (a new file)")
    args = ap.parse_args()
    from knee.app.experiments.case_set import CaseRow
    from knee.app.reports.case_set import plot, targets
    from knee.app.reports.compare import read_csv
    from knee.foundations.errors import KneeError

    paths = [Path(t) for t in args.tables]
    if len({p.resolve() for p in paths}) < len(paths):
        print("error: a table is given twice; its cases would count twice in the pool", file=sys.stderr)
        return 2
    if args.plot and (Path(args.plot).exists() or Path(args.plot).suffix.lower() != ".png"):
        print(f"error: --plot {args.plot}: " + ("exists; not overwritten (give a new file)" if Path(args.plot).exists()
                                                 else "give a .png file"), file=sys.stderr)
        return 2
    try:
        sets = [read_csv(p, CaseRow) for p in paths]
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    pooled = []
    for i, (p, rows) in enumerate(zip(paths, sets)):
        print(f"## {p} ({len({r.case for r in rows})} cases)")
        print("\n".join(targets(rows)))
        print()
        pooled += [dataclasses.replace(r, case=f"{i}:{r.case}") for r in rows]
    print(f"## pooled: {len(paths)} case sets ({len({r.case for r in pooled})} cases)")
    print("\n".join(targets(pooled)))
    if args.plot:
        methods = [m for m in ("links", "kinematics", "init", "paper") if any(r.method == m for r in pooled)]
        plot(pooled, methods, args.plot, title=f"{len(paths)} case sets pooled ({len({r.case for r in pooled})} cases)")
        print(f"figure: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
