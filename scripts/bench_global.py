"""How often the global search (no rough pose) finds the knee on a case set's views, and its time: the rough
registration alone (:func:`knee.models.prior.register_roughly` without ``T_init``) on every view, its match
compared with the true femur's pose (found: within 30 deg, and 40 mm at the knee's centre; the match from
the truth itself lies 4-13 deg and 7-18 mm off with the skin mismatch). ``knee compare CASE_SET
--no-initial-pose`` runs the methods so; this measures the search itself.

    .venv/bin/python scripts/bench_global.py CASE_SET [--only ID,...]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case_set", help="a case set folder (scripts/build_case_set.py)")
    ap.add_argument("--only", help="only the cases whose id contains one of these (comma list)")
    args = ap.parse_args()

    import numpy as np

    from knee.app.experiments.case_set import case_points_cam, iter_cases
    from knee.foundations.conventions import invert_poses
    from knee.models.fem.methods import skin_model
    from knee.models.fem.scene import build_knee_model
    from knee.models.prior import placements_apart, register_roughly

    only = [o.strip() for o in (args.only or "").split(",") if o.strip()]
    found, times = 0, []
    for c, (anatomy, prior, T_ct_model), i, n in iter_cases(args.case_set,
                                                            (lambda c: any(o in c["id"] for o in only)) if only else None):
        skin = skin_model(build_knee_model(anatomy, prior=prior), prior)
        pts = case_points_cam(args.case_set, c)
        t0 = time.process_time()
        r = register_roughly(skin, pts)
        times.append(time.process_time() - t0)
        turned, moved = placements_apart(skin, r.T_model_world, invert_poses(np.asarray(c["T_camera_femur_ct"]) @ T_ct_model))
        ok = turned < 30.0 and moved < 40.0
        found += ok
        print(f"[{i + 1}/{n}] {c['id']:<48} {'found' if ok else 'MISSED':<7} {100 * r.inliers:5.1f} % on the skin, "
              f"{turned:6.1f} deg, {moved:6.1f} mm off, {times[-1]:.1f} s CPU", flush=True)
    print(f"found the knee in {found} of {len(times)} views; CPU time per view median {statistics.median(times):.1f} s "
          f"(range {min(times):.1f}-{max(times):.1f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
