"""The subject folder: what a lab hands the fitting pipeline (README, "Subject folders").

::

    SUBJECT/
      subject.toml                  name, side, options (below)
      ct/femur.stl tibia.stl patella.stl     CT bone surfaces (STL/PLY/OBJ, mm; SPACE=LPS|RAS comment)
      ct/skin.stl                   optional: the skin at the same pose, in the same frame (a whole leg or
                                    a band around the knee; closed, or with small holes that close); the
                                    association FEM needs it, the fit does not
      ct/landmarks.mrk.json         anatomical landmarks (knee.fitting.frames) and the alignment fiducials
      ct/areas/femur_intercondylar.mrk.json  points of the intercondylar space (helical pitch)
      mri/femur.* tibia.* [patella.*]        MRI surfaces with cartilage (the fit needs mri/ and motion.csv;
                                    a subject for the association FEM alone may have neither)
      mri/landmarks.mrk.json        the alignment fiducials (knee.fitting.frames.FIDUCIALS) in MRI space
      mri/areas/<name>.mrk.json     point lists: attachment areas acl_femur, acl_tibia, pcl_femur,
                                    pcl_tibia, mcl_femur, mcl_tibia, tendon_tibia, tendon_patella; articular
                                    regions femur_lateral_condyle, femur_medial_condyle (posterior),
                                    tibia_lateral_facet, tibia_medial_facet, femur_lateral_trochlea,
                                    femur_medial_trochlea (anterior condyles)
      mri/labels/<bone>.json        optional instead of point lists: {"<name>": [vertex indices into
                                    mri/<bone>.*], ...}
      motion.csv                    measured TF (and PF) motion (knee.foundations.imaging.read_motion_csv),
                                    or an OpenSim body-transform table named in subject.toml's [motion]
      truth.toml                    optional (synthetic subjects): the generating parameter set

``subject.toml``::

    format = "knee-subject"
    version = 1
    name = "S01"
    side = "right"                  # or "left": mirrored into a right knee on the way in
    [pf]
    reference_flexion_deg = 55.0    # default: the middle of the measured flexion range
    project_tendon = true           # project the tendon-area centroids onto the CT surfaces
    [bundles]
    acl = "am"                      # restrict a ligament's search to the points with this label
    [fit]                           # optional: the fit's bounds (knee.fitting.optimize.FitBounds)
    pf_axis_point_mm = 20.0         # e.g. a helical axis far from the trochlear sphere fits

Without a patella surface, patellar fiducials, tendon areas or PF motion the subject is TF-only.
All geometry is returned in LPS (mm) of its scan; a left knee is mirrored (LPS x negated).
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from knee.fitting.frames import FIDUCIALS, LANDMARKS, femur_frame, patella_frame, tibia_frame
from knee.fitting.optimize import FitBounds
from knee.fitting.regions import REGION_NAMES, articular_regions
from knee.foundations.errors import KneeInputError
from knee.foundations.files import read_text
from knee.foundations.geometry import rigid_register
from knee.foundations.imaging import (
    Markups,
    MotionFile,
    find_surface,
    motion_from_body_transforms,
    read_body_transforms,
    read_markups,
    read_motion_csv,
    read_surface,
)
from knee.foundations.surfaces import SurfaceQuery, closed_surface

FORMAT_NAME = "knee-subject"
LIGAMENTS = ("acl", "pcl", "mcl")


@dataclass
class Area:
    """Named points (LPS of their scan) with a label per point."""

    name: str
    points: np.ndarray
    labels: list[str]
    source: str


@dataclass
class Subject:
    root: Path
    name: str
    side: str
    ct: dict[str, trimesh.Trimesh]
    ct_landmarks: Markups
    mri: dict[str, trimesh.Trimesh]
    mri_landmarks: Markups
    motion: MotionFile | None
    has_pf: bool
    reference_flexion_deg: float | None = None
    project_tendon: bool = True
    bundles: dict[str, str] = field(default_factory=dict)
    truth: Path | None = None
    skin: trimesh.Trimesh | None = None
    #: The fit's bounds for this subject (``[fit]`` in subject.toml; :class:`knee.fitting.optimize.FitBounds`).
    bounds: FitBounds = field(default_factory=FitBounds)
    _areas: dict = field(default_factory=dict)

    @property
    def can_fit(self) -> bool:
        """Whether the folder has what the fit needs: MRI surfaces and fiducials, and a measured motion."""
        return self.motion is not None and bool(self.mri)

    def require_fit_inputs(self) -> None:
        """Refuse (one line naming what is missing) a subject without the fit's inputs."""
        missing = [what for what, ok in (("mri/ (MRI surfaces and fiducials)", bool(self.mri)),
                                         ("motion.csv", self.motion is not None)) if not ok]
        if missing:
            raise KneeInputError(f"subject {self.root} has no {' and no '.join(missing)}: the fit needs them")

    def area(self, name: str, space: str = "mri") -> Area:
        """A named point set (attachment area or region) of the MRI (or CT) folder; error naming it."""
        key = (space, name)
        if key not in self._areas:
            self._areas[key] = self._load_area(name, space)
        return self._areas[key]

    def _load_area(self, name, space) -> Area:
        folder = self.root / space
        f = folder / "areas" / f"{name}.mrk.json"
        if f.is_file():
            mk = read_markups(f)
            if len(mk.points) == 0:
                raise KneeInputError(f"{f}: no defined points in the area {name}")
            return Area(name, self._mirror(mk.points), mk.labels, str(f))
        bone = name.split("_")[-1] if name.startswith(("acl", "pcl", "mcl", "tendon")) else name.split("_")[0]
        lab = folder / "labels" / f"{bone}.json"
        if lab.is_file():
            try:
                doc = json.loads(read_text(lab, "labels file"))
            except json.JSONDecodeError as e:
                raise KneeInputError(f"{lab}: not JSON ({e})") from None
            if not isinstance(doc, dict):
                raise KneeInputError(f"{lab}: must be a JSON object {{\"<region>\": [vertex indices]}}, got a "
                                     f"{type(doc).__name__}")
            idx = doc.get(name)
            if idx is not None:
                surf = (self.mri if space == "mri" else self.ct).get(bone)
                if surf is None:
                    raise KneeInputError(f"{lab}: labels given but there is no {space} {bone} surface")
                idx = _indices(idx, f"{lab}: {name}")
                if idx.size == 0 or idx.min() < 0 or idx.max() >= len(surf.vertices):
                    raise KneeInputError(f"{lab}: {name} has vertex indices outside 0..{len(surf.vertices) - 1}")
                return Area(name, surf.vertices[idx], [name] * idx.size, f"{lab}:{name}")
        if name in REGION_NAMES and self.mri:
            return self._computed_region(name, space)
        raise KneeInputError(f"missing area {name}: expected {f} (or an entry in {lab})")

    def _computed_region(self, name: str, space: str) -> Area:
        """An articular region the folder does not give, computed from the MRI surfaces
        (:func:`knee.fitting.regions.articular_regions`) in the CT landmarks' frames carried into MRI space by
        each bone's fiducial registration; the intercondylar groove in CT space when asked for there."""
        if "computed" not in self._areas:
            frames, T_mri = {}, {}
            for b, frame in (("femur", femur_frame), ("tibia", tibia_frame)):
                A, _ = rigid_register(self.mri_landmarks.require(FIDUCIALS[b]), self.ct_landmarks.require(FIDUCIALS[b]))
                T_mri[b] = A  # MRI -> CT
                frames[b] = np.linalg.inv(A) @ frame(self.ct_landmarks)
            lm = self.ct_landmarks
            width = float(np.linalg.norm(lm.get("LE") - lm.get("ME")))
            self._areas["computed"] = (articular_regions(self.mri["femur"].vertices, self.mri["tibia"].vertices,
                                                         frames["femur"], frames["tibia"], width), T_mri)
        regions, T_mri = self._areas["computed"]
        pts = regions[name]
        if space == "ct":
            A = T_mri[name.split("_")[0]]
            pts = pts @ A[:3, :3].T + A[:3, 3]
        return Area(name, pts, [name] * len(pts), f"computed from {self.root / 'mri'} surfaces ({name})")

    def _mirror(self, p):
        p = np.array(p, dtype=float, copy=True)
        if self.side == "left":
            p[..., 0] *= -1.0
        return p


