"""Closure equations of the knee mechanism, built symbolically in CasADi (seed 002, eqs. 1-4).

Unknowns
    TF: ``x = (beta, gamma, anterior, proximal, lateral)`` (rad, mm) at a prescribed flexion alpha,
    with ``R_ft = Rz(-alpha) Rx(beta) Ry(gamma)`` and ``P_ft = x[2:5]``.
    PF: ``psi``, the patella's rotation about the helical axis from the orientation ``R0`` that takes
    the patellar axis onto the femoral one (``R0 n_p = n_f``, the smallest such rotation), so that
    ``R_fp = Rot(n_f, psi) R0`` satisfies eq. 2 by construction. ``theta = psi - psi_ref`` is the
    rotation from the PF reference pose, and eq. 3 gives ``P_fp``.

Residuals (mm)
    ``distance`` link:      ``|c_f - R_ft c_t - P_ft| - l``                 (eq. 1)
    ``sphere-plane`` link:  ``n_t . (R_ft^T (c_f - P_ft) - c_t) - l``        (signed distance)
    tendon:                 ``|R_fp c_p6 + P_fp - (R_ft c_t6 + P_ft)| - l_6`` (eq. 4)

The flat parameter vector ``p`` is laid out as in :meth:`MechanismParams.to_vector`. Directions
(plane normals, helical axes) are normalised inside the equations, so derivatives with respect to their
raw components are well defined.
"""

from __future__ import annotations

import casadi as ca

from knee.models.mechanism.params import (
    LINK_FEMUR,
    LINK_LENGTH,
    LINK_NORMAL,
    LINK_TIBIA,
    N_PARAMS,
    PF_AXIS_FEMUR,
    PF_AXIS_PATELLA,
    PF_LAMBDA0,
    PF_LAMBDA1,
    PF_POINT_FEMUR,
    PF_POINT_PATELLA,
    PF_REFERENCE_FLEXION,
    PF_TENDON_LENGTH,
    PF_TENDON_PATELLA,
    PF_TENDON_TIBIA,
    link_entries,
)


def _rx(a):
    c, s = ca.cos(a), ca.sin(a)
    return ca.vertcat(ca.horzcat(1, 0, 0), ca.horzcat(0, c, -s), ca.horzcat(0, s, c))


def _ry(a):
    c, s = ca.cos(a), ca.sin(a)
    return ca.vertcat(ca.horzcat(c, 0, s), ca.horzcat(0, 1, 0), ca.horzcat(-s, 0, c))


def _rz(a):
    c, s = ca.cos(a), ca.sin(a)
    return ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))


def _skew(v):
    return ca.vertcat(ca.horzcat(0, -v[2], v[1]), ca.horzcat(v[2], 0, -v[0]), ca.horzcat(-v[1], v[0], 0))


def _unit(v):
    return v / ca.norm_2(v)


def tf_pose(x, alpha):
    """``(R_ft, P_ft)`` from the TF unknowns and the flexion."""
    R = ca.mtimes([_rz(-alpha), _rx(x[0]), _ry(x[1])])
    return R, x[2:5]


def tf_residual(x, alpha, p, kinds):
    """The five TF closure residuals (mm), (5, 1)."""
    R, P = tf_pose(x, alpha)
    out = []
    for i, kind in enumerate(kinds):
        cf, ct = p[link_entries(i, LINK_FEMUR)], p[link_entries(i, LINK_TIBIA)]
        n, length = p[link_entries(i, LINK_NORMAL)], p[link_entries(i, LINK_LENGTH)]
        if kind == "distance":
            out.append(ca.norm_2(cf - ca.mtimes(R, ct) - P) - length)
        elif kind == "sphere-plane":
            out.append(ca.dot(_unit(n), ca.mtimes(R.T, cf - P) - ct) - length)
        else:  # pragma: no cover - validated on load
            raise ValueError(f"unknown link kind {kind!r}")
    return ca.vertcat(*out)


def pf_pose(psi, theta, p):
    """``(R_fp, P_fp)`` of the patella on its helical axis (eqs. 2-3)."""
    nf, qf = _unit(p[PF_AXIS_FEMUR]), p[PF_POINT_FEMUR]
    npat, qp = _unit(p[PF_AXIS_PATELLA]), p[PF_POINT_PATELLA]
    lam0, lam1 = p[PF_LAMBDA0], p[PF_LAMBDA1]
    v = ca.cross(npat, nf)
    c = ca.dot(npat, nf)
    K = _skew(v)
    R0 = ca.DM.eye(3) + K + ca.mtimes(K, K) / (1 + c)
    Kn = _skew(nf)
    Rpsi = ca.DM.eye(3) + ca.sin(psi) * Kn + (1 - ca.cos(psi)) * ca.mtimes(Kn, Kn)
    R = ca.mtimes(Rpsi, R0)
    P = (lam0 + lam1 * theta) * nf + qf - ca.mtimes(R, qp)
    return R, P


