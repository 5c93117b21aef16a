"""Benchmark of the TF fit (issue: fit a subject-specific mechanism, section 4).

60 frames of noisy synthetic `volunteer` motion, first estimate = `volunteer` with every endpoint moved
up to 2 mm; the toolkit's fit (global stage + multi-start Gauss-Newton with exact derivatives) against a
baseline measured in the same run: the same local stage from the same starts with finite-difference
Jacobians (scipy's '2-point'). Then the whole pipeline (`knee fit`: first estimate from imaging, TF and
PF fits, report, figure, recording) on a synthetic `volunteer` subject with 60 frames, repeated with the
same seed (the results must be identical), and the PF local stage exact vs finite differences.

    .venv/bin/python scripts/bench_fit.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main():
    from knee.app.console import at_least

    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=at_least(1), default=3)
    args = ap.parse_args()

    from knee.fitting.optimize import (
        TFFit,
        fit_tf,
        motion_mae,
        noise_weights,
        perturb_endpoints,
        synthetic_motion,
    )
    from knee.models.mechanism import load_model

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
    t_exact, ex, t_fd, fd = exact_vs_fd(prob, w0)
    print("| what | median | ratio to baseline | notes |")
    print("|---|---:|---:|---|")
    print(f"| TF fit, 60 frames (global + 7 local starts, exact Jacobians) | {statistics.median(fit_times):.1f} s | – | "
          f"MAE vs noise-free truth, worst run: {np.max(maes, axis=0).round(2).tolist()} (deg, deg, mm, mm, mm) |")
    print(f"| local stage from a start near the optimum, exact Jacobian | {t_exact:.2f} s | {t_fd / t_exact:.1f}× | cost {2 * ex.cost:.1f} |")
    print(f"| baseline: the same local stage, finite-difference Jacobian | {t_fd:.2f} s | 1× | cost {2 * fd.cost:.1f} |")
    pipeline(args.repeat)


def exact_vs_fd(prob, w0):
    """The local stage from ``w0`` with the exact Jacobian and with scipy's finite differences (the
    same evaluation budget per Jacobian column): (seconds, result) of each."""
    from scipy.optimize import least_squares

    t = time.perf_counter()
    ex = least_squares(prob.residuals, w0, jac=prob.jacobian, method="trf", x_scale="jac", max_nfev=40)
    t_exact = time.perf_counter() - t
    t = time.perf_counter()
    fd = least_squares(prob.residuals, w0, jac="2-point", method="trf", x_scale="jac", max_nfev=40 * (w0.size + 1))
    return t_exact, ex, time.perf_counter() - t, fd


def pipeline(repeat):
    import shutil
    import tempfile
    from pathlib import Path

    from knee.app.reports.fit import write_outputs
    from knee.fitting.pf import PFFit
    from knee.fitting.pipeline import fit_subject
    from knee.fitting.synthetic import make_subject

    tmp = Path(tempfile.mkdtemp(prefix="knee-bench-fit-"))
    try:
        subj = make_subject(tmp / "subject", seed=0)
        times, vecs, outs = [], [], []
        for k in range(repeat):
            t = time.perf_counter()
            o = fit_subject(subj, seed=0)
            write_outputs(o, tmp / f"out{k}")
            times.append(time.perf_counter() - t)
            vecs.append(o.fitted.to_vector())
            outs.append(o)
        same = all(np.array_equal(vecs[0], v) for v in vecs[1:])
        o = outs[0]
        t_mae = o.truth_errors.tf.mae[1:]
        p_mae = o.truth_errors.pf.mae
        print(f"| whole pipeline, 60 frames, TF+PF (first estimate, fits, report, figure, recording) | "
              f"{statistics.median(times):.1f} s | – | fit alone {o.seconds.fit:.1f} s; same seed, same result: "
              f"{same}; vs noise-free truth TF {t_mae.round(2).tolist()}, PF {p_mae.round(2).tolist()} |")
        # PF local stage exact vs finite differences, from a start near the optimum
        from knee.fitting.optimize import Motion

        prob = PFFit(o.fitted, Motion(o.motion.tf, o.motion.pf))
        g = np.random.default_rng(0)
        w0 = g.normal(0, 0.2, prob.n_var)
        t_exact, ex, t_fd, fd = exact_vs_fd(prob, w0)
        print(f"| PF local stage, exact Jacobian | {t_exact:.2f} s | {t_fd / t_exact:.1f}× | cost {2 * ex.cost:.1f} |")
        print(f"| baseline: PF local stage, finite-difference Jacobian | {t_fd:.2f} s | 1× | cost {2 * fd.cost:.1f} |")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
