"""The honest benchmark's targets over several case sets: each ``knee compare CASE_SET`` table (``compare.csv``)
given, its targets for method (iii) as ``knee compare`` prints them, then the same targets over all of them
pooled (each set's cases kept apart, so that (iii) is compared with (iv) on its own case). Case sets built
from different seeds (``scripts/build_case_set.py --seed N``) draw other skin fields, deviations, noise,
camera guesses and synthetic phantom subjects: one seed's medians alone can be a lucky draw.

    .venv/bin/python scripts/pool_case_sets.py SEED0/compare.csv SEED1/compare.csv [...] [--plot POOLED.png]
        [--table POOLED.md]

Reads tables only (instant). One set's methods run apart (``knee compare SET --methods links,kinematics``
and later ``--methods paper,init``) are joined with ``+``: ``SEED0/a/compare.csv+SEED0/b/compare.csv`` is one
set (a case's method in both is refused). ``--plot``: every pooled case's footprint error per method, a panel
per anatomy and family, grouped by skin mismatch (the figure ``knee compare`` draws for one set). ``--table``:
the pooled medians per anatomy, family, skin mismatch and method, the targets and every run, as Markdown (the
report ``knee compare`` writes for one set).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tables", nargs="+", help="knee compare CSVs, one per case set (one set's tables joined by +)")
    ap.add_argument("--plot", help="a PNG of every pooled case's footprint error (a new file)")
    ap.add_argument("--table", help="a Markdown file of the pooled medians per family and method (a new file)")
    args = ap.parse_args()
    from knee.app.experiments.case_set import CaseRow
    from knee.app.reports.case_set import markdown, plot, targets
    from knee.app.reports.compare import read_csv
    from knee.foundations.errors import KneeError, KneeInputError

    groups = [[Path(t) for t in arg.split("+")] for arg in args.tables]
    paths = [p for g in groups for p in g]
    if len({p.resolve() for p in paths}) < len(paths):
        print("error: a table is given twice; its cases would count twice in the pool", file=sys.stderr)
        return 2
    for flag, out, suffix in (("--plot", args.plot, ".png"), ("--table", args.table, ".md")):
        if out and (Path(out).exists() or Path(out).suffix.lower() != suffix):
            print(f"error: {flag} {out}: " + ("exists; not overwritten (give a new file)" if Path(out).exists()
                                              else f"give a {suffix} file"), file=sys.stderr)
            return 2
    sets = []
    try:
        for g in groups:
            rows = [r for p in g for r in read_csv(p, CaseRow)]
            seen, truth = set(), {}
            for r in rows:
                if (r.case, r.method) in seen:
                    raise KneeInputError(f"{'+'.join(map(str, g))}: case {r.case} has method {r.method} twice; join only "
                                         "tables of one set's other methods")
                seen.add((r.case, r.method))
                # the same case of another set (another seed) has other truth poses under the same id
                t = truth.setdefault(r.case, r)
                # a failed run's shank count is unknown (-1): compared only where both tables know it
                counts_known = min(t.shank_points_true, r.shank_points_true) >= 0
                if abs(t.flexion_true_deg - r.flexion_true_deg) > 0.01 or (
                        counts_known and t.shank_points_true != r.shank_points_true):
                    raise KneeInputError(f"{'+'.join(map(str, g))}: case {r.case} differs between the tables joined "
                                         f"(true flexion {t.flexion_true_deg:g} / {r.flexion_true_deg:g} deg, shank "
                                         f"points {t.shank_points_true} / {r.shank_points_true}): they are not one "
                                         "case set's")
            sets.append(rows)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    pooled = []
    for i, (g, rows) in enumerate(zip(groups, sets)):
        p = "+".join(map(str, g))
        print(f"## {p} ({len({r.case for r in rows})} cases)")
        print("\n".join(targets(rows)))
        print()
        pooled += [dataclasses.replace(r, case=f"{i}:{r.case}") for r in rows]
    print(f"## pooled: {len(groups)} case sets ({len({r.case for r in pooled})} cases)")
    print("\n".join(targets(pooled)))
    methods = [m for m in ("links", "kinematics", "init", "paper") if any(r.method == m for r in pooled)]
    title = f"{len(groups)} case sets pooled ({len({r.case for r in pooled})} cases)"
    if args.plot:
        plot(pooled, methods, args.plot, title=title)
        print(f"figure: {args.plot}")
    if args.table:
        Path(args.table).write_text(markdown(pooled, methods, title))
        print(f"table: {args.table}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
