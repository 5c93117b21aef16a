"""Method (iii)'s time with its registrations on subsamples (this build) against the same registrations on
every point (the baseline), in one process: the two alternate case by case (the order swapped every case),
so that a shared machine's load falls on both alike. The subsamples, each a random, seeded one:

- ``rough``: the rough registration's guess refined with at most ``ROUGH_ICP_POINTS`` of the thinned points
  (baseline: all of them);
- ``coarse``: the flexion estimate's coarse scan registered with at most ``COARSE_ICP_POINTS`` (baseline: all);
- ``thigh``: the thigh's registration and its jackknife with at most ``THIGH_ICP_POINTS`` of the seen thigh's
  points (baseline: every third of them, the rule before).

Every ``--every``-th case of a case set (``scripts/build_case_set.py``). Prints each run, the medians of wall
and CPU time, the median per-case ratio of the two, and the footprint errors' median change.

    .venv/bin/python scripts/bench_subsamples.py CASE_SET [--every 6] [--subsample rough,coarse,thigh]
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
from pathlib import Path

SUBSAMPLES = ("rough", "coarse", "thigh")


def main() -> int:
    from knee.app.console import at_least
    from knee.foundations.errors import KneeError

    ap = argparse.ArgumentParser()
    ap.add_argument("cases")
    ap.add_argument("--every", type=at_least(1), default=6, help="time every n-th case (default 6: 10 of a 60-case "
                    "set)")
    ap.add_argument("--subsample", type=_subsamples, default=list(SUBSAMPLES),
                    help="which subsamples the baseline leaves out, comma-separated (default: all of "
                    f"{', '.join(SUBSAMPLES)})")
    args = ap.parse_args()
    try:
        return run(Path(args.cases), args.every, args.subsample)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def _subsamples(text: str) -> list[str]:
    """``--subsample``'s names, comma-separated, each one of :data:`SUBSAMPLES`."""
    which = [w.strip() for w in text.split(",") if w.strip()]
    if not which or any(w not in SUBSAMPLES for w in which):
        raise argparse.ArgumentTypeError(f"must be some of {', '.join(SUBSAMPLES)} (comma-separated), got {text}")
    return which


class Baseline:
    """Within this context the chosen registrations take every point (the thigh's: every third seen point)."""

    def __init__(self, which):
        import knee.models.fem.methods as M
        import knee.models.prior as P

        self.M, self.P, self.which = M, P, which
        self.kept = (P.ROUGH_ICP_POINTS, P.COARSE_ICP_POINTS, M.THIGH_ICP_POINTS, M.seeded_subsample)

    def __enter__(self):
        M, P = self.M, self.P
        if "rough" in self.which:
            P.ROUGH_ICP_POINTS = sys.maxsize
        if "coarse" in self.which:
            P.COARSE_ICP_POINTS = sys.maxsize
        if "thigh" in self.which:
            M.THIGH_ICP_POINTS = -1  # a marker: the methods' subsample of the thigh becomes every third point
            subsample = self.kept[3]
            M.seeded_subsample = lambda p, most: p[::3] if most == -1 else subsample(p, most)
        return self

    def __exit__(self, *exc):
        self.P.ROUGH_ICP_POINTS, self.P.COARSE_ICP_POINTS, self.M.THIGH_ICP_POINTS, self.M.seeded_subsample = self.kept
        return False


def run(folder: Path, every: int, which) -> int:
    from knee.app.experiments.case_set import iter_cases, run_case

    rows = {"subsample": [], "every point": []}
    for case, (anatomy, prior, T_ct_model), i, _ in iter_cases(folder):
        if i % every:
            continue
        order = ("subsample", "every point") if (i // every) % 2 == 0 else ("every point", "subsample")
        for name in order:
            with Baseline(which) if name == "every point" else contextlib.nullcontext():
                row, _ = run_case(folder, case, "links", anatomy, prior, T_ct_model)
            rows[name].append(row)
            print(f"{case['id']:45s} {name:12s} {row.wall_seconds:6.2f} s wall {row.cpu_seconds:6.2f} s CPU "
                  f"{row.footprints_mm:5.2f} mm", flush=True)
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
    print(f"subsamples ({', '.join(which)}) / every point, median per case: wall {wall:.3f}, CPU {cpu:.3f}; "
          f"footprints' median change {change:+.3f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
