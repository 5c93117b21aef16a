"""Build the FEM benchmark's case set (issue "an honest benchmark of the FEM methods") deterministically
from a seed, then run it with ``knee compare CASE_SET --out OUT``.

    .venv/bin/python scripts/build_case_set.py --out cases [--seed 0] [--data ../shared/data]
        [--anatomies phantom,visible-human-male] [--families mechanism+deviation,measured] [--patella]
        [--flying 0.5] [--noise-correlation 3] [--hole-size 4] [--noise-sigma 1.6] [--skin-band 1]
        [--truth-edge 0.05]

Without the data folder, only the phantom's mechanism cases are built. The cases, the truth and what the
methods are given: :mod:`knee.app.experiments.case_set`. About 2-5 min on 2 cores (the truth skins).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main() -> int:
    from knee.app.experiments.case_set import TRUTH_EDGE_WIDTHS, VH_SKIN_BAND_WIDTHS

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    ap.add_argument("--anatomies", default="phantom,visible-human-male",
                    help="any of phantom, visible-human-male, lenhart2015 (its MRI bones with the Visible Human's "
                         "skin carried over), comma-separated")
    ap.add_argument("--families", default="mechanism+deviation,measured")
    ap.add_argument("--skin-band", type=float, default=VH_SKIN_BAND_WIDTHS, metavar="WIDTHS",
                    help="how far (femur widths) either side of the joint line the Visible Human's skin and bones "
                         f"are kept ({VH_SKIN_BAND_WIDTHS:g}; 1 stands for a short scan)")
    ap.add_argument("--patella", action="store_true",
                    help="the truth's tissue holds the subject's patella, moved by the truth mechanism's PF motion")
    ap.add_argument("--flying", type=float, default=0.0,
                    help="share (0-1) of the pixels within two of each depth edge that return a blend of the "
                         "surfaces on either side, as a depth camera's flying pixels (0)")
    ap.add_argument("--noise-correlation", type=float, default=0.0, metavar="PX",
                    help="the width (pixels) over which neighbouring pixels' depth errors are correlated, as a "
                         "stereo camera's matching window makes them (0: each pixel's own)")
    ap.add_argument("--hole-size", type=float, default=0.0, metavar="PX",
                    help="the lost pixels (2 %%) come in blobs about this many pixels across (0: one by one)")
    ap.add_argument("--noise-sigma", type=float, default=1.0, metavar="MM",
                    help="the depth error's standard deviation at 400 mm, growing with the square of the depth (1)")
    ap.add_argument("--truth-edge", type=float, default=TRUTH_EDGE_WIDTHS, metavar="WIDTHS",
                    help="the truth tissue's node spacing in femur widths "
                         f"({TRUTH_EDGE_WIDTHS:g}; finer is closer to its converged answer and slower: at 0.05 a "
                         "pose flexed to 90 deg takes several minutes)")
    args = ap.parse_args()
    from knee.app.experiments.case_set import build_case_set
    from knee.app.console import say, take_terminations_as_interrupts
    from knee.foundations.errors import KneeError
    from knee.foundations.files import staged_folder

    out = Path(args.out)
    if out.exists():
        print(f"build_case_set: {out} exists; not overwritten", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    take_terminations_as_interrupts()  # a kill or a time limit leaves no partial set either
    try:
        with staged_folder(out) as tmp:
            build_case_set(tmp, args.seed, args.data if Path(args.data).is_dir() else None,
                           tuple(a.strip() for a in args.anatomies.split(",") if a.strip()),
                           tuple(f.strip() for f in args.families.split(",") if f.strip()),
                           progress=lambda s: say(f"[{time.perf_counter() - t0:5.0f} s] {s}"), patella=args.patella,
                           flying=args.flying, correlation_px=args.noise_correlation, hole_px=args.hole_size,
                           sigma_mm=args.noise_sigma, skin_band=args.skin_band, truth_edge=args.truth_edge)
    except KneeError as e:
        print(f"build_case_set: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"build_case_set: interrupted; {out} not written", file=sys.stderr)
        return 130
    print(f"case set: {out} ({time.perf_counter() - t0:.0f} s); run it with: knee compare {out} --out OUT")
    return 0


if __name__ == "__main__":
    sys.exit(main())
