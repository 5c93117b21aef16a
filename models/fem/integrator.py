"""Implicit Euler (seed 000, eqs. 2-3) with lumped mass and Rayleigh damping.

One linear solve per step: with C = a M + b K and the forces linearised about the current positions,

    ((1 + dt a) M + (dt b + dt^2) K) v' = M v + dt f(x),     x' = x + dt v'.

The matrix is never assembled per step: the conjugate-gradient solve applies the co-rotated element
stiffnesses directly (gather, element products, scatter), warm-started from the last velocity and
preconditioned with a sparse factorisation of the assembled matrix (:mod:`knee.models.fem.factor`: a supernodal
Cholesky, CHOLMOD, when available, else SuperLU's LU in symmetric mode; single-precision factors were tried and
cost more iterations after the prior's initialisation than they saved), warped by the nodes' rotations since
it was computed (nodal rotations: :func:`knee.models.fem.scene.node_rotations`). The factorisation is kept
across steps and refreshed (the fields' matrices scattered onto a lower-triangle pattern kept across
refreshes, :mod:`knee.models.fem.system`, built when the model is built by :meth:`ImplicitEuler.prepare`, and
refactorised with the symbolic analysis reused while that pattern stays) by an amortised rule: when the
iterations spent beyond the count right after the last refresh add up to more than the cost of a
refactorisation (in iterations: measured, its time over an iteration's, or a fixed ``refresh_cost``); and
at once, in the middle of a step, when CG has not converged within ``restart_iterations``, or earlier
when the rate at which the residual has fallen so far predicts that finishing would take longer than a
refactorisation and the few iterations after one (the matrix has moved too far from the factorised one,
e.g. when many surface springs or contact pairs switch at once; both costs are measured as the solver
runs): the solve then finishes from where it stopped with the new factors. The conjugate-gradient loop is
the toolkit's own, for that residual history. Fields that offer ``low_rank_factor()`` (springs between
wide bone attachments) enter the preconditioner by the Woodbury identity instead of the assembled matrix;
fields that offer ``factor_matrix()`` (the depth points' springs) are factorised by that narrower matrix,
their iterations still using the whole stiffness.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from knee.models.fem.factor import Refactorizer
from knee.models.fem.system import SystemAssembler


@dataclass
class StepInfo:
    iterations: int
    refreshed: bool
    residual: float  # CG's final residual (its recurrence) relative to the right-hand side


class ImplicitEuler:
    """Integrate ``x, v`` (N, 3) under ``fields`` plus an external-force callback.

    Parameters
    ----------
    mass : (N,) float
        Lumped nodal masses (tonne, with mm, N, s).
    fields : list
        Objects with ``forces(x)``, ``apply(p)`` and ``matrix()`` (see :mod:`knee.models.fem.fields`).
    dt : float
        Time step (s); the paper's 0.05.
    rayleigh_mass, rayleigh_stiffness : float
        Rayleigh damping coefficients a (1/s) and b (s).
    predict_refresh : bool
        Refactorise mid-step when the convergence so far predicts it pays (see the module docstring).
        The decision uses measured times, so where the refactorisations fall can differ between runs:
        every step is still solved to ``tol``, but results agree to that tolerance rather than bit for
        bit; ``False`` makes runs repeat exactly (refactorisations then only by the iteration counts).
    factor_backend : str
        "cholmod" (default: supernodal Cholesky when cvxopt is installed, SuperLU otherwise) or "superlu".
    """

    #: The integrator's settings (as opposed to its state): what a model's reset keeps as the user set them.
    SETTINGS = ("dt", "a", "b", "tol", "max_iterations", "refresh_cost", "adaptive_refresh", "restart_iterations",
                "predict_refresh", "factor_backend")

    def __init__(self, x0, mass, fields, dt=0.05, rayleigh_mass=0.1, rayleigh_stiffness=0.1,
                 tol=1e-5, max_iterations=200, refresh_cost=None, fixed=None, node_rotations=None,
                 restart_iterations=40, predict_refresh=True, factor_backend="cholmod"):
        self.x = np.array(x0, dtype=float)
        self.fixed = np.zeros(len(self.x), bool) if fixed is None else np.asarray(fixed, bool)
        self._free = np.repeat(~self.fixed, 3).astype(float)
        self.v = np.zeros_like(self.x)
        self.m = np.asarray(mass, dtype=float)
        self.fields = list(fields)
        self.dt = float(dt)
        self.a, self.b = float(rayleigh_mass), float(rayleigh_stiffness)
        self.tol, self.max_iterations = tol, max_iterations
        self.refresh_cost = 60 if refresh_cost is None else refresh_cost
        self.restart_iterations = restart_iterations
        self.predict_refresh = predict_refresh
        # the amortised rule's threshold measured (see _refresh_cost_iterations) unless refresh_cost is given
        self.adaptive_refresh = refresh_cost is None
        self.factor_backend = factor_backend  # "cholmod" (falls back to SuperLU when unavailable) or "superlu"
        self._t_iteration = None      # measured seconds per CG iteration (running estimate)
        self._t_factor = None         # measured seconds of the last refresh (assembly + factorisation; a
        #                               new pattern's one-off work left out)
        self._lu = None
        self._woodbury = None
        self._system = None    # the matrix's kept lower-triangle pattern (knee.models.fem.system)
        self._refactor = None  # CHOLMOD's analysis kept while that pattern stays
        self._best_iterations = None  # CG iterations of the first step after the last refresh
        self._excess = 0.0            # iterations spent beyond that since the last refresh
        # node_rotations(x) -> (N, 3, 3) rotations of the material around each node (for the warped
        # preconditioner W LU^-1 W^T, W = rotations since the last factorisation); None: no warping
        self.node_rotations = node_rotations
        self._R_ref = None
        self.time = 0.0
        self.steps = 0
        self.refreshes = 0
        self.last_info = None

    @property
    def _cm(self):
        return 1.0 + self.dt * self.a

    @property
    def _ck(self):
        return self.dt * self.b + self.dt * self.dt

    def _full(self, q):
        """A q with no projection (all DOFs)."""
        out = self._cm * self.m[:, None] * q
        for f in self.fields:
            out += self._ck * f.apply(q)
        return out

    def _operator(self, p):
        """A p on the free DOFs, identity on the fixed ones (velocities held at zero)."""
        fr = self._free.reshape(-1, 3)
        return self._full(p * fr) * fr + p * (1 - fr)

    def set_prescribed(self, mask) -> None:
        """Exclude the nodes of ``mask`` (N,) bool from the solve, like fixed ones (``None``: none); a step
        with ``prescribed`` sets this for its duration."""
        mask = np.zeros(len(self.x), bool) if mask is None else np.asarray(mask, bool)
        free = np.repeat(~(self.fixed | mask), 3).astype(float)
        if not np.array_equal(free, self._free):
            self._free = free
            self.invalidate()  # the preconditioner must see the same free set

    def invalidate(self) -> None:
        """Forget the factorisation: the next step refactorises before it solves. For changes the kept
        factors must not outlive: fields added or removed, damping changed, nodes held or released."""
        self._lu = None

    def prepare(self) -> None:
        """Build the matrix's kept pattern from the fields' current matrices (and what they reserve) now,
        with each field's positions in it, instead of at the first refactorisation: one-off set-up work
        (about 0.1 s on the knee model) done when the model is built."""
        self._system = None
        self._assembler().prime([f.matrix() for f in self.fields])

    def reserve_pattern(self, matrix) -> None:
        """Entries the matrix will need soon (e.g. contact pairs along a planned motion), added to the kept
        pattern now: see :meth:`knee.models.fem.system.SystemAssembler.reserve`."""
        self._assembler().reserve(matrix)

    def _assembler(self) -> SystemAssembler:
        n3 = 3 * len(self.m)
        if self._system is None or self._system.n != n3:
            self._system = SystemAssembler(n3, reserve=[r for r in (getattr(f, "pattern_reserve", lambda: None)()
                                                                    for f in self.fields) if r is not None])
        return self._system

    def _refresh(self):
        t0 = time.perf_counter()
        n3 = 3 * len(self.m)
        sysm = self._assembler()
        if self._refactor is None or self._refactor.prefer != self.factor_backend:
            self._refactor = Refactorizer(self.factor_backend)
        # a field may offer a narrower matrix to factorise (factor_matrix) than the one its iterations use
        mats = [getattr(f, "factor_matrix", f.matrix)() for f in self.fields]
        indptr, indices, data = sysm.assemble(np.repeat(self._cm * self.m, 3), mats, self._ck, self._free)
        self._lu = self._refactor.factor(sysm.version, n3, indptr, indices, data)
        # low-rank fields (springs between wide bone attachments) by the Woodbury identity:
        # (A + c U U^T)^-1 = A^-1 - Z (I/c + U^T Z)^-1 Z^T, Z = A^-1 U
        Us = [u for u in (getattr(f, "low_rank_factor", lambda: None)() for f in self.fields) if u is not None]
        if Us:
            U = np.hstack(Us) * self._free[:, None]
            Z = self._lu.solve(U)
            self._woodbury = (Z, np.linalg.inv(np.eye(U.shape[1]) / self._ck + U.T @ Z))
        else:
            self._woodbury = None
        self._R_ref = None if self.node_rotations is None else self.node_rotations(self.x)
        self._best_iterations, self._excess = None, 0.0
        self.refreshes += 1
        # what a refresh costs on the kept pattern: a new pattern's one-off work (positions, analysis) left out
        self._t_factor = time.perf_counter() - t0 - sysm.pattern_seconds - self._refactor.analysis_seconds

    def _solve_ref(self, r):
        """The refresh-time matrix's inverse applied to r (LU, plus the low-rank fields' correction)."""
        z = self._lu.solve(r)
        if self._woodbury is not None:
            Z, Minv = self._woodbury
            z -= Z @ (Minv @ (Z.T @ r))
        return z

    def _preconditioner(self):
        """z = P^-1 r: the refresh-time inverse, warped by the nodes' rotations since the refresh."""
        if self.node_rotations is None:
            return self._solve_ref
        W = self.node_rotations(self.x) @ np.swapaxes(self._R_ref, 1, 2)  # (N, 3, 3)

        def apply(r):  # (einsum: about three times cheaper than a batched product of 3 x 1 columns)
            z = self._solve_ref(np.einsum("nji,nj->ni", W, r.reshape(-1, 3)).ravel())
            return np.einsum("nij,nj->ni", W, z.reshape(-1, 3)).ravel()

        return apply

    def _pcg(self, rhs, x0, refreshed):
        """Preconditioned conjugate gradients from ``x0`` to ``tol`` (relative to |rhs|); returns (x,
        iterations, refreshed). When the kept factors fit this step's matrix badly, the solve refactorises
        at this step's linearisation and continues from where it is: at ``restart_iterations`` at the
        latest, and earlier when the convergence rate so far predicts that finishing would cost more than
        a refactorisation (``predict_refresh``; both costs measured as the solver runs)."""
        def A(p):
            return self._operator(p.reshape(-1, 3)).ravel()

        target = self.tol * max(float(np.linalg.norm(rhs)), 1e-300)
        x = np.array(x0, dtype=float)
        its = its_timed = 0  # its_timed: iterations before the last refresh
        t0 = time.perf_counter()
        while True:
            M = self._preconditioner()
            r = rhs - A(x)
            rn = r0 = float(np.linalg.norm(r))
            if rn <= target:
                break
            z = M(r)
            p = z.copy()
            rz = float(r @ z)
            cap = self.max_iterations if refreshed else min(self.max_iterations, self.restart_iterations)
            restart = False
            best = rn
            for i in range(1, cap + 1):
                Ap = A(p)
                alpha = rz / float(p @ Ap)
                x += alpha * p
                r -= alpha * Ap
                its += 1
                rn = float(np.linalg.norm(r))
                if rn <= target:
                    break
                best = min(best, rn)  # the residual norm of CG need not fall monotonically
                if not refreshed and (i == cap or self._refresh_pays(i, r0, best, target)):
                    restart = True
                    break
                z = M(r)
                rz, rz_old = float(r @ z), rz
                p = z + (rz / rz_old) * p
            if not restart:
                break
            # the kept factorisation no longer fits this step's matrix: refactorise now and go on from x
            self._time_iterations(time.perf_counter() - t0, its - its_timed)
            self._refresh()
            refreshed = True
            t0, its_timed = time.perf_counter(), its
        self._time_iterations(time.perf_counter() - t0, its - its_timed)
        return x, its, refreshed, its - its_timed, rn / max(float(np.linalg.norm(rhs)), 1e-300)

    def _refresh_cost_iterations(self) -> float:
        """What a refactorisation costs, in CG iterations: measured (its time over an iteration's) once both
        have been timed, ``refresh_cost`` until then."""
        if self.adaptive_refresh and self._t_factor is not None and self._t_iteration:
            return self._t_factor / self._t_iteration
        return self.refresh_cost

    def _time_iterations(self, seconds, n):
        """Running estimate of the time one CG iteration takes (operator plus preconditioner)."""
        if n >= 2:
            t = seconds / n
            self._t_iteration = t if self._t_iteration is None else 0.7 * self._t_iteration + 0.3 * t

    def _refresh_pays(self, i, r0, rn, target):
        """Whether refactorising now is predicted to cost less than finishing with the kept factors: the
        iterations still needed at the mean convergence rate so far, against a refactorisation plus the
        iterations that follow one."""
        if not self.predict_refresh or i < 4 or self._t_iteration is None or self._t_factor is None:
            return False
        rate = (rn / r0) ** (1.0 / i)
        if rate >= 1.0:
            return True
        remaining = math.log(target / rn) / math.log(rate)
        after = self._best_iterations if self._best_iterations is not None else 3
        return remaining * self._t_iteration > self._t_factor + after * self._t_iteration

    def step(self, external=None, prescribed=None) -> StepInfo:
        """One step; ``external(x)`` returns external forces (N, 3) or None.

        ``prescribed``: optional ``(mask (N,), positions (N, 3))``: the masked nodes move to the given
        positions in this step (Dirichlet conditions; the free nodes are solved with their coupling,
        ``A_ff v_f = r_f - A_fc v_c``)."""
        x = self.x
        f = sum(fl.forces(x) for fl in self.fields)
        if external is not None:
            fe = external(x)
            if fe is not None:
                f = f + fe
        vc = np.zeros_like(x)
        if prescribed is not None:
            mask, target = prescribed
            self.set_prescribed(mask)
            vc[mask] = (np.asarray(target, float)[mask] - x[mask]) / self.dt
        else:
            self.set_prescribed(None)
        rhs = (self.m[:, None] * self.v + self.dt * f)
        if prescribed is not None:
            rhs = rhs - self._full(vc)
        rhs = rhs.ravel() * self._free
        refreshed = False
        if self._lu is None:
            self._refresh()
            refreshed = True
        v, its, refreshed, its_fresh, res = self._pcg(rhs, self.v.ravel(), refreshed)
        if not refreshed:
            if self._best_iterations is None:
                self._best_iterations = its
            self._excess += max(0, its - self._best_iterations)
            if self._excess > self._refresh_cost_iterations():
                self._refresh()
                refreshed = True
        elif self._best_iterations is None:
            self._best_iterations = its_fresh
        self.v = v.reshape(-1, 3) + vc
        self.x = x + self.dt * self.v
        self.time += self.dt
        self.steps += 1
        self.last_info = StepInfo(iterations=its, refreshed=refreshed, residual=res)
        return self.last_info
