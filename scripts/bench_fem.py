"""Benchmark of the association FEM model (issue: association FEM, section 5).

For each configuration (run in its own subprocess, so peak memory is its own): build the model of the
bundled `volunteer` phantom, flex it with a posterior load on the distal tibia, and time implicit steps.
Rows: the model on the paper's grid (7x7 across, as in its figures; the model's default sizes x by the knee, 8x7 on
this phantom), graded along the limb, with the toolkit's solver (matrix-free CG,
reused warped Cholesky preconditioner), the same with SuperLU's LU as the preconditioner's factorisation,
the same with CG stopped at SOFA's default criterion (|r|^2/|b|^2 <= 1e-5, the paper's system) instead
of the toolkit's |r|/|b| <= 1e-5, and, as the baseline in the same run, the same steps with the matrix
assembled and solved directly (`spsolve`) every step; then the scaling table for uniform grids of 30,
100 and 300 cells along the limb. The median step is the benchmark's figure (the ratio is of medians);
the mean over the timed steps, which includes the amortised refactorisations, is printed beside it.

    .venv/bin/python scripts/bench_fem.py [--steps 30] [--skip-300]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np


def run_one(cfg: dict) -> dict:
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from knee.models.fem.grid import PAPER_CELLS_ACROSS
    from knee.models.fem.scene import FemSettings, build_association_model, knee_angles
    from knee.models.mechanism import Mechanism

    t0 = time.perf_counter()
    settings = FemSettings(n_across=PAPER_CELLS_ACROSS, n_along=cfg.get("n_along"))  # the paper's grid across
    model = build_association_model(Mechanism.from_name("volunteer"), settings)
    build = time.perf_counter() - t0
    s = model.solver
    s.factor_backend = cfg.get("backend", "cholmod")
    s.tol = cfg.get("tol", s.tol)
    tib = model.tibia
    end = np.argsort(tib.el.X[:, 1])[:5]

    def load(x):
        f = np.zeros((len(tib.el.X), 3))
        f[end, 0] = -200.0
        return tib.map.apply_transpose(f)

    if cfg.get("direct"):
        def step():  # naive implicit Euler: assemble and solve directly every step
            f = sum(fl.forces(s.x) for fl in s.fields) + load(s.x)
            K = sum((fl.matrix() for fl in s.fields), sp.csr_matrix((3 * len(s.m),) * 2))
            A = (sp.diags(np.repeat(s._cm * s.m, 3)) + s._ck * K).tocsr()
            P = sp.diags(s._free)
            A = (P @ A @ P + sp.diags(1 - s._free)).tocsc()
            rhs = (s.m[:, None] * s.v + s.dt * f).ravel() * s._free
            s.v = spla.spsolve(A, rhs).reshape(-1, 3)
            s.x = s.x + s.dt * s.v
            s.steps += 1
    else:
        def step():
            s.step(load)
    step()  # first step includes the first factorisation
    times = []
    for _ in range(cfg["steps"]):
        t = time.perf_counter()
        step()
        times.append(time.perf_counter() - t)
    flex, _ = knee_angles(model)
    return {"nodes": model.grid.n_nodes, "cells": len(model.grid.cells), "shape": model.grid.shape.tolist(),
            "tets": [len(model.femur.el.cells), len(model.tibia.el.cells)], "build_s": build,
            "median_step_s": float(np.median(times)),
            "mean_step_s": float(np.mean(times)), "flexion_deg": flex, "refreshes": s.refreshes,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        print(json.dumps(run_one(json.loads(sys.argv[2]))))
        return
    from knee.app.console import at_least

    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=at_least(1), default=30)
    ap.add_argument("--skip-300", action="store_true")
    args = ap.parse_args()
    configs = [("default model, toolkit solver", {"steps": args.steps}),
               ("default model, toolkit solver with SuperLU's LU instead of CHOLMOD", {"steps": args.steps,
                                                                                       "backend": "superlu"}),
               ("default model, toolkit solver, CG to SOFA's default criterion (|r|/|b| <= 3.2e-3)",
                {"steps": args.steps, "tol": 10 ** -2.5}),
               ("default model, baseline: assemble + spsolve every step", {"steps": max(5, args.steps // 3), "direct": True}),
               ("uniform grid, 30 cells along", {"steps": args.steps, "n_along": 30}),
               ("uniform grid, 100 cells along", {"steps": max(5, args.steps // 3), "n_along": 100})]
    if not args.skip_300:
        configs.append(("uniform grid, 300 cells along (the paper's)", {"steps": 3, "n_along": 300}))
    rows = []
    for name, cfg in configs:
        print(f"running: {name} ...", file=sys.stderr, flush=True)
        p = subprocess.run([sys.executable, __file__, "--child", json.dumps(cfg)], capture_output=True, text=True,
                           env=dict(os.environ), timeout=3600)
        if p.returncode != 0:
            rows.append((name, None, p.stderr.strip().splitlines()[-1:] if p.stderr else ["failed"]))
            continue
        rows.append((name, json.loads(p.stdout.strip().splitlines()[-1]), None))
    base = rows[3][1]["median_step_s"] if rows[3][1] else None
    print("| configuration | grid (x, y, z cells) / kept cells / nodes | bone tets | median step | steps/s | "
          "ratio to baseline | mean step (refreshes included) | peak memory |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for name, r, err in rows:
        if r is None:
            print(f"| {name} | failed: {err} | | | | | | |")
            continue
        ratio = f"{base / r['median_step_s']:.1f}×" if base else "–"
        print(f"| {name} | {tuple(r['shape'])} / {r['cells']} / {r['nodes']} | {r['tets'][0]} + {r['tets'][1]} | "
              f"{r['median_step_s'] * 1e3:.0f} ms | {1 / r['median_step_s']:.1f} | {ratio} | "
              f"{r['mean_step_s'] * 1e3:.0f} ms | {r['peak_rss_mb']:.0f} MB |")


if __name__ == "__main__":
    main()
