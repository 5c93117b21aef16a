"""Rerun recording helpers: one recording per command run, application id ``knee``.

Meshes are logged once (static) and moved with ``Transform3D`` columns; long series are sent
column-wise with ``send_columns``. Recordings are written to ``.rrd`` files that open with
``rerun FILE``; nothing here starts a viewer or touches the network.

Entity paths read like the anatomy: ``knee/femur``, ``knee/tibia``, ``knee/patella``,
``knee/links/<name>``, ``metrics/tf/<coordinate>``, ``metrics/pf/<coordinate>``, ``metrics/solver/...``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

APP_ID = "knee"

BONE_COLOURS = {"femur": (230, 220, 200), "tibia": (215, 205, 185), "patella": (200, 190, 170),
                "skin": (230, 170, 150, 90)}


def new_recording(app_id: str = APP_ID) -> rr.RecordingStream:
    """A fresh Rerun recording stream, application id ``knee`` (not the global one), to be saved with
    :func:`save` (``knee.save_recording``)."""
    return rr.RecordingStream(app_id)


def save(rec: rr.RecordingStream, path, blueprint: rrb.Blueprint | None = None) -> Path:
    """Write the recording to the file ``path`` (``.rrd``, opened with ``rerun FILE``), the blueprint first
    (the default layout of its views); returns the path. Data logged afterwards goes to the file."""
    path = Path(path)
    rec.save(str(path), default_blueprint=blueprint)
    return path


def close(rec: rr.RecordingStream) -> None:
    """Write out everything logged to ``rec`` and close its file (before the file is moved into place)."""
    rec.flush()
    rec.disconnect()


def log_mesh(rec, entity: str, mesh, colour=None) -> None:
    """Log a trimesh mesh once, statically, under ``entity`` (move it with transforms)."""
    rec.log(entity, rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices, np.float32),
                              triangle_indices=np.asarray(mesh.faces, np.uint32),
                              vertex_normals=np.asarray(mesh.vertex_normals, np.float32),
                              albedo_factor=colour), static=True)


def time_column(timeline: str, values) -> rr.TimeColumn:
    """A sequence column when all values are integers, otherwise a duration column (value = seconds)."""
    v = np.asarray(values, dtype=float)
    if np.all(np.abs(v - np.round(v)) < 1e-9):
        return rr.TimeColumn(timeline, sequence=np.round(v).astype(np.int64))
    return rr.TimeColumn(timeline, duration=v)


def send_poses(rec, entity: str, timeline: str, times, poses) -> None:
    """Move ``entity`` along a timeline: ``poses`` (n, 4, 4) sent as one ``Transform3D`` column."""
    poses = np.asarray(poses, dtype=float)
    rec.send_columns(entity, indexes=[time_column(timeline, times)],
                     columns=rr.Transform3D.columns(translation=poses[:, :3, 3], mat3x3=poses[:, :3, :3]))


def send_scalars(rec, entity: str, timeline: str, times, values) -> None:
    """A scalar series sent column-wise."""
    rec.send_columns(entity, indexes=[time_column(timeline, times)],
                     columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)))


def send_segments(rec, entity: str, timeline: str, times, a, b, colour=None, radius=0.6) -> None:
    """A line segment per time step from ``a`` (n, 3) to ``b`` (n, 3), sent column-wise."""
    strips = np.stack([np.asarray(a, float), np.asarray(b, float)], axis=1)  # (n, 2, 3)
    n = strips.shape[0]
    cols = rr.LineStrips3D.columns(strips=list(strips)).partition(np.ones(n, dtype=np.int64))
    rec.send_columns(entity, indexes=[time_column(timeline, times)], columns=cols)
    rec.log(entity, rr.LineStrips3D.from_fields(colors=[colour] if colour else None, radii=[radius]),
            static=True)
