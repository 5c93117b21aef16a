"""Method (iii)'s time per case on a machine shared with other work: the same cases of a case set
(``scripts/build_case_set.py``) run with 0, 1 or 2 busy processes (single-threaded loops) holding the cores
beside them, and with the libraries' default threads, a set number (``OMP_NUM_THREADS`` and the BLAS
variables) or ``auto``, the ``knee`` command's rule (:func:`knee.app.threads.set_threads`: the cores the
one-minute load average leaves free; the busy processes run until the load average shows them, up to
``--settle`` seconds, before such a run starts; the count given is reported). Each setting runs
in its own process (as a user's ``knee fem`` would), the settings alternated over ``--rounds`` so that a
drift of the machine falls on all of them alike. Per setting: the median wall time per case, its CPU time
(every thread's: what the case costs the machine, which the load does not change), the slowest case, each
round's median, and the ratio of the median to the baseline measured in the same run (no load, default
threads, the first grid); and the largest change of any case's footprint error between settings of the same
grid (the answer should not depend on the threads or the load). ``--grids`` times the association model's
grid choices side by side (``default`` the model's, ``knee`` sized by the knee, or N cells each way: as
``knee compare --cells-across``), each against the same baseline.

    .venv/bin/python scripts/bench_loaded.py CASE_SET [--cases 10] [--loads 0,1,2] [--threads default,1,auto]
        [--grids default,knee] [--rounds 2] [--settle 120] [--csv OUT.csv]

The cases are ``--cases`` of the set's views at the paper's placement, evenly spaced over the set. About
2-3 minutes per setting and round with 10 cases (12 runs with the defaults: 25-30 minutes).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time

#: The busy process: one core held by a loop that never sleeps.
BUSY = "while True: pass"


def listed(item):
    """An ``argparse`` type: a comma-separated list, each entry read by ``item`` (an ``argparse`` type)."""
    return lambda text: [item(v) for v in text.split(",")]


def thread_count(text: str) -> str:
    """``default`` (the thread variables unset), ``auto`` (the ``knee`` command's rule) or a count of at least 1."""
    from knee.app.console import at_least

    return text if text in ("default", "auto") else str(at_least(1)(text))


def grid_choice(text: str) -> str:
    """``default`` (the model's grid), ``knee`` or N cells each way (``--cells-across``'s rules), as text."""
    from knee.app.cli import cells_across

    if text.strip().lower() == "default":
        return "default"
    try:
        return str(cells_across(text))  # one entry of a comma-separated list: N or knee, never a pair
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be default, knee or N cells each way (3 to 24), got {text}") from None


def grid_settings(grid: str):
    """The association model's settings for a grid choice (None: the model's defaults)."""
    if grid == "default":
        return None
    from knee.models.fem.scene import FemSettings

    return FemSettings(n_across=grid if grid == "knee" else int(grid))


def main() -> int:
    from knee.app.console import at_least

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", help="a case set folder")
    ap.add_argument("--cases", dest="count", type=at_least(1), default=10, help="how many views (default 10)")
    ap.add_argument("--loads", type=listed(at_least(0)), default="0,1,2",
                    help="busy processes beside the run, a list (default 0,1,2)")
    ap.add_argument("--threads", type=listed(thread_count), default="default,1",
                    help="threads, a list of counts, 'default' (the thread variables unset) or 'auto' (the knee "
                         "command's rule by the load; default: default,1)")
    ap.add_argument("--grids", type=listed(grid_choice), default="default",
                    help="the model's grids, a list of 'default', 'knee' or N cells each way (default: default)")
    ap.add_argument("--rounds", type=at_least(1), default=2, help="times every setting runs (default 2)")
    ap.add_argument("--settle", type=at_least(0), default=120,
                    help="auto: seconds at most to wait for the load average to show the busy processes (120)")
    ap.add_argument("--csv", default=None, help="a row per case and run: setting, round, wall, CPU, footprints")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # internal: run these case ids, print JSON
    ap.add_argument("--worker-grid", default="default", help=argparse.SUPPRESS)  # internal: the worker's grid
    args = ap.parse_args()
    from knee.foundations.errors import KneeError

    try:
        if args.worker is not None:
            return worker(args.cases, args.worker.split(","), args.worker_grid)
        return run(args, args.loads, args.threads, args.grids)
    except (KneeError, RuntimeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def worker(folder: str, ids: list[str], grid: str = "default") -> int:
    """Method (iii) on the named cases with the model's ``grid`` (:func:`grid_choice`), one JSON line each on
    stdout (the model and its skin built before each case's clock, as ``knee compare`` times it), with the
    thread count the process was given."""
    from pathlib import Path

    from knee.app.experiments.case_set import iter_cases, run_case
    from knee.app.threads import THREAD_VARS

    chosen = os.environ.get(THREAD_VARS[0], "default")  # what the parent gave this process
    folder = Path(folder)
    for c, (anatomy, prior, T), _, _ in iter_cases(folder, select=lambda c: c["id"] in ids):
        row, _ = run_case(folder, c, "links", anatomy, prior, T, settings=grid_settings(grid))
        print(json.dumps({"case": c["id"], "wall": row.wall_seconds, "cpu": row.cpu_seconds,
                          "footprints": row.footprints_mm, "failed": row.failed, "threads": chosen}), flush=True)
    return 0


def pick(folder, count: int) -> list[str]:
    """``count`` views at the paper's placement, evenly spaced over the set (all of them when fewer)."""
    from knee.app.experiments.case_set import read_case_set
    from knee.foundations.errors import KneeInputError

    views = [c["id"] for c in read_case_set(folder)["case"] if c["camera"] == "paper"]
    if not views:
        raise KneeInputError(f"{folder}: no views at the paper's placement to time")
    n = min(count, len(views))
    return [views[round(i * (len(views) - 1) / max(n - 1, 1))] for i in range(n)]


def one_run(folder: str, ids: list[str], load: int, threads: str, grid: str = "default",
            settle: float = 120.0) -> list[dict]:
    """The cases in a process of their own with ``load`` busy processes beside it and the model's ``grid``;
    its JSON lines. ``threads="auto"``: the busy processes run until the one-minute load average reaches
    ``load - 0.5`` (``settle`` seconds at most), then the rule sets the threads the process starts with, as
    the installed ``knee`` script does before anything loads."""
    from knee.app.threads import THREAD_VARS, set_threads

    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
    if threads not in ("default", "auto"):
        env.update({k: threads for k in THREAD_VARS})
    busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(load)]
    try:
        t0 = time.perf_counter()
        while threads == "auto" and os.getloadavg()[0] < load - 0.5 and time.perf_counter() - t0 < settle:
            time.sleep(1.0)
        if threads == "auto":
            set_threads(env)
        out = subprocess.run([sys.executable, __file__, folder, "--worker", ",".join(ids), "--worker-grid", grid],
                             env=env, capture_output=True, text=True)
    finally:
        for p in busy:
            p.kill()
            p.wait()
    if out.returncode != 0:
        raise RuntimeError(f"the timed run failed: {out.stderr.strip().splitlines()[-1:] or out.returncode}")
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def run(args, loads, threads, grids=("default",)) -> int:
    from knee.app.console import new_files
    from knee.foundations.files import write_records

    ids = pick(args.cases, args.count)
    new_files(args.csv)
    # a terminated run still stops its busy processes and its timed one (the `finally` and subprocess.run's own)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))
    settings = [(n, t, g) for g in grids for n in loads for t in threads]
    results = {s: [] for s in settings}  # setting -> [(round, case line)]
    t0 = time.perf_counter()
    total = args.rounds * len(settings)
    for rnd in range(args.rounds):
        order = settings if rnd % 2 == 0 else settings[::-1]  # alternated: a drift falls on both ends alike
        for k, s in enumerate(order):
            done = rnd * len(settings) + k
            print(f"[{done + 1}/{total}] round {rnd + 1}, {s[0]} busy, threads {s[1]}, grid {s[2]} "
                  f"({time.perf_counter() - t0:.0f} s so far)", file=sys.stderr, flush=True)
            results[s] += [(rnd, line) for line in one_run(args.cases, ids, *s, settle=args.settle)]
    first = grids[0]
    base = settings[0] if (0, "default", first) not in results else (0, "default", first)
    base_wall = statistics.median(line["wall"] for _, line in results[base])
    print(f"{len(ids)} views of {args.cases} at the paper's placement, {args.rounds} rounds; baseline: "
          f"{base[0]} busy, threads {base[1]}, grid {base[2]}")
    print("| grid | busy processes | threads | threads used | wall per case (s) | CPU (s) | slowest (s) | "
          "rounds' medians (s) | ratio to the baseline |")
    print("|---|---:|---|---|---:|---:|---:|---|---:|")
    for s, rows in results.items():
        wall = statistics.median(line["wall"] for _, line in rows)
        cpu = statistics.median(line["cpu"] for _, line in rows)
        per_round = " / ".join(f"{statistics.median(line['wall'] for r, line in rows if r == k):.2f}"
                               for k in range(args.rounds))
        used = " / ".join(sorted({str(line.get("threads", "?")) for _, line in rows}))
        print(f"| {s[2]} | {s[0]} | {s[1]} | {used} | {wall:.2f} | {cpu:.2f} | {max(line['wall'] for _, line in rows):.2f} | "
              f"{per_round} | {wall / base_wall:.2f} |")
    by_case = {}  # (grid, case) -> footprints over the runs: the load and the threads should not change them
    for s, rows in results.items():
        for _, line in rows:
            by_case.setdefault((s[2], line["case"]), []).append(line["footprints"])
    spread = max(max(v) - min(v) for v in by_case.values())
    failed = sum(bool(line["failed"]) for rows in results.values() for _, line in rows)
    print(f"largest change of a case's footprint error between runs of the same grid: {spread:.4f} mm; "
          f"failed runs: {failed}")
    if len(grids) > 1:
        for g in grids[1:]:
            d = [statistics.median(by_case[(g, c)]) - statistics.median(by_case[(first, c)]) for c in ids]
            print(f"grid {g} against {first}: footprints {statistics.median(d):+.3f} mm a case (median of the "
                  f"{len(ids)} views' changes)")
    if args.csv:
        write_records(args.csv, ({"grid": s[2], "busy": s[0], "threads": s[1], "round": rnd, **line}
                                 for s, rows in results.items() for rnd, line in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
