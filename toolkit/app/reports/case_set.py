"""The case set's report (``knee compare CASE_SET``): every run listed, the medians per method and case
family, the issue's targets checked, a figure per method x family, and a Rerun recording.

Recording layout (:class:`CaseSetRecorder`), in the camera's frame (mm; x right, y down, z forward): one
``case`` step per case; ``compare/depth`` the case's depth points, ``compare/truth/{femur,tibia}`` the true
bones, ``compare/<method>/{femur,tibia}`` each method's bones at the rigid poses its errors are taken at
(absent where the run failed), ``compare/case`` what the case is; ``metrics/<method>/footprints_mm`` the
mean footprint error per case. Toggle a method's entity in the viewer's tree to show or hide it."""

from __future__ import annotations

import math
import statistics
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rerun as rr  # noqa: E402

from knee.app.experiments.skin_floor import placement_spread  # noqa: E402
from knee.app.reports.compare import METHOD_COLOURS, compare_blueprint, flexion_cell  # noqa: E402
from knee.foundations import recording as R  # noqa: E402
from knee.foundations.pointclouds import voxel_downsample  # noqa: E402
from knee.models.prior import MIN_SEEN_SHANK, POOR_FIT_RMS_MM, VOXEL_MM  # noqa: E402

#: The paper's own figures (seed 000): mean footprint and epiphysis errors, femur / tibia (mm).
PAPER_FOOTPRINTS_MM = (3.81, 3.89)
PAPER_EPIPHYSIS_MM = (4.88, 5.12)
NAMES = {"paper": "(i) paper", "init": "(ii) init", "links": "(iii) links", "kinematics": "(iv) kinematics"}


def _median(v) -> float:
    v = [x for x in v if x == x]
    return statistics.median(v) if v else float("nan")


def pose_of(row) -> str:
    """The case's truth pose: its id without the camera's name and the skin mismatch. The cases of one pose
    share the bones' poses (the deviation from the prior is drawn once per pose, whatever the mismatch);
    each mismatch draws its own skin field, shared by its views, and each view its own noise and rough
    camera guess."""
    case = row.case
    for suffix in (f"-{row.camera}", f"-{row.mismatch_mm:g}mm"):
        if row.camera and case.endswith(suffix):
            case = case[: -len(suffix)]
    return case


#: The resamples and the level of :func:`median_interval`.
BOOTSTRAP_RESAMPLES = 2000
INTERVAL_LEVEL = 0.95


