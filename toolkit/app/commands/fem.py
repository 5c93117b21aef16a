"""``knee fem MODEL``: the association model deformed toward a depth map by the paper's method, on the
standard case or on a measured point cloud or depth image, with an optional recording."""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path


from knee.app.commands import fem_subject
from knee.app.console import ProgressBar, check_max_steps, check_new, error, say
from knee.app.experiments.cases import case_points, case_truth, run_standard_case
from knee.app.views.fem import FemRecorder
from knee.foundations.conventions import read_pose_file
from knee.foundations.errors import EXIT_NUMERICAL, DivergenceError, KneeInputError
from knee.foundations.pointclouds import backproject, principal_point_note
from knee.models.fem.depth import DepthNoise, camera_from_spec
from knee.models.fem.methods import bone_phase_note
from knee.models.fem.scene import FemSettings, build_association_model
from knee.models.mechanism import Mechanism
from knee.models.mechanism.params import bundled_models


def measured_points(args):
    """A measured point cloud (P, 3) from --cloud or --depth/--intrinsics (None when neither is given)."""
    if args.cloud and args.depth:
        raise KneeInputError("give either --cloud or --depth, not both")
    pose = None
    if args.pose:
        pose = read_pose_file(args.pose, "--pose")
    if args.keep_flying and not (args.depth or args.cloud):
        raise KneeInputError("--keep-flying goes with --depth or --cloud (the measured points' flying pixels)")
    if args.cloud:
        pts = fem_subject.measured_cloud(args)[0]
        return pts if pose is None else pts @ pose[:3, :3].T + pose[:3, 3]
    if args.depth:
        depth, K = fem_subject.depth_input(args)
        note = principal_point_note(K, depth.shape)
        if note:
            print(f"warning: {note} (used as given)")
        return fem_subject.checked_span(backproject(depth, K, pose, args.depth_scale, drop_mixed=not args.keep_flying),
                                        "--depth-scale", args.depth_scale)
    if args.intrinsics or args.pose:
        raise KneeInputError("--intrinsics and --pose go with --depth or --cloud")
    return None


#: The options of a parameter set's phantom (its standard case), with their defaults; a subject's run
#: refuses them rather than ignore them.
PHANTOM_OPTIONS = {"flexion": 90.0, "truth": None, "camera": "oblique", "no_noise": False, "seed": 0, "pose": None,
                   "max_steps": 400, "bone_stall": 0.5, "rrd": None}


