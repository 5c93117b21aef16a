"""Outputs of ``knee osteotomy``: the report (Markdown), the figure and the recording (before and after
side by side at full extension)."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402
import trimesh  # noqa: E402

from knee.foundations import recording as R  # noqa: E402
from knee.foundations.conventions import joint_to_pose  # noqa: E402
from knee.models.osteotomy import (  # noqa: E402
    FUJISAWA,
    Cut,
    OsteotomyComparison,
    OsteotomyResult,
    gait_contact_summary,
)


def report_markdown(cut: Cut, res: OsteotomyResult, cmp: OsteotomyComparison) -> str:
    """The osteotomy's report (``report.md``)."""
    ab, aa = res.align_before, res.align_after
    d = cmp.tf_after - cmp.tf_before
    d[:, :3] = np.degrees(d[:, :3])
    names = ("adduction (deg)", "internal rotation (deg)", "anterior (mm)", "proximal (mm)", "lateral (mm)")
    gb, ga = gait_contact_summary(cmp.gait_before), gait_contact_summary(cmp.gait_after)
    lines = [f"# Virtual osteotomy: {res.before.params.name}, {cut.bone}, {cut.angle:+g} deg", "",
             f"Cut plane through {np.round(cut.plane_point, 1).tolist()} mm, normal {np.round(cut.plane_normal, 3).tolist()}; "
             f"hinge through {np.round(cut.hinge_point, 1).tolist()} mm along {np.round(cut.hinge_axis, 3).tolist()} "
             f"({cut.bone} frame). Positive angles open the wedge opposite the hinge.", "",
             "Moved with the fragment: " + (", ".join(res.moved) or "nothing") + ".", "",
             "## Alignment at full extension", "", "| | before | after |", "|---|---:|---:|",
             f"| hip-knee-ankle deviation (deg, + varus) | {ab.hka_deg:+.2f} | {aa.hka_deg:+.2f} |",
             f"| weight-bearing line across the plateau (% medial->lateral; target {FUJISAWA}) | {ab.wbl_percent:.1f} | "
             f"{aa.wbl_percent:.1f} |",
             f"| assembly range (deg) | {math.degrees(res.before.assembly_range[0]):.1f} to "
             f"{math.degrees(res.before.assembly_range[1]):.1f} | {math.degrees(res.after.assembly_range[0]):.1f} "
             f"to {math.degrees(res.after.assembly_range[1]):.1f} |", "",
             f"## Kinematics over {cmp.flexion_deg[0]:.0f}-{cmp.flexion_deg[-1]:.0f} deg flexion (after - before)", "",
             "| component | max abs change | at flexion (deg) |", "|---|---:|---:|"]
    for k, nm in enumerate(names):
        i = int(np.argmax(np.abs(d[:, k + 1])))
        lines.append(f"| {nm} | {abs(d[i, k + 1]):.2f} | {cmp.flexion_deg[i]:.0f} |")
    warn = [f"**Warning ({when}):** {g.flagged_note}." for when, g in (("before", cmp.gait_before),
                                                                      ("after", cmp.gait_after)) if g.flagged_note]
    if warn:
        lines[2:2] = [x for w in warn for x in (w, "")]  # at the top, under the title
    first = next(iter(gb.values()), None)
    used = "" if first is None else (f" Figures from the {first.frames} of {first.of} frames before and "
                                     f"{next(iter(ga.values())).frames} after with no flagged member (n/a: none).")
    lines += ["", f"## Contact in gait ({cmp.gait_before.trial.source})", "", used.strip(), "",
              "| contact | peak force before (N) | after | Hertz peak before (MPa) | after | share of contact force in stance before | after |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    def f(v, spec):
        return "n/a" if not math.isfinite(v) else format(v, spec)

    for nm in gb:
        lines.append(f"| {nm} | {f(gb[nm].peak_force_N, '.0f')} | {f(ga[nm].peak_force_N, '.0f')} | "
                     f"{f(gb[nm].hertz_peak_MPa, '.2f')} | {f(ga[nm].hertz_peak_MPa, '.2f')} | "
                     f"{f(gb[nm].mean_share, '.2f')} | {f(ga[nm].mean_share, '.2f')} |")
    nb = sum(1 for f in cmp.gait_before.statics.flags if f)
    na = sum(1 for f in cmp.gait_after.statics.flags if f)
    lines += ["", f"Frames with a member loaded the wrong way (flagged): {nb} before, {na} after (of "
                  f"{cmp.gait_before.trial.time.size}).", ""]
    return "\n".join(lines)


def plot(cut: Cut, res: OsteotomyResult, cmp: OsteotomyComparison, path) -> None:
    """Kinematics before and after, the frontal-plane axes, contact forces in gait and the weight-bearing
    line on the plateau (PNG)."""
    fig = plt.figure(figsize=(15, 8))
    fl = cmp.flexion_deg
    titles = ("adduction (deg)", "internal rotation (deg)", "anterior (mm)", "proximal (mm)", "lateral (mm)")
    for k in range(5):
        ax = fig.add_subplot(2, 4, k + 1)
        sc = 180 / math.pi if k < 2 else 1.0
        ax.plot(fl, cmp.tf_before[:, k + 1] * sc, "k", label="before")
        ax.plot(fl, cmp.tf_after[:, k + 1] * sc, "tab:red", label="after")
        ax.set_title(f"TF {titles[k]}", fontsize=9)
        ax.set_xlabel("flexion (deg)", fontsize=8)
        if k == 0:
            ax.legend(fontsize=7)
    ax = fig.add_subplot(2, 4, 6)
    for al, col, lab in ((res.align_before, "k", "before"), (res.align_after, "tab:red", "after")):
        pts = np.array([al.hip, al.knee, al.tibia_origin, al.ankle])
        ax.plot(pts[:, 2], pts[:, 1], "-o", color=col, ms=3, label=f"{lab}: HKA {al.hka_deg:+.1f} deg")
        ax.plot([al.hip[2], al.ankle[2]], [al.hip[1], al.ankle[1]], "--", color=col, lw=0.8)
    ax.set_title("frontal plane (z lateral, exaggerated; y proximal; mm)", fontsize=9)
    ax.legend(fontsize=7)
    ax = fig.add_subplot(2, 4, 7)
    for g, style, lab in ((cmp.gait_before, "-", "before"), (cmp.gait_after, "--", "after")):
        for nm, e in g.contact.items():
            ax.plot(g.trial.time, e.force, style, label=f"{nm} {lab}")
    ax.set_title("contact force in gait (N)", fontsize=9)
    ax.set_xlabel("time (s)", fontsize=8)
    ax.legend(fontsize=7)
    ax = fig.add_subplot(2, 4, 8)
    ax.plot([0, 100], [0, 0], "k", lw=6, alpha=0.3)
    for al, col in ((res.align_before, "k"), (res.align_after, "tab:red")):
        ax.plot([al.wbl_percent], [0], "o", color=col)
    ax.axvline(FUJISAWA, color="tab:green", ls=":", label=f"{FUJISAWA} % (Fujisawa)")
    ax.set_xlim(-10, 110)
    ax.set_yticks([])
    ax.set_title("weight-bearing line on the plateau (% medial -> lateral)", fontsize=9)
    ax.legend(fontsize=7)
    fig.suptitle(f"{res.before.params.name}: {cut.bone} osteotomy {cut.angle:+g} deg")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_recording(cut: Cut, res: OsteotomyResult, path) -> None:
    """Before and after side by side: femur, tibia fragments (the moved one turned), mechanical axes and
    the weight-bearing line, at full extension."""
    rec = R.new_recording()
    bp = rrb.Blueprint(rrb.Horizontal(rrb.Spatial3DView(origin="before", name="Before"),
                                      rrb.Spatial3DView(origin="after", name="After")), collapse_panels=True)
    R.save(rec, path, bp)
    ph = res.phantom
    bone = ph.tibia if cut.bone == "tibia" else ph.femur
    n = cut.plane_normal / np.linalg.norm(cut.plane_normal)
    knee_side = np.sign((np.zeros(3) - cut.plane_point) @ n) * n
    side = (bone.triangles_center - cut.plane_point) @ knee_side > 0  # faces by side (display only)
    fixed, moving = (trimesh.Trimesh(bone.vertices, bone.faces[m], process=False) for m in (side, ~side))
    for m in (fixed, moving):
        m.remove_unreferenced_vertices()
    for root, mech, al, W in (("before", res.before, res.align_before, np.eye(4)),
                              ("after", res.after, res.align_after, res.W)):
        rec.log(root, rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        T = joint_to_pose(mech.motion_at(np.array([0.0]))[0][0])
        frag = moving.copy().apply_transform(W)
        if cut.bone == "tibia":
            R.log_mesh(rec, f"{root}/femur", ph.femur, R.BONE_COLOURS["femur"])
            R.log_mesh(rec, f"{root}/tibia/proximal", fixed.copy().apply_transform(T), R.BONE_COLOURS["tibia"])
            R.log_mesh(rec, f"{root}/tibia/distal", frag.apply_transform(T), (200, 160, 140))
        else:
            R.log_mesh(rec, f"{root}/femur/distal", fixed, R.BONE_COLOURS["femur"])
            R.log_mesh(rec, f"{root}/femur/proximal", frag, (200, 160, 140))
            R.log_mesh(rec, f"{root}/tibia", ph.tibia.copy().apply_transform(T), R.BONE_COLOURS["tibia"])
        rec.log(f"{root}/axes", rr.LineStrips3D([[al.hip, al.knee], [al.tibia_origin, al.ankle]],
                                                colors=[(40, 90, 200)], radii=[1.0]), static=True)
        rec.log(f"{root}/weight_bearing_line", rr.LineStrips3D([[al.hip, al.ankle]], colors=[(220, 60, 40)],
                                                               radii=[0.8]), static=True)
        rec.log(f"{root}/wbl_crossing", rr.Points3D([al.crossing], colors=[(220, 60, 40)], radii=[3.0],
                                                    labels=[f"{al.wbl_percent:.1f} %"]), static=True)
    R.close(rec)
