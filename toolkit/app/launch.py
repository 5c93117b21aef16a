"""The installed ``knee`` script's entry point. It sets the BLAS libraries' threads by the machine's load
(:func:`knee.app.threads.set_threads`) before anything imports them, NumPy included (the command line's
own module does), then runs :func:`knee.app.cli.entry`."""

from __future__ import annotations

import importlib

from knee.app.threads import set_threads


def entry() -> None:
    """``knee``: the threads set first, then the command line (imported only then, as the command line
    imports each command's module when it runs)."""
    set_threads()
    importlib.import_module("knee.app.cli").entry()
