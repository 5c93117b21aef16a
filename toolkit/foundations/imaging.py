"""Imaging files: bone surfaces, 3D Slicer markups and measured-motion CSV files.

Everything is returned in **LPS** patient coordinates (mm), the DICOM convention:

* Surfaces (STL, PLY, OBJ) written by 3D Slicer carry a ``SPACE=LPS`` or ``SPACE=RAS`` comment (in the
  STL header, a PLY ``comment`` line or an OBJ ``#`` line). It is honoured; without it the file is taken
  as LPS. RAS -> LPS negates x and y.
* Markups JSON (``.mrk.json``, Slicer's schema): ``coordinateSystem`` ``LPS`` or ``RAS`` (default LPS);
  control points whose ``positionStatus`` is not ``defined`` are treated as missing.
* Motion CSV: one row per frame; TF (and optionally PF) poses either as the six joint coordinates of
  :mod:`knee.foundations.conventions` (columns ``tf_flexion_deg ... tf_lateral_mm``, ``pf_...``; degrees, mm) or
  as 4x4 matrices (columns ``tf_T00 ... tf_T23``, the first three rows, row-major). Rows with a missing
  or non-finite value are skipped and counted.

Shapes: points ``(n, 3)``, poses ``(n, 4, 4)``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from knee.foundations.conventions import joint_coordinates, joint_to_pose
from knee.foundations.errors import KneeInputError
from knee.foundations.files import read_text

SURFACE_SUFFIXES = (".stl", ".ply", ".obj")
_SPACE_RE = re.compile(rb"SPACE\s*=\s*(LPS|RAS)", re.IGNORECASE)
_RAS_TO_LPS = np.array([-1.0, -1.0, 1.0])
MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/main/Modules/Loadable/Markups/Resources/"
                  "Schema/markups-schema-v1.0.3.json#")


def _space(name: str, where: str) -> str:
    s = str(name).strip().upper()
    if s not in ("LPS", "RAS"):
        raise KneeInputError(f"{where}: coordinate system must be LPS or RAS, got {name!r}")
    return s


def surface_space(path) -> str:
    """The ``SPACE=`` comment of a surface file (``"LPS"`` when there is none)."""
    with Path(path).open("rb") as fh:
        head = fh.read(4096)
    m = _SPACE_RE.search(head)
    return m.group(1).decode().upper() if m else "LPS"


def _refuse_short_binary_stl(path: Path) -> None:
    """Refuse a binary STL shorter than the triangle count in its header says (an interrupted copy or
    export): 84 bytes of header and count, then 50 per triangle. An ASCII STL (it begins with 'solid' and
    holds 'facet' lines) is left to the reader."""
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(84)
        ascii_like = head[:5].lower() == b"solid" and b"facet" in head + fh.read(512)
    if ascii_like:
        return
    if size < 84:
        raise KneeInputError(f"{path}: truncated: {size} bytes, less than a binary STL's 84-byte header")
    n = int.from_bytes(head[80:84], "little")
    if size < 84 + 50 * n:
        raise KneeInputError(f"{path}: truncated: its header declares {n} triangles, the file holds "
                             f"{(size - 84) // 50}")


def read_surface(path, min_extent: float = 1.0) -> trimesh.Trimesh:
    """Read a bone surface in mm, converted to LPS.

    Raises :class:`KneeInputError` when the file is missing or unreadable, has no triangles, or its
    bounding box is under ``min_extent`` units (the surface looks like metres, not millimetres).
    """
    path = Path(path)
    if not path.is_file():
        raise KneeInputError(f"surface file {path} not found")
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise KneeInputError(f"{path}: surfaces must be STL, PLY or OBJ")
    if path.suffix.lower() == ".stl":
        _refuse_short_binary_stl(path)
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as e:  # trimesh raises many types on malformed files
        raise KneeInputError(f"{path}: cannot read the surface ({e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise KneeInputError(f"{path}: no triangles could be read from it (an empty, truncated or malformed file)")
    ext = float(np.ptp(mesh.vertices, axis=0).max())
    if not np.all(np.isfinite(mesh.vertices)):
        raise KneeInputError(f"{path}: non-finite vertex coordinates")
    if ext < min_extent:
        raise KneeInputError(f"{path}: bounding box is only {ext:.3g} units across; surfaces must be in mm "
                             "(this looks like metres)")
    if surface_space(path) == "RAS":
        mesh.vertices = mesh.vertices * _RAS_TO_LPS  # a reflection of x and y is a rotation: winding kept
    return mesh


def write_surface(path, mesh: trimesh.Trimesh, space: str = "LPS") -> Path:
    """Write ``mesh`` (given in LPS) to STL/PLY/OBJ in ``space`` with Slicer's ``SPACE=`` comment."""
    path = Path(path)
    space = _space(space, str(path))
    m = mesh.copy()
    if space == "RAS":
        m.vertices = m.vertices * _RAS_TO_LPS
    suf = path.suffix.lower()
    if suf == ".stl":
        data = bytearray(trimesh.exchange.stl.export_stl(m))
        data[:80] = f"SPACE={space} knee-toolkit".encode().ljust(80, b" ")
        path.write_bytes(bytes(data))
    elif suf == ".ply":
        data = trimesh.exchange.ply.export_ply(m, encoding="binary")
        first = data.index(b"\n", data.index(b"format")) + 1
        path.write_bytes(data[:first] + f"comment SPACE={space}\n".encode() + data[first:])
    elif suf == ".obj":
        path.write_text(f"# SPACE={space}\n" + trimesh.exchange.obj.export_obj(m), encoding="utf-8")
    else:
        raise KneeInputError(f"{path}: surfaces must be written as STL, PLY or OBJ")
    return path


