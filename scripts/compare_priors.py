"""The four methods of the kinematic-prior comparison on standard cases (issue "kinematic priors for the
FEM", section 3): (i) the paper's method, (ii) the prior as initialisation, (iii) initialisation plus the
five links, (iv) the mechanism alone. Truth `volunteer`; prior = `volunteer` with every TF endpoint moved
1-2 mm (seed 3). Depth noise on.

    .venv/bin/python scripts/compare_priors.py [--flexion 60,90] [--cameras oblique] [--out compare.csv]
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys

def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--flexion", default="60,90")
    ap.add_argument("--cameras", default="oblique")
    ap.add_argument("--methods", default="paper,init,links,kinematics")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    from fitting.optimize import perturb_endpoints
    from models.fem.case import camera_from_spec
    from models.fem.prior_case import compare_cases
    from models.mechanism import Mechanism
    from models.mechanism.params import load_model

    truth = Mechanism.from_name("volunteer")
    prior = Mechanism(perturb_endpoints(load_model("volunteer"), 1.0, 2.0, seed=3))
    cams = {c: camera_from_spec(c) for c in args.cameras.split(",")}
    rows = compare_cases(truth, prior, [float(v) for v in args.flexion.split(",")], cams,
                         methods=args.methods.split(","), progress=lambda i, n, t: print(f"... [{i}/{n}] {t}", file=sys.stderr, flush=True))
    print("| method | camera | flexion | estimate | femur footprints | tibia footprints | femur epiphysis | tibia epiphysis | steps | wall (s) | converged |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for r in rows:
        if r.get("failed"):
            print(f"| {r['method']} | {r['camera']} | {r['flexion_true_deg']:g} | failed: {r['failed']} |")
            continue
        print(f"| {r['method']} | {r['camera']} | {r['flexion_true_deg']:g} | {r['flexion_estimated_deg']:.1f} | "
              f"{r['femur_footprints_mm']:.2f} | {r['tibia_footprints_mm']:.2f} | {r['femur_epiphysis_mm']:.2f} | "
              f"{r['tibia_epiphysis_mm']:.2f} | {r['steps']} | {r['wall_seconds']:.1f} | {r['converged']} |")
    for m in args.methods.split(","):
        ok = [r for r in rows if r["method"] == m and not r.get("failed")]
        if ok:
            fp = [0.5 * (r["femur_footprints_mm"] + r["tibia_footprints_mm"]) for r in ok]
            print(f"{m}: median footprint error {statistics.median(fp):.2f} mm, median wall time "
                  f"{statistics.median(r['wall_seconds'] for r in ok):.1f} s over {len(ok)} cases")
    if args.out:
        with open(args.out, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=sorted({k for r in rows for k in r}))
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()
