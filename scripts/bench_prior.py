"""Wall time of method (iii), the FEM with the kinematic prior (issue "kinematic priors for the FEM",
target: at most 5 s per case), on the 15 standard cases of scripts/compare_priors.py, one process, one
case after another (nothing else of the toolkit running beside it).

Per case, timed as `knee compare` times it (the model is built once per prior and the depth points are
rendered before the clock starts): the flexion estimate, the registration, the tibia's correction, the
initialisation and the surface phase. In the same run, as baselines: method (iii) with SciPy's SuperLU
LU as the solver's factorisation instead of CHOLMOD's Cholesky (every case), and the paper's method (i)
on three of the cases (PAPER_CASES).

    .venv/bin/python scripts/bench_prior.py
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import statistics  # noqa: E402
import sys  # noqa: E402

CASES = ([("oblique", f) for f in (30, 45, 60, 75, 90, 105, 120)]
         + [(c, f) for c in ("frontal", "lateral") for f in (30, 60, 90, 120)])
#: The cases the paper's method (the baseline, about 20 s each) is timed on.
PAPER_CASES = {("oblique", 30), ("oblique", 105), ("frontal", 120)}


def main():
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()

    from fitting.optimize import perturb_endpoints
    from models.fem.case import camera_from_spec, case_points
    from models.fem.compare_report import footprint_error
    from models.fem.depth import DepthNoise
    from models.fem.prior_case import result_row, run_method
    from models.fem.scene import build_association_model
    from models.mechanism import Mechanism

    truth = Mechanism.from_name("volunteer")
    prior = Mechanism(perturb_endpoints(truth.params, 1.0, 2.0, seed=3))
    noise = DepthNoise()
    rows = []
    for i, (cam_name, fl) in enumerate(CASES):
        cam = camera_from_spec(cam_name)
        pts, _ = case_points(truth, fl, cam, noise, 3)
        out = {"case": f"{cam_name} {fl}"}
        for label, backend, method in (("links", "cholmod", "links"), ("links_superlu", "superlu", "links"),
                                       ("paper", "cholmod", "paper")):
            if method == "paper" and (cam_name, fl) not in PAPER_CASES:
                continue
            model = build_association_model(prior)
            model.solver.factor_backend = backend
            r = run_method(method, truth, prior, fl, cam, noise, 3, points=pts, model=model)
            row = result_row(cam_name, fl, r)
            out[label] = (r.wall_seconds, r.steps, footprint_error(row))
        rows.append(out)
        print(f"[{i + 1}/{len(CASES)}] {out['case']}: (iii) {out['links'][0]:.2f} s, {out['links'][1]} steps, "
              f"footprints {out['links'][2]:.2f} mm; with SuperLU {out['links_superlu'][0]:.2f} s"
              + (f"; paper's method {out['paper'][0]:.1f} s" if "paper" in out else ""), file=sys.stderr, flush=True)
    print("| case | (iii) wall (s) | steps | footprints (mm) | (iii) with SuperLU (s) | (i) paper's method (s) |")
    print("|---|---:|---:|---:|---:|---:|")
    for o in rows:
        paper = f"{o['paper'][0]:.1f}" if "paper" in o else ""
        print(f"| {o['case']} | {o['links'][0]:.2f} | {o['links'][1]} | {o['links'][2]:.2f} | "
              f"{o['links_superlu'][0]:.2f} | {paper} |")
    med = statistics.median(o["links"][0] for o in rows)
    med_lu = statistics.median(o["links_superlu"][0] for o in rows)
    paper = [o["paper"][0] for o in rows if "paper" in o]
    within = sum(o["links"][0] <= 5.0 for o in rows)
    print(f"\n(iii): median {med:.2f} s per case ({within} of {len(rows)} cases within 5 s; target: median <= 5 s "
          f"{'met' if med <= 5.0 else 'NOT met'}); with SuperLU {med_lu:.2f} s (ratio {med_lu / med:.2f}x)")
    if paper:
        print(f"(i) the paper's method on {len(paper)} of the cases: median {statistics.median(paper):.1f} s "
              f"(ratio to (iii) {statistics.median(paper) / med:.1f}x)")
    print(f"(iii) median footprint error {statistics.median(o['links'][2] for o in rows):.2f} mm")


if __name__ == "__main__":
    main()