def find_surface(folder, name: str) -> Path:
    """``folder/name.stl|.ply|.obj`` (the first that exists); error naming the bone when none does."""
    folder = Path(folder)
    for suf in SURFACE_SUFFIXES:
        p = folder / f"{name}{suf}"
        if p.is_file():
            return p
    raise KneeInputError(f"missing surface: {folder / name}.stl (or .ply/.obj)")


# ----------------------------------------------------------------------------------------------
# Markups


@dataclass
class Markups:
    """Control points of a markups file, in LPS (mm).

    Attributes
    ----------
    labels : list of str
        Label of each defined point.
    points : (n, 3) float
        The defined points.
    missing : list of str
        Labels of the points whose ``positionStatus`` is not ``defined``.
    """

    labels: list[str]
    points: np.ndarray
    missing: list[str] = field(default_factory=list)
    path: Path | None = None

    def get(self, label: str) -> np.ndarray:
        """The point with this label; error naming it (and the file) when absent, undefined, or given more than
        once at different positions (which one was meant cannot be told)."""
        where = f" in {self.path}" if self.path else ""
        if label in self.labels:
            at = [i for i, lb in enumerate(self.labels) if lb == label]
            if len(at) > 1 and np.ptp(self.points[at], axis=0).max() > 0.0:
                raise KneeInputError(f"landmark {label}{where} is given {len(at)} times at different positions; "
                                     "keep the one meant")
            return self.points[at[0]]
        if label in self.missing:
            raise KneeInputError(f"landmark {label}{where} is not defined (positionStatus)")
        raise KneeInputError(f"missing landmark {label}{where}")

    def require(self, labels) -> np.ndarray:
        """(k, 3) points of ``labels`` in that order."""
        return np.array([self.get(lb) for lb in labels])


def read_markups(path) -> Markups:
    """Read a Slicer markups JSON file (all its markups' control points), converted to LPS."""
    path = Path(path)
    text = read_text(path, "markups file")
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise KneeInputError(f"{path}: not a Slicer markups JSON file ({e})") from None
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list) or not all(isinstance(mk, dict) for mk in markups):
        raise KneeInputError(f"{path}: not a Slicer markups JSON file (its 'markups' must be a list of objects)")
    labels, pts, missing = [], [], []
    for mk in markups:
        flip = _space(mk.get("coordinateSystem", "LPS"), str(path)) == "RAS"
        cps = mk.get("controlPoints", [])
        if not isinstance(cps, list) or not all(isinstance(cp, dict) for cp in cps):
            raise KneeInputError(f"{path}: 'controlPoints' must be a list of objects")
        for i, cp in enumerate(cps):
            label = str(cp.get("label", f"point{i + 1}"))
            status = cp.get("positionStatus", "defined")
            pos = cp.get("position")
            if status != "defined" or pos is None:
                missing.append(label)
                continue
            ok = isinstance(pos, list) and len(pos) == 3 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in pos)
            p = np.asarray(pos, dtype=float) if ok else np.full(3, np.nan)
            if not np.all(np.isfinite(p)):
                raise KneeInputError(f"{path}: point {label!r} has an invalid position {pos!r} (three numbers)")
            labels.append(label)
            pts.append(p * _RAS_TO_LPS if flip else p)
    return Markups(labels, np.array(pts, dtype=float).reshape(-1, 3), missing, path)


