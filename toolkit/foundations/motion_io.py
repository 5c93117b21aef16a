"""Motion CSV files: one row per flexion angle, degrees and mm.

The header is exactly :data:`SWEEP_HEADER`: TF then PF joint coordinates (see
:mod:`knee.foundations.conventions`), then the largest closure residual (mm) and the condition number of the
TF closure Jacobian.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from knee.foundations.errors import KneeInputError

_COORDS = ["flexion_deg", "adduction_deg", "internal_rotation_deg", "anterior_mm", "proximal_mm", "lateral_mm"]
SWEEP_HEADER = [f"tf_{c}" for c in _COORDS] + [f"pf_{c}" for c in _COORDS] + ["max_residual_mm",
                                                                                  "jacobian_condition"]


def coordinates_to_csv_units(q: np.ndarray) -> np.ndarray:
    """(n, 6) joint coordinates in rad/mm -> degrees/mm."""
    q = np.array(q, dtype=float, copy=True)
    q[:, :3] = np.degrees(q[:, :3])
    return q


def sweep_table(tf, pf, residual, condition) -> np.ndarray:
    """The (n, 14) table of a sweep in CSV units."""
    tf = coordinates_to_csv_units(np.atleast_2d(tf))
    pf = coordinates_to_csv_units(np.atleast_2d(pf))
    return np.column_stack([tf, pf, residual, condition])


def write_sweep_csv(path, tf, pf, residual, condition) -> Path:
    """Write a sweep (rad/mm arrays, (n, 6) each) to ``path``; PF columns are empty when NaN."""
    path = Path(path)
    table = sweep_table(tf, pf, residual, condition)
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(SWEEP_HEADER)
        for row in table:
            w.writerow(["" if not math.isfinite(v) else f"{v:.10g}" for v in row])
    return path


def read_sweep_csv(path) -> np.ndarray:
    """Read a file written by :func:`write_sweep_csv` back as an (n, 14) array (NaN for empty)."""
    path = Path(path)
    with path.open(newline="", encoding="utf-8") as fh:
        r = csv.reader(fh)
        header = next(r, None)
        if header != SWEEP_HEADER:
            raise KneeInputError(f"{path}: header is not the sweep header ({','.join(SWEEP_HEADER)})")
        rows = [[float(v) if v != "" else np.nan for v in row] for row in r]
    return np.array(rows, dtype=float).reshape(-1, len(SWEEP_HEADER))
