"""Bounded optimisation of the patello-femoral group (seed 002, section 2.4), after the TF group.

The PF motion depends on the TF geometry (the tendon pulls on the tibia) but the TF motion does not
depend on the PF group, so the fit runs in two blocks: the TF group first (:func:`knee.fitting.optimize.fit_tf`,
35 parameters against the five TF components), then the PF group with the TF group fixed, against the
six PF components. The PF group's 17 parameters, bounded as in the paper:

* the helical axis direction in the femur and in the patella (2 + 2): within 5 deg of the first
  estimate (``n = n0 + tan(5 deg) v``, v in the unit disc of the plane normal to n0);
* the axis points in the sagittal planes of femur and patella (2 + 2): within 5 mm;
* the tendon endpoints on tibia and patella (3 + 3): within 2 mm;
* the tendon length and lambda0 (1 + 1): within 5 mm; the pitch lambda1 (1): within 2 mm/rad.

The objective is the squared, noise-weighted difference of the six PF components (flexion, tilt and
rotation in degrees, translations in mm) at the measured flexion angles; the Jacobian is exact (CasADi
sensitivities through the implicit function theorem, including the reference pose's dependence).
"""

from __future__ import annotations

import math
import time

import numpy as np

from knee.fitting.optimize import (
    NOISE_SD,
    FitResult,
    Motion,
    MotionFit,
    bounded_ball,
    dense_grid,
    two_stage,
)
from knee.foundations.errors import AssemblyError, KneeInputError
from knee.models.mechanism.params import (
    PF_AXIS_FEMUR,
    PF_AXIS_PATELLA,
    PF_LAMBDA0,
    PF_LAMBDA1,
    PF_POINT_FEMUR,
    PF_POINT_PATELLA,
    PF_TENDON_LENGTH,
    PF_TENDON_PATELLA,
    PF_TENDON_TIBIA,
    MechanismParams,
)
from knee.models.mechanism.solver import Mechanism, pf_sensitivities, quick_pf_sweep

AXIS_DEG = 5.0
AXIS_POINT_MM = 5.0
TENDON_MM = 2.0
LENGTH_MM = 5.0
PITCH_MM_PER_RAD = 2.0


def pf_noise_weights(sd=None) -> np.ndarray:
    """Weights 1/sd of the six PF components (flexion, tilt, rotation, anterior, proximal, lateral),
    normalised so the sagittal translations weigh 1."""
    sd = sd or NOISE_SD
    s = np.array([sd["sagittal_deg"], sd["out_of_plane_deg"], sd["out_of_plane_deg"], sd["sagittal_mm"],
                  sd["sagittal_mm"], sd["out_of_plane_mm"]])
    return sd["sagittal_mm"] / s


def _tangent_basis(n):
    n = n / np.linalg.norm(n)
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(n, e1)])  # (3, 2)


