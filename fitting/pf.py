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

from knee.fitting.diagnostics import FitDiagnostics, diagnose
from knee.fitting.optimize import (
    NOISE_SD,
    FitBounds,
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

    def __init__(self, params: MechanismParams, motion: Motion, weights=None, bounds: FitBounds | None = None):
        b = bounds or FitBounds()
        self.axis_deg, self.axis_point_mm, self.tendon_mm = b.pf_axis_deg, b.pf_axis_point_mm, b.pf_tendon_mm
        self.length_mm, self.pitch_mm_per_rad = b.pf_length_mm, b.pf_pitch_mm_per_rad
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
        t = math.tan(math.radians(self.axis_deg))
        # axes
        for k, (axis, point, n0, B) in enumerate(((PF_AXIS_FEMUR, PF_POINT_FEMUR, self.nf0, self.Bf),
                                                  (PF_AXIS_PATELLA, PF_POINT_PATELLA, self.np0, self.Bp))):
            v, Jv = bounded_ball(w[None, 4 * k:4 * k + 2], t)
            p[axis] = n0 + B @ v[0]
            D[axis, 4 * k:4 * k + 2] = B @ Jv[0]
            q, Jq = bounded_ball(w[None, 4 * k + 2:4 * k + 4], self.axis_point_mm)
            xy = slice(point.start, point.start + 2)  # the point moves in the sagittal plane (x, y)
            p[xy] += q[0]
            D[xy, 4 * k + 2:4 * k + 4] = Jq[0]
        for k, end in enumerate((PF_TENDON_TIBIA, PF_TENDON_PATELLA)):
            d, Jd = bounded_ball(w[None, 8 + 3 * k:11 + 3 * k], self.tendon_mm)
            p[end] += d[0]
            D[end, 8 + 3 * k:11 + 3 * k] = Jd[0]
        for k, (o, rng) in enumerate(((PF_TENDON_LENGTH, self.length_mm), (PF_LAMBDA0, self.length_mm),
                                      (PF_LAMBDA1, self.pitch_mm_per_rad))):
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

    def _dq(self, w):
        r = self._solve(w)
        if not r.ok:
            return None
        sens = pf_sensitivities(self.params_vector(w), self.kinds, r.Z[self.index], self.alphas)
        return self._units(sens.d_params[:, 6:12, :]).reshape(-1, self.p0.size)

    def jacobian(self, w) -> np.ndarray:
        dq = self._dq(w)
        if dq is None:
            return np.zeros((6 * len(self.alphas), self.n_var))
        return dq @ self._maps(w)[1]

    #: The variables' names and units (their physical offsets: axis tilts, point moves, lengths, pitch).
    NAMES = ("axis_femur.tilt1", "axis_femur.tilt2", "point_femur.x", "point_femur.y", "axis_patella.tilt1",
             "axis_patella.tilt2", "point_patella.x", "point_patella.y", "tendon_tibia.x", "tendon_tibia.y",
             "tendon_tibia.z", "tendon_patella.x", "tendon_patella.y", "tendon_patella.z", "tendon_length",
             "lambda0", "lambda1")
    UNITS = ("deg", "deg", "mm", "mm", "deg", "deg", "mm", "mm", "mm", "mm", "mm", "mm", "mm", "mm", "mm", "mm",
             "mm/rad")

    def diagnostics(self, w) -> FitDiagnostics:
        """Bounds used, identifiability and confidence intervals at ``w`` in the physical offsets (axis
        tilts in deg, points and lengths in mm, pitch in mm/rad; :mod:`knee.fitting.diagnostics`)."""
        w = np.asarray(w, float)
        t = math.tan(math.radians(self.axis_deg))
        scale = np.array([t, t, self.axis_point_mm, self.axis_point_mm] * 2 + [self.tendon_mm] * 6
                         + [self.length_mm, self.length_mm, self.pitch_mm_per_rad])
        per_deg = np.where(np.array(self.UNITS) == "deg", math.radians(1.0), 1.0)  # tan(tilt) ~ tilt
        D0 = self._maps(np.zeros(self.n_var))[1] / scale * per_deg  # d vector / d physical offset
        blocks = [(0, 2, t), (2, 4, self.axis_point_mm), (4, 6, t), (6, 8, self.axis_point_mm), (8, 11, self.tendon_mm),
                  (11, 14, self.tendon_mm)]
        use = np.zeros(self.n_var)
        for a, b, rad in blocks:
            use[a:b] = float(np.linalg.norm(bounded_ball(w[None, a:b], rad)[0])) / rad
        use[14:] = np.abs(np.tanh(w[14:]))
        dq = self._dq(w)
        J = np.zeros((6 * len(self.alphas), self.n_var)) if dq is None else dq @ D0
        return diagnose("pf", self.NAMES, self.UNITS, J, self.residuals(w), use)


PFFitResult = FitResult  # the same fields; ``mae`` (6,): deg x3, mm x3, fitted model vs measured


def fit_pf(params: MechanismParams, motion: Motion, seed: int = 0, global_stage: bool = True, popsize: int = 10,
           maxiter: int = 12, w_box: float = 2.5, local_starts: int = 4, progress=None,
           bounds: FitBounds | None = None, noise_sd: dict | None = None) -> PFFitResult:
    """Fit the PF group of ``params`` (TF group already fitted) to ``motion`` (see the module docstring)
    within ``bounds`` (default: the paper's, :class:`~knee.fitting.optimize.FitBounds`)."""
    t0 = time.perf_counter()
    prob = PFFit(params, motion, bounds=bounds, weights=pf_noise_weights(noise_sd))
    say = progress or (lambda f, t: None)
    w, c0, cg = two_stage(prob, prob.n_var, seed, global_stage, popsize, maxiter, w_box, local_starts, say,
                          "PF fit")
    if not prob.model_motion(w)[1]:
        raise KneeInputError("no PF candidate within the bounds assembles over the measured range")
    return PFFitResult(params=prob.params(w), w=w, cost_first=c0, cost_global=cg, cost_final=prob.cost(w),
                       evaluations=prob.evaluations, seconds=time.perf_counter() - t0, mae=prob.mae(w),
                       diagnostics=prob.diagnostics(w))