def median_interval(values, clusters, resamples: int = BOOTSTRAP_RESAMPLES, level: float = INTERVAL_LEVEL,
                    seed: int = 0) -> tuple[float, float]:
    """A percentile bootstrap interval of the median of ``values`` (V,), resampling whole ``clusters``
    (V,; any hashable labels) with replacement: the cases of one cluster (the views and mismatches of one
    truth pose) are not independent draws, so resampling them one by one would give too narrow an interval. Each resample draws
    as many clusters as there are, and its median is that of the cases they carry, each as often as its
    cluster was drawn (a weighted median over the sorted values, all resamples at once)."""
    v = np.asarray(values, float)
    ok = ~np.isnan(v)
    v = v[ok]
    labels = np.asarray([str(c) for c in np.asarray(clusters, object)[ok]])
    if v.size == 0:
        return float("nan"), float("nan")
    order = np.argsort(v, kind="stable")
    v, labels = v[order], labels[order]
    _, g = np.unique(labels, return_inverse=True)
    n = int(g.max()) + 1
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(n, np.full(n, 1.0 / n), size=resamples)  # (R, G): how often each cluster is drawn
    med = np.empty(resamples)
    chunk = max(1, 2_000_000 // v.size)  # resamples at a time, so that a large set stays within memory
    for a in range(0, resamples, chunk):
        cw = np.cumsum(counts[a:a + chunk, g], axis=1)  # cumulative weights over the sorted values
        half = cw[:, -1:] / 2.0
        lo = np.argmax(cw >= half, axis=1)  # the lower and upper middle values of each resample's multiset
        hi = np.argmax(cw > half, axis=1)
        med[a:a + chunk] = 0.5 * (v[lo] + v[hi])
    a = (1.0 - level) / 2.0
    return float(np.quantile(med, a)), float(np.quantile(med, 1.0 - a))


def interval_clause(rows) -> str:
    """" (95 % interval a-b mm, resampling its N poses)" for the median footprint error of ``rows``
    (:func:`median_interval` over :func:`pose_of`)."""
    lo, hi = median_interval([r.footprints_mm for r in rows], [pose_of(r) for r in rows])
    n = len({pose_of(r) for r in rows})
    return f" ({100 * INTERVAL_LEVEL:.0f} % interval {lo:.2f}-{hi:.2f} mm, resampling its {n} poses)"


def groups(rows):
    """{(anatomy, family, mismatch_mm): [rows]} in a stable order."""
    out = defaultdict(list)
    for r in rows:
        out[(r.anatomy, r.family, r.mismatch_mm)].append(r)
    return dict(sorted(out.items()))


def floor_clause(floors, mismatch_mm: float, rows) -> str:
    """What a perfect model reaches at one skin mismatch (:func:`knee.app.experiments.skin_floor.skin_floor`'s
    rows): the medians of its three floors and (iii)'s on the same cases, or "" when none was measured."""
    fl = [f for f in floors if f.mismatch_mm == mismatch_mm]
    if not fl:
        return ""
    mine = {r.case: r.footprints_mm for r in rows if r.method == "links" and not r.failed}
    ours = [mine[f.case] for f in fl if f.case in mine]
    return (f"; at {mismatch_mm:g} mm, on the {len(fl)} views also rendered at 0 mm, the truth's own skin registered rigidly gives "
            f"{_median(f.separate_mm for f in fl):.2f} mm with each bone read from its side of the knee and "
            f"{_median(f.joined_mm for f in fl):.2f} mm with the bones' relative pose known, "
            f"{_median(f.prior_mm for f in fl):.2f} mm with the prior's kinematics"
            + (f" ((iii) {_median(ours):.2f} mm there)" if ours else ""))


def targets(rows, floors=()) -> list[str]:
    """The issue's targets for (iii), each a line with met / NOT met and the figure measured; ``floors``
    (:func:`knee.app.experiments.skin_floor.skin_floor`'s rows) put what a perfect model reaches beside the
    skin mismatch targets."""
    ok = [r for r in rows if r.method == "links" and not r.failed]
    lines = []
    for lo, hi, target in ((0.0, 1.0, 2.0), (2.0, 2.0, 3.0)):
        sel = [r for r in ok if lo <= r.mismatch_mm <= hi]
        if sel:
            m = _median(r.footprints_mm for r in sel)
            what = "0 and 1 mm" if hi == 1.0 else "2 mm"
            lines.append(f"(iii) median footprint error at {what} skin mismatch: {m:.2f} mm over {len(sel)} cases"
                         + interval_clause(sel) + f" (target <= {target:g} mm): {'met' if m <= target else 'NOT met'}"
                         + floor_clause(floors, hi, ok))
    kin = {r.case: r for r in rows if r.method == "kinematics" and not r.failed}
    pairs = [(r, kin[r.case]) for r in ok if r.case in kin]
    if pairs:
        share = sum(a.footprints_mm < b.footprints_mm for a, b in pairs) / len(pairs)
        lines.append(f"(iii) lower than (iv) in {100 * share:.0f} % of {len(pairs)} cases (target >= 80 %): "
                     f"{'met' if share >= 0.8 else 'NOT met'}")
    if ok:
        m = _median(r.footprints_mm for r in ok)
        paper = sum(PAPER_FOOTPRINTS_MM) / 2
        lines.append(f"(iii) median footprint error over all cases {m:.2f} mm" + interval_clause(ok) + " against the paper's reported "
                     f"{paper:.2f} mm: {'lower' if m < paper else 'NOT lower'}")
        lines += flexion_targets(ok)
        lines += flexion_sd_calibration(ok)
        w = _median(r.wall_seconds for r in ok)
        cpu = [r.cpu_seconds for r in ok if math.isfinite(r.cpu_seconds)]
        lines.append(f"(iii) median time {w:.1f} s per case including the registration"
                     + (f" (CPU time {_median(cpu):.1f} s, every thread's)" if cpu else "")
                     + f" (target <= 5 s): {'met' if w <= 5 else 'NOT met'}")
    lines += estimate_fit(ok)
    lines += axial_disagreement(ok)
    failed = [r for r in rows if r.failed]
    if failed:
        lines.append(f"{len(failed)} runs failed (listed in the table)")
    return lines


def estimate_fit(rows, label: str = "(iii)") -> list[str]:
    """How well the subject's skin, posed at the estimated flexion, fits each view's points (the rows'
    ``estimate_rms_mm``; rows without it are left out): the median and the largest, the count within 2.5 mm,
    and the views over :data:`knee.models.prior.POOR_FIT_RMS_MM`, which the run warns of, worst first. A line
    starting with ``label``, or none where no row has the figure."""
    fit = sorted((r for r in rows if math.isfinite(getattr(r, "estimate_rms_mm", math.nan))),
                 key=lambda r: -r.estimate_rms_mm)
    if not fit:
        return []
    poor = [r for r in fit if r.estimate_rms_mm > POOR_FIT_RMS_MM]
    return [f"{label} the flexion estimate's fit to the points: median {_median(r.estimate_rms_mm for r in fit):.2f} mm "
            f"RMS over {len(fit)} views (largest {fit[0].estimate_rms_mm:.2f} mm), "
            f"{sum(r.estimate_rms_mm <= 2.5 for r in fit)} within 2.5 mm; "
            f"{len(poor)} over {POOR_FIT_RMS_MM:g} mm (warned of a poor fit)"
            + (": " + ", ".join(f"{getattr(r, 'case', '') or r.camera} {r.estimate_rms_mm:.1f} mm" for r in poor[:5])
               + (" ..." if len(poor) > 5 else "") if poor else "")]


#: What a run's notes say when the thigh's registration and the whole posed skin disagree about the femur's turn
#: (:attr:`knee.models.fem.methods.AxialPlacement.warning`).
AXIAL_WARNING = "the thigh's registration and the whole skin disagree"


def axial_disagreement(rows, label: str = "(iii)") -> list[str]:
    """The views whose run warned that the thigh's registration and the whole posed skin disagree about the
    femur's turn about the thigh's axis, with their footprint errors (the worse bone's), and how many of the
    other views ended as far off as the least of them: whether the warning tells the wrong matches apart. A line
    starting with ``label``, or none where no row has footprint errors."""
    ok = [r for r in rows if math.isfinite(r.femur_footprints_mm) and math.isfinite(r.tibia_footprints_mm)]
    if not ok:
        return []
    worse = {id(r): max(r.femur_footprints_mm, r.tibia_footprints_mm) for r in ok}
    warned = sorted((r for r in ok if AXIAL_WARNING in r.notes), key=lambda r: -worse[id(r)])
    if not warned:
        return [f"{label} no view warned that the thigh and the whole skin disagree about the femur's turn"]
    least = worse[id(warned[-1])]
    others = sum(worse[id(r)] >= least for r in ok if AXIAL_WARNING not in r.notes)
    spread = (f"{least:.1f} mm" if len(warned) == 1 else f"{least:.1f}-{worse[id(warned[0])]:.1f} mm (median "
              f"{_median(worse[id(r)] for r in warned):.1f})")
    return [f"{label} {len(warned)} of {len(ok)} view{'' if len(ok) == 1 else 's'} warned that the thigh and the whole "
            f"skin disagree about the femur's turn: the worse bone's footprint error {spread}; {others} other "
            f"view{'' if others == 1 else 's'} as far off or further: "
            + ", ".join(f"{getattr(r, 'case', '') or r.camera} {worse[id(r)]:.1f} mm" for r in warned[:5])
            + (" ..." if len(warned) > 5 else "")]


#: What a run's notes say when the view cannot show the flexion (the flexion estimate's warnings, its fallback).
UNSEEN_WARNINGS = ("shank is hardly seen", "too little of the shank", "hardly changes with flexion",
                   "flexion is the skin fit's alone")


def warned_unseen(row) -> bool:
    """Whether a run warned that the camera shows too little of the shank to see the flexion."""
    return any(w in row.notes for w in UNSEEN_WARNINGS)


def flexion_targets(rows) -> list[str]:
    """The flexion target, split by what the camera truly saw of the shank (``shank_points_true``, from the
    truth's tibia): within 2 deg where it sees the shank (at least :data:`MIN_SEEN_SHANK` depth points on
    it); a warning where it does not."""
    err = {id(r): abs(r.flexion_estimated_deg - r.flexion_true_deg) for r in rows}
    seen = [r for r in rows if r.shank_points_true >= MIN_SEEN_SHANK]
    unseen = [r for r in rows if 0 <= r.shank_points_true < MIN_SEEN_SHANK]
    lines = []
    if seen:
        within = sum(err[id(r)] <= 2.0 for r in seen)
        off = [r for r in seen if err[id(r)] > 2.0]
        lines.append(f"(iii) flexion where the camera sees the shank ({len(seen)} cases, >= {MIN_SEEN_SHANK} depth points "
                     f"on it): median error {_median(err[id(r)] for r in seen):.2f} deg, {within} of {len(seen)} "
                     f"within 2 deg (target: all): {'met' if within == len(seen) else 'NOT met'}"
                     + (f"; of the {len(off)} further off, {sum(warned_unseen(r) for r in off)} warned that the view "
                        f"shows the flexion poorly" if off else ""))
    if unseen:
        warned = sum(warned_unseen(r) for r in unseen)
        lines.append(f"(iii) flexion where the camera hardly sees the shank ({len(unseen)} cases): median error "
                     f"{_median(err[id(r)] for r in unseen):.2f} deg; warned in {warned} of {len(unseen)} "
                     f"(target: all): {'met' if warned == len(unseen) else 'NOT met'}")
    return lines


def flexion_sd_calibration(rows, label: str = "(iii)") -> list[str]:
    """How well the flexion's own standard error (the rows' ``flexion_sd_deg``, from the fits that set it)
    tells each view's error, over the views that see the shank and have one: its median, and how many
    errors lie within one and two of their own standard errors (about 68 and 95 % where it tells them
    right; fewer: it claims too much). A line starting with ``label``, or none where no row has it."""
    sel = [r for r in rows if r.shank_points_true >= MIN_SEEN_SHANK and math.isfinite(r.flexion_sd_deg)]
    if not sel:
        return []
    z = {id(r): abs(r.flexion_estimated_deg - r.flexion_true_deg) / r.flexion_sd_deg for r in sel}

    def within(rs, k):
        return sum(z[id(r)] <= k for r in rs)

    line = (f"{label} the flexion's own standard error: median {_median(r.flexion_sd_deg for r in sel):.2f} deg over "
            f"{len(sel)} views that see the shank; the error within one of it in {within(sel, 1)} "
            f"({100 * within(sel, 1) / len(sel):.0f} %, 68 % if it is right), within two in "
            f"{within(sel, 2)} ({100 * within(sel, 2) / len(sel):.0f} %, 95 %)")
    levels = sorted({r.mismatch_mm for r in sel if math.isfinite(getattr(r, "mismatch_mm", math.nan))})
    if len(levels) > 1:  # it does not know how far the skin is off: by the skin mismatch
        by = [[r for r in sel if getattr(r, "mismatch_mm", math.nan) == v] for v in levels]
        line += (f"; at {' / '.join(f'{v:g}' for v in levels)} mm skin mismatch "
                 f"{' / '.join(f'{100 * within(rs, 1) / len(rs):.0f}' for rs in by)} % within one, "
                 f"{' / '.join(f'{100 * within(rs, 2) / len(rs):.0f}' for rs in by)} % within two")
    return [line]


def markdown(rows, methods, title: str, floors=()) -> str:
    """The medians per family and method, the targets (``floors``: as :func:`targets`), then every run."""
    out = [f"# {title}", "", "Medians per case family (mm, deg; footprints = mean of femur and tibia ACL/PCL "
           "footprint errors). The paper reports footprints "
           f"{PAPER_FOOTPRINTS_MM[0]} / {PAPER_FOOTPRINTS_MM[1]} mm and epiphyses {PAPER_EPIPHYSIS_MM[0]} / "
           f"{PAPER_EPIPHYSIS_MM[1]} mm (femur / tibia) on its own cases.", "",
           "| anatomy | family | skin mismatch | method | cases | failed | footprints | femur fp | tibia fp | "
           "epiphysis | flexion error | time (s) |", "|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for (anat, fam, mm), rs in groups(rows).items():
        for m in methods:
            sel = [r for r in rs if r.method == m]
            ok = [r for r in sel if not r.failed]
            if not sel:
                continue
            out.append(f"| {anat} | {fam} | {mm:g} mm | {NAMES.get(m, m)} | {len(ok)} | {len(sel) - len(ok)} | "
                       f"{_median(r.footprints_mm for r in ok):.2f} | {_median(r.femur_footprints_mm for r in ok):.2f} | "
                       f"{_median(r.tibia_footprints_mm for r in ok):.2f} | {_median(r.epiphysis_mm for r in ok):.2f} | "
                       f"{_median(abs(r.flexion_estimated_deg - r.flexion_true_deg) for r in ok):.2f} | "
                       f"{_median(r.wall_seconds for r in ok):.1f} |")
    out += ["", "## Targets", ""] + [f"- {line}" for line in targets(rows, floors)]
    out += ["", "## Every run", "", "| case | method | true flexion | estimate ± its standard error | femur fp | tibia fp | femur epi | "
            "tibia epi | time (s) | notes |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        if r.failed:
            out.append(f"| {r.case} | {NAMES.get(r.method, r.method)} | {r.flexion_true_deg:.1f} | failed: {r.failed} "
                       f"| | | | | | |")
            continue
        out.append(f"| {r.case} | {NAMES.get(r.method, r.method)} | {r.flexion_true_deg:.1f} | "
                   f"{flexion_cell(r)} | {r.femur_footprints_mm:.2f} | {r.tibia_footprints_mm:.2f} | "
                   f"{r.femur_epiphysis_mm:.2f} | {r.tibia_epiphysis_mm:.2f} | {r.wall_seconds:.1f} | "
                   f"{r.notes[:160].replace('|', '/')} |")
    return "\n".join(out) + "\n"


def plot(rows, methods, path, title: str = "") -> None:
    """Footprint error per case, one panel per anatomy x family, methods side by side, grouped by skin
    mismatch; the paper's reported figure as a line."""
    panels = sorted({(r.anatomy, r.family) for r in rows})
    n = max(1, len(panels))
    fig, axes = plt.subplots(1, n, figsize=(4.6 * n, 4.2), squeeze=False, sharey=True)
    colours = {"paper": "tab:gray", "init": "tab:orange", "links": "tab:blue", "kinematics": "tab:green"}
    for ax, (anat, fam) in zip(axes[0], panels):
        mms = sorted({r.mismatch_mm for r in rows if (r.anatomy, r.family) == (anat, fam)})
        for k, m in enumerate(methods):
            for i, mm in enumerate(mms):
                v = [r.footprints_mm for r in rows if (r.anatomy, r.family, r.mismatch_mm, r.method) == (anat, fam, mm, m)
                     and not r.failed]
                x = i + (k - (len(methods) - 1) / 2) * 0.18
                ax.scatter(np.full(len(v), x), v, s=14, color=colours.get(m), alpha=0.8,
                           label=NAMES.get(m, m) if i == 0 else None)
                if v:
                    ax.plot([x - 0.07, x + 0.07], [np.median(v)] * 2, color=colours.get(m), lw=2)
        ax.axhline(sum(PAPER_FOOTPRINTS_MM) / 2, color="k", ls=":", lw=1, label="paper's reported")
        ax.set_xticks(range(len(mms)), [f"{mm:g} mm" for mm in mms])
        ax.set_xlabel("skin mismatch (RMS)")
        ax.set_title(f"{anat}\n{fam}", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("footprint error (mm)")
    axes[0][0].legend(fontsize=7)
    top = max([r.footprints_mm for r in rows if not r.failed and math.isfinite(r.footprints_mm)] or [10.0])
    axes[0][0].set_ylim(0, min(top * 1.05, 40.0))
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_floor(floors, errors: dict, path, label: str = "(iii) links") -> None:
    """A method's footprint error per case (``errors``: {case: mm}) against the skin mismatch's floors on
    that case (:func:`knee.app.experiments.skin_floor.skin_floor`'s rows): each bone read from its side
    of the knee (filled), the leg as one body with the bones' relative pose known (open) and with the
    prior's kinematics (crosses), coloured by the mismatch; on the diagonal the method is exactly at the
    floor."""
    fig, ax = plt.subplots(figsize=(5.2, 4.8))
    colours = {1.0: "tab:blue", 2.0: "tab:red"}
    top = 1.0
    for mm in sorted({f.mismatch_mm for f in floors}):
        fl = [f for f in floors if f.mismatch_mm == mm and f.case in errors]
        y = [errors[f.case] for f in fl]
        c = colours.get(mm, "tab:gray")
        ax.scatter([f.separate_mm for f in fl], y, s=22, color=c, label=f"{mm:g} mm: each bone from its side")
        ax.scatter([f.joined_mm for f in fl], y, s=22, facecolors="none", edgecolors=c,
                   label=f"{mm:g} mm: bones' relative pose known")
        ax.scatter([f.prior_mm for f in fl], y, s=22, marker="x", color=c, label=f"{mm:g} mm: the prior's kinematics")
        top = max([top, *y, *(f.separate_mm for f in fl), *(f.prior_mm for f in fl if np.isfinite(f.prior_mm))])
    ax.plot([0, top * 1.05], [0, top * 1.05], color="k", lw=1, ls=":")
    ax.set_xlim(0, top * 1.05)
    ax.set_ylim(0, top * 1.05)
    ax.set_xlabel("floor: the truth's own skin registered rigidly (mm)")
    ax.set_ylabel(f"{label} footprint error (mm)")
    ax.set_title("Footprint error against the skin mismatch's floor", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_flexion_floor(floors, errors: dict, path, label: str = "(iii) links",
                       min_seen: int = MIN_SEEN_SHANK) -> None:
    """A method's signed flexion error per view (``errors``: {case: deg}) against what the model's own skin
    reads with every other step exact (:func:`knee.app.experiments.skin_floor.tissue_floor`'s rows: the femur's
    floor with the tibia's on the FEM-posed shank), over the views that see the shank, one marker per camera
    and a colour per anatomy; the shaded band is the flexion target's 2 deg either side. A miss outside the
    band on both axes is one the model's skin makes too; one outside it only upwards or downwards is the
    method's own."""
    fig, ax = plt.subplots(figsize=(5.6, 5.0))
    seen = [f for f in floors if f.shank_points_true >= min_seen and f.case in errors]
    lim = max([4.0, *(abs(f.flexion_error_deg) for f in seen), *(abs(errors[f.case]) for f in seen)]) * 1.1
    ax.axhspan(-2.0, 2.0, color="tab:green", alpha=0.12, lw=0)
    ax.axvspan(-2.0, 2.0, color="tab:green", alpha=0.12, lw=0)
    markers = {"paper": "o", "frontal": "s", "lateral": "^"}
    anatomies = sorted({f.anatomy for f in seen})
    colours = dict(zip(anatomies, ("tab:blue", "tab:red", "tab:purple", "tab:orange", "tab:gray")))
    for a in anatomies:
        for cam in sorted({f.camera for f in seen if f.anatomy == a}):
            g = [f for f in seen if f.anatomy == a and f.camera == cam]
            ax.scatter([f.flexion_error_deg for f in g], [errors[f.case] for f in g], s=20, alpha=0.8,
                       color=colours[a], marker=markers.get(cam, "D"), label=f"{a}, {cam}")
    ax.plot([-lim, lim], [-lim, lim], color="k", lw=1, ls=":")
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_xlabel("the model's own skin, every other step exact: flexion error (deg)")
    ax.set_ylabel(f"{label} flexion error (deg)")
    ax.set_title("Flexion error against what the model's skin reads", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def stage_summary(records, stages, min_seen: int = MIN_SEEN_SHANK) -> dict:
    """Method (iii)'s error stage by stage (``scripts/diagnose_case_set.py``'s rows: dicts with ``anatomy``,
    ``stage``, ``mismatch_mm``, ``footprints_mm``, ``flexion_deg``, ``flexion_true_deg``, ``shank_points_true``),
    per anatomy and skin mismatch: {(anatomy, mm): {"median", "q1", "q3": footprint error (mm) per stage,
    "within": the share of the views that see the shank with the flexion within 2 deg per stage, "cases"}};
    a stage no row has is NaN."""
    out = {}
    for key in sorted({(r["anatomy"], float(r["mismatch_mm"])) for r in records}):
        g = [r for r in records if (r["anatomy"], float(r["mismatch_mm"])) == key]
        d = {"median": [], "q1": [], "q3": [], "within": [], "cases": len({r.get("key", r["case"]) for r in g})}
        for stage in stages:
            v = np.array([r["footprints_mm"] for r in g if r["stage"] == stage], float)
            v = v[np.isfinite(v)]
            q = np.percentile(v, [25, 50, 75]) if len(v) else np.full(3, np.nan)
            d["q1"].append(float(q[0]))
            d["median"].append(float(q[1]))
            d["q3"].append(float(q[2]))
            seen = [r for r in g if r["stage"] == stage and r["shank_points_true"] >= min_seen]
            d["within"].append(sum(abs(r["flexion_deg"] - r["flexion_true_deg"]) <= 2.0 for r in seen) / len(seen)
                               if seen else float("nan"))
        out[key] = d
    return out


def plot_stages(records, stages, path, min_seen: int = MIN_SEEN_SHANK, title: str = "") -> dict:
    """Method (iii)'s error stage by stage (:func:`stage_summary`), a column per anatomy: above, the median
    footprint error with its interquartile band, a line per skin mismatch, beside the 2 and 3 mm targets;
    below, the share of the views that see the shank with the flexion within 2 deg. Returns the summary."""
    data = stage_summary(records, stages, min_seen)
    anatomies = sorted({a for a, _ in data})
    n = max(1, len(anatomies))
    fig, axes = plt.subplots(2, n, figsize=(4.6 * n, 6.4), squeeze=False, sharex=True, sharey="row",
                             gridspec_kw={"height_ratios": [2, 1]})
    colours = {0.0: "tab:green", 1.0: "tab:blue", 2.0: "tab:red"}
    x = np.arange(len(stages))
    for col, a in enumerate(anatomies):
        top, bottom = axes[0][col], axes[1][col]
        for (anat, mm), d in data.items():
            if anat != a:
                continue
            c = colours.get(mm, "tab:gray")
            top.plot(x, d["median"], marker="o", color=c, label=f"{mm:g} mm ({d['cases']} cases)")
            top.fill_between(x, d["q1"], d["q3"], color=c, alpha=0.12, lw=0)
            bottom.plot(x, 100.0 * np.asarray(d["within"]), marker="o", color=c)
        for level, ls in ((2.0, "--"), (3.0, ":")):
            top.axhline(level, color="k", lw=1, ls=ls)
        top.set_title(a, fontsize=10)
        top.grid(alpha=0.3)
        top.legend(fontsize=7, title="skin mismatch", title_fontsize=7)
        bottom.set_ylim(0, 105)
        bottom.grid(alpha=0.3)
        bottom.set_xticks(x, [s.replace("_", " ") for s in stages], rotation=30, fontsize=8)
    axes[0][0].set_ylabel("footprint error (mm): median, quartiles")
    axes[1][0].set_ylabel("flexion within 2 deg (%)")
    axes[0][0].set_ylim(bottom=0)
    fig.suptitle(title or "Method (iii) stage by stage (targets: 2 mm at 0-1 mm, 3 mm at 2 mm)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110, format="png")
    plt.close(fig)
    return data


class CaseSetRecorder:
    """``on_result`` callback of :func:`knee.app.experiments.case_set.run_case_set` writing the recording
    (layout: the module docstring). Each bone's mesh is logged when its anatomy's first case comes (and
    again after a failed run cleared it); every case then only moves it, so the file holds two meshes per
    bone and entity, not one per case."""

    def __init__(self, path, methods):
        self.rec = R.new_recording()
        R.save(self.rec, path, compare_blueprint(methods))
        self.rec.log("compare", rr.ViewCoordinates.RDF, static=True)
        self.case, self.index, self.shown = None, -1, False
        self.meshes = {}  # entity -> the anatomy whose mesh it holds now

    def _place(self, entity: str, anatomy, bone: str, T, colour) -> None:
        if self.meshes.get(entity) != anatomy.name:
            mesh = getattr(anatomy, bone)
            self.rec.log(f"{entity}/mesh", rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices, np.float32),
                                                     triangle_indices=np.asarray(mesh.faces, np.uint32),
                                                     albedo_factor=colour))
            self.meshes[entity] = anatomy.name
        self.rec.log(entity, rr.Transform3D(translation=np.asarray(T, float)[:3, 3], mat3x3=np.asarray(T, float)[:3, :3]))

    def __call__(self, case: dict, anatomy, method: str, points_cam, truth, estimate, row) -> None:
        if case["id"] != self.case:
            self.case, self.index, self.shown = case["id"], self.index + 1, False
            self.rec.set_time("case", sequence=self.index)
            self.rec.log("compare/case", rr.TextDocument(
                f"{case['id']}: {case['family']}, true flexion {float(case['flexion_deg']):.1f} deg, skin mismatch "
                f"{float(case['mismatch_mm']):g} mm, camera {case['camera']}"))
            self.rec.log("compare/depth", rr.Clear(recursive=False))
        self.rec.set_time("case", sequence=self.index)
        if points_cam is not None and not self.shown:  # the first run of the case that did not fail
            self.shown = True
            self.rec.log("compare/depth", rr.Points3D(voxel_downsample(np.asarray(points_cam, float), VOXEL_MM),
                                                      colors=(150, 150, 150), radii=0.8))
            for bone in ("femur", "tibia"):
                self._place(f"compare/truth/{bone}", anatomy, bone, truth[bone], (235, 235, 235, 120))
        if estimate is None:  # a failed run: its bones are not shown at this case
            self.rec.log(f"compare/{method}", rr.Clear(recursive=True))
            for bone in ("femur", "tibia"):
                self.meshes.pop(f"compare/{method}/{bone}", None)
            return
        for bone in ("femur", "tibia"):
            self._place(f"compare/{method}/{bone}", anatomy, bone, estimate[bone], METHOD_COLOURS.get(method, (128, 128, 128)))
        self.rec.log(f"metrics/{method}/footprints_mm", rr.Scalars(row.footprints_mm))

    def finish(self) -> None:
        R.close(self.rec)


def plot_placement_floor(rows, path) -> dict:
    """The femur's tissue floor under each placement of the grid (:func:`knee.app.experiments.skin_floor.placement_floor`'s
    rows), a panel per anatomy: each case's floor against the grid's offset (thin lines), their median (thick), a
    colour per grid (cells across) and a line style per skin mismatch. Flat lines: the answer does not depend on
    where the cells fall. Returns :func:`knee.app.experiments.skin_floor.placement_spread`'s summary."""
    summary = placement_spread(rows)
    anatomies = sorted({r.anatomy for r in rows})
    grids = sorted({r.cells_across for r in rows})
    colours = dict(zip(grids, ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:orange", "tab:gray")))
    styles = {0.0: "-", 1.0: "--", 2.0: ":"}
    n = max(1, len(anatomies))
    fig, axes = plt.subplots(1, n, figsize=(4.8 * n, 4.2), squeeze=False, sharey=True)
    for ax, a in zip(axes[0], anatomies):
        for (anatomy, cells, mm), d in summary.items():
            if anatomy != a:
                continue
            ls = styles.get(mm, "-.")
            for view in d["table"]:
                ax.plot(d["offsets"], view, color=colours[cells], ls=ls, lw=0.7, alpha=0.35)
            ax.plot(d["offsets"], d["median"], color=colours[cells], ls=ls, lw=2.2,
                    label=f"{cells} across, {mm:g} mm: spread {d['spread']:.2f} mm ({d['cases']} views)")
        ax.set_title(a, fontsize=10)
        ax.set_xlabel("the grid moved by (fraction of a cell)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("the femur's tissue floor: footprint error (mm)")
    fig.suptitle("The femur placed on the model's posed skin, every other step exact, by the grid's placement",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110, format="png")
    plt.close(fig)
    return summary
