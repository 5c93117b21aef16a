"""The numeric libraries' threads, set by the machine's load before they load (:mod:`knee.app.threads`)."""

import os
import subprocess
import sys

import pytest

from knee.app.threads import THREAD_VARS, set_threads, threads_for


@pytest.mark.parametrize("cores, load, expected", [(2, 0.0, 2), (2, 0.4, 2), (2, 0.6, 1), (2, 1.0, 1), (2, 2.0, 1),
                                                   (2, 7.5, 1), (1, 0.0, 1), (8, 0.0, 8), (8, 2.4, 6), (8, 2.6, 5)])
def test_the_threads_are_the_cores_other_work_leaves(cores, load, expected):
    assert threads_for(cores, load) == expected


@pytest.mark.parametrize("cores, load", [(0, 0.0), (2, -1.0), (2, float("nan"))])
def test_the_rule_refuses_what_is_not_a_machine(cores, load):
    with pytest.raises(ValueError):
        threads_for(cores, load)


def test_the_variables_are_set_together_unless_the_user_set_one():
    env = {"PATH": "/bin"}
    assert set_threads(env, cores=4, load=1.2) == 3
    assert all(env[k] == "3" for k in THREAD_VARS) and env["PATH"] == "/bin"
    for k in THREAD_VARS:  # any one of them set by the user: all left as they are
        mine = {k: "7"}
        assert set_threads(mine, cores=4, load=0.0) is None
        assert mine == {k: "7"}
    empty = {"OMP_NUM_THREADS": ""}  # set but empty counts as unset
    assert set_threads(empty, cores=2, load=0.0) == 2


def test_the_command_sets_the_threads_before_anything_runs(monkeypatch):
    """``knee``'s entry point sets the variables by the load before the command (which imports the libraries)
    runs."""
    import knee.app.cli as cli

    for k in THREAD_VARS:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.0, 1.0, 1.0))
    monkeypatch.setattr(cli, "take_terminations_as_interrupts", lambda: None)
    seen = {}
    monkeypatch.setattr(cli, "main", lambda: seen.update({k: os.environ.get(k) for k in THREAD_VARS}) or 0)
    with pytest.raises(SystemExit) as e:
        cli.entry()
    assert e.value.code == 0
    n = str(threads_for(len(os.sched_getaffinity(0)), 1.0))
    assert seen == {k: n for k in THREAD_VARS}


@pytest.mark.parametrize("module, loaded", [("knee.app.launch", ()), ("knee.app.cli", ("numpy",))])
def test_no_blas_library_loads_before_the_rule(module, loaded):
    """The variables are read when a BLAS library loads (CVXOPT's CHOLMOD, SciPy's, NumPy's). The installed
    script's module (:mod:`knee.app.launch`) sets them before it imports anything of the kind; the command
    line's own module (``python -m knee.app.cli``) loads NumPy but none of the others."""
    code = (f"import sys, {module}; "
            "print(','.join(sorted(m for m in ('numpy', 'scipy', 'cvxopt', 'open3d') if m in sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ",".join(loaded)


def test_the_installed_script_sets_the_threads_first(monkeypatch):
    """:func:`knee.app.launch.entry` sets the variables, then hands over to the command line."""
    import knee.app.cli as cli
    from knee.app.launch import entry

    for k in THREAD_VARS:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setattr(os, "getloadavg", lambda: (0.0, 0.0, 0.0))
    seen = {}
    monkeypatch.setattr(cli, "entry", lambda: seen.update({k: os.environ.get(k) for k in THREAD_VARS}))
    entry()
    n = str(len(os.sched_getaffinity(0)))
    assert seen == {k: n for k in THREAD_VARS}
