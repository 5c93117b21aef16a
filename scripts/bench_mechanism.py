"""Benchmark of the mechanism solver (issue: kinematic core, section 6).

Measures, in one run on the same machine:
  * a 121-angle TF+PF sweep of `volunteer` (0..120 deg, 1 deg) on the compiled path: the solve
    (continuation, convergence and jump checks) and the solve plus condition numbers;
  * the same sweep through CasADi's virtual machine (no compiler);
  * the baseline: a plain `scipy.optimize.least_squares` loop over the same angles;
  * a single-angle TF+PF solve;
and prints a Markdown table with medians and ratios against the baseline. Usage:

    .venv/bin/python scripts/bench_mechanism.py [--repeat 300]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np


def timeit(fn, repeat):
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), ts


def main():
    from knee.app.console import at_least

    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=at_least(1), default=300)
    args = ap.parse_args()
    from knee.models.mechanism import Mechanism
    from knee.models.mechanism import reference as ref

    m = Mechanism.from_name("volunteer", compile=True)
    vm = Mechanism.from_name("volunteer", compile=False)
    assert m.compiled and not vm.compiled
    al = np.radians(np.arange(0.0, 121.0, 1.0))
    res = m.sweep(al)
    assert res.complete and res.flexion.size == 121

    def sweep_only():
        m.sweep(al)

    def sweep_cond():
        m.sweep(al).condition

    def sweep_vm():
        vm.sweep(al)

    x0, psi0 = res.tf[0, 1:], res.psi[0]

    def baseline():
        ref.solve_sweep_least_squares(m.params, al, x0, m.psi_ref, psi0)

    angles = iter(np.tile(al, 10_000))

    def single():
        m.solve(next(angles))

    k = 70  # single-angle baseline: least squares at one angle from the neighbouring solution

    def single_baseline():
        x = ref.solve_tf_least_squares(m.params, al[k], res.tf[k - 1, 1:])
        ref.solve_pf(m.params, x, al[k], m.psi_ref, res.psi[k - 1])

    for f in (sweep_only, sweep_cond, single):
        f()  # warm up
    r = args.repeat
    b_sweep = timeit(baseline, 5)
    b_single = timeit(single_baseline, 30)
    rows = [("121-angle TF+PF sweep, compiled (solve + checks)", *timeit(sweep_only, r), b_sweep[0]),
            ("121-angle TF+PF sweep, compiled, + condition numbers", *timeit(sweep_cond, r), b_sweep[0]),
            ("121-angle TF+PF sweep, CasADi virtual machine", *timeit(sweep_vm, max(5, r // 20)), b_sweep[0]),
            ("baseline: scipy least_squares loop, 121 angles", *b_sweep, b_sweep[0]),
            ("single-angle TF+PF solve, compiled", *timeit(single, r * 10), b_single[0]),
            ("baseline: single-angle scipy least_squares (TF + PF)", *b_single, b_single[0])]
    tf_b, pf_b = ref.solve_sweep_least_squares(m.params, al, x0, m.psi_ref, psi0)
    agree = max(np.abs(tf_b - res.tf).max(), np.abs(pf_b - res.pf).max())
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}")
    print(f"assembly range of volunteer: {np.degrees(m.assembly_range[0]):.2f} to "
          f"{np.degrees(m.assembly_range[1]):.2f} deg; sweep vs baseline max difference {agree:.1e} (rad/mm)")
    print()
    print("| what | median | ratio to its baseline (baseline / this) | runs |")
    print("|---|---:|---:|---:|")
    for name, med, ts, base in rows:
        unit = f"{med * 1e6:.1f} µs" if med < 1e-3 else f"{med * 1e3:.3f} ms"
        print(f"| {name} | {unit} | {base / med:,.0f}× | {len(ts)} |")


if __name__ == "__main__":
    main()