def write_markups(path, labels, points, space: str = "LPS", kind: str = "Fiducial") -> Path:
    """Write points (given in LPS) as a Slicer markups JSON file in ``space``."""
    path = Path(path)
    space = _space(space, str(path))
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    if space == "RAS":
        pts = pts * _RAS_TO_LPS
    cps = [{"id": str(i + 1), "label": str(lb), "position": [float(v) for v in p], "positionStatus": "defined"}
           for i, (lb, p) in enumerate(zip(labels, pts))]
    doc = {"@schema": MARKUPS_SCHEMA,
           "markups": [{"type": kind, "coordinateSystem": space, "coordinateUnits": "mm", "controlPoints": cps}]}
    path.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    return path


# ----------------------------------------------------------------------------------------------
# Measured motion

_COORDS = ["flexion_deg", "adduction_deg", "internal_rotation_deg", "anterior_mm", "proximal_mm", "lateral_mm"]
_MATRIX = [f"T{i}{j}" for i in range(3) for j in range(4)]


def motion_columns(group: str, form: str = "coordinates") -> list[str]:
    """Column names of one group (``"tf"`` or ``"pf"``) in a motion CSV."""
    return [f"{group}_{c}" for c in (_COORDS if form == "coordinates" else _MATRIX)]


@dataclass
class MotionFile:
    """A measured motion read from CSV: ``tf`` (n, 6) and ``pf`` (n, 6) or None, rad and mm, and the
    number of rows skipped for missing or non-finite values."""

    tf: np.ndarray
    pf: np.ndarray | None
    skipped: int
    rows: int


#: The largest joint angle (deg) and translation (mm) a motion file's row may hold: beyond a full turn or a
#: metre it is not a knee's motion in degrees and millimetres (radians read as degrees stay inside; a value
#: such as 1e308 or a column of timestamps does not).
MOTION_MAX_DEG, MOTION_MAX_MM = 360.0, 1000.0


def _check_motion_range(q, cols, path) -> None:
    """Refuse a finite joint coordinate beyond :data:`MOTION_MAX_DEG` (the first three columns of ``q``) or
    :data:`MOTION_MAX_MM` (the last three), naming the column and the data row; non-finite values are the
    reader's to skip."""
    q = np.asarray(q, float)
    limit = np.array([MOTION_MAX_DEG] * 3 + [MOTION_MAX_MM] * 3)
    bad = np.isfinite(q) & (np.abs(q) > limit)
    if bad.any():
        r, c = map(int, np.argwhere(bad)[0])
        unit = "deg" if c < 3 else "mm"
        raise KneeInputError(f"{path}: {cols[c]} is {q[r, c]:g} in data row {r + 1} (beyond {limit[c]:g} {unit}: "
                             f"not a knee's motion in degrees and millimetres)")


