"""The four methods of the kinematic-prior comparison on the standard cases (issue "kinematic priors for
the FEM", section 3), as recorded in BENCHMARKS.md: truth `volunteer`, prior = `volunteer` with every TF
link endpoint moved 1-2 mm (seed 3), depth noise on; the oblique camera at 30:120:15 and the frontal and
lateral cameras at 30:120:30, the two sets in parallel (one process per core). Each set is a
`knee compare` run; its table, plot and recording go to OUT/oblique and OUT/frontal-lateral.

    .venv/bin/python scripts/compare_priors.py [--out compare-priors]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
from pathlib import Path

SETS = {"oblique": ["--flexion", "30:120:15", "--cameras", "oblique"],
        "frontal-lateral": ["--flexion", "30:120:30", "--cameras", "frontal,lateral"]}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="compare-priors")
    args = ap.parse_args()
    out = Path(args.out)
    taken = [out / name for name in SETS if (out / name).exists()]
    if out.exists() and not out.is_dir() or taken:
        print(f"error: {out if not taken else taken[0]} exists; not overwritten (give a new --out)", file=sys.stderr)
        return 2
    from knee.app.console import take_terminations_as_interrupts

    # Ctrl-C handled here even when started with it ignored (in the background): the runs started below then
    # take it too, and each removes its unfinished output; a kill or a time limit does the same
    signal.signal(signal.SIGINT, signal.default_int_handler)
    take_terminations_as_interrupts()
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    procs = {name: subprocess.Popen([sys.executable, "-m", "knee.app.cli", "compare", "volunteer", *extra, "--quiet",
                                     "--out", str(out / name)], env=env, stdout=subprocess.PIPE, text=True)
             for name, extra in SETS.items()}
    failed = 0
    try:
        for name, p in procs.items():
            text, _ = p.communicate()
            print(f"## {name}\n{text}")
            failed |= p.returncode
    except KeyboardInterrupt:
        failed = 130
        print("compare_priors: interrupted; the runs stopped, no results written", file=sys.stderr)
    finally:
        # interrupted (Ctrl-C): the runs are stopped too, and each removes its unfinished output
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
    return failed


if __name__ == "__main__":
    sys.exit(main())