def pf_residual(psi, theta, x, alpha, p):
    """The patellar-tendon residual (mm, eq. 4)."""
    Rt, Pt = tf_pose(x, alpha)
    Rp, Pp = pf_pose(psi, theta, p)
    ct6, cp6, l6 = p[PF_TENDON_TIBIA], p[PF_TENDON_PATELLA], p[PF_TENDON_LENGTH]
    return ca.norm_2(ca.mtimes(Rp, cp6) + Pp - ca.mtimes(Rt, ct6) - Pt) - l6


def cardan(R):
    """``(alpha, beta, gamma)`` of ``R = Rz(-alpha) Rx(beta) Ry(gamma)`` (knee.foundations.conventions)."""
    return ca.vertcat(ca.atan2(R[0, 1], R[1, 1]), ca.asin(R[2, 1]), ca.atan2(-R[2, 0], R[2, 2]))


def pf_joint(psi, theta, p):
    """The six PF joint coordinates (rad, mm)."""
    R, P = pf_pose(psi, theta, p)
    return ca.vertcat(cardan(R), P)


# ----------------------------------------------------------------------------------------------
# Functions


def symbols():
    return ca.SX.sym("x", 5), ca.SX.sym("alpha"), ca.SX.sym("p", N_PARAMS), ca.SX.sym("psi"), \
        ca.SX.sym("psi_ref")


NEWTON_OPTS = {"abstol": 1e-12, "abstolStep": 1e-12, "max_iter": 40, "error_on_fail": False}
#: Length of the chunk of angles one call of the compiled sweep solves.
CHUNK = 64
#: Size of the step function's diagnostic output: TF residuals (5), PF residual (1),
#: TF Jacobian (25, column-major), PF joint coordinates (6); named below.
N_DIAG = 37
DIAG_TF_RESIDUAL, DIAG_PF_RESIDUAL = slice(0, 5), 5
DIAG_RESIDUALS = slice(0, 6)
DIAG_JACOBIAN = slice(6, 31)
DIAG_PF = slice(31, 37)
#: State carried by the continuation: (x[5], psi, alpha) now and at the previous step; named below (now).
N_STATE = 14
STATE_X, STATE_PSI, STATE_ALPHA = slice(0, 5), 5, 6


def build_step(kinds, has_pf):
    """One continuation step, TF then PF.

    ``step(state, alpha, p, psi_ref) -> (state', diag)`` where
    ``state = (x[5], psi, alpha, x_prev[5], psi_prev, alpha_prev)`` holds the last two solutions.
    The guess is the secant extrapolation of the last two solutions to the new angle (a first-order
    predictor; the extrapolation factor is capped at 3 and dropped when the last two angles coincide),
    then ``fast_newton`` (code-generatable) solves the five TF equations, and the PF angle follows from
    the tendon equation by a 1-D Newton solve from its own extrapolated guess.
    """
    x, a, p, psi, psi_ref = symbols()
    r = tf_residual(x, a, p, kinds)
    g_tf = ca.Function("g_tf", [x, ca.vertcat(a, p)], [r])
    rf_tf = ca.rootfinder("rf_tf", "fast_newton", g_tf, NEWTON_OPTS)

    state = ca.SX.sym("state", N_STATE)
    cur, prev = state[0:7], state[7:14]
    da_prev = cur[6] - prev[6]
    ratio = ca.if_else(ca.fabs(da_prev) > 1e-12, (a - cur[6]) / da_prev, 0)
    ratio = ca.fmin(ca.fmax(ratio, -3), 3)
    guess = cur[0:6] + ratio * (cur[0:6] - prev[0:6])
    xs = rf_tf(guess[0:5], ca.vertcat(a, p))
    r_at = ca.Function("r_tf", [x, a, p], [r])(xs, a, p)
    J_at = ca.Function("J_tf", [x, a, p], [ca.jacobian(r, x)])(xs, a, p)
    if has_pf:
        rp = pf_residual(psi, psi - psi_ref, x, a, p)
        g_pf = ca.Function("g_pf", [psi, ca.vertcat(x, a, p, psi_ref)], [rp])
        rf_pf = ca.rootfinder("rf_pf", "fast_newton", g_pf, NEWTON_OPTS)
        psis = rf_pf(guess[5], ca.vertcat(xs, a, p, psi_ref))
        rp_at = ca.Function("r_pf", [psi, x, a, p, psi_ref], [rp])(psis, xs, a, p, psi_ref)
        qpf = ca.Function("q_pf", [psi, p, psi_ref], [pf_joint(psi, psi - psi_ref, p)])(psis, p, psi_ref)
    else:
        psis, rp_at, qpf = ca.SX(0), ca.SX(0), ca.SX.zeros(6)
    new_state = ca.vertcat(xs, psis, a, cur)
    diag = ca.vertcat(r_at, rp_at, ca.reshape(J_at, 25, 1), qpf)
    return ca.Function("knee_step", [state, a, p, psi_ref], [new_state, diag],
                       ["state", "alpha", "p", "psi_ref"], ["state_out", "diag"])


