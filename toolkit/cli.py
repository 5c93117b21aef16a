"""The ``knee`` command line.

    knee models
    knee sweep MODEL [--from 0] [--to 120] [--step 1] [--out motion.csv] [--rrd sweep.rrd] [--force]
    knee demo [--out DIR] [--flexion 60] [--kinematics-only]
    knee synth-subject OUT_DIR [--model volunteer] [--seed N] [--frames 60]
    knee fit SUBJECT_DIR --out OUT_DIR [--seed N] [--quick] [--no-global] [--no-recording] [--force]
    knee gait MODEL [--trial CSV] [--mass 72] [--height 1.75] [--out DIR] [--rrd FILE] [--force]
    knee contact MODEL [--load 700] [--out DIR] [--force]
    knee osteotomy MODEL --bone tibia|femur --angle 8 [--plane px,py,pz,nx,ny,nz] [--hinge hx,hy,hz,ax,ay,az]
                   [--release mcl] [--trial CSV] [--mass 72] [--height 1.75] [--out DIR] [--force]
    knee compare MODEL [--truth MODEL] [--flexion 30:120:15] [--cameras oblique,frontal,lateral] [--out DIR]
    knee fem MODEL [--flexion 90] [--truth MODEL] [--camera oblique|frontal|lateral|AZ,EL,DIST] [--rrd FILE]
             [--cloud FILE | --depth FILE --intrinsics fx,fy,cx,cy [--depth-scale 1]] [--pose FILE]

Angles in degrees, lengths in mm. Bad input gives a one-line ``knee: error: ...`` and exit code 2; no
existing file is overwritten unless ``--force`` is given.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from toolkit.errors import KneeInputError

EXIT_BAD_INPUT = 2


def _err(msg: str) -> int:
    print(f"knee: error: {msg}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _check_new(path: Path | None, force: bool) -> None:
    if path is None:
        return
    if path.exists() and not force:
        raise KneeInputError(f"{path} exists; not overwritten (use --force to replace it)")
    if not path.parent.exists():
        raise KneeInputError(f"directory {path.parent} does not exist")


def _angles(a_from: float, a_to: float, step: float) -> np.ndarray:
    for name, v in (("--from", a_from), ("--to", a_to), ("--step", step)):
        if not math.isfinite(v):
            raise KneeInputError(f"{name} must be a finite number of degrees, got {v}")
    if step <= 0:
        raise KneeInputError(f"--step must be positive, got {step}")
    if step > 10:
        raise KneeInputError(f"--step must be at most 10 deg for continuation to follow one branch, got {step}")
    n = int(math.floor(abs(a_to - a_from) / step + 1e-9)) + 1
    if n > 1_000_000:
        raise KneeInputError(f"--from/--to/--step give {n} angles; at most 1000000")
    sign = 1.0 if a_to >= a_from else -1.0
    return a_from + sign * step * np.arange(n)


def cmd_models(args) -> int:
    from models.mechanism.params import bundled_models, load_model

    for name, desc in bundled_models().items():
        p = load_model(name)
        kinds = "/".join(sorted(set(p.kinds)))
        print(f"{name:22s} {'TF+PF' if p.has_pf else 'TF   '}  {kinds:22s} {desc}")
    return 0


def run_sweep(model: str, angles_deg: np.ndarray, out: Path | None, rrd: Path | None, quiet=False):
    """Solve, write CSV and recording; returns (mechanism, result, seconds)."""
    from models.mechanism import Mechanism
    from toolkit.motion_io import write_sweep_csv

    mech = Mechanism.from_name(model)
    t0 = time.perf_counter()
    res = mech.sweep(np.radians(angles_deg))
    dt = time.perf_counter() - t0
    if out is not None:
        write_sweep_csv(out, res.tf, res.pf, res.residual, res.condition)
    elif not quiet:
        from toolkit.motion_io import SWEEP_HEADER, sweep_table

        print(",".join(SWEEP_HEADER))
        for row in sweep_table(res.tf, res.pf, res.residual, res.condition):
            print(",".join("" if not math.isfinite(v) else f"{v:.10g}" for v in row))
    if rrd is not None and res.flexion.size:
        from models.phantom import build_phantom
        from models.views import log_sweep, sweep_blueprint
        from toolkit import recording

        rec = recording.new_recording()
        recording.save(rec, rrd, sweep_blueprint())
        log_sweep(rec, mech, res, build_phantom(mech.params))
        rec.flush()
    return mech, res, dt


def _summary(mech, res, dt) -> str:
    lo, hi = (math.degrees(v) for v in mech.assembly_range)
    backend = "compiled" if mech.compiled else "CasADi virtual machine"
    lines = [f"model {mech.params.name}: assembles from {lo:.2f} to {hi:.2f} deg flexion",
             f"solved {res.flexion.size} of {res.requested.size} angles in {dt * 1e3:.2f} ms ({backend})"
             + (f"; max closure residual {res.residual.max():.1e} mm" if res.residual.size else "")]
    if res.flexion.size:
        ns = np.nonzero(res.near_singular)[0]
        if ns.size:
            lines.append(f"near-singular Jacobian (condition > 1e4) at {ns.size} angles, first at "
                         f"{math.degrees(res.flexion[ns[0]]):.2f} deg")
    return "\n".join(lines)


def cmd_sweep(args) -> int:
    out = Path(args.out) if args.out else None
    rrd = Path(args.rrd) if args.rrd else None
    _check_new(out, args.force)
    _check_new(rrd, args.force)
    angles = _angles(args.a_from, args.a_to, args.step)
    mech, res, dt = run_sweep(args.model, angles, out, rrd)
    print(_summary(mech, res, dt), file=sys.stderr)
    if out is not None:
        print(f"wrote {res.flexion.size} rows to {out}", file=sys.stderr)
    if rrd is not None and res.flexion.size:
        print(f"recording: {rrd}  (open with: rerun {rrd})", file=sys.stderr)
    if not res.complete:
        return _err(f"sweep stopped: {res.message}; {res.flexion.size} rows written")
    return 0


def cmd_demo(args) -> int:
    if not (math.isfinite(args.flexion) and 15.0 <= args.flexion <= 110.0):
        raise KneeInputError(f"--flexion must be 15-110 deg (within the prior's range), got {args.flexion}")
    base = Path(args.out)
    out_dir = base
    k = 2
    while out_dir.exists():  # never overwrite an earlier demo
        out_dir = base.with_name(f"{base.name}-{k}")
        k += 1
    out_dir.mkdir(parents=True)
    fem = None
    if not args.kinematics_only:
        # the FEM comparison (two worker processes) starts first and runs while the sweep is solved and
        # recorded: the workers' start-up overlaps it
        from concurrent.futures import ThreadPoolExecutor

        from models.demo import run_demo_comparison

        print(f"knee demo: virtual depth map at {args.flexion:g} deg; the association FEM with the kinematic prior "
              f"and with the paper's forcing, two processes (started) ...", file=sys.stderr, flush=True)
        runner = ThreadPoolExecutor(max_workers=1)
        fem = runner.submit(run_demo_comparison, out_dir, args.flexion,
                            log=lambda t: print(t, file=sys.stderr, flush=True))
        runner.shutdown(wait=False)
    from models.mechanism import Mechanism

    mech = Mechanism.from_name("volunteer")
    hi = math.floor(math.degrees(mech.assembly_range[1]))
    angles = np.arange(0.0, hi + 1.0, 1.0)
    csv_path, rrd_path = out_dir / "volunteer-sweep.csv", out_dir / "volunteer-sweep.rrd"
    print(f"knee demo: sweeping the bundled 'volunteer' knee over 0..{hi} deg ...", file=sys.stderr)
    mech, res, dt = run_sweep("volunteer", angles, csv_path, rrd_path)
    print(_summary(mech, res, dt))
    i = np.searchsorted(res.flexion, math.radians(90.0))
    if i < res.flexion.size:
        tf, pf = res.tf[i], res.pf[i]
        print(f"at {math.degrees(tf[0]):.0f} deg: TF adduction {math.degrees(tf[1]):+.2f} deg, internal rotation "
              f"{math.degrees(tf[2]):+.2f} deg, translation ({tf[3]:+.1f}, {tf[4]:+.1f}, {tf[5]:+.1f}) mm; "
              f"PF flexion {math.degrees(pf[0]):.1f} deg")
    print(f"motion table: {csv_path}")
    print(f"recording:    {rrd_path}")
    print(f"open it with: rerun {rrd_path}")
    if not res.complete:
        if fem is not None and not fem.cancel():
            fem.exception()  # the comparison already runs: let it finish (its files) before reporting
        return _err(res.message)
    if fem is None:
        return 0
    from models.fem.compare_report import METHOD_LABELS

    out = fem.result()
    print(f"\nFEM at {args.flexion:g} deg flexion (truth: volunteer; prior: volunteer with TF endpoints moved 1-2 mm; "
          f"oblique camera, depth noise):")
    print(f"{'method':44s} {'flexion':>8s} {'footprints':>11s} {'epiphysis':>10s} {'steps':>6s} {'wall (s)':>9s}")
    for r in out["rows"]:
        fp = 0.5 * (r["femur_footprints_mm"] + r["tibia_footprints_mm"])
        ep = 0.5 * (r["femur_epiphysis_mm"] + r["tibia_epiphysis_mm"])
        print(f"{METHOD_LABELS[r['method']]:44s} {r['flexion_estimated_deg']:7.1f}° {fp:8.2f} mm {ep:7.2f} mm "
              f"{r['steps']:6d} {r['wall_seconds']:9.1f}")
        if math.isfinite(r.get("tibia_correction_deg", float("nan"))):
            print(f"  the tibia's pose corrected from the shank's depth points: {r['tibia_correction_deg']:.1f} deg, "
                  f"{r['tibia_correction_mm']:.1f} mm off the prior's path (its axial rotation kept)")
        if r["notes"]:
            print(f"  note: {r['notes']}")
    print(f"comparison: {out_dir / 'compare.md'}, {out_dir / 'compare.png'}")
    print(f"open it with: rerun {out_dir / 'compare.rrd'}")
    print(f"(the FEM part took {out['seconds']:.0f} s)", file=sys.stderr)
    return 0


class ProgressBar:
    """A one-line progress bar on standard error: ``[######....]  45%  text``."""

    def __init__(self, width: int = 30, stream=None):
        self.width = width
        self.stream = stream or sys.stderr
        self.last = ""

    def __call__(self, fraction: float, text: str) -> None:
        f = min(max(float(fraction), 0.0), 1.0)
        k = int(round(f * self.width))
        line = f"[{'#' * k}{'.' * (self.width - k)}] {100 * f:3.0f}%  {text}"
        pad = max(len(self.last) - len(line), 0)
        self.stream.write("\r" + line + " " * pad)
        if f >= 1.0:
            self.stream.write("\n")
        self.stream.flush()
        self.last = line


def cmd_synth_subject(args) -> int:
    from fitting.synthetic import make_subject

    out = Path(args.out_dir)
    print(f"knee synth-subject: writing a synthetic subject from '{args.model}' (seed {args.seed}) ...",
          file=sys.stderr)
    make_subject(out, model=args.model, seed=args.seed, frames=args.frames)
    print(f"subject folder: {out}")
    print(f"fit it with:    knee fit {out} --out {out}-fit")
    return 0


def cmd_fit(args) -> int:
    from fitting.pipeline import run_fit

    bar = ProgressBar() if not args.quiet else None
    o = run_fit(args.subject_dir, args.out, seed=args.seed, global_stage=not args.no_global, progress=bar,
                force=args.force, recording=not args.no_recording, effort="quick" if args.quick else "full")
    fe = o.fitted_errors
    print(f"subject {o.subject.name}: fitted on {len(o.motion.tf)} frames in {o.seconds['fit']:.1f} s "
          f"(total {o.seconds['total']:.1f} s)")
    names = ("adduction", "int.rot", "anterior", "proximal", "lateral")
    print("TF MAE  " + "  ".join(f"{n} {v:.2f}" for n, v in zip(names, fe["tf"]["mae"][1:])) + "  (deg, mm)")
    if "pf" in fe:
        pn = ("flexion", "tilt", "rotation", "anterior", "proximal", "lateral")
        print("PF MAE  " + "  ".join(f"{n} {v:.2f}" for n, v in zip(pn, fe["pf"]["mae"])) + "  (deg, mm)")
    for w in o.warnings:
        print(f"warning: {w}", file=sys.stderr)
    for k, f in o.files.items():
        print(f"{k:15s} {f}")
    if "recording" in o.files:
        print(f"open the recording with: rerun {o.files['recording']}")
    return 0


def _out_dir(path: str, force: bool) -> Path:
    """Check an output folder (created later, once the inputs have been checked)."""
    d = Path(path)
    if d.exists() and (not d.is_dir() or (any(d.iterdir()) and not force)):
        raise KneeInputError(f"output folder {d} exists and is not empty; not overwritten (use --force)")
    return d


def write_gait_table(path: Path, res) -> None:
    """One row per frame: time, knee flexion, knee load on the tibia, member forces, contact pressures."""
    import csv

    st = res.statics
    head = ["time_s", "knee_flexion_deg", "load_force_anterior_N", "load_force_proximal_N", "load_force_lateral_N",
            "load_moment_anterior_Nmm", "load_moment_proximal_Nmm", "load_moment_lateral_Nmm"]
    head += [f"{n}_force_N" for n in st.names]
    cols = [res.trial.time, np.degrees(res.trial.knee), *res.knee_force.T, *res.knee_moment.T, *st.forces.T]
    for name, e in res.contact.items():
        head += [f"{name}_contact_N", f"{name}_hertz_area_mm2", f"{name}_hertz_peak_MPa"]
        cols += [e["force"], e["hertz"].area, e["hertz"].peak]
        if "foundation_peak" in e:
            head += [f"{name}_foundation_area_mm2", f"{name}_foundation_peak_MPa"]
            cols += [e["foundation_area"], e["foundation_peak"]]
    head.append("flags")
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for k, row in enumerate(np.column_stack(cols)):
            w.writerow([f"{v:.6g}" for v in row] + ["; ".join(st.flags[k])])


def cmd_gait(args) -> int:
    from models.clinical_views import gait_blueprint, log_gait, plot_gait
    from models.gait import Anthropometry, analyse_gait, normative_trial, read_gait_csv
    from models.mechanism import Mechanism
    from toolkit import recording

    out = _out_dir(args.out, args.force)
    rrd = Path(args.rrd) if args.rrd else out / "gait.rrd"
    if args.rrd:
        _check_new(rrd, args.force)
    anthro = Anthropometry(args.mass, args.height)
    trial = read_gait_csv(args.trial, args.mass) if args.trial else normative_trial(args.mass)
    mech = Mechanism.from_name(args.model)
    res = analyse_gait(mech, trial, anthro)
    out.mkdir(parents=True, exist_ok=True)
    write_gait_table(out / "gait.csv", res)
    plot_gait(res, out / "gait.png", f"{mech.params.name}: {trial.source}")
    rec = recording.new_recording()
    recording.save(rec, rrd, gait_blueprint())
    log_gait(rec, mech, res)
    rec.flush()
    print(f"gait of {mech.params.name} ({trial.source}), {trial.time.size} frames, {args.mass:g} kg, "
          f"{args.height:g} m: analysed in {res.seconds:.2f} s")
    for name, e in res.contact.items():
        k = int(np.argmax(e["force"]))
        print(f"contact {name}: peak force {e['force'][k]:.0f} N at t = {trial.time[k]:.3f} s; Hertz peak pressure "
              f"{e['hertz'].peak.max():.2f} MPa, area {e['hertz'].area[k]:.0f} mm2"
              + (f"; elastic foundation peak {e['foundation_peak'].max():.2f} MPa" if "foundation_peak" in e else ""))
    nflag = sum(1 for f in res.statics.flags if f)
    if nflag:
        print(f"flagged frames: {nflag} of {trial.time.size} (a member would have to push or pull the wrong way; "
              f"see the flags column of {out / 'gait.csv'})")
    print(f"table: {out / 'gait.csv'}\nplot:  {out / 'gait.png'}\nrecording: {rrd}  (open with: rerun {rrd})")
    return 0


def cmd_contact(args) -> int:
    from models.clinical_views import contact_vs_flexion, plot_contact
    from models.mechanism import Mechanism

    if not (args.load > 0 and math.isfinite(args.load)):
        raise KneeInputError(f"--load must be a positive number of N, got {args.load}")
    out = _out_dir(args.out, args.force)
    mech = Mechanism.from_name(args.model)
    res = contact_vs_flexion(mech, args.load)
    out.mkdir(parents=True, exist_ok=True)
    plot_contact(res, out / "contact.png", f"{mech.params.name}: {args.load:g} N along the tibia")
    import csv

    with (out / "contact.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        names = list(res["contacts"])
        w.writerow(["flexion_deg"] + [f"{n}_{q}" for n in names for q in ("force_N", "hertz_area_mm2",
                                                                          "hertz_peak_MPa", "foundation_area_mm2",
                                                                          "foundation_peak_MPa")])
        for i, fl in enumerate(res["flexion_deg"]):
            row = [fl]
            for n in names:
                c = res["contacts"][n]
                row += [c["force"][i], c["hertz"].area[i], c["hertz"].peak[i], c["ef_area"][i], c["ef_peak"][i]]
            w.writerow([f"{v:.6g}" for v in row])
    print(f"contact of {mech.params.name} under {args.load:g} N: {out / 'contact.csv'}, {out / 'contact.png'}")
    return 0


def _six(text: str, what: str) -> tuple[np.ndarray, np.ndarray]:
    v = _numbers(text, 6, what, " (point x,y,z then direction x,y,z in mm)")
    return v[:3], v[3:]


def cmd_osteotomy(args) -> int:
    from models.gait import normative_trial, read_gait_csv
    from models.mechanism.params import load_model, save_toml
    from models.osteotomy import Cut, compare, default_cut, osteotomy, plot, report_markdown, write_recording
    from models.phantom import build_phantom

    params = load_model(args.model)
    if not math.isfinite(args.angle):
        raise KneeInputError(f"--angle must be a number of degrees, got {args.angle}")
    out = _out_dir(args.out, args.force)
    if args.plane is None or args.hinge is None:
        ph = build_phantom(params)
        base = default_cut(args.bone, ph.tibia if args.bone == "tibia" else ph.femur, args.angle)
    else:
        base = None
    pp, pn = _six(args.plane, "--plane") if args.plane else (base.plane_point, base.plane_normal)
    hp, ha = _six(args.hinge, "--hinge") if args.hinge else (base.hinge_point, base.hinge_axis)
    cut = Cut(args.bone, pp, pn, hp, ha, float(args.angle))
    res = osteotomy(params, cut, height=args.height, release=tuple(args.release or ()))
    trial = read_gait_csv(args.trial, args.mass) if args.trial else normative_trial(args.mass)
    cmp = compare(res, trial, height=args.height, mass=args.mass)
    md = report_markdown(cut, res, cmp)
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.md").write_text(md, encoding="utf-8")
    plot(cut, res, cmp, out / "osteotomy.png")
    write_recording(cut, res, out / "osteotomy.rrd")
    save_toml(res["params"], out / "after.toml", overwrite=True)
    ab, aa = res["align_before"], res["align_after"]
    print(f"{params.name}: {args.bone} osteotomy {args.angle:+g} deg; moved: {', '.join(res['moved']) or 'nothing'}")
    print(f"HKA deviation {ab.hka_deg:+.2f} -> {aa.hka_deg:+.2f} deg (+ varus); weight-bearing line "
          f"{ab.wbl_percent:.1f} -> {aa.wbl_percent:.1f} % of the plateau (target 62.5 %)")
    print(f"report: {out / 'report.md'}\nplot: {out / 'osteotomy.png'}\nparameters after: {out / 'after.toml'}\n"
          f"recording: {out / 'osteotomy.rrd'}  (open with: rerun {out / 'osteotomy.rrd'})")
    return 0


def _numbers(text: str, n: int, what: str, hint: str = "") -> np.ndarray:
    """``n`` finite comma-separated numbers, or a one-line error naming ``what``."""
    try:
        v = np.array([float(x) for x in str(text).split(",")])
    except ValueError:
        v = np.zeros(0)
    if v.size != n or not np.all(np.isfinite(v)):
        count = {3: "three", 4: "four", 6: "six"}.get(n, str(n))
        raise KneeInputError(f"{what} must be {count} comma-separated numbers{hint}, got {text!r}")
    return v


def _measured_points(args):
    """A measured point cloud from --cloud or --depth/--intrinsics (None when neither is given)."""
    from models.fem.depth import load_depth_image, load_point_cloud

    if args.cloud and args.depth:
        raise KneeInputError("give either --cloud or --depth, not both")
    pose = None
    if args.pose:
        try:
            pose = np.loadtxt(args.pose, dtype=float).reshape(4, 4)
        except (OSError, ValueError):
            raise KneeInputError(f"--pose {args.pose}: not a readable 4x4 matrix (16 numbers)") from None
    if args.cloud:
        pts = load_point_cloud(args.cloud)
        return pts if pose is None else pts @ pose[:3, :3].T + pose[:3, 3]
    if args.depth:
        if not args.intrinsics:
            raise KneeInputError("--depth needs --intrinsics fx,fy,cx,cy (pixels)")
        fx, fy, cx, cy = _numbers(args.intrinsics, 4, "--intrinsics")
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        if not (args.depth_scale > 0 and math.isfinite(args.depth_scale)):
            raise KneeInputError(f"--depth-scale must be a positive number, got {args.depth_scale}")
        return load_depth_image(args.depth, K, pose, args.depth_scale)
    if args.intrinsics or args.pose:
        raise KneeInputError("--intrinsics and --pose go with --depth or --cloud")
    return None


def cmd_fem(args) -> int:
    from models.fem.case import (FemDivergence, bone_phase_note, camera_from_spec, case_points, run_standard_case,
                                 truth_phantom, truth_targets)
    from models.fem.depth import DepthNoise
    from models.fem.scene import FemSettings, build_association_model
    from models.fem.views import FemRecorder
    from models.mechanism import Mechanism
    from toolkit.conventions import joint_to_pose

    rrd = Path(args.rrd) if args.rrd else None
    _check_new(rrd, args.force)
    if not (math.isfinite(args.flexion) and 0.0 <= args.flexion <= 150.0):
        raise KneeInputError(f"--flexion must be 0-150 deg, got {args.flexion}")
    if args.max_steps < 1:
        raise KneeInputError(f"--max-steps must be positive, got {args.max_steps}")
    if not (math.isfinite(args.bone_stall) and args.bone_stall >= 0.0):
        raise KneeInputError(f"--bone-stall must be a non-negative angle in degrees, got {args.bone_stall}")
    cam = camera_from_spec(args.camera)
    measured = _measured_points(args)
    mech = Mechanism.from_name(args.model)
    truth = Mechanism.from_name(args.truth) if args.truth else mech
    if measured is None and not truth.in_range(math.radians(args.flexion)):
        lo, hi = (math.degrees(v) for v in truth.assembly_range)
        raise KneeInputError(f"--flexion {args.flexion:g} deg is outside the assembly range of "
                             f"{truth.params.name} ({lo:.1f} to {hi:.1f} deg)")
    print(f"knee fem: building the association model of {mech.params.name} ...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    model = build_association_model(mech, FemSettings())
    print(f"  grid {tuple(int(v) for v in model.grid.shape)} ({len(model.grid.cells)} cells, {model.grid.n_nodes} nodes), bones "
          f"{len(model.femur.el.cells)} + {len(model.tibia.el.cells)} tetrahedra; {time.perf_counter() - t0:.1f} s",
          file=sys.stderr)
    truth_tf, truth_info = None, None
    if measured is None:
        pts, truth_tf = case_points(truth, args.flexion, cam, DepthNoise() if not args.no_noise else None,
                                    args.seed, model.settings)
        ph_t = truth_phantom(truth, model.settings)
        targets, truth_f, truth_t = truth_targets(model, mech, truth_tf)
        truth_info = {"targets": targets, "femur": truth_f, "tibia": truth_t,
                      "meshes": {"femur": ph_t.femur, "tibia": ph_t.tibia.copy().apply_transform(joint_to_pose(truth_tf))}}
        print(f"  case: {truth.params.name} at {args.flexion:g} deg seen by the {args.camera} camera, "
              f"{len(pts)} depth points", file=sys.stderr)
    else:
        pts = measured
        print(f"  measured point cloud: {len(pts)} points (no truth: no target point errors)", file=sys.stderr)
    recorder = (FemRecorder(rrd, model, every=max(2, args.max_steps // 80), truth=truth_info)
                if rrd is not None else None)
    bar = ProgressBar()

    def on_step(k, phase, model_, surf, bone):
        if recorder is not None:
            recorder(k, phase, model_, surf, bone)
        if not args.quiet:
            bar((k + 1) / args.max_steps, f"step {k + 1} [{phase} forces]")

    try:
        r = run_standard_case(mech, args.flexion, cam, model=model, seed=args.seed, progress=False,
                              bone_stall_deg=args.bone_stall,
                              max_steps=args.max_steps, points=pts, truth_tf=truth_tf, on_step=on_step)
    except FemDivergence as e:
        if not args.quiet:
            print(file=sys.stderr)
        if recorder is not None:
            recorder.finish(message=str(e))
            print(f"partial recording (steps 0-{recorder.last_step}): {rrd}", file=sys.stderr)
        return _err(str(e))
    if not args.quiet:
        bar(1.0, f"{r.steps} steps")
    if recorder is not None:
        recorder.finish(r, f"{r.steps} steps, {'converged' if r.converged else 'not converged'}")
    print(f"{mech.params.name}: {r.steps} steps ({r.steps_bone_phase} with bone forces) in {r.wall_seconds:.1f} s "
          f"({r.steps / r.wall_seconds:.1f} steps/s), {'converged' if r.converged else 'NOT converged'}; "
          f"registration ICP fitness {r.icp_fitness:.2f}")
    if r.bone_phase_end:
        print(bone_phase_note(r))
    if r.errors:
        print(f"flexion: true {r.flexion_true_deg:.1f} deg, FEM {r.flexion_estimated_deg:.1f} deg")
        print("target point errors, mean ± sd (mm):")
        for bone, e in r.errors.items():
            fp, ep = e["footprints"], e["epiphysis"]
            print(f"  {bone:5s}  ACL/PCL footprints {fp[0]:6.2f} ± {fp[1]:5.2f}   epiphysis {ep[0]:6.2f} ± {ep[1]:5.2f}")
    else:
        print(f"flexion of the FEM bones: {r.flexion_estimated_deg:.1f} deg")
    if rrd is not None:
        print(f"recording: {rrd}  (open with: rerun {rrd})")
    return 0


def _flexion_list(text: str) -> list[float]:
    """``A:B:STEP`` (inclusive) or a comma list of angles, deg."""
    t = str(text).strip()
    try:
        if ":" in t:
            a, b, st = (float(v) for v in t.split(":"))
            if not st > 0 or b < a:
                raise ValueError
            vals = list(np.arange(a, b + 1e-9, st))
        else:
            vals = [float(v) for v in t.split(",")]
    except ValueError:
        raise KneeInputError(f"--flexion must be FROM:TO:STEP (STEP > 0, TO >= FROM) or a comma list of "
                             f"degrees, got {text!r}") from None
    if not vals or len(vals) > 50 or not all(math.isfinite(v) and 0.0 <= v <= 150.0 for v in vals):
        raise KneeInputError(f"--flexion must give 1-50 angles within 0-150 deg, got {text!r}")
    return [float(v) for v in vals]


def _camera_list(text: str) -> list[str]:
    """Camera entries: placement names separated by commas, or any entries (AZ,EL,DIST) separated by ';'."""
    from models.fem.case import CAMERA_PLACEMENTS

    t = str(text).strip()
    parts = t.split(";") if ";" in t else t.split(",")
    parts = [p.strip() for p in parts if p.strip()]
    if ";" not in t and not all(p.lower() in CAMERA_PLACEMENTS for p in parts):
        parts = [t]  # a single AZ,EL,DIST camera
    if not parts:
        raise KneeInputError("--cameras is empty")
    return parts


def cmd_compare(args) -> int:
    from fitting.optimize import perturb_endpoints
    from models.fem.case import camera_from_spec, truth_phantom
    from models.fem.compare_report import CompareRecorder, floor_markdown, markdown, plot, summary, targets_check, write_csv
    from models.fem.depth import DepthNoise
    from models.fem.prior_case import METHODS, compare_cases, prior_floor
    from models.fem.scene import build_association_model
    from models.mechanism import Mechanism
    from models.mechanism.params import load_model

    flexions = _flexion_list(args.flexion)
    cams = {c: camera_from_spec(c) for c in _camera_list(args.cameras)}
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise KneeInputError(f"--methods must be a comma list of {', '.join(METHODS)}, got {args.methods!r}")
    if not (0.0 <= args.perturb <= 10.0):
        raise KneeInputError(f"--perturb must be 0-10 mm, got {args.perturb}")
    out = _out_dir(args.out, args.force)
    params = load_model(args.model)
    if args.truth:
        truth, prior = Mechanism.from_name(args.truth), Mechanism(params)
        origin = f"truth {truth.params.name}, prior {params.name}"
    else:
        truth = Mechanism(params)
        prior = Mechanism(perturb_endpoints(params, 0.5 * args.perturb, args.perturb, seed=args.seed))
        origin = (f"truth {params.name}; prior = {params.name} with every TF link endpoint moved "
                  f"{0.5 * args.perturb:g}-{args.perturb:g} mm (seed {args.seed})")
    out.mkdir(parents=True, exist_ok=True)
    print(f"knee compare: {origin}; {len(flexions)} flexion angles x {len(cams)} camera(s) x {len(methods)} methods",
          file=sys.stderr)
    recorder = CompareRecorder(out / "compare.rrd", truth_phantom(truth), truth_phantom(prior), methods)
    bar = ProgressBar()
    progress = None if args.quiet else (lambda i, n, t: bar(i / n, t))
    try:
        rows = compare_cases(truth, prior, flexions, cams, methods, noise=None if args.no_noise else DepthNoise(),
                             seed=args.seed, progress=progress, on_result=recorder)
    finally:
        recorder.finish()
    write_csv(rows, out / "compare.csv")
    title = f"Kinematic priors for the FEM: {origin}"
    floor = prior_floor(build_association_model(prior), truth, prior, flexions)
    (out / "compare.md").write_text(markdown(rows, methods, title) + floor_markdown(floor), encoding="utf-8")
    plot(rows, methods, out / "compare.png", title)
    summ = summary(rows, methods)
    print("method      cases  failed  footprints (mm)  epiphysis (mm)  |flexion error| (deg)  wall (s)")
    for m, v in summ.items():
        print(f"{m:11s} {v['cases']:5d}  {v['failed']:6d}  {v['footprints_mm']:15.2f}  {v['epiphysis_mm']:14.2f}  "
              f"{v['flexion_error_deg']:20.2f}  {v['wall_s']:8.1f}")
    for line in targets_check(summ):
        print(line)
    print("the prior's own tibia error (best-matching flexion, femur placed exactly), footprints mm: " +
          ", ".join(f"{r['flexion_deg']:g} deg {r['tibia_footprints_mm']:.2f}" for r in floor))
    print("of which the axial rotation alone (the skin cannot show it; (ii) and (iii) correct the rest from the "
          "shank's points), footprints mm: " +
          ", ".join(f"{r['flexion_deg']:g} deg {r['tibia_footprints_axial_mm']:.2f} ({r['axial_rotation_deg']:+.1f} deg)"
                    for r in floor))
    notes = sorted({r["notes"] for r in rows if r.get("notes")} | {f"failed: {r['failed']}" for r in rows if r.get("failed")})
    for n in notes:
        print(f"note: {n}")
    print(f"table: {out / 'compare.csv'}, {out / 'compare.md'}\nplot: {out / 'compare.png'}\n"
          f"recording: {out / 'compare.rrd'}  (open with: rerun {out / 'compare.rrd'})")
    return 0


def _gait_options(p) -> None:
    """The gait trial and the subject's anthropometry (knee gait, knee osteotomy)."""
    p.add_argument("--trial", help="gait CSV (README, 'Gait'); default: the bundled normative cycle")
    p.add_argument("--mass", type=float, default=72.0, help="body mass, kg (72)")
    p.add_argument("--height", type=float, default=1.75, help="body height, m (1.75)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="knee", description="Knee kinematics toolkit (mm, degrees at the CLI).")
    sub = ap.add_subparsers(dest="command", required=True)
    sub.add_parser("models", help="list the bundled parameter sets").set_defaults(func=cmd_models)
    sp = sub.add_parser("sweep", help="solve the mechanism over a flexion range")
    sp.add_argument("model", help="a bundled parameter set (see 'knee models') or a TOML file")
    sp.add_argument("--from", dest="a_from", type=float, default=0.0, help="first flexion angle, deg (0)")
    sp.add_argument("--to", dest="a_to", type=float, default=120.0, help="last flexion angle, deg (120)")
    sp.add_argument("--step", type=float, default=1.0, help="step, deg (1)")
    sp.add_argument("--out", help="CSV file to write (default: CSV on standard output)")
    sp.add_argument("--rrd", help="Rerun recording to write")
    sp.add_argument("--force", action="store_true", help="replace existing output files")
    sp.set_defaults(func=cmd_sweep)
    dp = sub.add_parser("demo", help="the main job on the bundled default knee, with a Rerun recording")
    dp.add_argument("--out", default="knee-demo", help="output folder (a new one if it exists)")
    dp.add_argument("--flexion", type=float, default=60.0, help="flexion of the virtual depth map, deg (60)")
    dp.add_argument("--kinematics-only", action="store_true", help="only the sweep (no FEM)")
    dp.set_defaults(func=cmd_demo)
    ss = sub.add_parser("synth-subject", help="write a synthetic subject folder from a parameter set")
    ss.add_argument("out_dir", help="folder to create (must not exist or be empty)")
    ss.add_argument("--model", default="volunteer", help="parameter set with a patella (volunteer)")
    ss.add_argument("--seed", type=int, default=0, help="random seed (0)")
    ss.add_argument("--frames", type=int, default=60, help="frames of the measured motion, 0-120 deg (60)")
    ss.set_defaults(func=cmd_synth_subject)
    fp = sub.add_parser("fit", help="fit a subject-specific mechanism to a subject folder")
    fp.add_argument("subject_dir", help="the subject folder (README, 'Subject folders'); never written to")
    fp.add_argument("--out", required=True, help="output folder (parameter files, report, figure, recording)")
    fp.add_argument("--seed", type=int, default=0, help="seed of the global stage (0); same seed, same result")
    fp.add_argument("--no-global", action="store_true", help="skip differential evolution (local stage only)")
    fp.add_argument("--quick", action="store_true", help="a small global stage (a first look; not for results)")
    fp.add_argument("--no-recording", action="store_true", help="do not write the Rerun recording")
    fp.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    fp.add_argument("--quiet", action="store_true", help="no progress bar")
    fp.set_defaults(func=cmd_fit)
    gp = sub.add_parser("gait", help="inverse dynamics, link forces and contact pressures over a gait cycle")
    gp.add_argument("model", help="a bundled parameter set with a patella, or a TOML file")
    _gait_options(gp)
    gp.add_argument("--out", default="knee-gait", help="output folder (knee-gait)")
    gp.add_argument("--rrd", help="recording path (default OUT/gait.rrd)")
    gp.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    gp.set_defaults(func=cmd_gait)
    cp = sub.add_parser("contact", help="contact area and peak pressure against flexion under a load")
    cp.add_argument("model")
    cp.add_argument("--load", type=float, default=700.0, help="compressive load along the tibia, N (700)")
    cp.add_argument("--out", default="knee-contact", help="output folder (knee-contact)")
    cp.add_argument("--force", action="store_true")
    cp.set_defaults(func=cmd_contact)
    op = sub.add_parser("osteotomy", help="virtual osteotomy: cut, open/close a wedge, recompute axes, kinematics, gait")
    op.add_argument("model")
    op.add_argument("--bone", choices=("tibia", "femur"), default="tibia")
    op.add_argument("--angle", type=float, required=True, help="wedge angle, deg (+ opens opposite the hinge)")
    op.add_argument("--plane", help="cut plane: point and normal in the bone frame, px,py,pz,nx,ny,nz (mm); "
                                    "default: transverse, 35 mm below (tibia) / 60 mm above (femur) the joint")
    op.add_argument("--hinge", help="hinge: point and axis, hx,hy,hz,ax,ay,az (mm); default: 8 mm inside the "
                                    "lateral cortex, along x")
    op.add_argument("--release", action="append", help="release a ligament whose insertion moves (repeatable)")
    _gait_options(op)
    op.add_argument("--out", default="knee-osteotomy", help="output folder (knee-osteotomy)")
    op.add_argument("--force", action="store_true")
    op.set_defaults(func=cmd_osteotomy)
    co = sub.add_parser("compare", help="the four ways to use the mechanism with the FEM, on standard cases")
    co.add_argument("model", help="the prior: a bundled parameter set or a TOML file")
    co.add_argument("--truth", help="parameter set generating the truth (default: MODEL, with the prior = MODEL "
                                    "perturbed by --perturb)")
    co.add_argument("--flexion", default="30:120:15", help="true flexion angles, FROM:TO:STEP or a list (30:120:15)")
    co.add_argument("--cameras", default="oblique", help="oblique, frontal, lateral separated by commas, or "
                                                         "entries AZ,EL,DIST separated by ';' (oblique)")
    co.add_argument("--methods", default="paper,init,links,kinematics", help="which methods (all four)")
    co.add_argument("--perturb", type=float, default=2.0, help="largest endpoint move of the default prior, mm (2)")
    co.add_argument("--seed", type=int, default=3, help="seed of the perturbation and the depth noise (3)")
    co.add_argument("--no-noise", action="store_true", help="no depth noise")
    co.add_argument("--out", default="knee-compare", help="output folder (knee-compare)")
    co.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    co.add_argument("--quiet", action="store_true", help="no progress bar")
    co.set_defaults(func=cmd_compare)
    fe = sub.add_parser("fem", help="the association FEM model deformed toward a depth map (the paper's method)")
    fe.add_argument("model", help="the parameter set the model is built from (bundled name or TOML)")
    fe.add_argument("--flexion", type=float, default=90.0, help="flexion of the standard case's truth, deg (90)")
    fe.add_argument("--truth", help="parameter set generating the truth (default: MODEL)")
    fe.add_argument("--camera", default="oblique", help="oblique, frontal, lateral or AZ,EL,DIST (oblique)")
    fe.add_argument("--no-noise", action="store_true", help="no depth noise")
    fe.add_argument("--seed", type=int, default=0, help="seed of the depth noise (0)")
    fe.add_argument("--cloud", help="a measured point cloud (.ply/.pcd/.xyz, mm) instead of the virtual camera")
    fe.add_argument("--depth", help="a measured depth image (16-bit PNG or .npy) instead of the virtual camera")
    fe.add_argument("--intrinsics", help="fx,fy,cx,cy of the depth image (pixels)")
    fe.add_argument("--depth-scale", type=float, default=1.0, help="depth units to mm (1)")
    fe.add_argument("--pose", help="text file with the 4x4 camera-to-model transform (default identity)")
    fe.add_argument("--max-steps", type=int, default=400, help="step limit (400)")
    fe.add_argument("--bone-stall", type=float, default=0.5, metavar="DEG",
                    help="end the bone forces when the largest flexion reached grows less than DEG over 10 steps "
                         "(0.5; 0: only the paper's femur-tibia angle below 100 deg or a third of --max-steps)")
    fe.add_argument("--rrd", help="Rerun recording to write")
    fe.add_argument("--force", action="store_true", help="replace an existing recording")
    fe.add_argument("--quiet", action="store_true", help="no progress bar")
    fe.set_defaults(func=cmd_fem)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except KneeInputError as e:
        return _err(str(e))
    except BrokenPipeError:
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