def _group(header, rows, group, path, side="right"):
    cols = motion_columns(group)
    mcols = motion_columns(group, "matrix")
    if all(c in header for c in cols):
        idx = [header.index(c) for c in cols]
        q = rows[:, idx]
        _check_motion_range(q, cols, path)
        q[:, :3] = np.radians(q[:, :3])
        return q, idx
    if all(c in header for c in mcols):
        idx = [header.index(c) for c in mcols]
        T = np.zeros((len(rows), 4, 4))
        T[:, :3, :] = rows[:, idx].reshape(-1, 3, 4)
        T[:, 3, 3] = 1.0
        _check_motion_range(np.column_stack([np.zeros((len(rows), 3)), T[:, :3, 3]]),
                            [""] * 3 + [mcols[3], mcols[7], mcols[11]], path)
        ok = np.all(np.isfinite(T), axis=(1, 2))
        R = T[ok, :3, :3]
        if R.size and np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max() > 1e-3:
            raise KneeInputError(f"{path}: the {group} matrices are not rotations (R R^T != I)")
        q = np.full((len(rows), 6), np.nan)
        if ok.any():
            q[ok] = joint_coordinates(T[ok], side)
        return q, idx
    present = [c for c in cols if c in header]
    if group == "pf" and not present and not any(c in header for c in mcols):
        return None, []
    missing = [c for c in cols if c not in header]
    raise KneeInputError(f"{path}: missing {group.upper()} column(s) {', '.join(missing)} (or the 4x4 form "
                         f"{group}_T00..{group}_T23)")


def read_motion_csv(path, side: str = "right") -> MotionFile:
    """Read a measured motion (see the module docstring).

    Joint coordinates are anatomical and used as they are for either side; 4x4 matrices of a left knee
    (right-handed frames whose z points to the subject's right) are mirrored into the right-knee
    equivalent (:func:`knee.foundations.conventions.joint_coordinates`)."""
    path = Path(path)
    reader = csv.reader(io.StringIO(read_text(path, "motion file"), newline=""))
    header = [h.strip() for h in next(reader, [])]
    raw = [row for row in reader if row and any(v.strip() for v in row)]
    if not header:
        raise KneeInputError(f"{path}: empty motion file")

    def num(v):
        try:
            return float(v)
        except ValueError:
            return math.nan

    rows = np.array([[num(v) for v in (row + [""] * len(header))[:len(header)]] for row in raw],
                    dtype=float).reshape(-1, len(header))
    tf, _ = _group(header, rows.copy(), "tf", path, side)
    pf, _ = _group(header, rows.copy(), "pf", path, side)
    good = np.all(np.isfinite(tf), axis=1)
    if pf is not None:
        good &= np.all(np.isfinite(pf), axis=1)
    if good.sum() < 2:
        raise KneeInputError(f"{path}: fewer than two complete frames ({good.sum()} of {len(rows)})")
    return MotionFile(tf[good], None if pf is None else pf[good], int((~good).sum()), len(rows))


# ----------------------------------------------------------------------------------------------
# OpenSim body-transform tables


@dataclass
class BodyTransforms:
    """An OpenSim body-transform table: ``time`` (n,) and per body its poses ``poses[body]`` (n, 4, 4), mm,
    in the table's ground frame; ``source`` the file."""

    time: np.ndarray
    poses: dict
    source: str = ""