def _indices(values, where: str) -> np.ndarray:
    """A list of whole vertex indices; one line naming ``where`` otherwise (no silent truncation)."""
    if not isinstance(values, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                               for v in values):
        raise KneeInputError(f"{where} must be a list of vertex indices (whole numbers), got {str(values)[:60]}")
    a = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
        bad = a[~np.isfinite(a) | (a != np.round(a))][0]
        raise KneeInputError(f"{where}: vertex indices must be whole numbers, got {bad:g}")
    return a.astype(int)


def mirror_mesh(m: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy of a surface mirrored in x (LPS: left-right), its winding restored: a left knee's scan read as
    a right knee's, or a right knee's reading of it returned to the scan."""
    m = m.copy()
    m.vertices = m.vertices * np.array([-1.0, 1.0, 1.0])
    m.invert()  # a reflection flips the winding; restore outward normals
    return m


def _read_options(root: Path) -> dict:
    f = root / "subject.toml"
    if not f.is_file():
        raise KneeInputError(f"{root} is not a subject folder: {f} not found")
    try:
        d = tomllib.loads(read_text(f, "subject file"))
    except tomllib.TOMLDecodeError as e:
        raise KneeInputError(f"{f}: not valid TOML ({e})") from None
    if d.get("format") != FORMAT_NAME:
        raise KneeInputError(f"{f}: field 'format' must be \"{FORMAT_NAME}\", got {d.get('format')!r}")
    if d.get("version") != 1:
        raise KneeInputError(f"{f}: field 'version' must be 1, got {d.get('version')!r}")
    side = d.get("side", "right")
    if side not in ("right", "left"):
        raise KneeInputError(f"{f}: side must be \"right\" or \"left\", got {side!r}")
    d["side"] = side
    if "name" in d and (not isinstance(d["name"], str) or not d["name"].strip()):
        raise KneeInputError(f"{f}: field 'name' must be a non-empty string, got {d['name']!r}")
    for table in ("pf", "bundles", "fit", "motion"):
        if table in d and not isinstance(d[table], dict):
            raise KneeInputError(f"{f}: '{table}' must be a table ([{table}]), got {d[table]!r}")
    pf = d.get("pf", {})
    if "project_tendon" in pf and not isinstance(pf["project_tendon"], bool):
        raise KneeInputError(f"{f}: [pf] project_tendon must be true or false (no quotes), got "
                             f"{pf['project_tendon']!r}")
    ref = pf.get("reference_flexion_deg")
    if ref is not None and (isinstance(ref, bool) or not isinstance(ref, (int, float)) or not math.isfinite(ref)):
        raise KneeInputError(f"{f}: [pf] reference_flexion_deg must be a number of degrees, got {ref!r}")
    unknown = sorted(set(pf) - {"project_tendon", "reference_flexion_deg"})
    if unknown:
        raise KneeInputError(f"{f}: unknown field(s) in [pf]: {', '.join(unknown)} (known: reference_flexion_deg, "
                             "project_tendon)")
    return d


#: A fiducial (a point picked on the bone) farther than this from its bone's surface is refused (mm):
#: picking error and cartilage are a few mm (the synthetic subject's schematic bones, up to 9.3 mm);
#: a wrong space, unit or bone is tens to hundreds.
LANDMARK_TOLERANCE_MM = 15.0


def check_landmarks_on_bones(landmarks: Markups, surfaces: dict, folder: Path, side: str) -> None:
    """Refuse landmarks that do not lie on their bones: the fiducials of each bone (``FIDUCIALS``, picked on
    the bone surface) within :data:`LANDMARK_TOLERANCE_MM` of it. The message says what it looks like: a
    file in metres, a wrong ``coordinateSystem`` or ``SPACE`` (x and y negated), or a misplaced point."""
    where = landmarks.path or folder / "landmarks.mrk.json"
    pts = landmarks.points
    if len(pts) and float(np.ptp(pts, axis=0).max()) < 1.0 and any(
            float(np.ptp(m.vertices, axis=0).max()) > 10.0 for m in surfaces.values()):
        raise KneeInputError(f"{where}: the landmarks span only {float(np.ptp(pts, axis=0).max()):.3g} units while the "
                             "surfaces span tens of mm: the landmarks look like metres; they must be in mm")
    for bone, labels in FIDUCIALS.items():
        if bone not in surfaces or not all(lb in landmarks.labels for lb in labels):
            continue
        q = SurfaceQuery.of(surfaces[bone])
        p = landmarks.require(labels)
        d = np.abs(q.signed_distance(p))
        if d.max() <= LANDMARK_TOLERANCE_MM:
            continue
        k = int(np.argmax(d))
        surf = f"{folder / bone}.*"
        negate = np.array([-1.0, -1.0, 1.0])
        # (a left knee's landmarks and surfaces are both mirrored: a space error is still x and y negated)
        if np.abs(q.signed_distance(p * negate)).max() <= LANDMARK_TOLERANCE_MM:
            raise KneeInputError(f"{where}: the {bone} landmarks lie on {surf} only with x and y negated: the "
                                 f"landmarks' coordinateSystem or the surface's SPACE comment is wrong (LPS vs RAS)")
        raise KneeInputError(f"{where}: landmark {labels[k]} is {d[k]:.1f} mm from the {bone} surface {surf} (at "
                             f"most {LANDMARK_TOLERANCE_MM:g} mm): picked in another space or on another bone?")


def _body_transform_motion(root: Path, m: dict, ct_lm: Markups, side: str) -> MotionFile:
    """The measured motion from an OpenSim body-transform table named by subject.toml's ``[motion]``::

        [motion]
        file = "passive.sto"          # .sto/.mot: time, <body>_T11 ... <body>_T44 per body
        femur = "femur_distal_r"      # the table's body of each bone
        tibia = "tibia_proximal_r"
        patella = "patella_r"         # optional: PF motion
        length_unit = "m"             # the table's translations: "m" (OpenSim's; default) or "mm"
        reference_row = 0             # optional: the CT shows the bones at this row's poses; without it
                                      # the poses take each bone's CT coordinates to the table's ground

    Joint coordinates in the anatomical frames of the CT landmarks (knee.foundations.imaging.
    motion_from_body_transforms)."""
    where = f"{root / 'subject.toml'} [motion]"
    for key in ("file", "femur", "tibia"):
        if not isinstance(m.get(key), str) or not m[key]:
            raise KneeInputError(f"{where}: field '{key}' must be a non-empty string")
    unknown = sorted(set(m) - {"file", "femur", "tibia", "patella", "length_unit", "reference_row"})
    if unknown:
        raise KneeInputError(f"{where}: unknown field(s) {', '.join(unknown)}")
    ref = m.get("reference_row")
    if ref is not None and (isinstance(ref, bool) or not isinstance(ref, int)):
        raise KneeInputError(f"{where}: reference_row must be a whole number, got {ref!r}")
    table = read_body_transforms(root / m["file"], str(m.get("length_unit", "m")))
    if side == "left":  # mirrored into a right knee, as the surfaces and landmarks are
        S = np.diag([-1.0, 1.0, 1.0, 1.0])
        table.poses = {b: S @ T @ S for b, T in table.poses.items()}
    bodies = {g: m[g] for g in ("femur", "tibia", "patella") if isinstance(m.get(g), str)}
    frames = {"femur": femur_frame(ct_lm), "tibia": tibia_frame(ct_lm)}
    if "patella" in bodies and all(k in ct_lm.labels for k in LANDMARKS["patella"]):
        frames["patella"] = patella_frame(ct_lm)
    tf, pf = motion_from_body_transforms(table, bodies, frames, ref)
    return MotionFile(tf, pf, 0, len(tf))


def load_subject(root) -> Subject:
    """Read and check a subject folder (see the module docstring). Nothing in it is written.

    Returns a :class:`Subject`: surfaces as ``trimesh.Trimesh`` in LPS of their scan (mm; a left knee
    mirrored into a right one), landmarks, the measured motion (rad, mm). Bad or missing files raise
    :class:`KneeInputError` naming them."""
    root = Path(root)
    if not root.is_dir():
        raise KneeInputError(f"subject folder {root} not found")
    opt = _read_options(root)
    side = opt["side"]
    has_mri = (root / "mri").is_dir()
    ct_lm = read_markups(root / "ct" / "landmarks.mrk.json")
    mri_lm = read_markups(root / "mri" / "landmarks.mrk.json") if has_mri else Markups([], np.zeros((0, 3)), [])
    if side == "left":
        for mk in (ct_lm, mri_lm):
            mk.points = mk.points * np.array([-1.0, 1.0, 1.0])
    ct, mri = {}, {}
    for bone in ("femur", "tibia"):
        ct[bone] = read_surface(find_surface(root / "ct", bone))
        if has_mri:
            mri[bone] = read_surface(find_surface(root / "mri", bone))
    optional = (("patella", "ct", ct), ("skin", "ct", ct)) + ((("patella", "mri", mri),) if has_mri else ())
    for bone, folder, store in optional:
        try:
            store[bone] = read_surface(find_surface(root / folder, bone))
        except KneeInputError as e:
            if "missing surface" not in str(e):
                raise
    if side == "left":
        ct = {k: mirror_mesh(v) for k, v in ct.items()}
        mri = {k: mirror_mesh(v) for k, v in mri.items()}
    skin = ct.pop("skin", None)
    if skin is not None:
        skin = closed_surface(skin, f"{root / 'ct'} skin")
    for bone in ("femur", "tibia"):
        ct_lm.require(LANDMARKS[bone])
        if has_mri:
            mri_lm.require(FIDUCIALS[bone])
    check_landmarks_on_bones(ct_lm, ct, root / "ct", side)
    if has_mri:
        check_landmarks_on_bones(mri_lm, mri, root / "mri", side)
    motion = read_motion_csv(root / "motion.csv", side) if (root / "motion.csv").exists() else None
    if opt.get("motion"):
        if motion is not None:
            raise KneeInputError(f"{root}: give the motion as motion.csv or as subject.toml's [motion] table, not both")
        motion = _body_transform_motion(root, opt["motion"], ct_lm, side)
    pf_opt = opt.get("pf", {}) or {}
    has_pf = ("patella" in ct and motion is not None and motion.pf is not None
              and all(k in ct_lm.labels for k in LANDMARKS["patella"])
              and all(k in mri_lm.labels for k in FIDUCIALS["patella"]))
    ref = pf_opt.get("reference_flexion_deg")
    bundles = opt.get("bundles", {}) or {}
    for k, v in bundles.items():
        if k not in LIGAMENTS or not isinstance(v, str):
            raise KneeInputError(f"{root / 'subject.toml'}: [bundles] entries must be one of {', '.join(LIGAMENTS)} "
                                 f"= \"<label>\", got {k} = {v!r}")
    truth = root / "truth.toml"
    bounds = FitBounds().updated(opt.get("fit", {}) or {}, f"{root / 'subject.toml'} [fit]")
    return Subject(root=root, name=str(opt.get("name", root.name)), side=side, ct=ct, ct_landmarks=ct_lm, mri=mri,
                   mri_landmarks=mri_lm, motion=motion, has_pf=bool(has_pf),
                   reference_flexion_deg=None if ref is None else float(ref),
                   project_tendon=bool(pf_opt.get("project_tendon", True)), bundles=dict(bundles),
                   truth=truth if truth.is_file() else None, skin=skin, bounds=bounds)
