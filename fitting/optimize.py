"""Bounded optimisation of a mechanism's tibio-femoral geometry against a measured motion (seed 002,
section 2.4; issue "fit a subject-specific mechanism", step 6).

Variables (the paper's 35 TF parameters): the ten link endpoints, each an offset from its first estimate
confined to a ball of radius ``radius`` mm (2 mm in the paper) by the smooth map
``offset = radius * tanh(|w|) * w / |w|``, and the five lengths (or sphere-plane distances), each within
``length_range`` mm of its first estimate by ``length_range * tanh(w)``. The objective: the squared
differences between the model's and the measured TF components (adduction and internal rotation in
degrees, the three translations in mm) at the measured flexion angles. A candidate that does not
assemble over the measured range, jumps between branches, or comes close to a singularity (Jacobian
condition number above ``max_condition``) is rejected (a large constant residual).

Stages: a global one (``scipy.optimize.differential_evolution``, seeded, on the unconstrained variables
within +-``w_box``), then a local Gauss-Newton (``scipy.optimize.least_squares``) with the exact Jacobian
from the mechanism's CasADi sensitivities, chained through the two maps above.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import differential_evolution, least_squares

from knee.fitting.diagnostics import FitDiagnostics, diagnose
from knee.foundations.errors import KneeInputError
from knee.models.mechanism.params import (
    LINK_FEMUR,
    LINK_LENGTH,
    LINK_TIBIA,
    N_LINKS,
    MechanismParams,
    link_entries,
)
from knee.models.mechanism.solver import (
    Mechanism,
    dense_grid,
    quick_tf_sweep,
    tf_sensitivities,
)

REJECTED = 1e3  # residual (deg or mm) given to every component of a rejected candidate


@dataclass
class Motion:
    """A measured (or generated) motion: ``tf`` (n, 6) and optionally ``pf`` (n, 6) joint coordinates
    (rad, mm), one row per frame, TF flexion first."""

    tf: np.ndarray
    pf: np.ndarray | None = None

    @property
    def flexion(self) -> np.ndarray:
        return self.tf[:, 0]


def cycle_phases(flexion, turn_deg: float = 3.0) -> list:
    """The trial's phases: (first row, last row, +1 flexing or -1 extending), split where the flexion turns
    back by more than ``turn_deg`` from its running extreme (smaller reversals are noise and stay in the
    phase; so does a first move smaller than ``turn_deg`` against the trial's first direction).
    Consecutive phases share their turning row. A trial that never moves by ``turn_deg`` is one phase of
    direction 0."""
    a = np.degrees(np.asarray(flexion, float))
    phases, start, ext, sign = [], 0, 0, 0
    lo_i = hi_i = 0
    for k in range(1, len(a)):  # a scan over the trial's frames, once, before the fit
        if sign == 0:
            lo_i = k if a[k] < a[lo_i] else lo_i
            hi_i = k if a[k] > a[hi_i] else hi_i
            if a[hi_i] - a[lo_i] > turn_deg:
                # the first move larger than turn_deg sets the direction; a turn before it splits there
                sign = 1 if hi_i > lo_i else -1
                turn = lo_i if sign > 0 else hi_i
                start = 0
                if abs(a[turn] - a[0]) > turn_deg:
                    phases.append((0, turn, -sign))
                    start = turn
                ext = hi_i if sign > 0 else lo_i
            continue
        if sign * (a[k] - a[ext]) >= 0:
            ext = k
        elif sign * (a[ext] - a[k]) > turn_deg:
            phases.append((start, ext, sign))
            start, sign, ext = ext, -sign, k
    phases.append((start, len(a) - 1, sign))
    return phases


def average_cycle_halves(motion: Motion, step_deg: float = 1.0, turn_deg: float = 3.0) -> Motion:
    """A trial's flexing and extending phases averaged (seed 002 fitted, and measured its errors against,
    the mean of a cycle's flexion and extension): the trial split into phases where the flexion turns
    back (:func:`cycle_phases`); each phase interpolated over flexion (every ``step_deg``); the phases of
    one direction averaged where they overlap and joined across gaps between them; then the two
    directions averaged component by component over the flexion both cover. A trial may start anywhere
    and turn several times (flex, extend past its start, flex again). Refused when one direction is
    missing or the two overlap by less than 5 deg."""
    a = motion.flexion
    phases = [p for p in cycle_phases(a, turn_deg) if p[2] != 0]
    spans = {d: [(a[s:e + 1].min(), a[s:e + 1].max()) for s, e, sd in phases if sd == d] for d in (1, -1)}
    if not spans[1] or not spans[-1]:
        raise KneeInputError("averaging the cycle's halves needs a flexion half and an extension half (the trial "
                             f"never turns back by more than {turn_deg:g} deg)")
    lo = max(min(s[0] for s in spans[d]) for d in (1, -1))
    hi = min(max(s[1] for s in spans[d]) for d in (1, -1))
    if hi - lo < math.radians(5.0) or any(max(s[1] - s[0] for s in spans[d]) < math.radians(5.0) for d in (1, -1)):
        raise KneeInputError("averaging the cycle's halves needs a flexion half and an extension half that each "
                             f"cover 5 deg or more and overlap by 5 deg (the halves cover {_spans_text(spans)})")
    grid = np.arange(lo, hi + 1e-12, math.radians(step_deg))

    def direction_mean(q, d):
        """(grid, c) the phases of direction d interpolated on the grid, averaged where they overlap,
        linearly joined across the gaps between them."""
        acc, cnt = np.zeros((grid.size, q.shape[1])), np.zeros(grid.size)
        for s, e, sd in phases:
            if sd != d:
                continue
            order = np.argsort(a[s:e + 1], kind="stable")
            x, y = a[s:e + 1][order], q[s:e + 1][order]
            inside = (grid >= x[0]) & (grid <= x[-1])
            acc[inside] += np.stack([np.interp(grid[inside], x, y[:, j]) for j in range(q.shape[1])], axis=1)
            cnt[inside] += 1
        have = cnt > 0
        out = acc[have] / cnt[have, None]
        return np.stack([np.interp(grid, grid[have], out[:, j]) for j in range(q.shape[1])], axis=1)

    def mean(q):
        if q is None:
            return None
        return 0.5 * (direction_mean(q, 1) + direction_mean(q, -1))

    tf = mean(motion.tf)
    tf[:, 0] = grid
    return Motion(tf, mean(motion.pf))


def _spans_text(spans) -> str:
    return "; ".join(("flexion " if d > 0 else "extension ")
                     + ", ".join(f"{math.degrees(s0):.1f}-{math.degrees(s1):.1f}" for s0, s1 in spans[d])
                     + " deg" for d in (1, -1))


def noise_weights(sd=None) -> np.ndarray:
    """Weights 1/sd for (adduction, internal rotation, anterior, proximal, lateral), normalised so the
    sagittal translations weigh 1: a maximum-likelihood objective under the measurement noise."""
    sd = sd or NOISE_SD
    s = np.array([sd["out_of_plane_deg"], sd["out_of_plane_deg"], sd["sagittal_mm"], sd["sagittal_mm"],
                  sd["out_of_plane_mm"]])
    return sd["sagittal_mm"] / s


#: Fluoroscopy-like noise (seed 002, 3DV accuracy): about 0.5 mm and 1 deg in the sagittal plane
#: (flexion, anterior, proximal) and 1.5 mm and 2 deg out of it (adduction, internal rotation, lateral).
NOISE_SD = {"sagittal_deg": 1.0, "sagittal_mm": 0.5, "out_of_plane_deg": 2.0, "out_of_plane_mm": 1.5}


def checked_numbers(values: dict | None, limits: dict, where: str, what: str) -> dict:
    """``values`` ({name: number}) checked against ``limits`` ({name: largest}): known names, numbers in
    (0, largest]; :class:`KneeInputError` naming ``where`` and ``what`` otherwise. Returns floats."""
    out = {}
    for k, v in (values or {}).items():
        if k not in limits:
            raise KneeInputError(f"{where}: unknown {what} {k!r} (known: {', '.join(limits)})")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0.0 < v <= limits[k]):
            raise KneeInputError(f"{where}: {what} {k} must be a number in (0, {limits[k]:g}], got {v!r}")
        out[k] = float(v)
    return out


#: The largest noise level (sd, deg or mm) accepted for each component group.
NOISE_LIMITS = {k: 100.0 for k in NOISE_SD}


def noise_sd(values: dict | None, where: str) -> dict:
    """:data:`NOISE_SD` with ``values`` ({name: sd}) over it, checked (:func:`checked_numbers`): the
    measurement's standard deviations, deg and mm, that weigh the fit's components."""
    return {**NOISE_SD, **checked_numbers(values, NOISE_LIMITS, where, "noise level")}


def synthetic_motion(params: MechanismParams, flexion_deg, noise: bool = True, seed: int = 0):
    """``(measured, truth)`` motions of a parameter set at the given flexion angles (degrees), the
    measured one with :data:`NOISE_SD` Gaussian noise on every TF and PF component."""
    mech = Mechanism(params)
    res = mech.sweep(np.radians(np.asarray(flexion_deg, float)))
    if not res.complete:
        raise KneeInputError(f"the model does not assemble over the requested flexion range: {res.message}")
    truth = Motion(res.tf.copy(), res.pf.copy() if params.has_pf else None)
    if not noise:
        return Motion(truth.tf.copy(), None if truth.pf is None else truth.pf.copy()), truth
    rng = np.random.default_rng(seed)
    sd = np.array([np.radians(NOISE_SD["sagittal_deg"]), np.radians(NOISE_SD["out_of_plane_deg"]),
                   np.radians(NOISE_SD["out_of_plane_deg"]), NOISE_SD["sagittal_mm"], NOISE_SD["sagittal_mm"],
                   NOISE_SD["out_of_plane_mm"]])
    tf = truth.tf + rng.normal(size=truth.tf.shape) * sd
    pf = None if truth.pf is None else truth.pf + rng.normal(size=truth.pf.shape) * sd
    return Motion(tf, pf), truth


def perturb_endpoints(params: MechanismParams, low: float = 0.5, high: float = 2.0,
                      seed: int | Sequence[int] | np.random.Generator = 0) -> MechanismParams:
    """A copy with every TF link endpoint moved in a random direction by a random distance in
    [low, high] mm (a first estimate within the paper's 2 mm of the truth). ``seed``: the random stream's
    seed, a whole number or a sequence of them, or the stream itself (what :func:`numpy.random.default_rng`
    takes)."""
    rng = np.random.default_rng(seed)
    v = params.to_vector().copy()
    for i in range(N_LINKS):
        for part in (LINK_FEMUR, LINK_TIBIA):
            d = rng.normal(size=3)
            v[link_entries(i, part)] += d * rng.uniform(low, high) / np.linalg.norm(d)
    return params.with_vector(v)


def bounded_ball(w, radius):
    """Offsets (k, d) in the open ball of ``radius`` from unconstrained w (k, d), and d offset / d w
    (k, d, d)."""
    r = np.linalg.norm(w, axis=1)
    safe = np.maximum(r, 1e-12)
    g = np.where(r > 1e-8, np.tanh(safe) / safe, 1.0 - safe ** 2 / 3)  # tanh(r)/r
    off = radius * g[:, None] * w
    # d(g w)/dw = g I + (g'(r)/r) w w^T with g'(r) = (sech^2 r - g)/r
    dg = np.where(r > 1e-8, (1 / np.cosh(safe) ** 2 - g) / safe, -2 * safe / 3)
    J = radius * (g[:, None, None] * np.eye(w.shape[1]) + (dg / safe)[:, None, None] * w[:, :, None] * w[:, None, :])
    return off, J


@dataclass(frozen=True)
class FitBounds:
    """How far the bounded fit may move each group's parameters from the first estimate (seed 002's values
    are the defaults): TF link endpoints within ``tf_endpoint_mm`` (a ball), lengths within
    ``tf_length_mm``; the PF helical axis directions within ``pf_axis_deg``, its points (in the sagittal
    planes) within ``pf_axis_point_mm``, the tendon endpoints within ``pf_tendon_mm``, the tendon length
    and lambda0 within ``pf_length_mm``, the pitch within ``pf_pitch_mm_per_rad``. Set per subject in
    ``subject.toml``'s ``[fit]`` table or with ``knee fit --bounds KEY=VALUE,...``."""

    tf_endpoint_mm: float = 2.0
    tf_length_mm: float = 5.0
    pf_axis_deg: float = 5.0
    pf_axis_point_mm: float = 5.0
    pf_tendon_mm: float = 2.0
    pf_length_mm: float = 5.0
    pf_pitch_mm_per_rad: float = 2.0

    #: The largest value each may take (beyond it the first estimate no longer anchors the fit).
    LIMITS = {"tf_endpoint_mm": 20.0, "tf_length_mm": 30.0, "pf_axis_deg": 45.0, "pf_axis_point_mm": 50.0,
              "pf_tendon_mm": 20.0, "pf_length_mm": 30.0, "pf_pitch_mm_per_rad": 20.0}

    def updated(self, values: dict, where: str) -> "FitBounds":
        """A copy with ``values`` ({name: number}) checked against :attr:`LIMITS` (:func:`checked_numbers`)."""
        return replace(self, **checked_numbers(values, self.LIMITS, where, "bound"))


class MotionFit:
    """The objective shared by the TF and PF fits: the noise-weighted differences between the model's and
    the measured components at the measured flexion angles, the first ``n_deg`` components (angles) in
    degrees, the others in mm. Subclasses give ``_compared(w) -> (model (n, c), measured (n, c), ok)``,
    ``weights`` (c,) and the exact ``jacobian``."""

    n_deg = 0

    def _compared(self, w):  # pragma: no cover - abstract
        raise NotImplementedError

    def _units(self, d):
        """Differences (n, c) or their derivatives (n, c, p): the first ``n_deg`` components rad -> deg,
        then weighted."""
        d = np.array(d, copy=True)
        d[:, :self.n_deg] = np.degrees(d[:, :self.n_deg])
        return d * self.weights.reshape((1, -1) + (1,) * (d.ndim - 2))

    def residuals(self, w) -> np.ndarray:
        """(c n,) model minus measured, weighted; a constant ``REJECTED`` for a rejected candidate."""
        model, measured, ok = self._compared(w)
        if not ok:
            return np.full(measured.size, REJECTED)
        return self._units(model - measured).ravel()

    def cost(self, w) -> float:
        r = self.residuals(w)
        return float(r @ r)

    def mae(self, w) -> np.ndarray:
        """(c,) mean absolute differences (deg, mm) of the candidate against the measured motion."""
        r = self.residuals(w).reshape(-1, len(self.weights))
        return np.abs(r / self.weights).mean(axis=0)


class TFFit(MotionFit):
    """The fitting problem of the TF group; see the module docstring.

    Parameters
    ----------
    first : MechanismParams
        The first estimate (its endpoints are the centres of the bound balls).
    motion : Motion
        The measured motion (rad, mm), frames in the order of the movement (the continuation follows
        them; small reversals from noise are fine).
    """

    def __init__(self, first: MechanismParams, motion: Motion, radius: float = 2.0, length_range: float = 5.0,
                 max_condition: float = 1e4, weights=None, assemble_over_deg=None):
        self.first = first
        self.motion = motion
        self.radius, self.length_range, self.max_condition = float(radius), float(length_range), max_condition
        self.p0 = first.to_vector()
        self.kinds = first.kinds
        self.n_var = 35
        if len(motion.tf) < 2 or not np.all(np.isfinite(motion.tf)):
            raise KneeInputError("the measured motion needs at least two finite frames")
        self.alphas = motion.flexion
        self.grid, self.index = dense_grid(self.alphas)
        self.x_start = motion.tf[int(np.argmin(self.alphas)), 1:]
        # beyond the measured range, a candidate must still assemble over ``assemble_over_deg`` (lo, hi): the
        # continuation runs on past the measured angles (1 deg steps) up to hi, and down from the first to lo
        self.grid_up = self.grid_down = None
        if assemble_over_deg is not None:
            lo, hi = (math.radians(v) for v in assemble_over_deg)
            if hi > self.grid[-1]:
                self.grid_up = np.linspace(self.grid[-1], hi, int(np.ceil((hi - self.grid[-1]) / math.radians(1))) + 1)[1:]
            if lo < self.grid[0]:
                self.grid_down = np.linspace(self.grid[0], lo, int(np.ceil((self.grid[0] - lo) / math.radians(1))) + 1)
        self.evaluations = 0
        # per-component weights on (adduction deg, internal rotation deg, anterior, proximal, lateral mm)
        self.weights = np.ones(5) if weights is None else np.asarray(weights, float)

    # -- parameter maps ------------------------------------------------------------------------
    def params_vector(self, w) -> np.ndarray:
        w = np.asarray(w, float)
        off, _ = bounded_ball(w[:30].reshape(10, 3), self.radius)
        p = self.p0.copy()
        for i in range(N_LINKS):
            p[link_entries(i, LINK_FEMUR)] += off[2 * i]
            p[link_entries(i, LINK_TIBIA)] += off[2 * i + 1]
            p[link_entries(i, LINK_LENGTH)] += self.length_range * np.tanh(w[30 + i])
        return p

    def params(self, w) -> MechanismParams:
        return self.first.with_vector(self.params_vector(w))

    def _dparams_dw(self, w) -> np.ndarray:
        """d(flat parameter vector)/dw, (N_PARAMS, 35)."""
        w = np.asarray(w, float)
        _, Jb = bounded_ball(w[:30].reshape(10, 3), self.radius)
        D = np.zeros((self.p0.size, 35))
        for i in range(N_LINKS):
            D[link_entries(i, LINK_FEMUR), 6 * i:6 * i + 3] = Jb[2 * i]
            D[link_entries(i, LINK_TIBIA), 6 * i + 3:6 * i + 6] = Jb[2 * i + 1]
            D[link_entries(i, LINK_LENGTH), 30 + i] = self.length_range / np.cosh(w[30 + i]) ** 2
        return D

    # -- objective -----------------------------------------------------------------------------
    def model_motion(self, w):
        """(tf (n, 6), ok) of the candidate at the measured flexion angles (swept along
        :func:`dense_grid`; ok also requires every grid angle's condition number below the limit)."""
        p = self.params_vector(w)
        grid = self.grid if self.grid_up is None else np.concatenate([self.grid, self.grid_up])
        tf, _, ok, cond = quick_tf_sweep(p, self.kinds, self.x_start, grid)
        self.evaluations += 1
        ok = bool(ok and np.all(cond[:self.grid.size] < self.max_condition))
        if ok and self.grid_down is not None:
            ok = bool(quick_tf_sweep(p, self.kinds, self.x_start, self.grid_down)[2])
        return tf[self.index], ok

    n_deg = 2  # adduction, internal rotation; then the three translations

    def _compared(self, w):
        tf, ok = self.model_motion(w)
        return tf[:, 1:], self.motion.tf[:, 1:], ok

    def _dq(self, w) -> np.ndarray | None:
        """d residuals / d (flat parameter vector), (5 n, N_PARAMS); None where the candidate is rejected."""
        tf, ok = self.model_motion(w)
        if not ok:
            return None
        sens = tf_sensitivities(self.params_vector(w), self.kinds, tf)
        dq = self._units(sens.d_params[:, 1:6, :])  # (n, 5, N_PARAMS): beta, gamma, P
        return dq.reshape(-1, self.p0.size)

    def jacobian(self, w) -> np.ndarray:
        """Exact d residuals / d w, (5 n, 35), from the mechanism's sensitivities."""
        dq = self._dq(w)
        if dq is None:
            return np.zeros((5 * len(self.alphas), 35))
        return dq @ self._dparams_dw(w)

    def diagnostics(self, w) -> FitDiagnostics:
        """Bounds used, identifiability and confidence intervals at ``w``, in the physical offsets: each
        endpoint's move (mm) and each length's change (mm) (:mod:`knee.fitting.diagnostics`)."""
        w = np.asarray(w, float)
        idx, names, use = [], [], []
        off, _ = bounded_ball(w[:30].reshape(10, 3), self.radius)
        for i, lk in enumerate(self.first.links):
            for j, (part, end) in enumerate(((LINK_FEMUR, "femur"), (LINK_TIBIA, "tibia"))):
                e = link_entries(i, part)
                idx += list(range(e.start, e.stop))
                names += [f"{lk.name}.{end}.{c}" for c in "xyz"]
                use += [float(np.linalg.norm(off[2 * i + j])) / self.radius] * 3
        for i, lk in enumerate(self.first.links):
            idx.append(link_entries(i, LINK_LENGTH))
            names.append(f"{lk.name}.length")
            use.append(abs(math.tanh(w[30 + i])))
        dq = self._dq(w)
        J = np.zeros((5 * len(self.alphas), len(idx))) if dq is None else dq[:, idx]
        return diagnose("tf", names, ["mm"] * len(idx), J, self.residuals(w), use)


@dataclass
class FitResult:
    params: MechanismParams
    w: np.ndarray
    cost_first: float
    cost_global: float
    cost_final: float
    evaluations: int
    seconds: float
    mae: np.ndarray  # of the fitted model vs the measured motion: TF (5,) deg, deg, mm, mm, mm; PF (6,)
    diagnostics: FitDiagnostics | None = None


def two_stage(prob, n_var: int, seed: int = 0, global_stage: bool = True, popsize: int = 12, maxiter: int = 15,
              w_box: float = 2.5, local_starts: int = 6, progress=None, label: str = "fit"):
    """The paper's two stages on a fitting problem ``prob`` (with ``cost``, ``residuals``, ``jacobian`` and
    ``model_motion`` of unconstrained variables w, (n_var,)): seeded differential evolution within
    +-``w_box``, then Gauss-Newton (trust region, exact Jacobian) from the first estimate (w = 0) and from
    the ``local_starts`` best members of the final population; the lowest cost wins.

    ``progress(fraction, text)`` is called as the work advances. Returns ``(w, cost_first, cost_global)``.
    """
    w = np.zeros(n_var)
    cost_first = prob.cost(w)
    cost_global = cost_first
    say = progress or (lambda f, t: None)
    if global_stage:
        gen = [0]

        def cb(xk, convergence=None):
            gen[0] += 1
            say(0.7 * gen[0] / maxiter, f"{label}: global stage, generation {gen[0]}/{maxiter}")

        de = differential_evolution(prob.cost, [(-w_box, w_box)] * n_var, seed=seed, popsize=popsize,
                                    maxiter=maxiter, tol=1e-8, polish=False, init="latinhypercube", x0=w,
                                    callback=cb, updating="immediate")
        order = np.argsort(de.population_energies)
        starts = [w] + [de.population[i] for i in order[:local_starts]]
        if de.fun < cost_first:
            w, cost_global = de.x, float(de.fun)
    else:
        starts = [w]
    best_w, best_cost = w, cost_global
    for k, w0 in enumerate(starts):
        if not prob.model_motion(w0)[1]:
            continue
        ls = least_squares(prob.residuals, w0, jac=prob.jacobian, method="trf", x_scale="jac", max_nfev=40)
        if 2 * ls.cost < best_cost:
            best_w, best_cost = ls.x, 2 * ls.cost
        say(0.7 + 0.3 * (k + 1) / len(starts), f"{label}: local stage {k + 1}/{len(starts)}, best cost {best_cost:.4g}")
    return best_w, cost_first, cost_global


def fit_tf(first: MechanismParams, motion: Motion, seed: int = 0, global_stage: bool = True,
           popsize: int = 12, maxiter: int = 15, w_box: float = 2.5, local_starts: int = 6,
           progress=None, bounds: FitBounds | None = None, **kwargs) -> FitResult:
    """Fit the TF group of ``first`` to ``motion`` (see the module docstring and :func:`two_stage`) within
    ``bounds`` (default: the paper's, :class:`FitBounds`).

    ``progress``: None or a callable ``progress(fraction, text)`` called as the work advances.
    """
    t0 = time.perf_counter()
    if bounds is not None:
        kwargs.update(radius=bounds.tf_endpoint_mm, length_range=bounds.tf_length_mm)
    prob = TFFit(first, motion, **kwargs)
    say = progress or (lambda f, t: None)
    w, cost_first, cost_global = two_stage(prob, 35, seed, global_stage, popsize, maxiter, w_box, local_starts,
                                           say, "TF fit")
    if not prob.model_motion(w)[1]:
        extra = "" if prob.grid_up is None and prob.grid_down is None else " and the range it must cover"
        raise KneeInputError(f"no candidate within the bounds assembles over the measured range{extra}; widen the "
                             "bounds (--bounds) or narrow the range (--assemble-over)")
    return FitResult(params=prob.params(w), w=w, cost_first=cost_first, cost_global=cost_global,
                     cost_final=prob.cost(w), evaluations=prob.evaluations, seconds=time.perf_counter() - t0,
                     mae=prob.mae(w), diagnostics=prob.diagnostics(w))


def motion_mae(params: MechanismParams, truth: Motion) -> np.ndarray:
    """Mean absolute differences (adduction, internal rotation in deg; three translations in mm; and
    flexion is the input) between a parameter set's TF motion and ``truth`` at truth's flexion angles."""
    tf, _, ok, _ = quick_tf_sweep(params.to_vector(), params.kinds, truth.tf[0, 1:], truth.flexion)
    if not ok:
        return np.full(5, np.inf)
    d = tf[:, 1:] - truth.tf[:, 1:]
    d[:, :2] = np.degrees(d[:, :2])
    return np.abs(d).mean(axis=0)


