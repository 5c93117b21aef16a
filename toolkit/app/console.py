"""What the command modules share: output-path checks, argument parsers for lists of numbers, and the
progress bar that renders the library's progress callbacks on standard error.

Every check raises :class:`~knee.foundations.errors.KneeInputError` with one line naming the flag.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import logging
import math
import signal
import sys
import time
from pathlib import Path

import numpy as np

from knee.foundations.errors import EXIT_BAD_INPUT, KneeInputError
from knee.foundations.files import check_output, staged_file


def error(message: str, code: int = EXIT_BAD_INPUT) -> int:
    """Print ``knee: error: message`` (one line) on standard error, on a line of its own even when a
    progress bar was interrupted mid-line; returns ``code``."""
    if ProgressBar.open_line:
        sys.stderr.write("\n")
        ProgressBar.open_line = False
    sys.stderr.write(f"knee: error: {' '.join(str(message).split())}\n")
    sys.stderr.flush()
    return code


def check_new(path: Path | None, force: bool, inputs=(), flag: str = "--out") -> None:
    """An output file to be written, checked before the work (:func:`knee.foundations.files.check_output`):
    not an input, not a folder or device, writable, and replaced only with ``force``."""
    if path is not None:
        check_output(path, "file", force, inputs, flag)


def out_dir(path: str, force: bool, inputs=(), flag: str = "--out") -> Path:
    """An output folder (written later, as a whole, once the inputs have been checked): refused when it
    is or holds an input, cannot be written, or exists and is not empty (unless ``force``)."""
    return check_output(path, "folder", force, inputs, flag)


def new_files(*paths) -> None:
    """The scripts' output files (None skipped): one that exists is refused, never overwritten."""
    for p in paths:
        if p is not None and Path(p).exists():
            raise KneeInputError(f"{p} exists; not overwritten (give a new file)")


def write_rows_csv(path, rows) -> None:
    """The scripts' tables of dataclass rows as CSV, written whole (:func:`knee.foundations.files.staged_file`):
    a header of the fields, then a row each, floats to 4 significant digits."""
    with staged_file(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([fl.name for fl in dataclasses.fields(rows[0])])
        for r in rows:
            w.writerow([f"{v:.4g}" if isinstance(v, float) else v for v in dataclasses.astuple(r)])


def timed_progress():
    """A progress callback ``(i, n, text)`` for the scripts: one line on standard error per call, with the
    seconds since it was made."""
    t0 = time.perf_counter()

    def progress(i, n, text):
        say(f"[{time.perf_counter() - t0:6.0f} s] {i}/{n} {text}")
    return progress


#: The largest step count a run accepts (a bound on what can hang a run).
MAX_STEPS = 100_000


def check_max_steps(n: int) -> None:
    """``--max-steps``: 1 to :data:`MAX_STEPS`."""
    if not 1 <= n <= MAX_STEPS:
        raise KneeInputError(f"--max-steps must be 1-{MAX_STEPS}, got {n}")


#: Set once Ctrl-C or a termination request has arrived (:func:`take_terminations_as_interrupts`).
_stop_requested = False


def _interrupted(signum, frame):
    global _stop_requested
    _stop_requested = True
    raise KeyboardInterrupt


def _not_an_interrupt(record) -> bool:
    """A logging filter: drop a record that carries the interrupt a library caught (trimesh, for one,
    catches every exception in its vertex normals, logs it with its traceback and falls back)."""
    return not (record.exc_info and isinstance(record.exc_info[1], KeyboardInterrupt))


def take_terminations_as_interrupts() -> None:
    """From now on a termination request (SIGTERM: ``kill``, a scheduler's time limit) raises
    ``KeyboardInterrupt`` as Ctrl-C does, so that the same clean-up runs (partial outputs removed, workers
    stopped), and either is remembered: :func:`stop_if_requested` (which the progress bar and :func:`say`
    call) raises it again, for the rare signal that lands where Python drops the exception its handler
    raises (in a finaliser, a callback from compiled code, or a library that catches every exception; the
    run would otherwise carry on), and the warning such a library logs with the interrupt's traceback is
    not printed. Ctrl-C is left ignored where it was (a background job). For a program's entry point; the
    main thread only."""
    for handler in [logging.lastResort, *logging.getLogger().handlers]:
        if handler is not None and _not_an_interrupt not in handler.filters:
            handler.addFilter(_not_an_interrupt)
    signal.signal(signal.SIGTERM, _interrupted)
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, _interrupted)