def run(args) -> int:
    if Path(args.model).is_dir():  # a subject folder: its own knee, with a fitted prior
        for flag in PHANTOM_OPTIONS:
            if getattr(args, flag, None) not in (None, False):
                raise KneeInputError(f"--{flag.replace('_', '-')} goes with a parameter set's phantom, not a subject "
                                     "folder")
        return fem_subject.run(args)
    for flag, default in PHANTOM_OPTIONS.items():
        if getattr(args, flag, None) is None:
            setattr(args, flag, default)
    for flag in ("prior", "method", "initial_pose", "out"):
        if getattr(args, flag):
            if not Path(args.model).exists() and args.model not in bundled_models():
                raise KneeInputError(f"{args.model}: no such subject folder (--{flag.replace('_', '-')} goes with a "
                                     "subject folder)")
            raise KneeInputError(f"--{flag.replace('_', '-')} goes with a subject folder, not a parameter set")
    rrd = Path(args.rrd) if args.rrd else None
    inputs = tuple(Path(v) for v in (args.model, args.truth, args.cloud, args.depth, args.pose)
                   if v and Path(v).is_file())
    check_new(rrd, args.force, inputs=inputs, flag="--rrd")
    if not (math.isfinite(args.flexion) and 0.0 <= args.flexion <= 150.0):
        raise KneeInputError(f"--flexion must be 0-150 deg, got {args.flexion}")
    check_max_steps(args.max_steps)
    if not (math.isfinite(args.bone_stall) and args.bone_stall >= 0.0):
        raise KneeInputError(f"--bone-stall must be a non-negative angle in degrees, got {args.bone_stall}")
    cam = camera_from_spec(args.camera)
    measured = measured_points(args)
    mech = Mechanism.from_name(args.model)
    truth = Mechanism.from_name(args.truth) if args.truth else mech
    if measured is None and not truth.in_range(math.radians(args.flexion)):
        lo, hi = (math.degrees(v) for v in truth.assembly_range)
        raise KneeInputError(f"--flexion {args.flexion:g} deg is outside the assembly range of "
                             f"{truth.params.name} ({lo:.1f} to {hi:.1f} deg)")
    say(f"knee fem: building the association model of {mech.params.name} ...")
    t0 = time.perf_counter()
    model = build_association_model(mech, fem_subject.model_settings(args) or FemSettings())
    say(f"  grid {tuple(int(v) for v in model.grid.shape)} ({len(model.grid.cells)} cells, {model.grid.n_nodes} nodes), "
        f"bones {len(model.femur.el.cells)} + {len(model.tibia.el.cells)} tetrahedra; {time.perf_counter() - t0:.1f} s")
    truth_tf, truth_info = None, None
    if measured is None:
        pts, truth_tf = case_points(truth, args.flexion, cam, DepthNoise() if not args.no_noise else None,
                                    args.seed, model.settings)
        truth_info = case_truth(model, mech, truth, truth_tf)
        say(f"  case: {truth.params.name} at {args.flexion:g} deg seen by the {args.camera} camera, {len(pts)} depth points "
            f"(the truth's skin: the phantom's envelope, made by the same code as the model's skin; not an independent "
            f"truth: knee demo's and the case sets' are)")
    else:
        pts = measured
        say(f"  measured point cloud: {len(pts)} points (no truth: no target point errors)")
    # the recording is written beside its place and moved there when complete (a diverged run keeps its
    # partial recording under a name of its own, for diagnosis; the previous recording is untouched)
    partial = rrd.with_name(f".{rrd.name}.partial-{os.getpid()}") if rrd is not None else None
    recorder = FemRecorder(partial, model, every=max(2, args.max_steps // 80), truth=truth_info) if rrd else None
    bar = ProgressBar()

    def on_step(k, phase, model_, surf, bone):
        if recorder is not None:
            recorder(k, phase, model_, surf, bone)
        if not args.quiet:
            bar((k + 1) / args.max_steps, f"step {k + 1} [{phase} forces]")

    try:
        r = run_standard_case(mech, args.flexion, cam, model=model, seed=args.seed, bone_stall_deg=args.bone_stall,
                              max_steps=args.max_steps, points=pts, truth_tf=truth_tf, on_step=on_step)
    except DivergenceError as e:
        if not args.quiet:
            print(file=sys.stderr)
        if recorder is not None:
            recorder.finish(message=str(e))
            diverged = rrd.with_name(rrd.stem + ".diverged.rrd")
            os.replace(partial, diverged)
            say(f"partial recording of the diverged run (steps 0-{recorder.last_step}): {diverged}")
        return error(str(e), EXIT_NUMERICAL)
    except BaseException:
        if partial is not None:
            partial.unlink(missing_ok=True)
        raise
    rec = r.reconstruction
    if not args.quiet:
        bar(1.0, f"{rec.steps} steps")
    if recorder is not None:
        recorder.finish(r, f"{rec.steps} steps, {'converged' if rec.converged else 'not converged'}")
        os.replace(partial, rrd)
    print(f"{mech.params.name}: {rec.steps} steps ({rec.steps_bone_phase} with bone forces) in {rec.wall_seconds:.1f} s "
          f"({rec.steps / rec.wall_seconds:.1f} steps/s), {'converged' if rec.converged else 'NOT converged'}; "
          f"registration ICP fitness {rec.icp_fitness:.2f}")
    if rec.bone_phase_end:
        print(bone_phase_note(rec))
    if r.errors is not None:
        print(f"flexion: true {r.flexion_true_deg:.1f} deg, FEM {r.flexion_estimated_deg:.1f} deg")
        print("target point errors, mean ± sd (mm):")
        for bone in ("femur", "tibia"):
            e = r.errors.bone(bone)
            print(f"  {bone:5s}  ACL/PCL footprints {e.footprints.mean:6.2f} ± {e.footprints.sd:5.2f}   "
                  f"epiphysis {e.epiphysis.mean:6.2f} ± {e.epiphysis.sd:5.2f}")
    else:
        print(f"flexion of the FEM bones: {r.flexion_estimated_deg:.1f} deg")
    if rrd is not None:
        print(f"recording: {rrd}  (open with: rerun {rrd})")
    return 0
