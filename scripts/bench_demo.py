"""Wall time of `knee demo` end to end (issue "kinematic priors for the FEM": within 60 s on this 2-core
machine), against a baseline measured in the same run: the demo's three methods (the paper's, the
prior with its links, the mechanism alone) one after another in one process, as the demo would take
without its two worker processes.

    .venv/bin/python scripts/bench_demo.py [--runs 2]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BASELINE = """
import time
from knee.app.demo import DEMO_METHODS, run_demo_method
t = time.perf_counter()
for m in DEMO_METHODS:
    run_demo_method(m, 60.0, 3, 2.0)
print(time.perf_counter() - t)
"""


def timed(cmd) -> float:
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"failed: {' '.join(map(str, cmd))}\n{p.stderr[-2000:]}")
    return time.perf_counter() - t


def main():
    from knee.app.console import at_least

    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=at_least(1), default=2, help="demo runs (2)")
    args = ap.parse_args()
    demo = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            print(f"knee demo, run {i + 1} of {args.runs} ...", file=sys.stderr, flush=True)
            demo.append(timed([sys.executable, "-m", "knee.app.cli", "demo", "--out", str(Path(tmp) / f"demo{i}")]))
    print("baseline: the three methods one after another ...", file=sys.stderr, flush=True)
    base = timed([sys.executable, "-c", BASELINE])
    med = statistics.median(demo)
    print("| configuration | runs | median wall | ratio to baseline |\n|---|---:|---:|---:|")
    print(f"| `knee demo` ((i) and (iii)+(iv) in two processes, the sweep alongside) | {len(demo)} | {med:.1f} s | "
          f"{base / med:.2f}× |")
    print(f"| baseline: (i), (iii), (iv) in one process, one after another | 1 | {base:.1f} s | 1.00× |")
    print(f"target 60 s: {'met' if med <= 60.0 else 'NOT met'} (runs: {', '.join(f'{t:.1f}' for t in demo)} s)")


if __name__ == "__main__":
    main()
