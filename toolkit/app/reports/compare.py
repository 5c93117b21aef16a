"""Outputs of ``knee compare``: the table (CSV and Markdown), the plot of error against flexion for the
four methods, and a Rerun recording in which each method's bones can be toggled against the truth.

Recording layout: one ``case`` step per (camera, flexion) case; ``compare/truth/{femur,tibia}`` are the true
bones, ``compare/<method>/{femur,tibia}`` each method's final bones (world frame, mm), ``compare/depth``
the case's depth points; ``metrics/<method>/footprints_mm`` the mean footprint error of each case.
Toggle a method's entity in the viewer's blueprint tree to show or hide it.
"""

from __future__ import annotations

import csv
import dataclasses
import statistics
from dataclasses import dataclass

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402

from knee.app.experiments.cases import CompareRow, FloorRow, MethodResult  # noqa: E402
from knee.foundations import recording as R  # noqa: E402
from knee.foundations.conventions import joint_to_pose  # noqa: E402
from knee.foundations.errors import KneeInputError  # noqa: E402

METHOD_LABELS = {"paper": "(i) paper: bone forces + surface forces",
                 "init": "(ii) prior as initialisation",
                 "links": "(iii) initialisation + the prior's links",
                 "kinematics": "(iv) kinematics alone"}
METHOD_COLOURS = {"paper": (220, 60, 60), "init": (240, 170, 40), "links": (40, 170, 90),
                  "kinematics": (70, 120, 230)}
COLUMNS = ["camera", "flexion_true_deg", "method", "flexion_estimated_deg", "femur_footprints_mm",
           "tibia_footprints_mm", "femur_epiphysis_mm", "tibia_epiphysis_mm", "steps", "wall_seconds", "converged",
           "tibia_correction_deg", "tibia_correction_mm", "notes", "failed", "flexion_sd_deg"]
NAN = float("nan")


@dataclass
class MethodSummary:
    """One method over a comparison's cases: how many ran and failed, and the medians over those that ran
    (footprint and epiphysis errors in mm, |flexion error| in deg, wall time in s)."""

    cases: int
    failed: int
    footprints_mm: float
    epiphysis_mm: float
    flexion_error_deg: float
    wall_s: float


def _median(values) -> float:
    values = list(values)
    return statistics.median(values) if values else NAN


def summary(rows: list[CompareRow], methods) -> dict[str, MethodSummary]:
    """Per method, its :class:`MethodSummary`."""
    out = {}
    for m in methods:
        ok = [r for r in rows if r.method == m and not r.failed]
        out[m] = MethodSummary(len(ok), sum(1 for r in rows if r.method == m and r.failed),
                               _median(r.footprints_mm for r in ok), _median(r.epiphysis_mm for r in ok),
                               _median(abs(r.flexion_estimated_deg - r.flexion_true_deg) for r in ok),
                               _median(r.wall_seconds for r in ok))
    return out


def targets_check(summ: dict[str, MethodSummary]) -> list[str]:
    """The comparison's three numbers for method (iii), each as a line with met / NOT met."""
    lines = []
    if "links" in summ and summ["links"].cases:
        fp, wall = summ["links"].footprints_mm, summ["links"].wall_s
        lines.append(f"(iii) median footprint error {fp:.2f} mm (target <= 2 mm): {'met' if fp <= 2 else 'NOT met'}")
        if "paper" in summ and summ["paper"].cases:
            ratio = summ["paper"].footprints_mm / fp if fp > 0 else float("inf")
            lines.append(f"(iii) {ratio:.1f}x lower than (i) (target >= 2x): {'met' if ratio >= 2 else 'NOT met'}")
        lines.append(f"(iii) median wall time {wall:.1f} s per case (target <= 5 s): {'met' if wall <= 5 else 'NOT met'}")
    return lines


