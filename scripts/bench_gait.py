"""Benchmark of the gait analysis (issue "contact mechanics, gait and virtual osteotomy", section 5).

A 101-frame gait cycle (the bundled normative one) on the bundled `volunteer`: knee kinematics from the
mechanism, inverse dynamics (Pinocchio RNEA), statics of the six members and Hertz at both contacts;
target at most 1 s. Baseline measured in the same run: the same statics solved frame by frame
(one `solve_statics` call per frame, as a loop over frames would do it). The elastic-foundation maps are
timed separately.

    .venv/bin/python scripts/bench_gait.py [--repeat 7]
"""

from __future__ import annotations

import argparse
import statistics
import time


def main():
    from knee.app.console import at_least

    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=at_least(1), default=7)
    args = ap.parse_args()
    from knee.models.gait import analyse_gait, normative_trial
    from knee.models.mechanism import Mechanism
    from knee.models.statics import solve_statics

    mech = Mechanism.from_name("volunteer")
    trial = normative_trial(72.0)
    analyse_gait(mech, trial, foundation=False)  # warm-up (compiled backend, imports)
    t_fast, t_ef = [], []
    for _ in range(args.repeat):
        t = time.perf_counter()
        res = analyse_gait(mech, trial, foundation=False)
        t_fast.append(time.perf_counter() - t)
        t = time.perf_counter()
        analyse_gait(mech, trial, foundation=True)
        t_ef.append(time.perf_counter() - t)
    t_base = []
    for _ in range(max(1, args.repeat // 3)):
        t = time.perf_counter()
        for k in range(trial.time.size):
            solve_statics(mech, trial.knee[k], res.knee_force[k], res.knee_moment[k])
        t_base.append(time.perf_counter() - t)
    m, b = statistics.median(t_fast), statistics.median(t_base)
    print("| what | median | ratio to baseline | notes |")
    print("|---|---:|---:|---|")
    print(f"| 101-frame gait: kinematics, RNEA, statics, Hertz at both contacts | {m * 1e3:.0f} ms | {b / m:.1f}× | "
          f"target 1 s |")
    print(f"| the same with elastic-foundation pressure maps | {statistics.median(t_ef) * 1e3:.0f} ms | – | "
          f"tabulated force-approach curve per contact, maps for every frame |")
    print(f"| baseline: statics alone, one solve_statics call per frame | {b * 1e3:.0f} ms | 1× | |")


if __name__ == "__main__":
    main()
