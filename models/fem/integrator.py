"""Implicit Euler (seed 000, eqs. 2-3) with lumped mass and Rayleigh damping.

One linear solve per step: with C = a M + b K and the forces linearised about the current positions,

    ((1 + dt a) M + (dt b + dt^2) K) v' = M v + dt f(x),     x' = x + dt v'.

The matrix is never assembled per step: the conjugate-gradient solve applies the co-rotated element
stiffnesses directly (gather, element products, scatter), warm-started from the last velocity and
preconditioned with a sparse LU factorisation of the assembled matrix (symmetric mode, minimum-degree
ordering of A + A^T: about half the fill and factorisation time of the default; single-precision factors
were tried and cost more iterations after the prior's initialisation than they saved), warped by the nodes' rotations since it was computed. The factorisation is kept
across steps and refreshed (assembled on the fixed pattern, refactorised) by an amortised rule: when the
iterations spent beyond the count right after the last refresh add up to more than the cost of a
refactorisation (``refresh_cost`` iterations); and at once, in the middle of a step, when CG has not
converged within ``restart_iterations`` (the matrix has moved too far from the factorised one, e.g. when
many surface springs switch at once): the solve then finishes from where it stopped with the new factors.
Fields that offer ``low_rank_factor()`` (springs between wide bone attachments) enter the preconditioner
by the Woodbury identity instead of the assembled matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


@dataclass
class StepInfo:
    iterations: int
    refreshed: bool
    residual: float


class ImplicitEuler:
    """Integrate ``x, v`` (N, 3) under ``fields`` plus an external-force callback.

    Parameters
    ----------
    mass : (N,) float
        Lumped nodal masses (tonne, with mm, N, s).
    fields : list
        Objects with ``forces(x)``, ``apply(p)`` and ``matrix()`` (see :mod:`models.fem.fields`).
    dt : float
        Time step (s); the paper's 0.05.
    rayleigh_mass, rayleigh_stiffness : float
        Rayleigh damping coefficients a (1/s) and b (s).
    """

    def __init__(self, x0, mass, fields, dt=0.05, rayleigh_mass=0.1, rayleigh_stiffness=0.1,
                 tol=1e-5, max_iterations=200, refresh_cost=60, fixed=None, node_rotations=None,
                 restart_iterations=40):
        self.x = np.array(x0, dtype=float)
        self.fixed = np.zeros(len(self.x), bool) if fixed is None else np.asarray(fixed, bool)
        self._free = np.repeat(~self.fixed, 3).astype(float)
        self.v = np.zeros_like(self.x)
        self.m = np.asarray(mass, dtype=float)
        self.fields = list(fields)
        self.dt = float(dt)
        self.a, self.b = float(rayleigh_mass), float(rayleigh_stiffness)
        self.tol, self.max_iterations, self.refresh_cost = tol, max_iterations, refresh_cost
        self.restart_iterations = restart_iterations
        self._lu = None
        self._woodbury = None
        self._best_iterations = None  # CG iterations of the first step after the last refresh
        self._excess = 0.0            # iterations spent beyond that since the last refresh
        # node_rotations() -> (N, 3, 3) rotations of the material around each node (for the warped
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

    def _set_prescribed(self, mask):
        """Nodes whose motion is prescribed this step are excluded from the solve, like fixed ones."""
        mask = np.zeros(len(self.x), bool) if mask is None else np.asarray(mask, bool)
        free = np.repeat(~(self.fixed | mask), 3).astype(float)
        if not np.array_equal(free, self._free):
            self._free = free
            self._lu = None  # the preconditioner must see the same free set

    def _refresh(self):
        K = sum((f.matrix() for f in self.fields), sp.csr_matrix((3 * len(self.m),) * 2))
        A = (sp.diags(np.repeat(self._cm * self.m, 3)) + self._ck * K).tocsr()
        P = sp.diags(self._free)
        A = (P @ A @ P + sp.diags(1 - self._free)).tocsc()
        self._lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                             options={"SymmetricMode": True})
        # low-rank fields (springs between wide bone attachments) by the Woodbury identity:
        # (A + c U U^T)^-1 = A^-1 - Z (I/c + U^T Z)^-1 Z^T, Z = A^-1 U
        Us = [u for u in (getattr(f, "low_rank_factor", lambda: None)() for f in self.fields) if u is not None]
        if Us:
            U = np.hstack(Us) * self._free[:, None]
            Z = self._lu.solve(np.asfortranarray(U))
            self._woodbury = (Z, np.linalg.inv(np.eye(U.shape[1]) / self._ck + U.T @ Z))
        else:
            self._woodbury = None
        self._R_ref = None if self.node_rotations is None else self.node_rotations()
        self._best_iterations, self._excess = None, 0.0
        self.refreshes += 1

    def _solve_ref(self, r):
        """The refresh-time matrix's inverse applied to r (LU, plus the low-rank fields' correction)."""
        z = self._lu.solve(r)
        if self._woodbury is not None:
            Z, Minv = self._woodbury
            z -= Z @ (Minv @ (Z.T @ r))
        return z

    def _preconditioner(self, n):
        if self.node_rotations is None:
            return spla.LinearOperator((n, n), matvec=self._solve_ref, dtype=float)
        W = self.node_rotations() @ np.swapaxes(self._R_ref, 1, 2)  # (N, 3, 3)
        Wt = np.swapaxes(W, 1, 2)

        def apply(r):
            z = self._solve_ref((Wt @ r.reshape(-1, 3, 1)).ravel())
            return (W @ z.reshape(-1, 3, 1)).ravel()

        return spla.LinearOperator((n, n), matvec=apply, dtype=float)

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
            self._set_prescribed(mask)
            vc[mask] = (np.asarray(target, float)[mask] - x[mask]) / self.dt
        else:
            self._set_prescribed(None)
        rhs = (self.m[:, None] * self.v + self.dt * f)
        if prescribed is not None:
            rhs = rhs - self._full(vc)
        rhs = rhs.ravel() * self._free
        n = rhs.size
        A = spla.LinearOperator((n, n), matvec=lambda p: self._operator(p.reshape(-1, 3)).ravel(), dtype=float)
        refreshed = False
        if self._lu is None:
            self._refresh()
            refreshed = True
        its = [0]

        def count(_):
            its[0] += 1

        M = self._preconditioner(n)
        cap = self.max_iterations if refreshed else min(self.max_iterations, self.restart_iterations)
        v, info = spla.cg(A, rhs, x0=self.v.ravel(), M=M, rtol=self.tol, maxiter=cap, callback=count)
        if info > 0 and not refreshed:
            # the kept factorisation no longer fits this step's matrix: refactorise now, at this step's
            # linearisation, and finish the solve from where CG stopped
            self._refresh()
            refreshed = True
            v, _ = spla.cg(A, rhs, x0=v, M=self._preconditioner(n), rtol=self.tol, maxiter=self.max_iterations,
                           callback=count)
        elif not refreshed:
            if self._best_iterations is None:
                self._best_iterations = its[0]
            self._excess += max(0, its[0] - self._best_iterations)
            if self._excess > self.refresh_cost:
                self._refresh()
                refreshed = True
        elif self._best_iterations is None:
            self._best_iterations = its[0]
        self.v = v.reshape(-1, 3) + vc
        self.x = x + self.dt * self.v
        self.time += self.dt
        self.steps += 1
        res = float(np.linalg.norm(A @ v - rhs) / max(np.linalg.norm(rhs), 1e-300))
        self.last_info = StepInfo(iterations=its[0], refreshed=refreshed, residual=res)
        return self.last_info
