"""``knee osteotomy MODEL --angle A``: a virtual osteotomy, its alignment, kinematics and contact in gait
before and after (:mod:`knee.models.osteotomy`, :mod:`knee.app.reports.osteotomy`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from knee.app.console import numbers, out_dir
from knee.app.reports.osteotomy import plot, report_markdown, write_recording
from knee.foundations.errors import KneeInputError
from knee.foundations.files import staged_folder
from knee.models.gait import normative_trial, read_gait_csv
from knee.models.mechanism.params import load_model, save_toml
from knee.models.osteotomy import Cut, compare, default_cut, osteotomy
from knee.models.phantom import build_phantom


def _six(text: str, what: str) -> tuple[np.ndarray, np.ndarray]:
    v = numbers(text, 6, what, " (point x,y,z then direction x,y,z in mm)")
    return v[:3], v[3:]


def run(args) -> int:
    model_file = Path(args.model) if Path(args.model).is_file() else None
    trial_file = Path(args.trial) if args.trial else None
    out = out_dir(args.out, args.force, inputs=(model_file, trial_file))
    params = load_model(args.model)
    if not math.isfinite(args.angle):
        raise KneeInputError(f"--angle must be a number of degrees, got {args.angle}")
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
    with staged_folder(out) as tmp:
        (tmp / "report.md").write_text(md, encoding="utf-8")
        plot(cut, res, cmp, tmp / "osteotomy.png")
        write_recording(cut, res, tmp / "osteotomy.rrd")
        save_toml(res.params, tmp / "after.toml", overwrite=True)
    ab, aa = res.align_before, res.align_after
    print(f"{params.name}: {args.bone} osteotomy {args.angle:+g} deg; moved: {', '.join(res.moved) or 'nothing'}")
    print(f"HKA deviation {ab.hka_deg:+.2f} -> {aa.hka_deg:+.2f} deg (+ varus); weight-bearing line "
          f"{ab.wbl_percent:.1f} -> {aa.wbl_percent:.1f} % of the plateau (target 62.5 %)")
    print(f"report: {out / 'report.md'}\nplot: {out / 'osteotomy.png'}\nparameters after: {out / 'after.toml'}\n"
          f"recording: {out / 'osteotomy.rrd'}  (open with: rerun {out / 'osteotomy.rrd'})")
    return 0