def read_body_transforms(path, length_unit: str = "m") -> BodyTransforms:
    """Read an OpenSim ``.sto``/``.mot`` table of body transforms: header lines up to ``endheader``, then a
    tab-separated table with a ``time`` column and, per body, ``<body>_T11`` ... ``<body>_T44`` (the 4x4
    pose row by row). Translations are in ``length_unit`` (``"m"``, OpenSim's, or ``"mm"``) and returned in
    mm. Rows with a non-finite entry are dropped for every body (counted in the error when too few are
    left); rotations are checked."""
    path = Path(path)
    if length_unit not in ("m", "mm"):
        raise KneeInputError(f"{path}: the length unit must be \"m\" or \"mm\", got {length_unit!r}")
    lines = read_text(path, "body-transform table").splitlines()
    try:
        start = next(i for i, ln in enumerate(lines) if ln.strip().lower() == "endheader") + 1
    except StopIteration:
        raise KneeInputError(f"{path}: not an OpenSim table (no 'endheader' line)") from None
    rows = [ln.split("\t") for ln in lines[start:] if ln.strip()]
    if len(rows) < 3:
        raise KneeInputError(f"{path}: needs a header row and at least two rows of values")
    header = [h.strip() for h in rows[0]]
    if header[0].lower() != "time":
        raise KneeInputError(f"{path}: the first column must be 'time', got {header[0]!r}")
    try:
        data = np.array([[float(v) for v in r] for r in rows[1:]], dtype=float)
    except ValueError as e:
        raise KneeInputError(f"{path}: a value is not a number ({e})") from None
    if data.ndim != 2 or data.shape[1] != len(header):
        raise KneeInputError(f"{path}: every row needs {len(header)} values")
    bodies = sorted({h[:-4] for h in header if re.fullmatch(r".+_T[1-4][1-4]", h)})
    if not bodies:
        raise KneeInputError(f"{path}: no body-transform columns (<body>_T11 ... <body>_T44)")
    good = np.all(np.isfinite(data), axis=1)
    if good.sum() < 2:
        raise KneeInputError(f"{path}: fewer than two complete rows ({good.sum()} of {len(data)})")
    scale = 1000.0 if length_unit == "m" else 1.0
    poses = {}
    for b in bodies:
        cols = [f"{b}_T{i}{j}" for i in range(1, 5) for j in range(1, 5)]
        missing = [c for c in cols if c not in header]
        if missing:
            raise KneeInputError(f"{path}: body {b} lacks column(s) {', '.join(missing)}")
        T = data[good][:, [header.index(c) for c in cols]].reshape(-1, 4, 4)
        R = T[:, :3, :3]
        if np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max() > 1e-3 or np.any(np.linalg.det(R) < 0):
            raise KneeInputError(f"{path}: the poses of {b} are not rotations")
        T[:, :3, 3] *= scale
        T[:, 3] = [0.0, 0.0, 0.0, 1.0]
        poses[b] = T
    return BodyTransforms(data[good, 0], poses, str(path))


def motion_from_body_transforms(table: BodyTransforms, bodies: dict, frames: dict, reference_row=None,
                                side: str = "right") -> tuple[np.ndarray, np.ndarray | None]:
    """TF (and PF) joint coordinates (rad, mm), (n, 6) each, from a body-transform table.

    ``bodies``: {"femur": body name, "tibia": ..., optional "patella": ...}. ``frames``: the bones'
    anatomical frames ``T_ct_bone`` (4, 4) in the CT's coordinates. The table's poses take each bone's CT
    coordinates to ground when ``reference_row`` is None (the transforms of the static scan's bones into
    each dynamic frame); with ``reference_row`` k, the CT shows the bones at row k's poses (the CT's
    coordinates are ground's at that row), so bone b moves by ``T_b(i) T_b(k)^-1``."""
    missing = [f"{g} = {b!r}" for g, b in bodies.items() if b not in table.poses]
    if missing:
        raise KneeInputError(f"{table.source}: no columns for {', '.join(missing)} (bodies in the table: "
                             f"{', '.join(table.poses)})")

    def moved(bone):
        T = table.poses[bodies[bone]]
        if reference_row is None:
            return T
        if not 0 <= reference_row < len(T):
            raise KneeInputError(f"{table.source}: reference row {reference_row} outside 0..{len(T) - 1}")
        return T @ np.linalg.inv(T[reference_row])

    def relative(bone):
        A = moved("femur") @ frames["femur"]
        B = moved(bone) @ frames[bone]
        return joint_coordinates(np.linalg.inv(A) @ B, side)

    tf = relative("tibia")
    pf = relative("patella") if "patella" in bodies and "patella" in frames else None
    return tf, pf


def write_motion_csv(path, tf, pf=None, form: str = "coordinates") -> Path:
    """Write a motion (rad, mm; (n, 6) each) as CSV, joint coordinates or 4x4 matrices."""
    path = Path(path)
    groups = [("tf", np.asarray(tf, float))] + ([("pf", np.asarray(pf, float))] if pf is not None else [])
    header = ["frame"]
    cols = []
    for g, q in groups:
        header += motion_columns(g, form)
        if form == "coordinates":
            d = q.copy()
            d[:, :3] = np.degrees(d[:, :3])
            cols.append(d)
        else:
            cols.append(joint_to_pose(q)[:, :3, :].reshape(-1, 12))
    table = np.column_stack([np.arange(len(tf))] + cols)
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for row in table:
            w.writerow([str(int(row[0]))] + [f"{v:.9g}" for v in row[1:]])
    return path