def write_csv(rows: list[CompareRow], path, extra=()) -> None:
    """The comparison table as CSV, one row per run, columns :data:`COLUMNS` (then ``extra``)."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(COLUMNS) + list(extra), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            d = dataclasses.asdict(r)
            if r.failed:  # a failed run has no figures
                d = {k: (v if k in ("method", "camera", "flexion_true_deg", "failed") + tuple(extra) else "")
                     for k, v in d.items()}
            w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in d.items()})


#: Columns a table written before they were added may lack: their rows take the field's default.
LATER_COLUMNS = ("cpu_seconds", "estimate_rms_mm", "flexion_sd_deg")


def read_csv(path, row_type=CompareRow) -> list:
    """The rows :func:`write_csv` wrote (``row_type``: :class:`CompareRow` or a subclass naming the extra
    columns), each field converted back to its type (a failed run's empty figures to their defaults);
    :class:`KneeInputError` naming the file when it lacks a column of ``row_type`` (but those of
    :data:`LATER_COLUMNS`)."""
    fields = {f.name: f for f in dataclasses.fields(row_type)}
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            table = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise KneeInputError(f"{path}: not a readable comparison table ({e})") from None
    missing = sorted(set(fields) - set(table[0] if table else ()) - set(LATER_COLUMNS))
    if missing:
        raise KneeInputError(f"{path}: not a comparison table of these rows (missing {', '.join(missing)})")
    convert = {"float": float, "int": lambda v: int(float(v)), "bool": lambda v: v == "True", "str": str}
    out = []
    for rec in table:
        kw = {k: convert[f.type if isinstance(f.type, str) else f.type.__name__](rec[k])
              for k, f in fields.items() if rec.get(k, "") != ""}
        out.append(row_type(**kw))
    return out


def floor_markdown(floor: list[FloorRow]) -> str:
    """A Markdown section from :func:`knee.app.experiments.cases.prior_floor`'s rows."""
    lines = ["", "", "The prior's own tibia error: the prior posed at its best-matching flexion with the femur placed "
             "exactly (tibia target point errors, mm); of that pose error, the rotation about the tibia's long axis, "
             "which the skin around the shank cannot show (methods ii and iii correct the tibia's pose from the "
             "shank's depth points except for it), and the footprint error it alone leaves: about what remains "
             "at best.", "",
             "| flexion | prior's flexion | tibia footprints | tibia epiphysis | axial rotation off (deg) | "
             "footprints, axial rotation alone |", "|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {r.flexion_deg:g} | {r.prior_flexion_deg:.1f} | {r.tibia_footprints_mm:.2f} | "
              f"{r.tibia_epiphysis_mm:.2f} | {r.axial_rotation_deg:+.1f} | {r.tibia_footprints_axial_mm:.2f} |"
              for r in floor]
    return "\n".join(lines) + "\n"


def flexion_cell(r: CompareRow) -> str:
    """A run's estimated flexion for a table, with its standard error where the method gives one."""
    sd = getattr(r, "flexion_sd_deg", NAN)
    return f"{r.flexion_estimated_deg:.1f}" + (f" ± {sd:.1f}" if np.isfinite(sd) else "")


def markdown(rows: list[CompareRow], methods, title: str) -> str:
    """The comparison table, the medians per method and the checks of :func:`targets_check`."""
    summ = summary(rows, methods)
    lines = [f"# {title}", "",
             "Target point errors: mean distance (mm) between the estimated and the true bone surface points, "
             "ACL/PCL footprints and the whole epiphysis, per bone.", "",
             "| camera | flexion | method | estimate ± its standard error (deg) | femur footprints | tibia footprints | femur epiphysis | "
             "tibia epiphysis | steps | wall (s) | converged | tibia corrected (deg / mm) | notes |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---|"]
    for r in rows:
        if r.failed:
            lines.append(f"| {r.camera} | {r.flexion_true_deg:g} | {r.method} | failed: {r.failed} | | | | | | | | | |")
            continue
        deg, mm = r.tibia_correction_deg, r.tibia_correction_mm
        corr = "" if not np.isfinite(deg) else f"{deg:.1f} / {mm:.1f}"
        lines.append(f"| {r.camera} | {r.flexion_true_deg:g} | {r.method} | {flexion_cell(r)} | "
                     f"{r.femur_footprints_mm:.2f} | {r.tibia_footprints_mm:.2f} | {r.femur_epiphysis_mm:.2f} | "
                     f"{r.tibia_epiphysis_mm:.2f} | {r.steps} | {r.wall_seconds:.1f} | {r.converged} | "
                     f"{corr} | {r.notes} |")
    lines += ["", "## Summary (medians over the cases)", "",
              "| method | cases | failed | footprints (mm) | epiphysis (mm) | flexion error (deg) | wall (s) |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    for m, v in summ.items():
        lines.append(f"| {METHOD_LABELS.get(m, m)} | {v.cases} | {v.failed} | {v.footprints_mm:.2f} | "
                     f"{v.epiphysis_mm:.2f} | {v.flexion_error_deg:.2f} | {v.wall_s:.1f} |")
    checks = targets_check(summ)
    if checks:
        lines += [""] + [f"- {c}" for c in checks]
    return "\n".join(lines) + "\n"


def plot(rows: list[CompareRow], methods, path, title: str = "") -> None:
    """Footprint and epiphysis errors against the true flexion, a colour per method and a line style per
    camera (PNG)."""
    cams = sorted({r.camera for r in rows})
    styles = ["-o", "--s", ":^", "-.v"]
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5), sharex=True)
    for m in methods:
        col = np.array(METHOD_COLOURS.get(m, (0, 0, 0))) / 255
        for ci, cam in enumerate(cams):
            ok = sorted((r for r in rows if r.method == m and r.camera == cam and not r.failed),
                        key=lambda r: r.flexion_true_deg)
            if not ok:
                continue
            fl = [r.flexion_true_deg for r in ok]
            label = METHOD_LABELS.get(m, m) + (f" [{cam}]" if len(cams) > 1 else "")
            ax[0].plot(fl, [r.footprints_mm for r in ok], styles[ci % 4], color=col, label=label)
            ax[1].plot(fl, [r.epiphysis_mm for r in ok], styles[ci % 4], color=col)
    ax[0].axhline(2.0, color="grey", lw=0.8, ls=":")
    ax[0].set_title("ACL/PCL footprint error (mean of femur and tibia)")
    ax[1].set_title("epiphysis error (mean of femur and tibia)")
    for a in ax:
        a.set_xlabel("true flexion (deg)")
        a.set_ylabel("mm")
        a.set_yscale("log")
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def compare_blueprint(methods) -> rrb.Blueprint:
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="compare", name="Bones: truth and the methods (toggle in the tree)"),
        rrb.TimeSeriesView(origin="metrics", name="Footprint error per case (mm)"),
        column_shares=[3, 2]), collapse_panels=True)


