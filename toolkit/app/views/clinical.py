"""Plots and Rerun recordings of the clinical analyses: gait (``time`` timeline) and contact against
flexion (``flexion_deg`` timeline); pressure maps as vertex colours on the condylar caps."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import trimesh  # noqa: E402

from knee.foundations import recording as R  # noqa: E402
from knee.foundations.conventions import joint_to_pose  # noqa: E402
from knee.models.contact import ContactAlongFlexion  # noqa: E402
from knee.models.gait import GaitResult  # noqa: E402
from knee.models.mechanism.solver import Mechanism  # noqa: E402
from knee.models.phantom import build_phantom  # noqa: E402


def _colours(values, vmax):
    cmap = matplotlib.colormaps["viridis"]
    return (cmap(np.clip(values / max(vmax, 1e-9), 0, 1)) * 255).astype(np.uint8)


def _vertex_values(cap: trimesh.Trimesh, face_values):
    """(n, faces) -> (n, vertices), each vertex the mean of its faces."""
    nf, nv = len(cap.faces), len(cap.vertices)
    inc = sp.csr_matrix((np.ones(3 * nf), (np.repeat(np.arange(nf), 3), cap.faces.ravel())), shape=(nf, nv))
    count = np.asarray(inc.sum(axis=0)).ravel()
    return np.asarray(inc.T @ np.asarray(face_values).T).T / np.maximum(count, 1)


def _align_minus_z(d):
    """Rotations (n, 3, 3) taking (0, 0, -1) to unit vectors d (n, 3) (Rodrigues, vectorised)."""
    a = np.array([0.0, 0.0, -1.0])
    v = np.cross(a, d)
    c = d @ a
    K = np.zeros((len(d), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    K = K - np.swapaxes(K, 1, 2)
    return np.eye(3) + K + K @ K / (1 + c)[:, None, None]


def contact_directions(params, tf):
    """Unit direction (n, 3), femur frame, from each contact's femoral centre toward its contact point."""
    T = joint_to_pose(tf)
    out = {}
    for lk in params.links:
        if lk.role != "contact":
            continue
        if lk.kind == "sphere-plane":
            d = -(T[:, :3, :3] @ (lk.normal / np.linalg.norm(lk.normal)))
        else:
            bt = T[:, :3, :3] @ lk.tibia + T[:, :3, 3]
            d = bt - lk.femur
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            if lk.tibia_surface == "concave":
                d = -d
        out[lk.name] = d
    return out


def gait_blueprint():
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="leg", name="Leg"),
        rrb.Vertical(rrb.TimeSeriesView(origin="metrics/knee_load", name="Knee load on the tibia"),
                     rrb.TimeSeriesView(origin="metrics/members", name="Link and tendon forces (N)"),
                     rrb.TimeSeriesView(origin="metrics/pressure", name="Peak pressure (MPa)")),
        column_shares=[3, 2]), collapse_panels=True)


