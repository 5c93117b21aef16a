"""The demo's worker processes, started before the main process imports the FEM (this module imports
nothing heavy): ``knee demo`` starts them first, so that their start-up overlaps the sweep it solves and
records meanwhile; :mod:`knee.app.demo` holds what they run and collects their results."""

from __future__ import annotations

import concurrent.futures as cf
import importlib
import multiprocessing as mp
import os
import signal

from knee.app.threads import THREAD_VARS

#: The demo's methods: the paper's (i), the prior with its links (iii), the mechanism alone (iv).
DEMO_METHODS = ("paper", "links", "kinematics")


def call(module: str, function: str, *args):
    """``module.function(*args)``, the module imported here, in the worker (not by the process that
    submits the call)."""
    return getattr(importlib.import_module(module), function)(*args)


def _ignore_interrupt() -> None:
    """Workers leave Ctrl-C to the main process, which stops them (:func:`stop_workers`): no traceback from
    each worker."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def stop_workers(pool: cf.ProcessPoolExecutor) -> None:
    """Terminate the pool's worker processes now (their running cases are abandoned)."""
    terminate = getattr(pool, "terminate_workers", None)  # Python 3.14
    if terminate is not None:
        terminate()
        return
    for proc in list((getattr(pool, "_processes", None) or {}).values()):  # before 3.14: the processes
        proc.terminate()


def start_workers(flexion_deg: float, seed: int, perturb: float):
    """Two worker processes running :func:`knee.app.demo.run_demo_method` for each of
    :data:`DEMO_METHODS`; returns (pool, {future: method}). The caller shuts the pool down."""
    ctx = mp.get_context("spawn")  # no fork of a process that holds recording threads
    # one BLAS/OpenMP thread per worker: two workers on two cores, not four threads fighting over them
    saved = {k: os.environ.get(k) for k in THREAD_VARS}
    os.environ.update({k: "1" for k in THREAD_VARS})
    try:
        pool = cf.ProcessPoolExecutor(max_workers=2, mp_context=ctx, initializer=_ignore_interrupt)
        # the workers are spawned by these submissions, with the environment set above
        futures = {pool.submit(call, "knee.app.demo", "run_demo_method", m, flexion_deg, seed, perturb): m
                   for m in DEMO_METHODS}
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return pool, futures