def build_sweep(step, n=CHUNK):
    """``n`` continuation steps in one call: ``(state0, alphas[1 x n], p, psi_ref) -> (states, diags)``."""
    acc = step.mapaccum("acc", n)
    s0 = ca.MX.sym("state", N_STATE)
    al = ca.MX.sym("alphas", 1, n)
    p = ca.MX.sym("p", N_PARAMS)
    pr = ca.MX.sym("psi_ref")
    states, diags = acc(s0, al, ca.repmat(p, 1, n), ca.repmat(pr, 1, n))
    return ca.Function("knee_sweep", [s0, al, p, pr], [states, diags],
                       ["state", "alphas", "p", "psi_ref"], ["states", "diags"])


def build_tf_newton(kinds):
    """``tf_newton(x0, alpha, p) -> (x, r)``: TF Newton from a given guess (multi-start, modes)."""
    x, a, p, _, _ = symbols()
    r = tf_residual(x, a, p, kinds)
    rf = ca.rootfinder("rf_tf", "fast_newton", ca.Function("g", [x, ca.vertcat(a, p)], [r]), NEWTON_OPTS)
    x0 = ca.SX.sym("x0", 5)
    xs = rf(x0, ca.vertcat(a, p))
    rs = ca.Function("r", [x, a, p], [r])(xs, a, p)
    return ca.Function("knee_tf_newton", [x0, a, p], [xs, rs], ["x0", "alpha", "p"], ["x", "r"])


#: Starts per call of the batched TF Newton solve (multi-start searches).
BATCH = 256


def build_pf_scan():
    """``pf_scan(psi, x, alpha, p) -> r``: tendon residual at the reference pose (theta = 0), used to
    find the PF reference roots; and its derivative in psi."""
    x, a, p, psi, _ = symbols()
    r = pf_residual(psi, 0, x, a, p)
    return ca.Function("pf_scan", [psi, x, a, p], [r, ca.jacobian(r, psi)])


def build_sensitivity(kinds, has_pf):
    """Implicit-function pieces for the derivatives of the motion.

    Unknowns ``z = (x, psi, x_ref, psi_ref)`` (TF+PF) or ``z = x`` (TF only); equations ``F(z, alpha, p)``:
    closure at alpha and, with a patella, the TF closure and the tendon equation at the reference
    flexion (which fixes psi_ref). Outputs ``y``: the 12 (or 6) joint coordinates. Returns a function
    ``(z, alpha, p) -> (F, F_z, F_alpha, F_p, y, y_z, y_alpha, y_p)``; then
    ``dy/dq = y_q - y_z F_z^-1 F_q``.
    """
    x, a, p, psi, psi_ref = symbols()
    if has_pf:
        xr = ca.SX.sym("x_ref", 5)
        a_ref = p[PF_REFERENCE_FLEXION]
        z = ca.vertcat(x, psi, xr, psi_ref)
        F = ca.vertcat(tf_residual(x, a, p, kinds), pf_residual(psi, psi - psi_ref, x, a, p),
                       tf_residual(xr, a_ref, p, kinds), pf_residual(psi_ref, 0, xr, a_ref, p))
        y = ca.vertcat(a, x, pf_joint(psi, psi - psi_ref, p))
    else:
        z = x
        F = tf_residual(x, a, p, kinds)
        y = ca.vertcat(a, x)
    outs = [F, ca.jacobian(F, z), ca.jacobian(F, a), ca.jacobian(F, p),
            y, ca.jacobian(y, z), ca.jacobian(y, a), ca.jacobian(y, p)]
    return ca.Function("knee_sensitivity", [z, a, p], outs)
