"""Rerun views of the kinematic model: a sweep on the ``flexion_deg`` timeline.

The phantom bones are logged once (static, in their own frames) and moved with ``Transform3D``
columns; the five TF links and the patellar tendon are line strips in the femur frame; the twelve motion
components and the solver diagnostics are scalar series; a default blueprint shows the 3D view beside
the plots.
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from knee.foundations import recording as rec_
from knee.foundations.conventions import JOINT_COORDINATES, transform_points
from knee.models.mechanism.solver import Mechanism, SweepResult
from knee.models.phantom import Phantom

LINK_COLOURS = {"ligament": (200, 40, 40), "contact": (40, 160, 60)}
UNITS = ("deg", "deg", "deg", "mm", "mm", "mm")


def sweep_blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="knee", name="Knee (femur frame)"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="metrics/tf", name="Tibio-femoral motion"),
                rrb.TimeSeriesView(origin="metrics/pf", name="Patello-femoral motion"),
                rrb.TimeSeriesView(origin="metrics/solver", name="Solver"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def log_sweep(rec: rr.RecordingStream, mech: Mechanism, res: SweepResult, phantom: Phantom | None) -> None:
    """Log a sweep: bones moved along ``flexion_deg``, links, tendon, motion plots, diagnostics."""
    n = res.flexion.size
    if n == 0:
        return
    t = np.degrees(res.flexion)
    tl = "flexion_deg"
    rec.log("knee", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
    if phantom is not None:
        rec_.log_mesh(rec, "knee/femur", phantom.femur, rec_.BONE_COLOURS["femur"])
        rec_.log_mesh(rec, "knee/tibia", phantom.tibia, rec_.BONE_COLOURS["tibia"])
        if phantom.patella is not None and mech.has_pf:
            rec_.log_mesh(rec, "knee/patella", phantom.patella, rec_.BONE_COLOURS["patella"])
    Ttf = res.tf_poses
    rec_.send_poses(rec, "knee/tibia", tl, t, Ttf)
    if mech.has_pf:
        rec_.send_poses(rec, "knee/patella", tl, t, res.pf_poses)
    for lk in mech.params.links:
        a = np.broadcast_to(lk.femur, (n, 3))
        b = transform_points(Ttf, lk.tibia[None, :])[:, 0, :]
        if lk.kind == "sphere-plane":  # draw the sphere centre's normal to the plane
            nrm = lk.normal / np.linalg.norm(lk.normal)
            nw = np.einsum("nij,j->ni", Ttf[:, :3, :3], nrm)
            b = a - lk.length * nw
        rec_.send_segments(rec, f"knee/links/{lk.name}", tl, t, a, b, LINK_COLOURS[lk.role])
    if mech.has_pf:
        pf = mech.params.pf
        a = transform_points(res.pf_poses, pf.tendon_patella[None, :])[:, 0, :]
        b = transform_points(Ttf, pf.tendon_tibia[None, :])[:, 0, :]
        rec_.send_segments(rec, "knee/links/patellar_tendon", tl, t, a, b, (60, 60, 200))
    for group, q in (("tf", res.tf), ("pf", res.pf)):
        if group == "pf" and not mech.has_pf:
            continue
        for j, (name, unit) in enumerate(zip(JOINT_COORDINATES, UNITS)):
            v = np.degrees(q[:, j]) if unit == "deg" else q[:, j]
            rec_.send_scalars(rec, f"metrics/{group}/{name}_{unit}", tl, t, v)
    rec_.send_scalars(rec, "metrics/solver/log10_max_residual_mm", tl, t, np.log10(np.maximum(res.residual, 1e-17)))
    rec_.send_scalars(rec, "metrics/solver/log10_jacobian_condition", tl, t, np.log10(res.condition))
