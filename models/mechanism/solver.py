"""Solving the knee mechanism: single angles, sweeps by continuation, assembly modes, derivatives.

A :class:`Mechanism` is built from :class:`~knee.models.mechanism.params.MechanismParams`. On construction it
chooses an assembly branch (the parameter file's ``[initial]`` pose, or a multi-start search) and
tabulates that branch at 1-degree spacing over the whole flexion range where it assembles, refining
both ends of the range to 1e-6 degrees. Every later solve starts from the nearest tabulated state, so a
solve at any angle stays on the chosen branch.

Angles are radians throughout (degrees only in the CLI and CSV); lengths mm.

Example
-------
>>> from knee.models.mechanism import Mechanism
>>> m = Mechanism.from_name("volunteer")
>>> res = m.sweep(np.radians(np.arange(0, 121)))
>>> res.tf.shape, float(res.residual.max()) < 1e-9
((121, 6), True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from knee.foundations.conventions import joint_to_pose, pose_to_joint
from knee.foundations.errors import AssemblyError, KneeInputError
from knee.models.mechanism import closure, compiled
from knee.models.mechanism.params import (
    N_PARAMS,
    PF_REFERENCE_FLEXION,
    MechanismParams,
    load_model,
)

#: Closure residual (mm) above which a solve counts as not converged.
RESIDUAL_TOL = 1e-9
#: Jacobian condition number above which an angle is reported as near-singular.
SINGULAR_COND = 1e4
#: A step whose rate of change (mm or degrees per degree of flexion) exceeds both this and
#: JUMP_RATIO times the previous step's rate is reported as a jump between branches.
JUMP_RATE = 2.0
JUMP_RATIO = 5.0
_TABLE_STEP = math.radians(1.0)
_SEARCH_LIMIT = math.radians(180.0)


def detect_jumps(x0, a0, x, alpha) -> np.ndarray:
    """Flag steps where a continuation path jumps to another branch.

    Parameters
    ----------
    x0 : (5,) float and a0 : float
        The TF unknowns and flexion the path starts from.
    x : (n, 5) float and alpha : (n,) float
        The TF unknowns (rad, mm) solved at each flexion (rad).

    Returns
    -------
    (n,) bool
        True where the rate of change of the unknowns (mm, or degrees, per degree of flexion) exceeds
        both ``JUMP_RATE`` and ``JUMP_RATIO`` times the previous step's rate.
    """
    x = np.asarray(x, dtype=float)
    alpha = np.asarray(alpha, dtype=float)
    prev_x = np.vstack([np.asarray(x0, float)[None, :], x[:-1]])
    prev_a = np.r_[a0, alpha[:-1]]
    with np.errstate(invalid="ignore"):
        d = np.abs(x - prev_x)
        d[:, :2] = np.degrees(d[:, :2])
        da = np.degrees(np.abs(alpha - prev_a))
        rate = d.max(axis=1) / np.maximum(da, 1e-12)
        rate[da < 1e-9] = 0.0
        jump = np.zeros(x.shape[0], bool)
        jump[1:] = (rate[1:] > JUMP_RATE) & (rate[1:] > JUMP_RATIO * rate[:-1])
    return jump


#: Largest step (rad) the continuation takes between two angles; larger requested steps are subdivided.
MAX_STEP = math.radians(2.0)
#: A sweep whose first angle lies within _FOLD_TOL of an end of the assembly range starts _FOLD_STEP inside.
_FOLD_TOL = math.radians(0.25)
_FOLD_STEP = math.radians(0.5)


def _subdivide(al, max_step):
    """The path through angles ``al`` with no step above ``max_step``, and the positions of ``al`` in it."""
    if al.size < 2:
        return al, np.arange(al.size)
    k = np.maximum(np.ceil(np.abs(np.diff(al)) / max_step).astype(int), 1)
    if np.all(k == 1):
        return al, np.arange(al.size)
    keep = np.r_[0, np.cumsum(k)]
    t = np.concatenate([np.arange(1, kk + 1) / kk for kk in k])
    start = np.repeat(al[:-1], k)
    step = np.repeat(np.diff(al), k)
    return np.r_[al[0], start + t * step], keep


def _residual_text(res: float) -> str:
    """A closure residual for a message: the value in mm, or what a non-finite one means."""
    if not math.isfinite(res):
        return "Newton diverged: no finite pose near the start; the links cannot close there"
    return f"residual {res:.3g} mm"


def dense_grid(flexion, max_gap: float = math.radians(1.0)):
    """The angles sorted, with angles added so that no gap exceeds ``max_gap`` (rad): continuation along
    it cannot step over a fold or onto another branch between two requested angles. Returns
    ``(grid (m,), index (n,))`` with ``grid[index] == flexion``."""
    a = np.asarray(flexion, float)
    u = np.unique(a)
    fill = [u[:1]]
    for lo, hi in zip(u[:-1], u[1:]):
        k = int(np.ceil((hi - lo) / max_gap))
        fill.append(np.linspace(lo, hi, k + 1)[1:])
    grid = np.concatenate(fill)
    return grid, np.searchsorted(grid, a)


def _run_chunks(sw, state, al):
    """Run the compiled chunked sweep ``sw`` (inputs already holding p and psi_ref) along angles ``al``
    from ``state``; returns (states (n, N_STATE), diags (n, N_DIAG))."""
    n, C = al.size, closure.CHUNK
    states = np.empty((n, closure.N_STATE))
    diags = np.empty((n, closure.N_DIAG))
    for k in range(0, n, C):
        m = min(C, n - k)
        sw.inputs[0][:] = state
        sw.inputs[1][:m] = al[k:k + m]
        sw.inputs[1][m:] = al[k + m - 1]
        sw.call()
        states[k:k + m] = sw.outputs[0].reshape(C, closure.N_STATE)[:m]
        diags[k:k + m] = sw.outputs[1].reshape(C, closure.N_DIAG)[:m]
        state = states[k + m - 1]
    return states, diags


def condition_numbers(J: np.ndarray) -> np.ndarray:
    """2-norm condition numbers of (n, k, k) matrices.

    From the eigenvalues of J^T J (faster than a batched SVD); where that gives more than 1e6, where
    squaring loses accuracy, the SVD is used instead.
    """
    if len(J) == 0:
        return np.zeros(0)
    e = np.linalg.eigvalsh(np.swapaxes(J, 1, 2) @ J)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.sqrt(e[:, -1] / e[:, 0])
    bad = ~(np.isfinite(c) & (c < 1e6) & (e[:, 0] > 0))
    if bad.any():
        sv = np.linalg.svd(J[bad], compute_uv=False)
        with np.errstate(divide="ignore"):
            c[bad] = sv[:, 0] / sv[:, -1]
    return c


_SENS_FNS: dict = {}


def _sensitivities(kinds, has_pf, Z, al, p) -> Sensitivity:
    """Implicit-function derivatives of the joint coordinates at solved states ``Z`` (n, nz) and
    angles ``al`` (n,), for the flat parameter vector ``p`` (see closure.build_sensitivity)."""
    key = (tuple(kinds), bool(has_pf))
    if key not in _SENS_FNS:
        _SENS_FNS[key] = closure.build_sensitivity(*key)
    n, nz = Z.shape
    out = _SENS_FNS[key].map(n)(Z.T, al[None, :], np.tile(p[:, None], (1, n)))
    k = 12 if has_pf else 6

    def blocks(m, rows, cols):  # map() stacks the n per-angle blocks horizontally
        return np.asarray(m).reshape(rows, n, cols).transpose(1, 0, 2)

    Fz, Fa, Fp = blocks(out[1], nz, nz), blocks(out[2], nz, 1)[:, :, 0], blocks(out[3], nz, N_PARAMS)
    yz, ya, yp = blocks(out[5], k, nz), blocks(out[6], k, 1)[:, :, 0], blocks(out[7], k, N_PARAMS)
    dz = -np.linalg.solve(Fz, np.concatenate([Fa[:, :, None], Fp], axis=2))
    dy = np.concatenate([ya[:, :, None], yp], axis=2) + yz @ dz
    return Sensitivity(flexion=al, d_flexion=dy[:, :, 0], d_params=dy[:, :, 1:])


def tf_sensitivities(params_vector, kinds, tf) -> Sensitivity:
    """Derivatives of the TF joint coordinates at already solved TF states ``tf`` (n, 6) (for example from
    :func:`quick_tf_sweep`), without building a :class:`Mechanism`."""
    tf = np.asarray(tf, dtype=float)
    return _sensitivities(kinds, False, tf[:, 1:], tf[:, 0].copy(), np.asarray(params_vector, float))


def _fresh(x, psi, alpha):
    """A continuation state with no history: the previous solution equals the current one."""
    cur = np.r_[x, psi, alpha]
    return np.r_[cur, cur]


@dataclass
class SweepResult:
    """The motion of the mechanism over flexion angles.

    Attributes
    ----------
    requested : (m,) float
        The flexion angles asked for (rad).
    flexion : (n,) float
        The angles solved, n <= m (rad): the sweep stops at the first failure.
    tf, pf : (n, 6) float
        TF and PF joint coordinates (alpha, beta, gamma rad; anterior, proximal, lateral mm).
        ``pf`` is NaN for a model without a patella.
    residual : (n,) float
        Largest absolute closure residual (mm) at each angle.
    condition : (n,) float
        Condition number of the TF closure Jacobian (rows mm, columns rad for beta and gamma and mm
        for the translations); computed from the Jacobians the solver returns on first access.
    near_singular : (n,) bool
        ``condition > SINGULAR_COND``.
    jacobian : (n, 5, 5) float
        The TF closure Jacobian at each solution.
    psi : (n,) float
        The patella's rotation about the helical axis from the orientation that aligns the axes (rad).
    status : str
        ``"ok"``, ``"no-convergence"`` (no closure at the next angle), ``"jump"`` (the solution jumped
        to another branch) or ``"out-of-range"`` (the first angle is outside the assembly range).
    message : str
        One line describing a stop, empty when ``status == "ok"``.
    limit : float or None
        When stopped: the last angle (rad) up to which the branch still assembles, refined by bisection.
    """

    requested: np.ndarray
    flexion: np.ndarray
    tf: np.ndarray
    pf: np.ndarray
    residual: np.ndarray
    jacobian: np.ndarray
    psi: np.ndarray
    status: str = "ok"
    message: str = ""
    limit: float | None = None
    _states: np.ndarray = field(default=None, repr=False)
    _cond: np.ndarray = field(default=None, repr=False)

    @property
    def condition(self) -> np.ndarray:
        if self._cond is None:
            self._cond = condition_numbers(self.jacobian)
        return self._cond

    @property
    def near_singular(self) -> np.ndarray:
        return self.condition > SINGULAR_COND

    @property
    def complete(self) -> bool:
        return self.status == "ok"

    @property
    def tf_poses(self) -> np.ndarray:
        """Tibia in femur, (n, 4, 4)."""
        return joint_to_pose(self.tf)

    @property
    def pf_poses(self) -> np.ndarray:
        """Patella in femur, (n, 4, 4) (NaN without a patella)."""
        return joint_to_pose(self.pf)


@dataclass
class Sensitivity:
    """Derivatives of the 12 joint coordinates (TF then PF; 6 for a TF-only model).

    Attributes
    ----------
    flexion : (n,) float
    d_flexion : (n, k) float
        d(coordinate)/d(flexion), per radian of TF flexion.
    d_params : (n, k, N_PARAMS) float
        d(coordinate)/d(parameter), for the flat parameter vector (see ``parameter_names``).
    """

    flexion: np.ndarray
    d_flexion: np.ndarray
    d_params: np.ndarray


class Mechanism:
    """The 1-DoF spatial parallel mechanism of a knee, solved with CasADi (see module docstring).

    Parameters
    ----------
    params : MechanismParams
    compile : bool or None
        Use the compiled (C) functions: True, False, or None for "when a compiler is available".

    Attributes
    ----------
    assembly_range : (float, float)
        Flexion range (rad) over which the chosen branch assembles (TF, and PF with a patella).
    psi_ref : float
        The patella's axis rotation at the PF reference pose (0 without a patella).
    """

    def __init__(self, params: MechanismParams, compile: bool | None = None):
        self.params = params
        self.p = params.to_vector()
        self._compile = compile
        self.has_pf = params.has_pf
        self.psi_ref = 0.0
        self._build_branch()

    @classmethod
    def from_name(cls, name_or_path, compile: bool | None = None) -> "Mechanism":
        """A mechanism from a bundled parameter-set name or a TOML path."""
        return cls(load_model(name_or_path), compile)

    @property
    def backend(self) -> compiled.Backend:
        """The calling thread's numeric functions for this mechanism's structure (each thread has its own
        buffers, so one mechanism, or two of one structure, can be used from several threads)."""
        return compiled.backend(self.params.kinds, self.has_pf, self._compile)

    @property
    def compiled(self) -> bool:
        """Whether the numeric functions run compiled (else in CasADi's virtual machine)."""
        return self.backend.compiled

    # ------------------------------------------------------------------------------------------
    # Low-level steps

    def _claim(self, fn):
        """Write this mechanism's parameters into a shared backend function's inputs, once."""
        if fn.owner is not self:
            fn.inputs[2][:] = self.p
            fn.owner = self
        fn.inputs[3][0] = self.psi_ref

    def _step(self, state, alpha):
        st = self.backend.step
        self._claim(st)
        st.inputs[0][:] = state
        st.inputs[1][0] = alpha
        st.call()
        return st.outputs[0].copy(), st.outputs[1].copy()

    def _ok(self, diag, use_pf=True) -> bool:
        r = np.abs(diag[closure.DIAG_RESIDUALS] if (use_pf and self.has_pf) else diag[closure.DIAG_TF_RESIDUAL])
        return bool(np.all(r < RESIDUAL_TOL))

    @staticmethod
    def _rate(s0, s1, da):
        d = np.abs(s1[closure.STATE_X] - s0[closure.STATE_X])
        d[:2] = np.degrees(d[:2])
        return float(d.max() / max(abs(math.degrees(da)), 1e-12))

    def _walk(self, state, direction, limit, use_pf):
        """Continue from ``state`` in 1-degree steps towards ``limit``. Returns the states visited; when
        a step fails, the last one is the end of the assembly range, refined by bisection to 1e-6 deg.
        """
        out = [state]
        prev_rate = None
        while (limit - out[-1][closure.STATE_ALPHA]) * direction > 1e-12:
            a = out[-1][closure.STATE_ALPHA]
            target = a + direction * min(_TABLE_STEP, abs(limit - a))
            s, d = self._step(out[-1], target)
            rate = self._rate(out[-1], s, target - a)
            if self._ok(d, use_pf) and not (prev_rate is not None and rate > JUMP_RATE
                                            and rate > JUMP_RATIO * prev_rate):
                out.append(s)
                prev_rate = rate
                continue
            out.extend(self._bisect_end(out[-1], target, use_pf))
            break
        return out

    def _bisect_end(self, base, bad_alpha, use_pf):
        """States approaching the end of the range between ``base`` (closes) and ``bad_alpha`` (does
        not). Near a fold the two branches merge, so a step is accepted when it closes and moves the
        unknowns by less than ``JUMP_RATE`` mm (or degrees)."""
        lo, hi, visited = base, bad_alpha, []
        while abs(hi - lo[closure.STATE_ALPHA]) > math.radians(1e-6):
            mid = 0.5 * (lo[closure.STATE_ALPHA] + hi)
            s, d = self._step(lo, mid)
            step = np.abs(s[closure.STATE_X] - lo[closure.STATE_X])
            step[:2] = np.degrees(step[:2])
            if self._ok(d, use_pf) and step.max() < JUMP_RATE:
                lo = s
                visited.append(s)
            else:
                hi = mid
        return visited[-1:] if visited else []

    def _initial_state(self):
        ini = self.params.initial
        if ini is not None:
            s, d = self._newton(ini.unknowns, ini.flexion)
            if not self._ok(np.r_[d, 0.0], use_pf=False):
                raise AssemblyError(
                    f"{self.params.name}: the stored initial pose does not close at "
                    f"{math.degrees(ini.flexion):.3g} deg ({_residual_text(np.abs(d).max())})")
            return _fresh(s, 0.0, ini.flexion)
        for deg in (0, 10, 20, 30, 45, 60, 90, -10):
            modes = self.assembly_modes(math.radians(deg), _all=True)
            if modes:
                x = min(modes, key=lambda m: m[0] ** 2 + m[1] ** 2)
                return _fresh(x, 0.0, math.radians(deg))
        raise AssemblyError(f"{self.params.name}: the mechanism does not assemble at any of the tried "
                            "flexion angles (multi-start found no closure)")

    def _newton(self, x0, alpha):
        f = self.backend.tf_newton
        f.inputs[0][:] = x0
        f.inputs[1][0] = alpha
        f.inputs[2][:] = self.p
        f.owner = None
        f.call()
        return f.outputs[0].copy(), f.outputs[1].copy()

    def _build_branch(self):
        s0 = self._initial_state()
        use_pf = False
        if self.has_pf:
            a_ref = self.params.pf.reference_flexion
            path = self._walk(s0, 1.0 if a_ref >= s0[closure.STATE_ALPHA] else -1.0, a_ref, use_pf=False)
            if abs(path[-1][closure.STATE_ALPHA] - a_ref) > 1e-9:
                raise AssemblyError(
                    f"{self.params.name}: the TF mechanism stops assembling at "
                    f"{math.degrees(path[-1][closure.STATE_ALPHA]):.2f} deg, before the PF reference flexion "
                    f"{math.degrees(a_ref):.1f} deg")
            self.x_ref = path[-1][closure.STATE_X].copy()
            self.psi_ref = self._reference_psi(self.x_ref, a_ref)
            s0 = _fresh(self.x_ref, self.psi_ref, a_ref)
            use_pf = True
        else:
            self.x_ref = None
        up = self._walk(s0, 1.0, _SEARCH_LIMIT, use_pf)
        down = self._walk(s0, -1.0, -_SEARCH_LIMIT, use_pf)
        table = np.array(down[::-1] + up[1:])
        self._table = table
        self._table_alpha = table[:, closure.STATE_ALPHA]
        self.assembly_range = (float(table[0, 6]), float(table[-1, 6]))

    def _reference_psi(self, x_ref, a_ref) -> float:
        """The PF reference pose: of the roots of the tendon equation (theta = 0) at the reference
        flexion, the one with the patella's origin most anterior in the femur frame."""
        fn = closure.build_pf_scan()
        grid = np.linspace(-math.pi, math.pi, 721)
        vals = np.asarray(fn.map(grid.size)(grid[None, :], x_ref, a_ref, self.p)[0]).ravel()
        roots = []
        for i in np.nonzero(np.sign(vals[:-1]) != np.sign(vals[1:]))[0]:
            psi = 0.5 * (grid[i] + grid[i + 1])
            for _ in range(50):
                r, dr = (float(v) for v in fn(psi, x_ref, a_ref, self.p))
                step = r / dr
                psi -= step
                if abs(step) < 1e-14:
                    break
            if abs(float(fn(psi, x_ref, a_ref, self.p)[0])) < RESIDUAL_TOL:
                roots.append(psi)
        if not roots:
            raise AssemblyError(f"{self.params.name}: the patellar tendon cannot close at the reference "
                                f"flexion {math.degrees(a_ref):.1f} deg (no root of eq. 4)")
        psi_s, p_s = ca.SX.sym("psi"), ca.SX.sym("p", N_PARAMS)
        q = ca.Function("q", [psi_s, p_s], [closure.pf_joint(psi_s, 0, p_s)])
        anterior = [float(q(r, self.p)[3]) for r in roots]
        return float(roots[int(np.argmax(anterior))])

    def _nearest(self, alpha) -> np.ndarray:
        i = int(np.argmin(np.abs(self._table_alpha - alpha)))
        return self._table[i]

    # ------------------------------------------------------------------------------------------
    # Public API

    def in_range(self, alpha) -> bool:
        lo, hi = self.assembly_range
        return lo - 1e-12 <= alpha <= hi + 1e-12

    def solve(self, flexion: float):
        """Solve the mechanism at one flexion angle (rad) on the chosen branch.

        Returns
        -------
        (tf, pf, residual) : (6,) float, (6,) float, float
            Joint coordinates (PF NaN without a patella) and the largest closure residual (mm).

        Raises
        ------
        AssemblyError
            The angle is outside the assembly range, or Newton does not converge.
        """
        a = float(flexion)
        if not math.isfinite(a):
            raise KneeInputError(f"flexion must be finite, got {flexion}")
        if not self.in_range(a):
            lo, hi = (math.degrees(v) for v in self.assembly_range)
            raise AssemblyError(f"flexion {math.degrees(a):.2f} deg is outside the assembly range "
                                f"{lo:.2f} to {hi:.2f} deg of {self.params.name}")
        st = self.backend.step
        self._claim(st)
        st.inputs[0][:] = self._table[int(np.abs(self._table_alpha - a).argmin())]
        st.inputs[1][0] = a
        st.call()
        s, d = st.outputs
        res = float(np.abs(d[:6 if self.has_pf else 5]).max())
        if not res < RESIDUAL_TOL:
            raise AssemblyError(f"no closure at {math.degrees(a):.3f} deg ({_residual_text(res)})")
        tf = np.empty(6)
        tf[0] = a
        tf[1:] = s[closure.STATE_X]
        pf = d[31:37].copy() if self.has_pf else np.full(6, np.nan)
        return tf, pf, res

    def _sweep_rows(self, req, path, keep) -> SweepResult:
        """Sweep ``path`` and return the rows ``keep`` of it, as the result for the requested ``req``."""
        full = self.sweep(path)
        solved = int(np.searchsorted(keep, full.flexion.size))  # requested rows before any stop
        rows = keep[:solved]
        return SweepResult(requested=req, flexion=full.flexion[rows], tf=full.tf[rows], pf=full.pf[rows],
                           residual=full.residual[rows], jacobian=full.jacobian[rows], psi=full.psi[rows],
                           status=full.status, message=full.message, limit=full.limit,
                           _states=None if full._states is None else full._states[rows])

    def sweep(self, flexion) -> SweepResult:
        """Solve over a sequence of flexion angles (rad) by continuation along the chosen branch.

        The first angle starts from the nearest tabulated branch state; each next one from the previous
        solution moved along the branch tangent. The sweep stops at the first angle that does not
        close (residual above ``RESIDUAL_TOL``) or that jumps to another branch, and reports where the
        branch stops assembling; rows before the stop are returned.

        Steps larger than :data:`MAX_STEP` between consecutive angles are subdivided internally (only
        the requested angles are returned): a large step could otherwise converge onto another branch
        without any sign in the residual. A sweep that begins at an end of the assembly range (where the
        branches meet) starts half a degree inside and walks out to it, for the same reason.

        Parameters
        ----------
        flexion : (m,) float
            Angles in rad, in the order to visit.
        """
        req = np.asarray(flexion, dtype=float).ravel()
        if req.size > 1 and np.all(np.isfinite(req)):
            lo, hi = self.assembly_range
            if min(abs(req[0] - lo), abs(req[0] - hi)) < _FOLD_TOL:
                # at an end of the range both assembly branches meet (a fold): continuing from there can
                # leave the chosen branch, so the sweep starts half a degree inside and walks out to it
                inner = lo + _FOLD_STEP if abs(req[0] - lo) < abs(req[0] - hi) else hi - _FOLD_STEP
                return self._sweep_rows(req, np.r_[inner, req], np.arange(1, req.size + 1))
        if req.size and np.all(np.isfinite(req)):
            path, keep = _subdivide(req, MAX_STEP)
            if path.size != req.size:
                return self._sweep_rows(req, path, keep)
        al = req
        if al.size == 0:
            raise KneeInputError("sweep needs at least one flexion angle")
        if not np.all(np.isfinite(al)):
            raise KneeInputError("flexion angles must be finite")
        if not self.in_range(al[0]):
            lo, hi = (math.degrees(v) for v in self.assembly_range)
            return self._result(al, np.zeros((0, 7)), np.zeros((0, 37)), "out-of-range",
                                f"{math.degrees(al[0]):.2f} deg is outside the assembly range "
                                f"{lo:.2f} to {hi:.2f} deg of {self.params.name}; nothing solved", None)
        sw = self.backend.sweep
        start = self._nearest(al[0])
        self._claim(sw)
        states, diags = _run_chunks(sw, start, al)
        # checks, vectorised: convergence, then jumps between branches
        res = np.abs(diags[:, closure.DIAG_RESIDUALS] if self.has_pf else diags[:, closure.DIAG_TF_RESIDUAL]).max(axis=1)
        bad = ~(res < RESIDUAL_TOL)
        jump = detect_jumps(start[closure.STATE_X], start[closure.STATE_ALPHA], states[:, closure.STATE_X], al)
        stop = np.nonzero(bad | jump)[0]
        if stop.size == 0:
            return self._result(al, states, diags, "ok", "", None, res)
        k = int(stop[0])
        if bad[k]:
            status = "no-convergence"
        else:
            status = "jump"
        # where does the branch stop assembling? refine between the last good angle and al[k]
        base = states[k - 1] if k > 0 else start
        ends = self._bisect_end(base, al[k], self.has_pf)
        limit = float(ends[-1][closure.STATE_ALPHA]) if ends else float(base[closure.STATE_ALPHA])
        last = f"{math.degrees(al[k - 1]):.2f} deg" if k > 0 else "none"
        if status == "jump":
            msg = (f"jumped to another assembly branch at {math.degrees(al[k]):.2f} deg "
                   f"(last angle solved: {last})")
        else:
            msg = (f"no closure at {math.degrees(al[k]):.2f} deg: the mechanism stops assembling at "
                   f"{math.degrees(limit):.2f} deg (last angle solved: {last})")
        return self._result(al, states[:k], diags[:k], status, msg, limit)

    def _result(self, al, states, diags, status, msg, limit, res=None) -> SweepResult:
        n = states.shape[0]
        tf = np.column_stack([states[:, closure.STATE_ALPHA], states[:, closure.STATE_X]]) if n else np.zeros((0, 6))
        pf = diags[:, closure.DIAG_PF].copy() if self.has_pf else np.full((n, 6), np.nan)
        if res is None:
            res = np.abs(diags[:, closure.DIAG_RESIDUALS] if self.has_pf else diags[:, closure.DIAG_TF_RESIDUAL]).max(axis=1) if n else np.zeros(0)
        J = diags[:, closure.DIAG_JACOBIAN].reshape(n, 5, 5).transpose(0, 2, 1)  # column-major -> rows
        return SweepResult(requested=al, flexion=tf[:, 0].copy(), tf=tf, pf=pf, residual=res,
                           jacobian=J, psi=states[:, closure.STATE_PSI].copy(), status=status, message=msg,
                           limit=limit, _states=states)

    def assembly_modes(self, flexion: float, n_starts: int = 2000, seed: int = 0, _all=False):
        """All TF assembly modes found at a flexion angle by multi-start Newton.

        Starts are drawn uniformly (beta, gamma in [-90, 90] deg, translations in [-100, 100] mm);
        converged solutions (residual < 1e-9 mm) are merged when closer than 1e-6, and kept only when their
        pose's joint coordinates give ``flexion`` back (a solution past |beta| = 90 deg is a pose at flexion
        +- 180 deg). A multi-start search can miss modes; the real solutions of a 5-5 mechanism are at most 40.

        Returns
        -------
        list of (5,) float
            ``(beta, gamma, anterior, proximal, lateral)``, sorted by beta**2 + gamma**2. With a built
            branch, the mode on it comes first when found.
        """
        rng = np.random.default_rng(seed)
        starts = np.column_stack([rng.uniform(-math.pi / 2, math.pi / 2, (n_starts, 2)),
                                  rng.uniform(-100, 100, (n_starts, 3))])
        f = self.backend.tf_newton_batch
        f.owner = None
        f.inputs[1][0] = flexion
        f.inputs[2][:] = self.p
        B = closure.BATCH
        sols = []
        for k in range(0, n_starts, B):  # batches of starts through one compiled call each
            chunk = starts[k:k + B]
            f.inputs[0][:] = np.vstack([chunk, np.repeat(chunk[-1:], B - len(chunk), axis=0)]).ravel()
            f.call()
            x = f.outputs[0].reshape(B, 5)[:len(chunk)]
            r = f.outputs[1].reshape(B, 5)[:len(chunk)]
            sols.append(x[np.all(np.abs(r) < RESIDUAL_TOL, axis=1)])
        x = np.vstack(sols)
        x[:, :2] = np.arctan2(np.sin(x[:, :2]), np.cos(x[:, :2]))
        # Newton can drift past |beta| = 90 deg: such a pose's joint coordinates are those of flexion
        # alpha +- 180 deg, not a mode at alpha; keep the solutions whose decomposition gives alpha back
        back = pose_to_joint(joint_to_pose(np.column_stack([np.full(len(x), flexion), x])))
        x = x[np.abs(np.angle(np.exp(1j * (back[:, 0] - flexion)))) < 1e-6]
        modes: list[np.ndarray] = []
        for m in x:  # merge the converged starts into distinct modes (at most 40 of them)
            if not any(np.abs(m - q).max() < 1e-6 for q in modes):
                modes.append(m)
        modes.sort(key=lambda m: m[0] ** 2 + m[1] ** 2)
        if not _all and hasattr(self, "_table") and modes and self.in_range(flexion):
            on = self.solve(flexion)[0][1:]
            modes.sort(key=lambda m: float(np.abs(m - on).max() > 1e-6))
        return modes

    def motion_at(self, flexion):
        """TF and PF joint coordinates ``(tf (n, 6), pf (n, 6))`` at angles in any order (rad): the distinct
        angles are swept in increasing order (the sweep subdivides large steps) and the rows returned in
        the order asked. Raises :class:`AssemblyError` when an angle is outside the assembly range."""
        al = np.atleast_1d(np.asarray(flexion, dtype=float))
        if al.size == 0 or not np.all(np.isfinite(al)):
            raise KneeInputError("flexion angles must be finite and at least one")
        grid, idx = np.unique(al, return_inverse=True)
        sw = self.sweep(grid)
        if not sw.complete:
            raise AssemblyError(f"{self.params.name}: {sw.message}")
        return sw.tf[idx.ravel()], sw.pf[idx.ravel()]

    def sensitivities(self, flexion) -> Sensitivity:
        """Derivatives of the joint coordinates with respect to flexion and to every parameter.

        Computed from CasADi's exact Jacobians of the closure equations by the implicit function
        theorem; with a patella, the dependence of the PF reference pose on the parameters is included.

        Parameters
        ----------
        flexion : (n,) float
            Angles (rad) inside the assembly range.
        """
        al = np.atleast_1d(np.asarray(flexion, dtype=float))
        sw = self.sweep(al)
        if not sw.complete:
            raise AssemblyError(sw.message)
        if self.has_pf:
            n = al.size
            Z = np.column_stack([sw._states[:, : closure.STATE_PSI + 1], np.tile(np.r_[self.x_ref, self.psi_ref], (n, 1))])
        else:
            Z = sw._states[:, closure.STATE_X]
        return _sensitivities(self.params.kinds, self.has_pf, Z, al, self.p)


def quick_tf_sweep(params_vector, kinds, x_start, alphas, compile: bool | None = None):
    """TF motion of a parameter vector without building a :class:`Mechanism` (for optimisers).

    Newton from ``x_start`` (the TF unknowns, (5,)) at ``alphas[0]``, then continuation along ``alphas``
    (rad, (n,)). Returns ``(tf (n, 6), residual (n,), ok, condition (n,))`` where ``ok`` is False when any
    angle fails to close (residual above ``RESIDUAL_TOL``) or the path jumps between branches.
    """
    b = compiled.backend(tuple(kinds), False, compile)
    p = np.asarray(params_vector, dtype=float)
    al = np.asarray(alphas, dtype=float)
    f = b.tf_newton
    f.owner = None
    f.inputs[0][:] = x_start
    f.inputs[1][0] = al[0]
    f.inputs[2][:] = p
    f.call()
    x0 = f.outputs[0].copy()
    if not np.all(np.abs(f.outputs[1]) < RESIDUAL_TOL):
        return np.full((al.size, 6), np.nan), np.full(al.size, np.inf), False, np.full(al.size, np.inf)
    sw = b.sweep
    sw.owner = None
    sw.inputs[2][:] = p
    sw.inputs[3][0] = 0.0
    n = al.size
    states, diags = _run_chunks(sw, _fresh(x0, 0.0, al[0]), al)
    res = np.abs(diags[:, closure.DIAG_TF_RESIDUAL]).max(axis=1)
    jump = detect_jumps(x0, al[0], states[:, closure.STATE_X], al)
    ok = bool(np.all(res < RESIDUAL_TOL) and not jump.any())
    tf = np.column_stack([states[:, closure.STATE_ALPHA], states[:, closure.STATE_X]])
    cond = condition_numbers(diags[:, closure.DIAG_JACOBIAN].reshape(n, 5, 5).transpose(0, 2, 1)) if ok else np.full(n, np.inf)
    return tf, res, ok, cond


_PF_SCAN: dict = {}


@dataclass(frozen=True)
class PFSweep:
    """:func:`quick_pf_sweep`'s result: TF and PF joint coordinates (n, 6) (rad, mm), whether every angle
    solved on one branch, the states ``Z`` (n, 12) for :func:`pf_sensitivities`, and the TF unknowns (5,)
    and patellar angle (rad) at the reference flexion."""

    tf: np.ndarray
    pf: np.ndarray
    ok: bool
    Z: np.ndarray
    x_ref: np.ndarray
    psi_ref: float


def quick_pf_sweep(params_vector, kinds, x_ref_guess, psi_ref_guess, alphas, compile: bool | None = None,
                   max_step: float = math.radians(2.0)):
    """TF and PF motion of a parameter vector with a patella, without building a :class:`Mechanism`
    (for the PF fit, whose candidates stay close to a known assembly).

    The TF closure is solved at the reference flexion from ``x_ref_guess`` (5,), the PF reference angle by
    Newton on the tendon equation from ``psi_ref_guess``; continuation then runs from the reference flexion
    to ``alphas[0]`` in steps of at most ``max_step`` and on along ``alphas`` (rad, (n,)).

    Returns
    -------
    dict with ``tf`` (n, 6), ``pf`` (n, 6), ``ok`` (bool), ``Z`` (n, 12): the states
    ``(x, psi, x_ref, psi_ref)`` for :func:`pf_sensitivities`, and ``x_ref``, ``psi_ref``.
    """
    p = np.asarray(params_vector, dtype=float)
    al = np.asarray(alphas, dtype=float)
    n = al.size
    fail = PFSweep(np.full((n, 6), np.nan), np.full((n, 6), np.nan), False, None, None, None)
    a_ref = float(p[PF_REFERENCE_FLEXION])
    b = compiled.backend(tuple(kinds), True, compile)
    f = b.tf_newton
    f.owner = None
    f.inputs[0][:] = x_ref_guess
    f.inputs[1][0] = a_ref
    f.inputs[2][:] = p
    f.call()
    x_ref = f.outputs[0].copy()
    if not np.all(np.abs(f.outputs[1]) < RESIDUAL_TOL):
        return fail
    if "fn" not in _PF_SCAN:
        _PF_SCAN["fn"] = closure.build_pf_scan()
    fn = _PF_SCAN["fn"]
    psi = float(psi_ref_guess)
    for _ in range(30):
        r, dr = (float(v) for v in fn(psi, x_ref, a_ref, p))
        if dr == 0 or not math.isfinite(r):
            return fail
        step = r / dr
        psi -= max(-0.3, min(0.3, step))
        if abs(step) < 1e-13:
            break
    if not abs(float(fn(psi, x_ref, a_ref, p)[0])) < RESIDUAL_TOL:
        return fail
    lead = _subdivide(np.array([a_ref, al[0]]), max_step)[0][1:-1]  # from the reference to the first angle
    path = np.r_[lead, al]
    sw = b.sweep
    sw.owner = None
    sw.inputs[2][:] = p
    sw.inputs[3][0] = psi
    states, diags = _run_chunks(sw, _fresh(x_ref, psi, a_ref), path)
    states, diags = states[lead.size:], diags[lead.size:]
    res = np.abs(diags[:, closure.DIAG_RESIDUALS]).max(axis=1)
    x = states[:, closure.STATE_X]
    jump = detect_jumps(x[0], al[0], x, al)
    ok = bool(np.all(res < RESIDUAL_TOL) and not jump.any() and np.all(np.isfinite(diags[:, closure.DIAG_PF])))
    Z = np.column_stack([states[:, : closure.STATE_PSI + 1], np.tile(np.r_[x_ref, psi], (n, 1))])
    return PFSweep(np.column_stack([al, x]), diags[:, closure.DIAG_PF].copy(), ok, Z, x_ref, psi)


def pf_sensitivities(params_vector, kinds, Z, alphas) -> Sensitivity:
    """Derivatives of the 12 joint coordinates at states ``Z`` from :func:`quick_pf_sweep`."""
    return _sensitivities(kinds, True, np.asarray(Z, float), np.asarray(alphas, float).copy(),
                          np.asarray(params_vector, float))