def stop_if_requested() -> None:
    """Raise ``KeyboardInterrupt`` if Ctrl-C or a termination request has arrived
    (:func:`take_terminations_as_interrupts`)."""
    if _stop_requested:
        raise KeyboardInterrupt


def at_least(lo: float, kind=int, hi: float | None = None):
    """An ``argparse`` type: a number of ``kind`` no smaller than ``lo`` (and no larger than ``hi``), so that
    a count of runs or steps out of range is refused in one line instead of failing later."""
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {'an integer' if kind is int else 'a number'}, got {text!r}")
        if not (isinstance(v, int) or math.isfinite(v)) or v < lo or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"must be {'at least ' + format(lo, 'g') if hi is None else f'from {lo:g} to {hi:g}'}"
                                             f", got {text}")
        return v
    return parse


def numbers(text: str, n: int | None, what: str, hint: str = "") -> np.ndarray:
    """``n`` finite comma-separated numbers (None: one or more), or a one-line error naming ``what``."""
    try:
        v = np.array([float(x) for x in str(text).split(",")])
    except ValueError:
        v = np.zeros(0)
    if (v.size != n if n is not None else v.size == 0) or not np.all(np.isfinite(v)):
        count = "" if n is None else {3: "three ", 4: "four ", 6: "six "}.get(n, f"{n} ")
        raise KneeInputError(f"{what} must be {count}comma-separated numbers{hint}, got {text!r}")
    return v


def flexion_list(text: str) -> list[float]:
    """``A:B:STEP`` (inclusive) or a comma list of angles, deg."""
    t = str(text).strip()
    try:
        if ":" in t:
            a, b, st = (float(v) for v in t.split(":"))
            if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(st)) or not st > 0 or b < a:
                raise ValueError
            vals = list(np.arange(a, b + 1e-9, st))
        else:
            vals = [float(v) for v in t.split(",")]
    except ValueError:
        raise KneeInputError(f"--flexion must be FROM:TO:STEP (finite, STEP > 0, TO >= FROM) or a comma list of "
                             f"degrees, got {text!r}") from None
    if not vals or len(vals) > 50 or not all(math.isfinite(v) and 0.0 <= v <= 150.0 for v in vals):
        raise KneeInputError(f"--flexion must give 1-50 angles within 0-150 deg, got {text!r}")
    return [float(v) for v in vals]


class ProgressBar:
    """A one-line progress bar on standard error: ``[######....]  45%  text``; call it with the fraction
    done and a short text."""

    #: Whether a bar has left its line unfinished (an error then starts a new line).
    open_line = False

    def __init__(self, width: int = 30, stream=None):
        self.width = width
        self.stream = stream or sys.stderr
        self.last = ""

    def __call__(self, fraction: float, text: str) -> None:
        stop_if_requested()
        f = min(max(float(fraction), 0.0), 1.0)
        k = int(round(f * self.width))
        line = f"[{'#' * k}{'.' * (self.width - k)}] {100 * f:3.0f}%  {text}"
        pad = max(len(self.last) - len(line), 0)
        self.stream.write("\r" + line + " " * pad)
        ProgressBar.open_line = f < 1.0
        if f >= 1.0:
            self.stream.write("\n")
        self.stream.flush()
        self.last = line


def say(text: str) -> None:
    """A status line on standard error (results go to standard output)."""
    stop_if_requested()
    sys.stderr.write(f"{text}\n")  # one write: a Ctrl-C cannot land between the text and its newline
    sys.stderr.flush()
