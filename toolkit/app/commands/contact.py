"""``knee contact MODEL``: contact area and peak pressure against flexion under an axial load (seed 001
Fig. 3d), as CSV and PNG."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from knee.app.console import out_dir
from knee.app.views.clinical import plot_contact
from knee.foundations.errors import KneeInputError
from knee.foundations.files import staged_folder
from knee.models.contact import contact_along_flexion
from knee.models.mechanism import Mechanism


def run(args) -> int:
    if not (args.load > 0 and math.isfinite(args.load)):
        raise KneeInputError(f"--load must be a positive number of N, got {args.load}")
    model_file = Path(args.model) if Path(args.model).is_file() else None
    out = out_dir(args.out, args.force, inputs=(model_file,))
    mech = Mechanism.from_name(args.model)
    res = contact_along_flexion(mech, args.load)
    with staged_folder(out) as tmp:
        _write(tmp, mech, res, args.load)
    print(f"contact of {mech.params.name} under {args.load:g} N: {out / 'contact.csv'}, {out / 'contact.png'}")
    return 0


def _write(out: Path, mech, res, load: float) -> None:
    plot_contact(res, out / "contact.png", f"{mech.params.name}: {load:g} N along the tibia")
    with (out / "contact.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        names = list(res.contacts)
        w.writerow(["flexion_deg"] + [f"{n}_{q}" for n in names for q in ("force_N", "hertz_area_mm2",
                                                                          "hertz_peak_MPa", "foundation_area_mm2",
                                                                          "foundation_peak_MPa")])
        for i, fl in enumerate(res.flexion_deg):
            row = [fl]
            for n in names:
                c = res.contacts[n]
                row += [c.force[i], c.hertz.area[i], c.hertz.peak[i], c.foundation.area[i], c.foundation.peak[i]]
            w.writerow([f"{v:.6g}" for v in row])
