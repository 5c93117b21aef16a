"""Benchmark of the TF fit (issue: fit a subject-specific mechanism, section 4).

60 frames of noisy synthetic `volunteer` motion, first estimate = `volunteer` with every endpoint moved
up to 2 mm; the toolkit's fit (global stage + multi-start Gauss-Newton with exact derivatives) against a
baseline measured in the same run: the same local stage from the same starts with finite-difference
Jacobians (scipy's '2-point').

    .venv/bin/python scripts/bench_fit.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    from scipy.optimize import least_squares

    from fitting.optimize import TFFit, fit_tf, motion_mae, noise_weights, perturb_endpoints, synthetic_motion
    from models.mechanism import load_model

    truth_p = load_model("volunteer")
    meas, truth = synthetic_motion(truth_p, np.linspace(0, 120, 60), seed=1)
    first = perturb_endpoints(truth_p, 0.5, 2.0, seed=7)
    fit_times, maes = [], []
    for k in range(args.repeat):
        t = time.perf_counter()
        res = fit_tf(first, meas, seed=k, weights=noise_weights())
        fit_times.append(time.perf_counter() - t)
        maes.append(motion_mae(res.params, truth))
    # local stage alone, exact vs finite-difference Jacobian, from the first estimate
    prob = TFFit(first, meas, weights=noise_weights())
    g = np.random.default_rng(0)
    while True:  # an assembling start near the fitted optimum
        w0 = res.w + g.normal(0, 0.3, 35)
        if prob.model_motion(w0)[1]:
            break
    t = time.perf_counter()
    ex = least_squares(prob.residuals, w0, jac=prob.jacobian, method="trf", x_scale="jac", max_nfev=40)
    t_exact = time.perf_counter() - t
    t = time.perf_counter()
    fd = least_squares(prob.residuals, w0, jac="2-point", method="trf", x_scale="jac", max_nfev=40 * 36)
    t_fd = time.perf_counter() - t
    print("| what | median | ratio to baseline | notes |")
    print("|---|---:|---:|---|")
    print(f"| TF fit, 60 frames (global + 7 local starts, exact Jacobians) | {statistics.median(fit_times):.1f} s | – | "
          f"MAE vs noise-free truth, worst run: {np.max(maes, axis=0).round(2).tolist()} (deg, deg, mm, mm, mm) |")
    print(f"| local stage from a start near the optimum, exact Jacobian | {t_exact:.2f} s | {t_fd / t_exact:.1f}× | cost {2 * ex.cost:.1f} |")
    print(f"| baseline: the same local stage, finite-difference Jacobian | {t_fd:.2f} s | 1× | cost {2 * fd.cost:.1f} |")


if __name__ == "__main__":
    main()
