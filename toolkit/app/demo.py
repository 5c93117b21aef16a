"""The FEM half of ``knee demo``: a virtual depth map of the bundled volunteer at a flexion angle, the
association model with the kinematic prior (method iii), the paper's method (i) and the mechanism alone
(iv) on the same points, compared.

The truth is `volunteer`; the prior is `volunteer` with every TF link endpoint moved 1-2 mm (so that it
is realistically wrong). The three methods run in two worker processes (the machine's two cores), the
mechanism-only estimate in whichever finishes first.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from knee.app.experiments.cases import (
    CompareRow,
    MethodResult,
    case_points,
    result_row,
    run_method,
    truth_phantom,
)
from knee.app.reports.compare import (
    CompareRecorder,
    MethodSummary,
    markdown,
    plot,
    summary,
    write_csv,
)
from knee.fitting.optimize import perturb_endpoints
from knee.models.fem.depth import DepthNoise, default_camera
from knee.models.fem.scene import build_association_model
from knee.models.mechanism import Mechanism
from knee.models.mechanism.params import load_model

DEMO_METHODS = ("paper", "links", "kinematics")
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def demo_case(seed: int, perturb: float) -> tuple[Mechanism, Mechanism]:
    """The demo's truth (``volunteer``) and prior (``volunteer`` with every TF link endpoint moved
    ``perturb / 2`` to ``perturb`` mm)."""
    truth = Mechanism.from_name("volunteer")
    prior = Mechanism(perturb_endpoints(load_model("volunteer"), 0.5 * perturb, perturb, seed=seed))
    return truth, prior


def run_demo_method(method: str, flexion_deg: float, seed: int, perturb: float):
    """One method on the demo case (run in a worker process); returns (MethodResult, truth TF coordinates)."""
    truth, prior = demo_case(seed, perturb)
    cam = default_camera()
    model = build_association_model(prior)
    pts, tf = case_points(truth, flexion_deg, cam, DepthNoise(), seed, model.settings)
    return run_method(method, truth, prior, flexion_deg, cam, DepthNoise(), seed, points=pts, model=model), tf


@dataclass
class DemoComparison:
    """The demo's comparison: one row per method, the medians per method and the wall time (s)."""

    rows: list[CompareRow]
    summary: dict[str, MethodSummary]
    seconds: float


def run_demo_comparison(out_dir: Path, flexion_deg: float = 60.0, seed: int = 3, perturb: float = 2.0,
                        log: Callable[[str], None] | None = None) -> DemoComparison:
    """Run the three methods, write ``compare.csv``, ``compare.md``, ``compare.png`` and ``compare.rrd`` to
    ``out_dir``; ``log(text)`` hears when each method is done."""
    t0 = time.perf_counter()
    results: dict[str, tuple[MethodResult, object]] = {}
    ctx = mp.get_context("spawn")  # no fork of a process that holds recording threads
    # one BLAS/OpenMP thread per worker: two workers on two cores, not four threads fighting over them
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS})
    try:
        with cf.ProcessPoolExecutor(max_workers=2, mp_context=ctx) as pool:
            futures = {pool.submit(run_demo_method, m, flexion_deg, seed, perturb): m for m in DEMO_METHODS}
            for fut in cf.as_completed(futures):
                m = futures[fut]
                results[m] = fut.result()
                if log:
                    log(f"  {m} done after {time.perf_counter() - t0:.1f} s")
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    truth, prior = demo_case(seed, perturb)
    rec = CompareRecorder(out_dir / "compare.rrd", truth_phantom(truth), truth_phantom(prior), DEMO_METHODS)
    rows = []
    for m in DEMO_METHODS:
        r, tf = results[m]
        rec("oblique", flexion_deg, m, r, tf)
        rows.append(result_row("oblique", flexion_deg, r))
    rec.finish()
    title = (f"knee demo: volunteer at {flexion_deg:g} deg, oblique camera; prior = volunteer with TF endpoints "
             f"moved {0.5 * perturb:g}-{perturb:g} mm")
    write_csv(rows, out_dir / "compare.csv")
    (out_dir / "compare.md").write_text(markdown(rows, DEMO_METHODS, title), encoding="utf-8")
    plot(rows, DEMO_METHODS, out_dir / "compare.png", title)
    return DemoComparison(rows, summary(rows, DEMO_METHODS), time.perf_counter() - t0)
