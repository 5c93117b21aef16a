"""Flexion from depth and the kinematics-alone estimate (method iv) on the standard cases (issue "kinematic
priors for the FEM", section 3).

Truth: the bundled `volunteer` (phantom skin posed at each flexion, a virtual 1280x720 camera, depth noise
on). Prior: `volunteer` with every TF link endpoint moved 1-2 mm (seed 3), i.e. realistically wrong. For each
flexion 30:120:15 and three camera placements (oblique 35 deg, frontal 0 deg, lateral 70 deg; 350 mm, 30 deg
elevation): the flexion estimate's error, the fit quality, the wall time and the target point errors of the
mechanism alone at the estimated angle (epiphysis and ACL/PCL footprints, per bone).

    .venv/bin/python scripts/prior_cases.py [--out prior_cases.csv] [--flexions 30:120:15] [--azimuths 35,0,70]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time

import numpy as np


def _cases(flexions, azimuths) -> list[dict]:
    """One row per camera placement and true flexion."""
    from knee.app.experiments.cases import phantom_targets
    from knee.fitting.optimize import perturb_endpoints
    from knee.foundations.conventions import joint_to_pose
    from knee.foundations.pointclouds import backproject
    from knee.models.evaluation import pose_errors
    from knee.models.fem.depth import DepthNoise, default_camera, render_depth
    from knee.models.mechanism import Mechanism
    from knee.models.mechanism.params import load_model
    from knee.models.phantom import build_phantom
    from knee.models.prior import SkinModel, estimate_flexion, kinematic_estimate

    truth = Mechanism.from_name("volunteer")
    prior = Mechanism(perturb_endpoints(load_model("volunteer"), 1.0, 2.0, seed=3))
    ph_t, ph_p = build_phantom(truth.params), build_phantom(prior.params)
    tg = phantom_targets(truth, ph_t)
    skin = SkinModel(prior, ph_p)  # built once: its parts are meshed and sampled once, moved per candidate
    rng = np.random.default_rng(0)
    rows = []
    for az in azimuths:
        cam = default_camera(azimuth_deg=az)
        for deg in flexions:
            tf, pf, _ = truth.solve(math.radians(deg))
            truth_skin = ph_t.skin(joint_to_pose(tf), joint_to_pose(pf))
            pts = backproject(DepthNoise().apply(render_depth(truth_skin.vertices, truth_skin.faces, cam), rng), cam.K,
                              cam.T_world_cam)
            t = time.perf_counter()
            est = estimate_flexion(skin, pts)
            wall = time.perf_counter() - t
            Tf, Tt = kinematic_estimate(prior, est)
            e = pose_errors(tg, np.eye(4), joint_to_pose(tf), Tf, Tt)
            rows.append({"camera_azimuth_deg": az, "flexion_true_deg": deg,
                         "flexion_est_deg": math.degrees(est.flexion), "error_deg": math.degrees(est.flexion) - deg,
                         "rms_mm": est.rms, "seconds": wall, "at_range_end": est.at_range_end,
                         "shank_points": est.shank_points, "warning": "; ".join(est.warnings),
                         "femur_footprints_mm": e.femur.footprints.mean, "tibia_footprints_mm": e.tibia.footprints.mean,
                         "femur_epiphysis_mm": e.femur.epiphysis.mean, "tibia_epiphysis_mm": e.tibia.epiphysis.mean})
            r = rows[-1]
            print(f"camera {az:4.0f} deg, flexion {deg:5.1f}: estimate {r['flexion_est_deg']:6.2f} ({r['error_deg']:+.2f}) "
                  f"in {wall:.1f} s; footprints femur {r['femur_footprints_mm']:.2f} tibia {r['tibia_footprints_mm']:.2f} mm"
                  + (f"  [{r['warning'][:60]}...]" if r["warning"] else ""), flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=None)
    ap.add_argument("--flexions", default="30:120:15", help="true flexions, deg: FROM:TO:STEP or a comma list")
    ap.add_argument("--azimuths", default="35,0,70",
                    help="camera placements: azimuths, deg, a comma list (35 oblique, 0 frontal, 70 lateral)")
    args = ap.parse_args()
    from knee.app.console import flexion_list, new_files
    from knee.foundations.errors import KneeError
    from knee.foundations.files import write_records

    try:
        new_files(args.out)
        flexions = flexion_list(args.flexions)
        azimuths = [float(a) for a in args.azimuths.split(",")]
        if not all(math.isfinite(a) and -180.0 <= a <= 180.0 for a in azimuths):
            raise ValueError
    except KneeError as e:
        print(f"error: {str(e).replace('--flexion ', '--flexions ')}", file=sys.stderr)
        return 2
    except ValueError:
        print(f"error: --azimuths must be a comma list of degrees within -180-180, got {args.azimuths!r}",
              file=sys.stderr)
        return 2
    try:
        rows = _cases(flexions, azimuths)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    ok = [r for r in rows if not r["at_range_end"]]  # the truth beyond the prior's range: no measurement
    if not ok:
        print(f"error: none of the {len(rows)} cases lies within the prior's range; nothing to summarise",
              file=sys.stderr)
        return 1
    print(f"\nin-range cases: {len(ok)} of {len(rows)}; |flexion error| median "
          f"{statistics.median(abs(r['error_deg']) for r in ok):.2f} deg, max {max(abs(r['error_deg']) for r in ok):.2f} deg, "
          f"within 2 deg: {sum(abs(r['error_deg']) <= 2 for r in ok)}")
    fp = [0.5 * (r["femur_footprints_mm"] + r["tibia_footprints_mm"]) for r in ok]
    print(f"method (iv) kinematics alone: median footprint error {statistics.median(fp):.2f} mm "
          f"(femur {statistics.median(r['femur_footprints_mm'] for r in ok):.2f}, tibia "
          f"{statistics.median(r['tibia_footprints_mm'] for r in ok):.2f}); median wall time "
          f"{statistics.median(r['seconds'] for r in rows):.1f} s")
    if args.out:
        write_records(args.out, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
