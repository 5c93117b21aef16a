"""Run the paper's method (bone forces, then surface forces towards the depth points) on the phantom
standard case and print the target point errors (association FEM issue, section 3).

    .venv/bin/python scripts/fem_standard_case.py [--flexion 90] [--scale 1] [--max-steps 200]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main():
    from knee.app.console import at_least

    ap = argparse.ArgumentParser()
    ap.add_argument("--flexion", type=at_least(0.0, float, 150.0), default=90.0)
    ap.add_argument("--scale", type=at_least(0.0, float), default=1.0, help="factor on the paper's bone-force magnitudes")
    ap.add_argument("--max-steps", type=at_least(1), default=200)
    args = ap.parse_args()
    from knee.app.experiments.cases import run_standard_case
    from knee.foundations.errors import KneeError
    from knee.models.mechanism import Mechanism

    try:
        c = run_standard_case(Mechanism.from_name("volunteer"), args.flexion, bone_force_scale=args.scale,
                              max_steps=args.max_steps)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    r = c.reconstruction
    print(f"true flexion {c.flexion_true_deg:.1f} deg, estimated {r.flexion_deg:.1f} deg; "
          f"{r.steps} steps ({r.steps_bone_phase} with bone forces), {r.wall_seconds:.1f} s, "
          f"{'converged' if r.converged else 'not converged'}")
    print("| bone | footprints (mm) | epiphysis (mm) |")
    print("|---|---|---|")
    for bone in ("femur", "tibia"):
        e = c.errors.bone(bone)
        print(f"| {bone} | {e.footprints.mean:.2f} ± {e.footprints.sd:.2f} | {e.epiphysis.mean:.2f} ± {e.epiphysis.sd:.2f} |")
    if r.steps_bone_phase:
        print(f"flexion reached in the bone-force phase: "
              f"{np.nanmax(r.history['flexion_deg'][:r.steps_bone_phase]):.1f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
