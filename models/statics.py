"""Statics of the knee mechanism: forces in the five TF links and the patellar tendon under a load on
the tibia (issue "contact mechanics, gait and virtual osteotomy", section 1).

At a flexion angle the tibia's pose is fixed by the mechanism. A link i acts on the tibia along a known
line: a ``distance`` link along the segment from its tibial point to its femoral point, a
``sphere-plane`` contact along the tibial plane's normal through the sphere centre; the patellar tendon
along the segment from its tibial point to its patellar point. Its force on the tibia is ``f_i`` times the
unit wrench (Pluecker coordinates) of that line, ``w_i = (u_i, b_i x u_i)`` in the femur frame, with
``u_i`` pointing from the tibia toward the femur (or patella) and ``b_i`` the point of application.
These unit wrenches are, up to sign and scale, the rows of the constraint Jacobian with respect to the
tibia's twist, so the equilibrium ``sum_i f_i w_i + w_ext = 0`` is the virtual-work statement that the
load does no work on any motion the constraints allow, plus one equation for the free flexion, which the
tendon carries. Six unknowns, six equations: solved directly, with the condition number reported.

Sign convention: ``f > 0`` is tension (a ligament pulls, the tendon pulls), ``f < 0`` compression (a
contact pushes). A concave (medial) facet holds the condyle from outside: surface compression there
stretches the equivalent link between the sphere centres, so its column is reported with both force and
direction negated, and every contact reads compression as negative. A ligament or tendon with ``f < 0`` would have to push and a contact with ``f > 0``
would have to pull: both are flagged, never hidden. Forces in N, moments in N*mm, lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from knee.foundations.conventions import joint_to_pose
from knee.foundations.errors import KneeInputError
from knee.models.mechanism.solver import Mechanism

#: Force (N) below which a member counts as unloaded when flagging (numerical noise).
FORCE_TOL = 1e-6


@dataclass
class StaticsResult:
    """Member forces at each flexion angle.

    Attributes
    ----------
    names : list of str
        The five TF links and ``"tendon"`` (the last column).
    roles : list of str
        ``"ligament"``, ``"contact"`` or ``"tendon"``.
    forces : (n, 6) float
        Member forces, N (tension +).
    directions : (n, 6, 3) float
        Unit direction of each member's pull on the tibia (femur frame).
    points : (n, 6, 3) float
        Point of application on the tibia (femur frame, mm).
    condition : (n,) float
        Condition number of the 6x6 equilibrium matrix (in N and N*m units).
    flags : list of list of str
        Per angle, what is wrong (a ligament pushing, a contact pulling, every ligament slack, ...).
    """

    flexion: np.ndarray
    names: list
    roles: list
    forces: np.ndarray
    directions: np.ndarray
    points: np.ndarray
    condition: np.ndarray
    flags: list = field(default_factory=list)

    def force(self, name: str) -> np.ndarray:
        return self.forces[:, self.names.index(name)]

    @property
    def ok(self) -> np.ndarray:
        """(n,) bool: no flag at that angle."""
        return np.array([not f for f in self.flags], dtype=bool)


def member_lines(params, tf, pf):
    """Unit pull directions (n, 6, 3) and application points (n, 6, 3) on the tibia, femur frame, of the
    five links and the tendon, for solved TF and PF joint coordinates ``tf``, ``pf`` (n, 6)."""
    T = joint_to_pose(np.atleast_2d(tf))
    R, P = T[:, :3, :3], T[:, :3, 3]
    n = T.shape[0]
    u = np.empty((n, 6, 3))
    b = np.empty((n, 6, 3))
    for i, lk in enumerate(params.links):
        if lk.kind == "distance":
            bt = R @ lk.tibia + P
            d = lk.femur - bt
            u[:, i] = d / np.linalg.norm(d, axis=1, keepdims=True)
            b[:, i] = bt
        else:  # sphere-plane: along the plane normal (toward the sphere) at the contact point
            nrm = lk.normal / np.linalg.norm(lk.normal)
            nf = R @ nrm
            u[:, i] = nf
            b[:, i] = lk.femur - lk.length * nf
    if params.pf is None:
        u[:, 5] = np.nan
        b[:, 5] = np.nan
    else:
        Tp = joint_to_pose(np.atleast_2d(pf))
        bt = R @ params.pf.tendon_tibia + P
        d = Tp[:, :3, :3] @ params.pf.tendon_patella + Tp[:, :3, 3] - bt
        u[:, 5] = d / np.linalg.norm(d, axis=1, keepdims=True)
        b[:, 5] = bt
    return u, b


def solve_statics(mech: Mechanism, flexion, force_tibia, moment_tibia=None) -> StaticsResult:
    """Member forces balancing an external load on the tibia.

    Parameters
    ----------
    mech : Mechanism
        With a patella (the tendon carries the flexion equilibrium).
    flexion : float or (n,) float
        Flexion angles, rad, any order (solved with :meth:`Mechanism.motion_at`).
    force_tibia : (3,) or (n, 3) float
        External force on the tibia, N, in the tibia frame.
    moment_tibia : (3,) or (n, 3) float, optional
        External moment about the tibia origin, N*mm, tibia frame.
    """
    if not mech.has_pf:
        raise KneeInputError(f"{mech.params.name}: the statics needs the patellar tendon (a model with a patella)")
    al = np.atleast_1d(np.asarray(flexion, float))
    n = al.size
    F = np.broadcast_to(np.asarray(force_tibia, float), (n, 3))
    M = np.zeros((n, 3)) if moment_tibia is None else np.broadcast_to(np.asarray(moment_tibia, float), (n, 3))
    if not (np.all(np.isfinite(F)) and np.all(np.isfinite(M))):
        raise KneeInputError("the load must be finite")
    tf, pf = mech.motion_at(al)
    u, b = member_lines(mech.params, tf, pf)
    T = joint_to_pose(tf)
    R, P = T[:, :3, :3], T[:, :3, 3]
    Fw = np.einsum("nij,nj->ni", R, F)
    Mw = np.einsum("nij,nj->ni", R, M) + np.cross(P, Fw)  # about the femur origin
    # equilibrium rows in N and N*m (balanced units for the solve and the condition number)
    A = np.concatenate([u, np.cross(b, u) * 1e-3], axis=2).transpose(0, 2, 1)  # (n, 6, 6)
    rhs = -np.concatenate([Fw, Mw * 1e-3], axis=1)
    cond = np.linalg.cond(A)
    forces = np.linalg.solve(A, rhs[:, :, None])[:, :, 0]
    for i, lk in enumerate(mech.params.links):  # concave facet: surface compression = link tension
        if lk.role == "contact" and lk.kind == "distance" and lk.tibia_surface == "concave":
            forces[:, i] *= -1.0
            u[:, i] *= -1.0
    names = [lk.name for lk in mech.params.links] + ["tendon"]
    roles = [lk.role for lk in mech.params.links] + ["tendon"]
    flags = _flags(forces, names, roles, cond)
    return StaticsResult(flexion=al, names=names, roles=roles, forces=forces, directions=u, points=b,
                         condition=cond, flags=flags)


def _flags(forces, names, roles, cond) -> list[list[str]]:
    """Per angle, the members loaded the wrong way (detected with array masks; text only where flagged)."""
    roles = np.asarray(roles)
    lig, con, ten = roles == "ligament", roles == "contact", roles == "tendon"
    push = (forces < -FORCE_TOL) & (lig | ten)
    pull = (forces > FORCE_TOL) & con
    slack = np.all(forces[:, lig] <= FORCE_TOL, axis=1) if lig.any() else np.zeros(len(forces), bool)
    singular = ~np.isfinite(cond) | (cond > 1e8)
    out = [[] for _ in range(len(forces))]
    for k in np.nonzero(push.any(axis=1) | pull.any(axis=1) | slack | singular)[0]:
        f = out[k]
        if singular[k]:
            f.append(f"near-singular equilibrium (condition {cond[k]:.3g})")
        for j in np.nonzero(push[k] | pull[k])[0]:
            v = forces[k, j]
            if lig[j]:
                f.append(f"{names[j]} would have to push ({v:.1f} N)")
            elif ten[j]:
                f.append(f"tendon would have to push ({v:.1f} N): the load needs a knee flexor, not in the model")
            else:
                f.append(f"contact {names[j]} would have to pull ({v:.1f} N)")
        if slack[k]:
            f.append("every ligament is slack or pushing")
    return out
