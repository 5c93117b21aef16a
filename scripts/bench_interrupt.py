"""How fast Ctrl-C stops ``knee demo`` while its FEM workers run: SIGINT is sent once the demo says it is
sweeping (its two worker processes then run the FEM cases), and the times to the error line and to the
process's end are measured. Baseline in the same run: the same demo left to finish, from that moment.

    .venv/bin/python scripts/bench_interrupt.py [--runs 3]
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run(interrupt: bool) -> tuple[float, float, int]:
    """(seconds to the error line or None, seconds to the end, exit code), from the 'sweeping' line."""
    with tempfile.TemporaryDirectory() as tmp:
        p = subprocess.Popen([sys.executable, "-m", "knee.app.cli", "demo", "--out", str(Path(tmp) / "d")],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        err = b""
        while b"sweeping" not in err and p.poll() is None:
            if select.select([p.stderr], [], [], 0.05)[0]:
                err += os.read(p.stderr.fileno(), 4096)
        t0 = time.monotonic()
        line = float("nan")
        if interrupt:
            p.send_signal(signal.SIGINT)
            while b"interrupted" not in err and p.poll() is None:
                if select.select([p.stderr], [], [], 0.01)[0]:
                    err += os.read(p.stderr.fileno(), 4096)
            line = time.monotonic() - t0
        p.communicate()
        return line, time.monotonic() - t0, p.returncode


def main() -> None:
    from knee.app.console import at_least

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=at_least(1), default=3)
    args = ap.parse_args()
    stops = [run(True) for _ in range(args.runs)]
    base = run(False)
    assert all(code == 130 for _, _, code in stops) and base[2] == 0
    line = statistics.median(s[0] for s in stops)
    end = statistics.median(s[1] for s in stops)
    print("| what | median (s) | ratio to baseline |\n|---|---:|---:|")
    print(f"| Ctrl-C during the FEM: the error line | {line:.2f} | {line / base[1]:.3f} |")
    print(f"| Ctrl-C during the FEM: the process ends | {end:.2f} | {end / base[1]:.3f} |")
    print(f"| baseline: the demo left to finish, from the same moment | {base[1]:.2f} | 1 |")


if __name__ == "__main__":
    main()