class CompareRecorder:
    """``on_result`` callback of :func:`knee.app.experiments.cases.compare_cases` writing the recording."""

    def __init__(self, path, truth_phantom, prior_phantom, methods):
        """``truth_phantom``: the bones of the truth; ``prior_phantom``: those the methods' models are built
        from (their faces go with the surfaces in the results): a phantom, or the faces themselves,
        ``{"femur": (F, 3), "tibia": (F, 3)}``."""
        self.rec = R.new_recording()
        R.save(self.rec, path, compare_blueprint(methods))
        self.rec.log("compare", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        self.phantom = truth_phantom
        self.faces = {k: np.asarray(prior_phantom[k] if isinstance(prior_phantom, dict) else getattr(prior_phantom, k).faces,
                                    np.uint32) for k in ("femur", "tibia")}
        self.cases: dict = {}

    def __call__(self, cam_name: str, flexion_deg: float, method: str, result: MethodResult, truth_tf) -> None:
        key = (cam_name, flexion_deg)
        if key not in self.cases:
            self.cases[key] = len(self.cases)
            self.rec.set_time("case", sequence=self.cases[key])
            ph = self.phantom
            tib = ph.tibia.copy().apply_transform(joint_to_pose(truth_tf))
            for name, mesh in (("femur", ph.femur), ("tibia", tib)):
                self.rec.log(f"compare/truth/{name}", rr.Mesh3D(
                    vertex_positions=np.asarray(mesh.vertices, np.float32),
                    triangle_indices=np.asarray(mesh.faces, np.uint32), albedo_factor=(235, 235, 235, 120)))
            self.rec.log("compare/case", rr.TextDocument(f"camera {cam_name}, true flexion {flexion_deg:g} deg"))
        self.rec.set_time("case", sequence=self.cases[key])
        col = METHOD_COLOURS.get(method, (128, 128, 128))
        for name, v in result.surfaces.items():
            self.rec.log(f"compare/{method}/{name}", rr.Mesh3D(vertex_positions=np.asarray(v, np.float32),
                                                               triangle_indices=self.faces[name], albedo_factor=col))
        self.rec.log(f"metrics/{method}/footprints_mm", rr.Scalars(result.errors.footprints_mm))

    def finish(self) -> None:
        R.close(self.rec)
