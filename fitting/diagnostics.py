"""What a fit can and cannot tell: parameters on their bounds, identifiability, confidence intervals.

At the optimum of a bounded fit (:mod:`knee.fitting.optimize`, :mod:`knee.fitting.pf`), in the physical
offsets each bounded variable stands for (an endpoint's move in mm, a length's change in mm, a helical
axis's tilt in rad, ...):

* ``bound_use``: how much of its bound each variable uses (an endpoint's offset over the ball's radius,
  |tanh| for a range); 0.95 or more is "on its bound" - the data pushed it there and the bound decides it;
* the singular values of the weighted residuals' Jacobian with respect to those offsets: its condition
  number, and the directions (parameter combinations) it cannot see, named by their largest entries;
* 95 % confidence half-widths of each offset from the Gauss-Newton covariance
  ``s^2 (J^T J)^-1`` with ``s^2 = r.r / (m - p)`` (a pseudo-inverse: an invisible direction gives an
  infinite half-width, not a made-up one).

These are local, linearised statements: they say what the measured arc determines, not what a wider arc
would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: A variable using this fraction of its bound or more is reported as on its bound.
ON_BOUND = 0.95
#: Singular values below this fraction of the largest count as directions the data cannot see.
INVISIBLE = 1e-6


@dataclass(frozen=True)
class FitDiagnostics:
    """Diagnostics of one group's fit (TF or PF); see the module docstring. ``names`` and ``units`` per
    variable; ``bound_use`` (p,) in [0, 1]; ``singular_values`` (p,) descending; ``ci95`` (p,) half-widths
    in the variables' units (inf where not determined); ``weak`` the three least visible directions as
    text; ``dof`` = m - p."""

    group: str
    names: list
    units: list
    bound_use: np.ndarray
    singular_values: np.ndarray
    ci95: np.ndarray
    weak: list
    residual_rms: float
    dof: int
    #: (m, p) the weighted residuals' Jacobian with respect to the physical offsets.
    jacobian: np.ndarray | None = None

    @property
    def condition(self) -> float:
        s = self.singular_values
        return float(s[0] / s[-1]) if s[-1] > 0 else math.inf

    @property
    def on_bound(self) -> list[tuple[str, float]]:
        """(name, fraction of the bound used) of every variable at or beyond :data:`ON_BOUND`."""
        return [(n, float(u)) for n, u in zip(self.names, self.bound_use) if u >= ON_BOUND]

    @property
    def rank(self) -> int:
        s = self.singular_values
        return int(np.sum(s > INVISIBLE * s[0])) if s.size and s[0] > 0 else 0

    def as_dict(self) -> dict:
        return {"group": self.group, "variables": len(self.names), "dof": self.dof,
                "residual_rms": self.residual_rms, "condition_number": self.condition, "rank": self.rank,
                "singular_values": self.singular_values.tolist(),
                "on_bound": [{"name": n, "fraction": u} for n, u in self.on_bound],
                "weakest_directions": list(self.weak),
                "ci95": {n: {"half_width": (float(c) if math.isfinite(c) else None), "unit": u}
                         for n, u, c in zip(self.names, self.units, self.ci95)}}


def diagnose(group: str, names, units, J, residuals, bound_use) -> FitDiagnostics:
    """:class:`FitDiagnostics` from the weighted residuals (m,) and their Jacobian (m, p) with respect to
    the physical offsets, and each variable's bound use (p,)."""
    J = np.asarray(J, float)
    r = np.asarray(residuals, float)
    m, p = J.shape
    U, s, Vt = np.linalg.svd(J, full_matrices=False)
    dof = max(m - p, 1)
    s2 = float(r @ r) / dof
    visible = s > INVISIBLE * (s[0] if s.size else 0.0)
    inv = np.where(visible, 1.0 / np.where(visible, s, 1.0) ** 2, 0.0)
    var = (Vt.T ** 2) @ inv * s2
    # a variable with weight on an invisible direction is not determined
    blind = (np.abs(Vt[~visible]) > 1e-3).any(axis=0) if (~visible).any() else np.zeros(p, bool)
    ci = np.where(blind, np.inf, 1.96 * np.sqrt(var))
    weak = []
    for k in range(min(3, p)):
        v = Vt[p - 1 - k]
        top = np.argsort(-np.abs(v))[:3]
        combo = " ".join(f"{v[i]:+.2f} {names[i]}" for i in top)
        weak.append(f"singular value {s[p - 1 - k]:.3g} (largest {s[0]:.3g}): {combo}")
    return FitDiagnostics(group, list(names), list(units), np.asarray(bound_use, float), s, ci, weak,
                          float(math.sqrt(float(r @ r) / max(m, 1))), m - p, J)


__all__ = ["FitDiagnostics", "diagnose", "ON_BOUND"]
