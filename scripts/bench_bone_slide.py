"""The bones slid apart (method (iii)'s ``keep_bones_apart``) with the slide bracketed near the pose, against
the same slide searched over the whole 30 mm reach (the baseline, the rule before), on real case sets'
anatomies: each case's true tibia pushed into its femur (seeded: 1-5 mm along the tibia's axis, up to 1 mm
across and 2 deg about each axis, as the placements from the skin leave it) and slid back both ways, the
two alternating (the order swapped every push) so that a shared machine's load falls on both alike.

Prints each push (its shortfall, both times and clearance counts, the slides' difference along the axis),
then the medians: wall and CPU time a slide, the per-push ratio, the clearances asked. Every ``--every``-th
case of a case set (``scripts/build_case_set.py``).

    .venv/bin/python scripts/bench_bone_slide.py CASE_SET [--every 6] [--pushes 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path


def main() -> int:
    from knee.app.console import at_least
    from knee.foundations.errors import KneeError

    ap = argparse.ArgumentParser()
    ap.add_argument("cases")
    ap.add_argument("--every", type=at_least(1), default=6, help="every n-th case (default 6: 10 of a 60-case set)")
    ap.add_argument("--pushes", type=at_least(1), default=3, help="pushes of each case's tibia (default 3)")
    args = ap.parse_args()
    try:
        rows = run(Path(args.cases), args.every, args.pushes)
    except KneeError as e:
        print(f"bench_bone_slide: {e}", file=sys.stderr)
        return 2
    if not rows:
        print("bench_bone_slide: no push brought the bones closer than at the scan", file=sys.stderr)
        return 2
    med = statistics.median
    print(f"\n{len(rows)} slides: bracketed {med(r['near_wall'] for r in rows) * 1e3:.0f} ms "
          f"(CPU {med(r['near_cpu'] for r in rows) * 1e3:.0f} ms, {med(r['near_n'] for r in rows):.0f} clearances), "
          f"whole reach {med(r['full_wall'] for r in rows) * 1e3:.0f} ms "
          f"(CPU {med(r['full_cpu'] for r in rows) * 1e3:.0f} ms, {med(r['full_n'] for r in rows):.0f} clearances); "
          f"ratio wall {med(r['near_wall'] / r['full_wall'] for r in rows):.3f}, "
          f"CPU {med(r['near_cpu'] / r['full_cpu'] for r in rows):.3f}; "
          f"slides' largest difference {max(r['diff'] for r in rows):.4f} mm")
    return 0


def run(folder: Path, every: int, pushes: int) -> list[dict]:
    import numpy as np

    import knee.models.fem.anatomy as anatomy_module
    from knee.app.experiments.case_set import iter_cases
    from knee.foundations.conventions import invert_poses
    from knee.models.fem.anatomy import bone_clearance, bone_queries, in_contact
    from knee.models.fem.scene import build_knee_model
    from knee.models.prior import small_pose

    real = anatomy_module.bone_clearance
    asked = [0]

    def counted(*a, **k):
        asked[0] += 1
        return real(*a, **k)

    rows = []
    models = {}
    for c, (anat, prior, T_ct_model), i, _ in iter_cases(folder):
        if i % every:
            continue
        if c["anatomy"] not in models:
            models[c["anatomy"]] = build_knee_model(anat, prior=prior).anatomy
        ka = models[c["anatomy"]]
        queries = bone_queries(ka)
        c0 = bone_clearance(ka, ka.tibia_pose, queries)
        T_cam_femur = np.asarray(c["T_camera_femur_ct"]) @ T_ct_model
        T_cam_tibia = np.asarray(c["T_camera_tibia_ct"]) @ T_ct_model
        T_true = invert_poses(T_cam_femur) @ T_cam_tibia @ ka.tibia_pose
        rng = np.random.default_rng(i)
        for k in range(pushes):
            xi = np.r_[np.radians(rng.uniform(-2.0, 2.0, 3)), rng.uniform(-1.0, 1.0, 3)]
            xi[4] += rng.uniform(1.0, 5.0)  # proximally, into the femur
            T = T_true @ small_pose(xi)
            now = bone_clearance(ka, T, queries)
            if now >= c0:
                continue
            out = {}
            anatomy_module.bone_clearance = counted
            try:
                for which in (("near", "full") if (len(rows) % 2 == 0) else ("full", "near")):
                    asked[0] = 0
                    t0, p0 = time.perf_counter(), time.process_time()
                    slid = in_contact(ka, T, c0, queries=queries, now=now if which == "near" else None)
                    out[which + "_wall"], out[which + "_cpu"] = time.perf_counter() - t0, time.process_time() - p0
                    out[which + "_n"], out[which] = asked[0], slid
            finally:
                anatomy_module.bone_clearance = real
            out["diff"] = abs(float((out["near"][:3, 3] - out["full"][:3, 3]) @ T[:3, 1]))
            rows.append(out)
            print(f"{c['id']:48s} push {k}: {c0 - now:5.2f} mm short; bracketed {out['near_wall'] * 1e3:6.1f} ms "
                  f"({out['near_n']} clearances), whole reach {out['full_wall'] * 1e3:6.1f} ms ({out['full_n']}); "
                  f"slides {out['diff']:.4f} mm apart", flush=True)
    return rows


if __name__ == "__main__":
    sys.exit(main())
