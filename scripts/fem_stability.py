"""Stability check of the association model (issue: association FEM, section 4): the default model at
dt = 0.05 s with the stiff bones, 2000 implicit steps. A posterior force on the distal tibia (1000 N)
flexes the knee for the first 200 steps and is then released (``--release -1``: kept on throughout). Prints progress and, at the end, the
largest displacement, the final flexion and whether every step stayed finite.

    .venv/bin/python scripts/fem_stability.py [--steps 2000]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main():
    from knee.app.console import at_least

    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=at_least(1), default=2000)
    ap.add_argument("--force", type=at_least(0.0, float), default=1000.0)
    ap.add_argument("--release", type=at_least(-1), default=200, help="step at which the load is removed (-1: never)")
    args = ap.parse_args()
    from knee.models.fem.scene import build_association_model, knee_angles
    from knee.models.mechanism import Mechanism

    model = build_association_model(Mechanism.from_name("volunteer"))
    s = model.solver
    tib = model.tibia
    end = np.argsort(tib.el.X[:, 1])[:5]

    def load(x):
        if 0 <= args.release <= s.steps:
            return None
        f = np.zeros((len(tib.el.X), 3))
        f[end, 0] = -args.force / len(end)
        return tib.map.apply_transpose(f)

    t0 = time.perf_counter()
    worst, finite, its = 0.0, True, []
    for k in range(args.steps):
        info = s.step(load)
        its.append(info.iterations)
        d = float(np.abs(s.x - model.grid.X).max())
        finite &= bool(np.all(np.isfinite(s.x)))
        worst = max(worst, d)
        if k % 100 == 0 or k == args.steps - 1:
            flex, between = knee_angles(model)
            print(f"step {k:5d}  t={s.time:7.2f}s  max displacement {d:8.2f} mm  flexion {flex:6.2f} deg  "
                  f"CG iterations {info.iterations:3d}  refreshes {s.refreshes}  "
                  f"wall {time.perf_counter() - t0:7.1f}s", file=sys.stderr, flush=True)
        if not finite or d > 1e4:
            break
    flex, _ = knee_angles(model)
    print(f"steps {s.steps}, finite {finite}, largest displacement {worst:.2f} mm, final flexion {flex:.2f} deg, "
          f"median CG iterations {np.median(its):.0f}, {s.steps / (time.perf_counter() - t0):.2f} steps/s")
    return 0 if finite and worst < 1e4 else 1


if __name__ == "__main__":
    sys.exit(main())
