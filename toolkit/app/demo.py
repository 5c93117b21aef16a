"""The FEM half of ``knee demo``: a virtual depth map of the bundled volunteer at a flexion angle, the
association model with the kinematic prior (method iii), the paper's method (i) and the mechanism alone
(iv) on the same points, compared.

The truth is `volunteer`; the prior is `volunteer` with every TF link endpoint moved 1-2 mm (so that it
is realistically wrong). The skin the camera sees is made independently of the association model: the
tetrahedral tissue around the demo subject's bones (:class:`knee.models.fem.tissue.TetTissue`, the honest
benchmark's truth) posed by the truth. The three methods run in two worker processes (the machine's two
cores; started by :mod:`knee.app.demo_workers`), the mechanism-only estimate in whichever finishes first;
each worker makes the truth's points once (the truth and the paper's method are the longest steps, so
making the truth in one worker and handing it to the other saves nothing: measured, 41 against 37 s).
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from knee.app.demo_workers import DEMO_METHODS, start_workers
from knee.app.experiments.cases import (
    CompareRow,
    MethodResult,
    result_row,
    run_method,
    tissue_case_points,
    truth_phantom,
)
from knee.app.reports.compare import CompareRecorder, MethodSummary, markdown, plot, summary, write_csv
from knee.fitting.optimize import perturb_endpoints
from knee.fitting.subject import load_subject
from knee.fitting.subject_anatomy import subject_anatomy
from knee.fitting.synthetic import make_subject
from knee.models.fem.anatomy import KneeAnatomy
from knee.models.fem.depth import DepthNoise, default_camera
from knee.models.fem.scene import build_knee_model
from knee.models.fem.tissue import TetTissue
from knee.models.mechanism import Mechanism
from knee.models.mechanism.params import load_model


def demo_case(seed: int, perturb: float) -> tuple[Mechanism, Mechanism]:
    """The demo's truth (``volunteer``) and prior (``volunteer`` with every TF link endpoint moved
    ``perturb / 2`` to ``perturb`` mm)."""
    truth = Mechanism.from_name("volunteer")
    prior = Mechanism(perturb_endpoints(load_model("volunteer"), 0.5 * perturb, perturb, seed=seed))
    return truth, prior


@functools.lru_cache(maxsize=2)
def _demo_anatomy(seed: int, perturb: float) -> KneeAnatomy:
    return demo_anatomy(demo_case(seed, perturb)[1])


def demo_anatomy(prior: Mechanism) -> KneeAnatomy:
    """The demo subject's knee: the phantom of `volunteer` written as a subject folder (CT bones, landmarks
    and skin; :func:`knee.fitting.synthetic.make_subject`, into a temporary folder) and read back as any
    subject's is (:func:`knee.fitting.subject_anatomy.subject_anatomy`), with the prior's MCL."""
    with tempfile.TemporaryDirectory(prefix="knee-demo-subject-") as tmp:
        folder = make_subject(Path(tmp) / "volunteer", model="volunteer", seed=0)
        return subject_anatomy(load_subject(folder), prior.params)


@functools.lru_cache(maxsize=2)
def demo_truth_points(flexion_deg: float, seed: int, perturb: float) -> tuple[np.ndarray, np.ndarray]:
    """The demo case's depth points (P, 3) (mm, femur frame) and the truth's TF joint coordinates (6,): the
    demo subject's tetrahedral tissue (:func:`demo_anatomy`'s bones and skin) posed with the tibia at the
    truth's pose, seen by the oblique camera with noise (:func:`knee.app.experiments.cases.tissue_case_points`;
    made once per process: about 13 s at 60 deg)."""
    truth, _ = demo_case(seed, perturb)
    tf = truth.solve(np.radians(flexion_deg))[0]
    tissue = TetTissue(_demo_anatomy(seed, perturb), seed=0)
    return tissue_case_points(tissue, tf, default_camera(), DepthNoise(), seed), tf


def run_demo_method(method: str, flexion_deg: float, seed: int, perturb: float):
    """One method on the demo case (run in a worker process); returns (MethodResult, truth TF coordinates,
    the model's bone faces {bone: (F, 3)}). The model is the demo subject's (:func:`demo_anatomy`, made once
    per process); the points are :func:`demo_truth_points`'s (made once per process): the truth's skin comes
    from another model of the tissue than the association model the methods use."""
    truth, prior = demo_case(seed, perturb)
    model = build_knee_model(_demo_anatomy(seed, perturb), prior=prior)
    points, tf = demo_truth_points(flexion_deg, seed, perturb)
    faces = {b: np.asarray(getattr(model, f"{b}_surface").faces) for b in ("femur", "tibia")}
    return (run_method(method, truth, prior, flexion_deg, default_camera(), DepthNoise(), seed, points=points,
                       model=model), tf, faces)


@dataclass
class DemoComparison:
    """The demo's comparison: one row per method, the medians per method and the wall time (s)."""

    rows: list[CompareRow]
    summary: dict[str, MethodSummary]
    seconds: float


def collect_demo_comparison(out_dir: Path, futures: dict, flexion_deg: float = 60.0, seed: int = 3,
                            perturb: float = 2.0, t0: float | None = None,
                            log: Callable[[str], None] | None = None) -> DemoComparison:
    """Wait for the workers' results ({future: method}, :func:`knee.app.demo_workers.start_workers`), write
    ``compare.csv``, ``compare.md``, ``compare.png`` and ``compare.rrd`` to ``out_dir``; ``log(text)`` hears
    when each method is done. ``t0``: when the workers started (perf_counter), for the wall time."""
    t0 = time.perf_counter() if t0 is None else t0
    results: dict[str, tuple[MethodResult, object, dict]] = {}
    for fut in cf.as_completed(futures):
        m = futures[fut]
        results[m] = fut.result()
        if log:
            log(f"  {m} done after {time.perf_counter() - t0:.1f} s")
    truth, _ = demo_case(seed, perturb)
    rec = CompareRecorder(out_dir / "compare.rrd", truth_phantom(truth), results[DEMO_METHODS[0]][2], DEMO_METHODS)
    rows = []
    for m in DEMO_METHODS:
        r, tf, _ = results[m]
        rec("oblique", flexion_deg, m, r, tf)
        rows.append(result_row("oblique", flexion_deg, r))
    rec.finish()
    title = (f"knee demo: volunteer at {flexion_deg:g} deg, its skin by the tetrahedral tissue, oblique camera; "
             f"prior = volunteer with TF endpoints moved {0.5 * perturb:g}-{perturb:g} mm")
    write_csv(rows, out_dir / "compare.csv")
    (out_dir / "compare.md").write_text(markdown(rows, DEMO_METHODS, title), encoding="utf-8")
    plot(rows, DEMO_METHODS, out_dir / "compare.png", title)
    return DemoComparison(rows, summary(rows, DEMO_METHODS), time.perf_counter() - t0)


def run_demo_comparison(out_dir: Path, flexion_deg: float = 60.0, seed: int = 3, perturb: float = 2.0,
                        log: Callable[[str], None] | None = None) -> DemoComparison:
    """The demo's comparison from Python: start the workers, collect their results and write the files
    (see :func:`collect_demo_comparison`)."""
    t0 = time.perf_counter()
    pool, futures = start_workers(flexion_deg, seed, perturb)
    try:
        return collect_demo_comparison(out_dir, futures, flexion_deg, seed, perturb, t0, log)
    finally:
        pool.shutdown()
