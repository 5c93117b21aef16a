"""The association model with the kinematic prior on a real leg: the Visible Human Male's right knee
(``../shared/data/visible-human-male``, README "Real data"), posed at 30, 60 and 90 deg (issue "the FEM
and the prior on a subject's own imaging", section 3).

That knee has no measured motion, so no fitted prior: the prior here is a template, the bundled
`volunteer` parameter set scaled to this knee's femoral width (its link endpoints and lengths; its PF group
dropped), with every TF link endpoint then moved 1-2 mm (seed 3), and the truth is the unperturbed
template's motion, anchored at the scanned pose (the template's motion from its pose at the scanned
flexion carries this knee's tibia). The truth skin is posed with the bones by another model of the tissue than the
methods' (the tetrahedral tissue around the knee's bones, :mod:`knee.app.experiments.subject_cases`), seen
by an oblique camera aimed at the joint line, 350 mm away; the methods get the points in the camera's frame and a rough pose
15 deg and 25 mm off.

    .venv/bin/python scripts/real_knee_cases.py [--data ../shared/data] [--out real_knee_cases.csv]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    ap.add_argument("--out", default=None)
    ap.add_argument("--methods", default="links,kinematics,init")
    ap.add_argument("--truth-motion", choices=("template", "lenhart2015"), default="template",
                    help="the truth's motion: the template mechanism's (30/60/90 deg), or the lenhart2015 knee's "
                         "measured dynamic-MRI motion transferred as joint coordinates (20/30/45 deg)")
    args = ap.parse_args()
    from knee.app.console import new_files
    from knee.foundations.errors import KneeError, KneeInputError
    from knee.models.fem.methods import METHODS

    try:
        methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
        unknown = [m for m in methods if m not in METHODS]
        if unknown or not methods:
            raise KneeInputError(f"--methods must be a comma list of {', '.join(METHODS)}, got {args.methods!r}")
        new_files(args.out)
        return run(args, methods)
    except KneeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def run(args, methods) -> int:
    from knee.app.experiments.case_set import template_prior
    from knee.app.experiments.subject_cases import compare_subject
    from knee.fitting.optimize import perturb_endpoints
    from knee.fitting.reference_data import visible_human_knee
    from knee.models.fem.anatomy import anatomy_in_femur_frame, clip_anatomy, default_collaterals
    from knee.models.fem.scene import build_knee_model
    from knee.models.mechanism import Mechanism

    t0 = time.perf_counter()
    vh = visible_human_knee(args.data)
    anatomy = clip_anatomy(anatomy_in_femur_frame(vh.femur, vh.tibia, vh.skin, vh.frames["femur"], vh.frames["tibia"],
                                                  name=vh.name))
    mcl, lcl = default_collaterals(anatomy)
    anatomy = dataclasses.replace(anatomy, mcl=mcl, lcl=lcl)
    t_read = time.perf_counter() - t0
    template, scale = template_prior(anatomy)
    truth = Mechanism(template)
    prior = Mechanism(perturb_endpoints(template, 1.0, 2.0, seed=3))
    t1 = time.perf_counter()
    build_knee_model(anatomy, prior=prior)
    t_build = time.perf_counter() - t1
    print(f"Visible Human knee: read and clipped in {t_read:.1f} s; femoral width {anatomy.width:.1f} mm; scanned at "
          f"{math.degrees(anatomy.scan_tf[0]):.1f} deg flexion; model built in {t_build:.2f} s; template scale "
          f"{scale:.3f}", file=sys.stderr, flush=True)
    # the truth's motion anchored at the scan (the template is another knee: its own pose at the scanned
    # flexion differs from this knee's; its motion from there is what poses this knee)
    from knee.foundations.conventions import invert_poses, joint_to_pose, pose_to_joint

    if args.truth_motion == "template":
        flexions = np.radians([30.0, 60.0, 90.0])
        T = joint_to_pose(truth.motion_at(flexions)[0])
        T_scan = joint_to_pose(truth.motion_at(np.array([anatomy.scan_tf[0]]))[0][0])
    else:
        # a measured motion, not a mechanism's: the lenhart2015 knee's joint coordinates (its anatomical
        # frames), transferred as the case set does (flexion as measured; the other coordinates as this
        # knee's own at its scan plus the measured knee's change from the start of its arc; then the tibia
        # slid along its axis to the bones' clearance at the scan)
        from knee.app.experiments.case_set import measured_poses

        T, T_scan = measured_poses(args.data, anatomy, [20.0, 30.0, 45.0]), None
    if T_scan is not None:
        tf = pose_to_joint(T @ invert_poses(T_scan) @ anatomy.tibia_pose)
    else:
        tf = pose_to_joint(T)
    rows = compare_subject(anatomy, prior, tf, methods, azimuths=(35.0,), seed=3,
                           progress=lambda i, n, t: print(f"[{i}/{n}] {t}", file=sys.stderr, flush=True))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("| flexion | method | estimate (deg) | femur footprints | tibia footprints | femur epiphysis | tibia epiphysis "
          "| wall (s) | notes |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---|")
    for r in rows:
        if r.failed:
            print(f"| {r.flexion_true_deg:.0f} | {r.method} | failed: {r.failed} | | | | | | |")
            continue
        print(f"| {r.flexion_true_deg:.0f} | {r.method} | {r.flexion_estimated_deg:.1f} | {r.femur_footprints_mm:.2f} | "
              f"{r.tibia_footprints_mm:.2f} | {r.femur_epiphysis_mm:.2f} | {r.tibia_epiphysis_mm:.2f} | "
              f"{r.wall_seconds:.1f} | {r.notes[:120]} |")
    for m in methods:
        ok = [r for r in rows if r.method == m and not r.failed]
        if ok:
            print(f"\n{m}: median footprints {statistics.median(r.footprints_mm for r in ok):.2f} mm, median wall "
                  f"{statistics.median(r.wall_seconds for r in ok):.1f} s ({len(ok)} of "
                  f"{sum(r.method == m for r in rows)} cases)")
    print(f"model build {t_build:.2f} s; peak memory {peak:.0f} MB")
    if args.out:
        from knee.foundations.files import write_records

        write_records(args.out, (dataclasses.asdict(r) for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
