"""Isotropic linear elastic material (units: MPa = N/mm^2)."""

from __future__ import annotations

import numpy as np

from knee.foundations.errors import KneeInputError


def elasticity_matrix(E: float, nu: float) -> np.ndarray:
    """The 6x6 matrix D with sigma = D eps in Voigt order (xx, yy, zz, xy, yz, zx), engineering shear.

    Raises
    ------
    KneeInputError
        E not positive or nu outside (-1, 0.5).
    """
    if not (np.isfinite(E) and E > 0):
        raise KneeInputError(f"Young's modulus must be positive, got {E}")
    if not (np.isfinite(nu) and -1.0 < nu < 0.5):
        raise KneeInputError(f"Poisson's ratio must be in (-1, 0.5), got {nu}")
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[[0, 1, 2], [0, 1, 2]] += 2 * mu
    D[[3, 4, 5], [3, 4, 5]] = mu
    return D
