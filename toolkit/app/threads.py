"""How many threads the BLAS libraries may use, set before they load (this module imports nothing heavy).

CHOLMOD's factorisations (CVXOPT's OpenBLAS), NumPy's and SciPy's OpenBLAS, and any OpenMP code read their
thread counts from the environment when they are loaded. Their threads wait for work by spinning, so on a
machine whose cores other work holds they cost time, and on this toolkit's problems they gain little even
on an idle machine. Measured on method (iii)'s cases on two cores (BENCHMARKS.md, "The BLAS threads by the
machine's load"): with nothing else running, one BLAS thread takes the same wall time as two and 10 % less
CPU; beside one or two busy processes it takes 7 % and 6 % less wall time. (Open3D's registrations and distance queries run on TBB, which
these variables do not bound; bounded to one thread, they took a third longer on an idle machine and gained
nothing beside busy processes, so they keep their own default.)

So the ``knee`` command gives the BLAS libraries the cores that other work leaves free, by the one-minute
load average (the signal ``make -l`` and job schedulers use), at least one: :func:`threads_for`. A thread
count the user set (any of :data:`THREAD_VARS` in the environment) is kept as it is.
"""

from __future__ import annotations

import os

#: The environment variables the BLAS and OpenMP libraries read their thread counts from.
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the system has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def threads_for(cores: int, load: float) -> int:
    """The threads to use on ``cores`` cores with ``load`` (the one-minute load average: runnable
    processes, averaged) taken by other work: the cores left, at least 1 and at most ``cores``."""
    if cores < 1:
        raise ValueError(f"cores must be at least 1, got {cores}")
    if not load >= 0.0:  # also NaN
        raise ValueError(f"load must be a number of at least 0, got {load}")
    return max(1, min(cores, cores - int(round(load))))


def set_threads(environ=None, cores: int | None = None, load: float | None = None) -> int | None:
    """Set :data:`THREAD_VARS` in ``environ`` (default ``os.environ``) to :func:`threads_for` this machine,
    unless one of them is set already (the user's choice, kept); returns the count set, or None when kept or
    when the load cannot be read. Call it before the libraries are imported (a child process given
    ``environ`` reads it at its start)."""
    environ = os.environ if environ is None else environ
    if any(environ.get(k) for k in THREAD_VARS):
        return None
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (AttributeError, OSError):  # no load average on this system: the libraries' own defaults
            return None
    n = threads_for(usable_cores() if cores is None else cores, load)
    environ.update({k: str(n) for k in THREAD_VARS})
    return n