def log_gait(rec, mech: Mechanism, res: GaitResult) -> None:
    """The leg on the ``time`` timeline, GRF arrow, pressure maps on the condyles, forces as plots."""
    t = res.trial.time
    n = t.size
    rec.log("leg", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
    ph = build_phantom(mech.params)
    mm = {k: p.copy() for k, p in res.poses.items()}
    for p in mm.values():
        p[:, :3, 3] *= 1e3
    R.log_mesh(rec, "leg/femur", ph.femur, R.BONE_COLOURS["femur"])
    R.log_mesh(rec, "leg/tibia", ph.tibia, R.BONE_COLOURS["tibia"])
    if ph.patella is not None:
        R.log_mesh(rec, "leg/patella", ph.patella, R.BONE_COLOURS["patella"])
        R.send_poses(rec, "leg/patella", "time", t, mm["patella"])
    foot = trimesh.creation.box(extents=[200.0, 40.0, 80.0]).apply_translation([50.0, -45.0, 0.0])
    R.log_mesh(rec, "leg/foot", foot, (190, 180, 160))
    for k in ("femur", "tibia", "foot"):
        R.send_poses(rec, f"leg/{k}", "time", t, mm[k])
    # GRF as an arrow at the centre of pressure (world, mm; 1 mm per 2 N)
    cop = mm["foot"][:, :3, :3] @ np.array([0.0, -68.0, 0.0]) + mm["foot"][:, :3, 3]
    rec.send_columns("leg/grf", indexes=[R.time_column("time", t)],
                     columns=rr.Arrows3D.columns(origins=cop, vectors=res.trial.grf * 0.5).partition(np.ones(n, int)))
    # pressure maps on the condylar caps (elastic foundation), moved with the femur
    dirs = contact_directions(mech.params, res.tf)
    for name, e in res.contact.items():
        if e.foundation is None:
            continue
        cap = e.foundation.cap
        lk = mech.params.link(name)
        vals = _vertex_values(cap, e.foundation.pressure)
        cols = _colours(vals, max(e.foundation.peak.max(), 1e-6))
        ent = f"leg/femur/{name}_pressure"
        rec.log(ent, rr.Mesh3D(vertex_positions=cap.vertices.astype(np.float32),
                               triangle_indices=cap.faces.astype(np.uint32)), static=True)
        rec.send_columns(ent, indexes=[R.time_column("time", t)],
                         columns=rr.Mesh3D.columns(vertex_colors=cols.reshape(-1, 4)).partition(
                             np.full(n, len(cap.vertices))))
        Rd = _align_minus_z(dirs[name])
        Tl = np.tile(np.eye(4), (n, 1, 1))
        Tl[:, :3, :3] = Rd
        Tl[:, :3, 3] = lk.femur + 0.3 * dirs[name]  # just proud of the bone surface
        R.send_poses(rec, ent, "time", t, Tl)
    st = res.statics
    for j, nm in enumerate(st.names):
        R.send_scalars(rec, f"metrics/members/{nm}", "time", t, st.forces[:, j])
    for k, ax in enumerate(("anterior", "proximal", "lateral")):
        R.send_scalars(rec, f"metrics/knee_load/force_{ax}_N", "time", t, res.knee_force[:, k])
        R.send_scalars(rec, f"metrics/knee_load/moment_{ax}_Nm", "time", t, res.knee_moment[:, k] * 1e-3)
    for name, e in res.contact.items():
        R.send_scalars(rec, f"metrics/pressure/{name}_hertz_peak", "time", t, e.hertz.peak)
        if e.foundation is not None:
            R.send_scalars(rec, f"metrics/pressure/{name}_foundation_peak", "time", t, e.foundation.peak)
        R.send_scalars(rec, f"metrics/contact_force/{name}", "time", t, e.force)
    R.send_scalars(rec, "metrics/knee_flexion_deg", "time", t, np.degrees(res.trial.knee))


def plot_gait(res: GaitResult, path, title: str = "") -> None:
    """Knee flexion, member forces, contact forces and peak pressures over the cycle (PNG)."""
    t = res.trial.time
    fig, ax = plt.subplots(2, 2, figsize=(12, 7))
    ax[0, 0].plot(t, np.degrees(res.trial.knee), "k")
    ax[0, 0].set_title("knee flexion (deg)")
    for j, nm in enumerate(res.statics.names):
        ax[0, 1].plot(t, res.statics.forces[:, j], label=nm)
    ax[0, 1].set_title("member forces (N; tension +, contact compression -)")
    ax[0, 1].legend(fontsize=7)
    for nm, e in res.contact.items():
        ax[1, 0].plot(t, e.force, label=nm)
        ax[1, 1].plot(t, e.hertz.peak, label=f"{nm} Hertz")
        if e.foundation is not None:
            ax[1, 1].plot(t, e.foundation.peak, "--", label=f"{nm} elastic foundation")
    ax[1, 0].set_title("contact force (N, compression)")
    ax[1, 1].set_title("peak pressure (MPa)")
    ax[1, 0].legend(fontsize=7)
    ax[1, 1].legend(fontsize=7)
    flagged = ~res.valid
    for a in ax.ravel():
        a.set_xlabel("time (s)")
        if flagged.any():  # flagged frames shaded: their forces and pressures are not valid
            a.fill_between(t, 0, 1, where=flagged, transform=a.get_xaxis_transform(), color="0.85", zorder=0,
                           step="mid")
    if res.flagged_note:
        fig.text(0.5, 0.995, f"WARNING: {int(flagged.sum())} of {flagged.size} frames flagged (shaded): their forces "
                 f"and pressures are not physically valid", ha="center", va="top", color="firebrick", fontsize=11,
                 weight="bold")
        fig.suptitle(title, y=0.955)
    else:
        fig.suptitle(title)
    fig.tight_layout(rect=(0, 0, 1, 0.96) if res.flagged_note else None)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_contact(res: ContactAlongFlexion, path, title: str = "") -> None:
    """Contact area and peak pressure against flexion, Hertz and elastic foundation (PNG, seed 001
    Fig. 3d)."""
    fl = res.flexion_deg
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    tot_h = sum(c.hertz.area for c in res.contacts.values())
    tot_e = sum(c.foundation.area for c in res.contacts.values())
    ax[0].plot(fl, tot_h / 100, "k", label="total (Hertz)")
    ax[0].plot(fl, tot_e / 100, "k--", label="total (elastic foundation)")
    for nm, c in res.contacts.items():
        ax[0].plot(fl, c.hertz.area / 100, label=f"{nm} (Hertz)")
        ax[0].plot(fl, c.foundation.area / 100, ":", label=f"{nm} (elastic foundation)")
        ax[1].plot(fl, c.hertz.peak, label=f"{nm} (Hertz)")
        ax[1].plot(fl, c.foundation.peak, ":", label=f"{nm} (elastic foundation)")
    ax[0].set_title("contact area (cm$^2$)")
    ax[1].set_title("peak pressure (MPa)")
    for a in ax:
        a.set_xlabel("flexion (deg)")
        a.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
