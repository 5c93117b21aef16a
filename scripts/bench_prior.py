"""Wall time of method (iii), the FEM with the kinematic prior (issue "kinematic priors for the FEM",
target: at most 5 s per case), on the 15 standard cases of scripts/compare_priors.py, one process, one
case after another (nothing else of the toolkit running beside it).

Per case, timed as `knee compare` times it (the model is built once per prior and the depth points are
rendered before the clock starts): the flexion estimate, the registration, the tibia's correction, the
initialisation and the surface phase. The sweep runs ``--repeat`` times (default 2) and the table gives
each case's best and worst time: on a shared machine the same case's time moves by 20-50 % between runs,
and the best of the runs is the closest measure of the toolkit's own time. In the same runs, as
baselines: method (iii) with SciPy's SuperLU LU as the solver's factorisation instead of CHOLMOD's
Cholesky (every case), and the paper's method (i) on three of the cases (PAPER_CASES).

    .venv/bin/python scripts/bench_prior.py [--repeat 2]
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
    from knee.app.console import at_least

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=at_least(1), default=2,
                    help="runs of every case and configuration (the sweep repeated; default 2); the table gives "
                         "each case's best and worst")
    args = ap.parse_args()

    from knee.app.experiments.cases import case_points, result_row, run_method
    from knee.fitting.optimize import perturb_endpoints
    from knee.models.fem.depth import DepthNoise, camera_from_spec
    from knee.models.fem.scene import build_association_model
    from knee.models.mechanism import Mechanism

    truth = Mechanism.from_name("volunteer")
    prior = Mechanism(perturb_endpoints(truth.params, 1.0, 2.0, seed=3))
    noise = DepthNoise()
    points = {c: case_points(truth, c[1], camera_from_spec(c[0]), noise, 3)[0] for c in CASES}
    runs = {c: {} for c in CASES}  # case -> label -> [(wall, steps, footprints)] over the repeats
    for rep in range(args.repeat):
        for i, (cam_name, fl) in enumerate(CASES):
            cam = camera_from_spec(cam_name)
            for label, backend, method in (("links", "cholmod", "links"), ("links_superlu", "superlu", "links"),
                                           ("paper", "cholmod", "paper")):
                if method == "paper" and (cam_name, fl) not in PAPER_CASES:
                    continue
                model = build_association_model(prior)
                model.solver.factor_backend = backend
                r = run_method(method, truth, prior, fl, cam, noise, 3, points=points[(cam_name, fl)], model=model)
                row = result_row(cam_name, fl, r)
                runs[(cam_name, fl)].setdefault(label, []).append((row.wall_seconds, row.steps, row.footprints_mm))
            o = runs[(cam_name, fl)]
            paper = f"; paper's method {o['paper'][-1][0]:.1f} s" if "paper" in o else ""
            print(f"[run {rep + 1}/{args.repeat}, {i + 1}/{len(CASES)}] {cam_name} {fl}: "
                  f"(iii) {o['links'][-1][0]:.2f} s, {o['links'][-1][1]} steps, footprints {o['links'][-1][2]:.2f} mm; "
                  f"with SuperLU {o['links_superlu'][-1][0]:.2f} s{paper}", file=sys.stderr, flush=True)

    def best(c, label):
        return min(w for w, _, _ in runs[c][label])

    def worst(c, label):
        return max(w for w, _, _ in runs[c][label])

    n = args.repeat
    print(f"| case | (iii) wall, best of {n} (s) | worst of {n} (s) | steps | footprints (mm) | "
          f"(iii) with SuperLU, best of {n} (s) | (i) paper's method, best of {n} (s) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for c in CASES:
        o = runs[c]
        paper = f"{best(c, 'paper'):.1f}" if "paper" in o else ""
        print(f"| {c[0]} {c[1]} | {best(c, 'links'):.2f} | {worst(c, 'links'):.2f} | {o['links'][0][1]} | "
              f"{o['links'][0][2]:.2f} | {best(c, 'links_superlu'):.2f} | {paper} |")
    med = statistics.median(best(c, "links") for c in CASES)
    med_worst = statistics.median(worst(c, "links") for c in CASES)
    med_lu = statistics.median(best(c, "links_superlu") for c in CASES)
    paper = [best(c, "paper") for c in CASES if "paper" in runs[c]]
    within = sum(best(c, "links") <= 5.0 for c in CASES)
    within_worst = sum(worst(c, "links") <= 5.0 for c in CASES)
    print(f"\n(iii): median {med:.2f} s per case, best of {n} runs ({within} of {len(CASES)} cases within 5 s; "
          f"worst of {n}: median {med_worst:.2f} s, {within_worst} of {len(CASES)} within 5 s; target: median <= 5 s "
          f"{'met' if med <= 5.0 else 'NOT met'}); with SuperLU {med_lu:.2f} s (ratio {med_lu / med:.2f}x)")
    if paper:
        print(f"(i) the paper's method on {len(paper)} of the cases: median {statistics.median(paper):.1f} s "
              f"(ratio to (iii) {statistics.median(paper) / med:.1f}x)")
    print(f"(iii) median footprint error {statistics.median(runs[c]['links'][0][2] for c in CASES):.2f} mm")


if __name__ == "__main__":
    main()
