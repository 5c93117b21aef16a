"""An independent NumPy/SciPy implementation of the closure equations (seed 002, eqs. 1-4).

It shares no code with the CasADi path (:mod:`.closure`): rotations come from
:mod:`knee.foundations.conventions`, the PF pose from Rodrigues' formula written out again, and the solves use
``scipy.optimize.least_squares`` and ``brentq``. Tests check the CasADi solver against it, and the
benchmark uses :func:`solve_sweep_least_squares` as its baseline.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from knee.foundations.conventions import cardan_to_matrix, matrix_to_cardan
from knee.models.mechanism.params import MechanismParams


def _axis_angle(n, a):
    n = n / np.linalg.norm(n)
    K = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _align(a, b):
    """Smallest rotation taking unit vector a onto unit vector b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    s = np.linalg.norm(v)
    if s < 1e-15:
        return np.eye(3)
    return _axis_angle(v / s, np.arctan2(s, np.dot(a, b)))


def tf_residuals(params: MechanismParams, x, alpha) -> np.ndarray:
    """The five TF residuals (mm) for unknowns ``x = (beta, gamma, P)`` at flexion ``alpha``."""
    R = cardan_to_matrix(alpha, x[0], x[1])
    P = np.asarray(x[2:5])
    r = np.empty(5)
    for i, lk in enumerate(params.links):
        if lk.kind == "distance":
            r[i] = np.linalg.norm(lk.femur - R @ lk.tibia - P) - lk.length
        else:
            n = lk.normal / np.linalg.norm(lk.normal)
            r[i] = n @ (R.T @ (lk.femur - P) - lk.tibia) - lk.length
    return r


def pf_pose(params: MechanismParams, psi, theta):
    """``(R_fp, P_fp)`` for the patella at axis rotation ``psi``, ``theta = psi - psi_ref``."""
    f = params.pf
    nf = f.axis_femur / np.linalg.norm(f.axis_femur)
    R = _axis_angle(nf, psi) @ _align(f.axis_patella, nf)
    P = (f.lambda0 + f.lambda1 * theta) * nf + f.point_femur - R @ f.point_patella
    return R, P


def tendon_residual(params, psi, theta, x, alpha) -> float:
    f = params.pf
    Rt = cardan_to_matrix(alpha, x[0], x[1])
    Rp, Pp = pf_pose(params, psi, theta)
    return float(np.linalg.norm(Rp @ f.tendon_patella + Pp - Rt @ f.tendon_tibia - x[2:5]) - f.tendon_length)


def solve_tf_least_squares(params, alpha, x0) -> np.ndarray:
    """TF unknowns at ``alpha`` by ``scipy.optimize.least_squares`` from ``x0`` (tight tolerances)."""
    sol = least_squares(lambda x: tf_residuals(params, x, alpha), x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return sol.x


def solve_pf(params, x, alpha, psi_ref, psi0) -> float:
    """PF axis rotation from the tendon equation, by least squares from ``psi0``."""
    sol = least_squares(lambda p: [tendon_residual(params, p[0], p[0] - psi_ref, x, alpha)], [psi0],
                        xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return float(sol.x[0])


def solve_sweep_least_squares(params, alphas, x0, psi_ref=0.0, psi0=0.0):
    """A plain loop over angles, each solved by ``least_squares`` from the previous solution.

    Returns
    -------
    tf : (n, 6) float and pf : (n, 6) float (NaN without a patella)
    """
    alphas = np.asarray(alphas, dtype=float)
    tf = np.empty((alphas.size, 6))
    pf = np.full((alphas.size, 6), np.nan)
    x, psi = np.asarray(x0, float), psi0
    for i, a in enumerate(alphas):
        x = solve_tf_least_squares(params, a, x)
        tf[i] = np.r_[a, x]
        if params.pf is not None:
            psi = solve_pf(params, x, a, psi_ref, psi)
            R, P = pf_pose(params, psi, psi - psi_ref)
            pf[i] = np.r_[matrix_to_cardan(R), P]
    return tf, pf
