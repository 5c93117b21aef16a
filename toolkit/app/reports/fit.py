"""Outputs of ``knee fit``: the parameter files, the report (JSON and Markdown, seed 002 Table 2
layout), the figure of measured against model motion (seed 002 Fig. 3) and the Rerun recording (measured
and fitted bones side by side on the ``frame`` timeline)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402

from knee.fitting.pipeline import (  # noqa: E402
    NEEDED_RANGE_DEG,
    TF_NAMES,
    UNITS,
    ComponentErrors,
    FitOutcome,
    Validation,
)
from knee.foundations import recording as R  # noqa: E402
from knee.foundations.conventions import invert_poses, joint_to_pose  # noqa: E402
from knee.foundations.files import check_output, staged_folder  # noqa: E402
from knee.models.mechanism.params import save_toml  # noqa: E402


def _table_rows(err: ComponentErrors, group: str) -> dict:
    rng = range(1, 6) if group == "tf" else range(6)
    return {TF_NAMES[k]: {"mae": float(err.mae[k]), "max": float(err.max[k]), "unit": UNITS[k]} for k in rng}


def _tables(v: Validation) -> dict:
    out = {"tf": _table_rows(v.tf, "tf")}
    if v.pf is not None:
        out["pf"] = _table_rows(v.pf, "pf")
    return out


def report_dict(o: FitOutcome) -> dict:
    """The report as a JSON-ready dict (``report.json``)."""
    info = o.info
    rep = {
        "subject": o.subject.name, "side": o.subject.side, "folder": str(o.subject.root), "seed": o.seed,
        "motion": {"frames_used": int(len(o.motion.tf)), "rows": o.subject.motion.rows,
                   "rows_skipped": o.subject.motion.skipped,
                   "flexion_range_deg": [float(np.degrees(o.motion.flexion.min())),
                                         float(np.degrees(o.motion.flexion.max()))],
                   "patella": o.subject.has_pf},
        "frames": {b: {"origin_ct": T[:3, 3].tolist(), "axes_ct": T[:3, :3].T.tolist()}
                   for b, T in info.frames.items()},
        "mri_to_ct_fre_mm": {b: a.fre for b, a in info.alignment.items()},
        "contact_spheres": {s: {"femur_centre": c.femur.centre.tolist(), "femur_radius": c.femur.radius,
                                "femur_rms": c.femur.rms, "femur_points": c.femur.points,
                                "tibia_centre": c.tibia.centre.tolist(), "tibia_radius": c.tibia.radius,
                                "tibia_rms": c.tibia.rms, "tibia_points": c.tibia.points,
                                "tibia_surface": c.surface, "link_length": c.length}
                            for s, c in info.contacts.items()},
        "isometric_fibres": {k: {"femur": v.femur.tolist(), "tibia": v.tibia.tolist(), "length": v.length,
                                 "length_sd": v.length_sd, "candidates": list(v.candidates)}
                             for k, v in info.fibres.items()},
        "seconds": {**dataclasses.asdict(o.seconds), "fit": o.seconds.fit}, "warnings": o.warnings,
        "first_estimate": None if o.first_errors is None else _tables(o.first_errors),
        "fitted": _tables(o.fitted_errors),
        "assembly_range_deg": {"fitted": list(o.assembly_range_deg),
                               "measured": [float(np.degrees(o.motion.flexion.min())),
                                            float(np.degrees(o.motion.flexion.max()))],
                               "needed": list(NEEDED_RANGE_DEG)},
        "identifiability": {g: d.as_dict() for g, d in o.diagnostics.items() if d is not None},
        "bounds": None if o.bounds is None else dataclasses.asdict(o.bounds),
        "cross_trial": {name: _tables(v) for name, v in o.cross_trial},
        "fitted_as_measured": None if o.as_measured_errors is None else _tables(o.as_measured_errors),
    }
    if info.axis is not None:
        ax, pt = info.axis, info.pitch
        rep["helical_axis"] = {"n_femur": ax.n.tolist(), "q_femur": ax.q.tolist(),
                               "sphere_rms": [ax.lateral.rms, ax.medial.rms],
                               "pitch_mm_per_rad": pt.lambda1, "groove_plane_angle_to_axis_deg": pt.angle_to_axis_deg,
                               "groove_plane_rms": pt.rms}
        mo = info.motion_axis
        if mo is not None:
            rep["helical_axis"]["from_motion"] = {
                "n_femur": mo.n.tolist(), "q_femur": mo.q.tolist(), "pitch_mm_per_rad": mo.lambda1,
                "span_deg": mo.span_deg, "angle_to_imaging_deg": mo.angle_to_imaging_deg,
                "distance_to_imaging_mm": mo.distance_to_imaging_mm, "used": True}
    if o.truth_errors is not None:
        rep["fitted_vs_truth"] = _tables(o.truth_errors)
        if o.truth_first_errors is not None:
            rep["first_estimate_vs_truth"] = {"tf": _table_rows(o.truth_first_errors.tf, "tf")}
    return rep


def _md_table(title, block):
    cols = [n for n in TF_NAMES]
    lines = [f"### {title}", "", "| Group | | " + " | ".join(f"{c} ({u})" for c, u in zip(cols, UNITS)) + " |",
             "|---|---|" + "---|" * 6]
    for g in ("tf", "pf"):
        if g not in block:
            continue
        for stat in ("mae", "max"):
            cells = [f"{block[g][c][stat]:.2f}" if c in block[g] else "input" for c in cols]
            lines.append(f"| {g.upper()} | {stat.upper()} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def report_markdown(rep: dict) -> str:
    """The report in Markdown (``report.md``) from :func:`report_dict`."""
    s = [f"# Fit report: subject {rep['subject']} ({rep['side']} knee)", "",
         f"Seed {rep['seed']}; {rep['motion']['frames_used']} frames used "
         f"({rep['motion']['rows_skipped']} of {rep['motion']['rows']} rows skipped), flexion "
         f"{rep['motion']['flexion_range_deg'][0]:.1f} to {rep['motion']['flexion_range_deg'][1]:.1f} deg. "
         f"Fit time {rep['seconds']['fit']:.1f} s (TF {rep['seconds']['tf_fit']:.1f} s, PF "
         f"{rep['seconds']['pf_fit']:.1f} s); total {rep['seconds']['total']:.1f} s.", ""]
    if rep["warnings"]:
        s += ["**Warnings**", ""] + [f"- {w}" for w in rep["warnings"]] + [""]
    s += ["## Accuracy (model against the measured motion; seed 002 Table 2 layout)", ""]
    if rep.get("fitted_as_measured"):
        s += ["Fitted to, and compared with, the mean of the trial's flexing and extending phases "
              "(--average-halves; seed 002's reference motion). Against every frame as measured, below, the "
              "differences between the phases (hysteresis) add to the errors: a 1-DoF model gives one pose per "
              "flexion angle.", ""]
    s.append(_md_table("Fitted model", rep["fitted"]))
    if rep.get("fitted_as_measured"):
        s.append(_md_table("Fitted model against the trial as measured (every frame, not averaged)",
                           rep["fitted_as_measured"]))
    if rep.get("first_estimate"):
        s.append(_md_table("First estimate", rep["first_estimate"]))
    if "fitted_vs_truth" in rep:
        s += ["## Against the noise-free truth (synthetic subject)", ""]
        s.append(_md_table("Fitted model vs truth", rep["fitted_vs_truth"]))
        if "first_estimate_vs_truth" in rep:
            s.append(_md_table("First estimate vs truth", rep["first_estimate_vs_truth"]))
    for name, block in rep.get("cross_trial", {}).items():
        s += [f"## Cross-trial check: {name} (not fitted)", ""]
        s.append(_md_table("Fitted model on the held-out trial", block))
    if rep.get("bounds"):
        s += ["Bounds around the first estimate: " + ", ".join(f"{k} {v:g}" for k, v in rep["bounds"].items())
              + " (subject.toml [fit], knee fit --bounds).", ""]
    ar = rep["assembly_range_deg"]
    s += ["## Assembly range", "",
          f"The fitted model assembles from {ar['fitted'][0]:.1f} to {ar['fitted'][1]:.1f} deg; the motion was measured "
          f"over {ar['measured'][0]:.1f} to {ar['measured'][1]:.1f} deg; a user is likely to need "
          f"{ar['needed'][0]:g} to {ar['needed'][1]:g} deg.", ""]
    for g, d in rep["identifiability"].items():
        s += [f"## What the fit determines: {g.upper()} group", "",
              f"{d['variables']} variables against {d['variables'] + d['dof']} weighted residuals; condition number of "
              f"the weighted Jacobian (in the variables' physical offsets) {d['condition_number']:.3g}, rank "
              f"{d['rank']}; residual RMS {d['residual_rms']:.3g} (noise units).", ""]
        if d["on_bound"]:
            s += ["On (within 5 % of) their bounds, decided by the bounds, not the data: "
                  + ", ".join(f"{b['name']} ({100 * b['fraction']:.0f} %)" for b in d["on_bound"]) + ".", ""]
        s += ["Parameter combinations the measured motion hardly sees (smallest singular values):", ""]
        s += [f"- {w}" for w in d["weakest_directions"]] + [""]
        s += ["| variable | 95 % CI half-width |", "|---|---:|"]
        for n, c in d["ci95"].items():
            hw = "not determined" if c["half_width"] is None else f"{c['half_width']:.3g} {c['unit']}"
            s.append(f"| {n} | {hw} |")
        s.append("")
    s += ["## Steps", "", "MRI-to-CT fiducial registration error (mm):", ""]
    for b, fre in rep["mri_to_ct_fre_mm"].items():
        s.append(f"- {b}: " + ", ".join(f"{k} {v:.2f}" for k, v in fre.items()))
    s += ["", "Contact spheres (bone frames, mm):", ""]
    for side, c in rep["contact_spheres"].items():
        s.append(f"- {side}: femur R {c['femur_radius']:.2f} (rms {c['femur_rms']:.3f}, {c['femur_points']} pts), "
                 f"tibia R {c['tibia_radius']:.2f} {c['tibia_surface']} (rms {c['tibia_rms']:.3f}, "
                 f"{c['tibia_points']} pts), link length {c['link_length']:.2f}")
    s += ["", "Isometric fibres:", ""]
    for k, v in rep["isometric_fibres"].items():
        s.append(f"- {k}: length at extension {v['length']:.2f} mm, sd over the motion {v['length_sd']:.3f} mm "
                 f"({v['candidates'][0]} x {v['candidates'][1]} candidate pairs)")
    if "helical_axis" in rep:
        h = rep["helical_axis"]
        s += ["", f"Helical axis: n = {np.round(h['n_femur'], 4).tolist()}, q = {np.round(h['q_femur'], 2).tolist()} "
                  f"mm; pitch {h['pitch_mm_per_rad']:.3f} mm/rad (intercondylar plane normal "
                  f"{h['groove_plane_angle_to_axis_deg']:.2f} deg from the axis)."]
        if "from_motion" in h:
            m = h["from_motion"]
            s += ["", f"The first estimate uses the measured motion's mean helical axis instead (the patella turns "
                      f"{m['span_deg']:.1f} deg): n = {np.round(m['n_femur'], 4).tolist()}, q = "
                      f"{np.round(m['q_femur'], 2).tolist()} mm, pitch {m['pitch_mm_per_rad']:.3f} mm/rad; "
                      f"{m['angle_to_imaging_deg']:.1f} deg and {m['distance_to_imaging_mm']:.1f} mm from the "
                      f"imaging axis."]
    return "\n".join(s) + "\n"


def plot_motion(o: FitOutcome, path) -> Path:
    """Measured (black dashed) against model (blue) motion per component over TF flexion, the largest
    discrepancy circled in red (like seed 002 Fig. 3); PNG."""
    v = o.fitted_errors
    groups = [("tf", o.motion.tf, v.model_tf, v.tf)]
    if v.model_pf is not None and o.motion.pf is not None:
        groups.append(("pf", o.motion.pf, v.model_pf, v.pf))
    fig, axes = plt.subplots(len(groups), 6, figsize=(18, 3.2 * len(groups)), squeeze=False)
    x = np.degrees(o.motion.flexion)
    for r, (g, meas, model, err) in enumerate(groups):
        for k in range(6):
            ax = axes[r, k]
            if g == "tf" and k == 0:
                ax.axis("off")
                ax.text(0.05, 0.5, f"{o.subject.name}\nTF flexion is the input\nblack dashed: measured\n"
                        "blue: model\nred: largest difference", transform=ax.transAxes, va="center")
                continue
            scale = 180 / math.pi if k < 3 else 1.0
            ax.plot(x, meas[:, k] * scale, "k--", lw=1)
            ax.plot(x, model[:, k] * scale, "-", color="tab:blue", lw=1.5)
            i = int(err.argmax[k])
            ax.plot(x[i], meas[i, k] * scale, "o", mfc="none", mec="red", ms=9)
            ax.set_title(f"{g.upper()} {TF_NAMES[k].replace('_', ' ')} ({UNITS[k]})", fontsize=9)
            ax.set_xlabel("TF flexion (deg)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def write_recording(o: FitOutcome, path) -> Path:
    """Measured and model bones side by side (two 3D views) on the ``frame`` timeline, and each component's
    measured and model series."""
    rec = R.new_recording()
    views = [rrb.Spatial3DView(origin="measured", name="Measured motion"),
             rrb.Spatial3DView(origin="model", name="Fitted model")]
    bp = rrb.Blueprint(rrb.Vertical(rrb.Horizontal(*views),
                                    rrb.Horizontal(rrb.TimeSeriesView(origin="metrics/tf", name="TF"),
                                                   rrb.TimeSeriesView(origin="metrics/pf", name="PF")),
                                    row_shares=[3, 2]), collapse_panels=True)
    R.save(rec, path, bp)
    frames = np.arange(len(o.motion.tf))
    v = o.fitted_errors
    meshes = {b: o.subject.ct[b].copy().apply_transform(invert_poses(T)) for b, T in o.info.frames.items()}
    poses = {"measured": {"tibia": joint_to_pose(o.motion.tf)}, "model": {"tibia": joint_to_pose(v.model_tf)}}
    if v.model_pf is not None and o.motion.pf is not None:
        poses["measured"]["patella"] = joint_to_pose(o.motion.pf)
        poses["model"]["patella"] = joint_to_pose(v.model_pf)
    for root in ("measured", "model"):
        rec.log(root, rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        for b, m in meshes.items():
            if b != "femur" and b not in poses[root]:
                continue
            R.log_mesh(rec, f"{root}/{b}", m, R.BONE_COLOURS[b])
            if b in poses[root]:
                R.send_poses(rec, f"{root}/{b}", "frame", frames, poses[root][b])
    for g, meas, model in (("tf", o.motion.tf, v.model_tf), ("pf", o.motion.pf, v.model_pf)):
        if meas is None or model is None:
            continue
        for k in range(6):
            sc = 180 / math.pi if k < 3 else 1.0
            R.send_scalars(rec, f"metrics/{g}/{TF_NAMES[k]}/measured", "frame", frames, meas[:, k] * sc)
            R.send_scalars(rec, f"metrics/{g}/{TF_NAMES[k]}/model", "frame", frames, model[:, k] * sc)
    R.close(rec)
    return Path(path)


def check_output_folder(subject_dir: Path, out_dir: Path, force: bool, trials=()) -> None:
    """The output folder of a fit, checked before the fit: never the subject folder or a trial's file,
    inside them or around them; writable; an existing, non-empty one only with ``force``."""
    check_output(out_dir, "folder", force, inputs=(Path(subject_dir), *trials))


def write_outputs(o: FitOutcome, out_dir, recording: bool = True, figure: bool = True) -> dict[str, Path]:
    """The fit's files in ``out_dir``: ``first_estimate.toml`` and ``fitted.toml`` (loadable by ``knee
    sweep``), ``report.json``, ``report.md``, and unless turned off ``motion.png`` and ``fit.rrd``;
    returns {kind: path}. The files are written beside ``out_dir`` and moved into place together
    (:func:`knee.foundations.files.staged_folder`): an existing folder is replaced as a whole."""
    out_dir = Path(out_dir)
    with staged_folder(out_dir) as tmp:
        files = _write_into(o, tmp, recording, figure)
    return {k: out_dir / f.name for k, f in files.items()}


def _write_into(o: FitOutcome, out_dir: Path, recording: bool, figure: bool) -> dict[str, Path]:
    files = {"first_estimate": out_dir / "first_estimate.toml", "fitted": out_dir / "fitted.toml",
             "report_json": out_dir / "report.json", "report_md": out_dir / "report.md"}
    save_toml(o.first, files["first_estimate"], overwrite=True)
    save_toml(o.fitted, files["fitted"], overwrite=True)
    rep = report_dict(o)
    files["report_json"].write_text(json.dumps(rep, indent=1, default=float), encoding="utf-8")
    files["report_md"].write_text(report_markdown(rep), encoding="utf-8")
    if figure:
        files["figure"] = plot_motion(o, out_dir / "motion.png")
    if recording:
        files["recording"] = write_recording(o, out_dir / "fit.rrd")
    return files
