"""Where method (iii)'s error comes from, stage by stage, on a case set (``scripts/build_case_set.py``): after
the flexion estimate (the tibia on the prior's path), after the femur's placement by the thigh with the
tibia's first correction, after its placement again on the skin the FEM posed with the second correction,
after the bones were slid apart where they overlapped, and at the end of the FEM's surface phase (the bones'
rigid poses, what ``knee compare`` measures). Per stage: the median footprint error (mm; femur / tibia) at 0-1
mm and at 2 mm skin mismatch and over all cases, the flexions within 2 deg of the truth among the cases that
see the shank, and the medians of the femur's error (rotation, deg; translation at the knee's centre, mm; in
the true femur's frame: x anterior, y proximal, z the medio-lateral axis) and of the tibia's rotation relative
to the femur (deg, the true tibia's frame; its z is the flexion's error with the sign reversed).

A second table splits the flexion by anatomy, camera and skin mismatch (the views that see the shank, final
bones): within 2 deg, the median signed error, the median absolute sagittal tilt (rotation about the
medio-lateral axis) of the femur after the thigh's placement, after the posed skin's and at the end, the
tibia's own at the end, and of the misses how many the femur's tilt leads (larger than the tibia's). About
that axis the flexion's error is about the femur's tilt less the tibia's: which bone's placement to look at.

    .venv/bin/python scripts/diagnose_case_set.py CASE_SET [--only ID,...] [--method links|init]
        [--cells-across N|NX,NZ|knee] [--csv OUT.csv] [--plot OUT.png]
    .venv/bin/python scripts/diagnose_case_set.py --from-csv A.csv [B.csv ...] [--plot OUT.png]

The CSV has a row per case and stage. About 5 s per case on the 2-core machine (60 cases: 5 min).
``--from-csv`` prints both tables again from such CSVs, pooled (e.g. one per seed), without running anything.
``--plot`` draws the stage-by-stage figure (:func:`knee.app.reports.case_set.plot_stages`): per anatomy, the
median footprint error at each stage with its quartiles, a line per skin mismatch, and the share of the views
that see the shank with the flexion within 2 deg.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from pathlib import Path

import numpy as np

#: The columns a row of the CSV holds: text, then numbers.
TEXT = ("case", "anatomy", "family", "camera", "stage")
NUMBERS = ("mismatch_mm", "shank_points_true", "flexion_true_deg", "femur_footprints_mm", "tibia_footprints_mm",
           "footprints_mm", "flexion_deg",
           *(f"{k}_{a}_{u}" for k, u in (("femur_rotation", "deg"), ("femur_translation", "mm"),
                                          ("relative_rotation", "deg"), ("tibia_rotation", "deg"))
             for a in "xyz"))


def _median(values) -> float:
    v = [x for x in values if np.isfinite(x)]
    return statistics.median(v) if v else float("nan")


def read_rows(paths) -> list[dict]:
    """The rows of CSVs this script wrote; each file's cases kept apart from the others' (the same case id in
    two seeds' sets is two cases). A missing file or column is a :class:`KneeInputError`."""
    from knee.foundations.errors import KneeInputError

    records = []
    for i, path in enumerate(paths):
        path = Path(path)
        if not path.is_file():
            raise KneeInputError(f"{path} is not a file")
        try:
            with open(path, newline="", encoding="utf-8") as fh:
                reader = csv.DictReader(fh)
                fields, table = reader.fieldnames or [], list(reader)
        except (OSError, UnicodeDecodeError, csv.Error) as e:
            raise KneeInputError(f"{path}: cannot read it as a CSV ({e})") from None
        missing = [c for c in (*TEXT, *NUMBERS) if c not in fields]
        if missing:
            raise KneeInputError(f"{path} is not a diagnosis table (no column {missing[0]}); write one with --csv")
        for r in table:
            try:
                rec = {**{k: r[k] for k in TEXT}, **{k: float(r[k]) for k in NUMBERS}}
            except (TypeError, ValueError) as e:
                raise KneeInputError(f"{path}: a row of case {r['case']} has a value that is not a number "
                                     f"({e})") from None
            rec["key"] = (i, rec["case"])
            records.append(rec)
    return records


def stage_table(records, stages, min_seen: int) -> list[str]:
    """The stage-by-stage table's lines (Markdown)."""
    groups = {"0-1 mm": lambda r: r["mismatch_mm"] <= 1, "2 mm": lambda r: r["mismatch_mm"] > 1, "all": lambda r: True}
    lines = ["| stage | " + " | ".join(f"footprints {g} (femur / tibia)" for g in groups)
             + " | flexion within 2 deg | femur rotation (deg) | femur at the knee (mm) | tibia rotation (deg) |",
             "|---|" + "---:|" * (len(groups) + 4)]
    for stage in stages:
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
        seen = [r for r in rs if r["shank_points_true"] >= min_seen]
        within = sum(abs(r["flexion_deg"] - r["flexion_true_deg"]) <= 2.0 for r in seen)
        vec = [" / ".join(f"{_median(r[f'{k}_{a}_{u}'] for r in rs):+.2f}" for a in "xyz")
               for k, u in (("femur_rotation", "deg"), ("femur_translation", "mm"), ("relative_rotation", "deg"))]
        lines.append(f"| {stage} | " + " | ".join(cells) + f" | {within} of {len(seen)} | " + " | ".join(vec) + " |")
    return lines


def flexion_table(records, min_seen: int) -> list[str]:
    """The flexion by anatomy, camera and skin mismatch (Markdown lines): the views that see the shank at
    their final bones, with the femur's tilt at its placements and the tibia's own."""
    by_case: dict = {}
    for r in records:
        by_case.setdefault(r["key"], {})[r["stage"]] = r
    views = [s for s in by_case.values() if "final" in s and s["final"]["shank_points_true"] >= min_seen]
    lines = ["| anatomy | camera | skin mismatch | views | flexion within 2 deg | signed error (deg) | femur tilt: "
             "thigh / posed skin / final (deg) | tibia tilt (deg) | misses led by the femur |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]

    def row(label, vs):
        fin = [v["final"] for v in vs]
        err = np.array([r["flexion_deg"] - r["flexion_true_deg"] for r in fin])
        fz = np.array([abs(r["femur_rotation_z_deg"]) for r in fin])
        tz = np.array([abs(r["tibia_rotation_z_deg"]) for r in fin])
        miss = np.abs(err) > 2.0
        tilt = [_median(abs(v[s]["femur_rotation_z_deg"]) for v in vs if s in v) for s in ("placed", "posed_skin")]
        lines.append(f"| {label} | {len(vs)} | {int((~miss).sum())} | {_median(err):+.2f} | "
                     f"{tilt[0]:.2f} / {tilt[1]:.2f} / {_median(fz):.2f} | {_median(tz):.2f} | "
                     f"{int((miss & (fz > tz)).sum())} of {int(miss.sum())} |")

    keys = sorted({(v["final"]["anatomy"], v["final"]["camera"], v["final"]["mismatch_mm"]) for v in views})
    for anatomy in sorted({k[0] for k in keys}):
        for a, cam, mm in (k for k in keys if k[0] == anatomy):
            row(f"{a} | {cam} | {mm:g} mm", [v for v in views if (v["final"]["anatomy"], v["final"]["camera"],
                                                                 v["final"]["mismatch_mm"]) == (a, cam, mm)])
        row(f"{anatomy} | all | all", [v for v in views if v["final"]["anatomy"] == anatomy])
    if len({k[0] for k in keys}) > 1:
        row("all | all | all", views)
    return lines


def main() -> int:
    from knee.app.cli import CELLS_ACROSS_HELP, cells_across

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", nargs="?", help="a case set folder (scripts/build_case_set.py)")
    ap.add_argument("--only", default="", help="comma-separated parts of case ids to run")
    ap.add_argument("--method", default="links", choices=("links", "init"))
    ap.add_argument("--cells-across", type=cells_across, default=None, metavar="N|NX,NZ|knee",
                    help=f"the model's grid, as knee compare takes it: {CELLS_ACROSS_HELP}")
    ap.add_argument("--csv", default=None, help="write a row per case and stage here")
    ap.add_argument("--from-csv", nargs="+", default=None, metavar="CSV",
                    help="print the tables from CSVs this script wrote (pooled), running nothing")
    ap.add_argument("--plot", default=None, help="draw the stage-by-stage figure here (PNG)")
    args = ap.parse_args()
    from knee.app.console import new_files, timed_progress
    from knee.foundations.errors import KneeError
    from knee.models.fem.methods import STAGES
    from knee.models.prior import MIN_SEEN_SHANK  # the cases that see the shank, as knee compare counts them

    if args.plot and Path(args.plot).suffix.lower() != ".png":
        print(f"error: --plot {args.plot}: the figure is a PNG; give a .png file", file=sys.stderr)
        return 2
    if (args.cases is None) == (args.from_csv is None):
        print("error: give a case set or --from-csv, not both" if args.cases else
              "error: give a case set folder to run, or --from-csv with the tables of earlier runs", file=sys.stderr)
        return 2
    if args.from_csv is not None and args.cells_across is not None:
        print("error: --cells-across sets the grid of cases run; --from-csv runs none", file=sys.stderr)
        return 2
    if args.from_csv is not None:
        try:
            new_files(args.plot)
            records = read_rows(args.from_csv)
        except KneeError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print("\n".join(stage_table(records, (*STAGES, "final"), MIN_SEEN_SHANK)))
        print()
        print("\n".join(flexion_table(records, MIN_SEEN_SHANK)))
        _plot(records, (*STAGES, "final"), args.plot, MIN_SEEN_SHANK)
        return 0

    from knee.app.experiments.case_set import diagnose_case_set, read_case_set
    from knee.foundations.files import write_records

    try:
        new_files(args.csv, args.plot)
        read_case_set(args.cases)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    only = [o for o in args.only.split(",") if o]
    select = (lambda c: any(o in c["id"] for o in only)) if only else None
    progress = timed_progress()

    from knee.models.fem.scene import FemSettings

    settings = None if args.cells_across is None else FemSettings(n_across=args.cells_across)
    runs = diagnose_case_set(args.cases, args.method, progress, select, settings=settings)
    if not runs:
        print(f"error: no case of {args.cases} matches --only {args.only}", file=sys.stderr)
        return 2
    records = []
    for row, stages in runs:
        if row.failed:
            print(f"{row.case}: failed ({row.failed})", file=sys.stderr)
            continue
        for s in stages:
            records.append({"case": row.case, "anatomy": row.anatomy, "family": row.family, "camera": row.camera,
                            "stage": s.stage, "mismatch_mm": row.mismatch_mm, "shank_points_true": row.shank_points_true,
                            "flexion_true_deg": row.flexion_true_deg,
                            "femur_footprints_mm": s.femur_footprints_mm, "tibia_footprints_mm": s.tibia_footprints_mm,
                            "footprints_mm": s.footprints_mm, "flexion_deg": s.flexion_deg,
                            **{f"femur_rotation_{a}_deg": v for a, v in zip("xyz", s.femur_rotation_deg)},
                            **{f"femur_translation_{a}_mm": v for a, v in zip("xyz", s.femur_translation_mm)},
                            **{f"relative_rotation_{a}_deg": v for a, v in zip("xyz", s.relative_rotation_deg)},
                            **{f"tibia_rotation_{a}_deg": v for a, v in zip("xyz", s.tibia_rotation_deg)}})
    if args.csv:
        write_records(args.csv, records)
    for r in records:
        r["key"] = (0, r["case"])
    print("\n".join(stage_table(records, (*STAGES, "final"), MIN_SEEN_SHANK)))
    print()
    print("\n".join(flexion_table(records, MIN_SEEN_SHANK)))
    _plot(records, (*STAGES, "final"), args.plot, MIN_SEEN_SHANK)
    return 0


def _plot(records, stages, path, min_seen: int) -> None:
    """The stage-by-stage figure at ``path`` (written whole or not at all), when one is asked for."""
    if not path:
        return
    from knee.app.reports.case_set import plot_stages
    from knee.foundations.files import staged_file

    with staged_file(path) as tmp:
        plot_stages(records, stages, tmp, min_seen)
    print(f"figure: {path}")


if __name__ == "__main__":
    sys.exit(main())