class PFFit(MotionFit):
    """The PF fitting problem (see the module docstring). ``params`` holds the fitted TF group and the
    PF first estimate; ``motion`` needs ``pf``."""

    n_var = 17
    n_deg = 3  # PF flexion, tilt, rotation; then the three translations

    def __init__(self, params: MechanismParams, motion: Motion, weights=None):
        if not params.has_pf:
            raise KneeInputError("the PF fit needs a parameter set with a patella")
        if motion.pf is None:
            raise KneeInputError("the PF fit needs the measured patella motion")
        self.first = params
        self.motion = motion
        self.p0 = params.to_vector()
        self.kinds = params.kinds
        self.alphas = motion.flexion
        self.grid, self.index = dense_grid(self.alphas)
        self.weights = pf_noise_weights() if weights is None else np.asarray(weights, float)
        try:
            mech = Mechanism(params)
        except AssemblyError as e:
            raise KneeInputError(f"the PF first estimate does not assemble: {e}") from None
        self.x_ref0, self.psi_ref0 = mech.x_ref.copy(), float(mech.psi_ref)
        self.Bf = _tangent_basis(self.p0[PF_AXIS_FEMUR])
        self.Bp = _tangent_basis(self.p0[PF_AXIS_PATELLA])
        self.nf0 = self.p0[PF_AXIS_FEMUR] / np.linalg.norm(self.p0[PF_AXIS_FEMUR])
        self.np0 = self.p0[PF_AXIS_PATELLA] / np.linalg.norm(self.p0[PF_AXIS_PATELLA])
        self.evaluations = 0
        self._cache = (None, None)

    def _maps(self, w):
        """(flat parameter vector, d vector / d w (N_PARAMS, 17))."""
        w = np.asarray(w, float)
        p = self.p0.copy()
        D = np.zeros((p.size, self.n_var))
        t = math.tan(math.radians(AXIS_DEG))
        # axes
        for k, (axis, point, n0, B) in enumerate(((PF_AXIS_FEMUR, PF_POINT_FEMUR, self.nf0, self.Bf),
                                                  (PF_AXIS_PATELLA, PF_POINT_PATELLA, self.np0, self.Bp))):
            v, Jv = bounded_ball(w[None, 4 * k:4 * k + 2], t)
            p[axis] = n0 + B @ v[0]
            D[axis, 4 * k:4 * k + 2] = B @ Jv[0]
            q, Jq = bounded_ball(w[None, 4 * k + 2:4 * k + 4], AXIS_POINT_MM)
            xy = slice(point.start, point.start + 2)  # the point moves in the sagittal plane (x, y)
            p[xy] += q[0]
            D[xy, 4 * k + 2:4 * k + 4] = Jq[0]
        for k, end in enumerate((PF_TENDON_TIBIA, PF_TENDON_PATELLA)):
            d, Jd = bounded_ball(w[None, 8 + 3 * k:11 + 3 * k], TENDON_MM)
            p[end] += d[0]
            D[end, 8 + 3 * k:11 + 3 * k] = Jd[0]
        for k, (o, rng) in enumerate(((PF_TENDON_LENGTH, LENGTH_MM), (PF_LAMBDA0, LENGTH_MM),
                                      (PF_LAMBDA1, PITCH_MM_PER_RAD))):
            p[o] += rng * math.tanh(w[14 + k])
            D[o, 14 + k] = rng / math.cosh(w[14 + k]) ** 2
        return p, D

    def params_vector(self, w):
        return self._maps(w)[0]

    def params(self, w) -> MechanismParams:
        return self.first.with_vector(self.params_vector(w))

    def _solve(self, w):
        key = np.asarray(w, float).tobytes()
        if self._cache[0] == key:
            return self._cache[1]
        r = quick_pf_sweep(self.params_vector(w), self.kinds, self.x_ref0, self.psi_ref0, self.grid)
        self.evaluations += 1
        self._cache = (key, r)
        return r

    def model_motion(self, w):
        r = self._solve(w)
        return r.pf[self.index], r.ok

    def _compared(self, w):
        pf, ok = self.model_motion(w)
        return pf, self.motion.pf, ok

    def jacobian(self, w) -> np.ndarray:
        r = self._solve(w)
        if not r.ok:
            return np.zeros((6 * len(self.alphas), self.n_var))
        p, D = self._maps(w)
        sens = pf_sensitivities(p, self.kinds, r.Z[self.index], self.alphas)
        dq = self._units(sens.d_params[:, 6:12, :])
        return dq.reshape(-1, p.size) @ D


PFFitResult = FitResult  # the same fields; ``mae`` (6,): deg x3, mm x3, fitted model vs measured


def fit_pf(params: MechanismParams, motion: Motion, seed: int = 0, global_stage: bool = True, popsize: int = 10,
           maxiter: int = 12, w_box: float = 2.5, local_starts: int = 4, progress=None) -> PFFitResult:
    """Fit the PF group of ``params`` (TF group already fitted) to ``motion`` (see the module docstring)."""
    t0 = time.perf_counter()
    prob = PFFit(params, motion)
    say = progress or (lambda f, t: None)
    w, c0, cg = two_stage(prob, prob.n_var, seed, global_stage, popsize, maxiter, w_box, local_starts, say,
                          "PF fit")
    if not prob.model_motion(w)[1]:
        raise KneeInputError("no PF candidate within the bounds assembles over the measured range")
    return PFFitResult(params=prob.params(w), w=w, cost_first=c0, cost_global=cg, cost_final=prob.cost(w),
                       evaluations=prob.evaluations, seconds=time.perf_counter() - t0, mae=prob.mae(w))
