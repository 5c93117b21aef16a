"""The depth image's flying pixels (``knee.foundations.pointclouds.mixed_pixels``, once per depth image read):
each neighbour pair's step computed once and given to both pixels, within the seen pixels' bounding box,
against the baseline of eight whole-image shifts (the rule before: every pixel against each of its eight
neighbours, over the whole image), on a case set's depth images (``scripts/build_case_set.py``). The two
alternate image by image (the order swapped each time) so that a shared machine's load falls on both alike,
and each image's two answers must be the same pixels.

Prints each image (its size, its seen share, both times), then the medians: wall and CPU time an image and
the per-image ratio.

    .venv/bin/python scripts/bench_depth_edges.py CASE_SET [--every 6] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path


def eight_shifts(depth, K, footprints: float, support: int):
    """The baseline: each pixel against each of its eight neighbours by a whole-image shift of a NaN-padded
    copy, both pixels of a pair computed separately."""
    import numpy as np

    d = np.asarray(depth, dtype=float)
    f = 0.5 * (K[0, 0] + K[1, 1])
    seen = np.isfinite(d) & (d > 0)
    z = np.where(seen, d, np.nan)
    padded = np.pad(z, 1, constant_values=np.nan)
    h, w = d.shape
    worst = np.zeros_like(d)
    smooth = np.zeros(d.shape, np.int8)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            if dv or du:
                other = padded[1 + dv:1 + dv + h, 1 + du:1 + du + w]
                step = np.abs(other - z) / (np.fmin(other, z) / f)
                worst = np.fmax(worst, np.where(np.isnan(step), 0.0, step))
                smooth += step <= footprints
    return seen & (worst > footprints) & (smooth < support)


def main() -> int:
    from knee.app.console import at_least
    from knee.foundations.errors import KneeError

    ap = argparse.ArgumentParser()
    ap.add_argument("cases")
    ap.add_argument("--every", type=at_least(1), default=6, help="every n-th case (default 6: 10 of a 60-case set)")
    ap.add_argument("--repeats", type=at_least(1), default=5, help="timed runs of each image, each way (default 5)")
    args = ap.parse_args()
    try:
        rows = run(Path(args.cases), args.every, args.repeats)
    except KneeError as e:
        print(f"bench_depth_edges: {e}", file=sys.stderr)
        return 2
    med = statistics.median
    print(f"\n{len(rows)} images: pairs once, in the seen box {med(r['new_wall'] for r in rows) * 1e3:.1f} ms "
          f"(CPU {med(r['new_cpu'] for r in rows) * 1e3:.1f} ms), eight whole-image shifts "
          f"{med(r['old_wall'] for r in rows) * 1e3:.1f} ms (CPU {med(r['old_cpu'] for r in rows) * 1e3:.1f} ms); "
          f"ratio wall {med(r['new_wall'] / r['old_wall'] for r in rows):.3f}, "
          f"CPU {med(r['new_cpu'] / r['old_cpu'] for r in rows):.3f}; the same pixels in every image")
    return 0


def run(folder: Path, every: int, repeats: int) -> list[dict]:
    import numpy as np

    from knee.app.experiments.case_set import case_intrinsics, read_case_set
    from knee.foundations.errors import KneeError
    from knee.foundations.pointclouds import EDGE_FOOTPRINTS, EDGE_SUPPORT, mixed_pixels

    def timed(fn, *a):
        t, c = time.perf_counter(), time.process_time()
        out = fn(*a)
        return out, time.perf_counter() - t, time.process_time() - c

    rows = []
    for case in read_case_set(folder)["case"][::every]:
        K = case_intrinsics(case)
        depth = np.load(folder / case["depth"]).astype(float)
        times = {"new": ([], []), "old": ([], [])}
        for i in range(repeats):
            order = (("new", mixed_pixels), ("old", eight_shifts)) if i % 2 == 0 else \
                (("old", eight_shifts), ("new", mixed_pixels))
            answers = {}
            for name, fn in order:
                answers[name], wall, cpu = timed(fn, depth, K, EDGE_FOOTPRINTS, EDGE_SUPPORT)
                times[name][0].append(wall)
                times[name][1].append(cpu)
            if not np.array_equal(answers["new"], answers["old"]):
                raise KneeError(f"{case['id']}: the two ways find different flying pixels "
                                f"({int(np.sum(answers['new'] != answers['old']))} pixels differ)")
        r = {f"{k}_{m}": statistics.median(v[j]) for k, v in times.items() for j, m in enumerate(("wall", "cpu"))}
        rows.append(r)
        print(f"{case['id']}: {depth.shape[1]}x{depth.shape[0]}, {np.mean(depth > 0):.0%} seen, "
              f"{int(answers['new'].sum())} flying; new {r['new_wall'] * 1e3:.1f} ms, old {r['old_wall'] * 1e3:.1f} ms",
              flush=True)
    return rows


if __name__ == "__main__":
    sys.exit(main())
