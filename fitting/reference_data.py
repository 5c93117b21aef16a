"""Readers for the public, real knee data the toolkit is developed and tested on (README, "Real data").

- :func:`visible_human_knee`: the HuBMAP 3D reference objects made from the NLM Visible Human Male
  (``VH_M_Knee_R.glb``, ``VH_M_Skin.glb``; CC BY 4.0): a right leg's femur, tibia, fibula and patella
  and the whole-body skin, in one frame (metres; x the subject's left, y superior, z anterior).
- :func:`lenhart_subject`: the lenhart2015 knee (Apache-2.0; MRI bones and cartilage in their OpenSim body
  frames, ligament insertions digitised on its MRI, its dynamic-MRI passive motion) written as a subject
  folder that ``knee fit`` reads.

Each returns the surfaces in mm in the source's frame, the bones' anatomical frames from landmarks found
on the surfaces (:mod:`knee.fitting.landmarks`; the source's own annotations, such as entheses, are
returned beside them, not used for them), so that what is computed from them can be checked against the
annotations.
"""

from __future__ import annotations

import shutil
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from knee.fitting.frames import femur_frame, patella_frame, tibia_frame
from knee.fitting.landmarks import femur_landmarks, patella_landmarks, tibia_landmarks
from knee.fitting.regions import articular_regions
from knee.foundations.errors import KneeInputError
from knee.foundations.imaging import read_body_transforms, write_markups, write_surface
from knee.foundations.surfaces import SurfaceQuery, clip_to_slab, closed_surface

#: The Visible Human files, relative to the data folder.
VISIBLE_HUMAN = ("visible-human-male/VH_M_Knee_R.glb", "visible-human-male/VH_M_Skin.glb")


@dataclass
class RealKnee:
    """A real knee's surfaces (mm, the source's frame), landmarks and frames (``T_source_bone`` (4, 4))
    and the source's own annotations (named point sets, mm)."""

    name: str
    femur: trimesh.Trimesh
    tibia: trimesh.Trimesh
    patella: trimesh.Trimesh | None
    skin: trimesh.Trimesh | None
    landmarks: dict
    frames: dict
    annotations: dict = field(default_factory=dict)


def _scene(path: Path) -> dict:
    if not path.is_file():
        raise KneeInputError(f"{path}: not found")
    loaded = trimesh.load(str(path))
    geoms = loaded.geometry if isinstance(loaded, trimesh.Scene) else {path.stem: loaded}
    out = {}
    for name, g in geoms.items():
        m = g.copy()
        m.apply_scale(1000.0)  # metres to mm
        out[name] = m
    return out


def visible_human_knee(data_folder) -> RealKnee:
    """The Visible Human Male's right knee (see the module docstring) from ``data_folder`` (the folder
    holding ``visible-human-male/``). The distal femur comes split into named patches (articular
    cartilage, fossa, entheses, condyle regions); they are joined back onto the femur on their shared
    vertices and the seams' small holes closed. The patches whose names say ``enthesis`` are returned as
    annotations (their vertices)."""
    folder = Path(data_folder)
    knee = _scene(folder / VISIBLE_HUMAN[0])
    skin_scene = _scene(folder / VISIBLE_HUMAN[1])
    bones = {"tibia": "VH_M_tibia_R", "fibula": "VH_M_fibula_R", "patella": "VH_M_patella_R"}
    missing = [n for n in [*bones.values(), "VH_M_femur_R"] if n not in knee]
    if missing:
        raise KneeInputError(f"{folder / VISIBLE_HUMAN[0]}: missing {', '.join(missing)}")
    femur_parts = [m for n, m in knee.items() if n not in bones.values() and "meniscus" not in n]
    femur = trimesh.util.concatenate(femur_parts)
    femur.merge_vertices(digits_vertex=2)  # the patches share vertices with the femur (to 0.01 mm)
    femur = closed_surface(femur, "Visible Human femur")
    tibia, fibula, patella = (knee[bones[k]] for k in ("tibia", "fibula", "patella"))
    skin = next(iter(skin_scene.values()))
    up, anterior = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    lm = {"femur": femur_landmarks(femur.vertices, up, anterior),
          "tibia": tibia_landmarks(tibia.vertices, up, anterior, fibula.vertices),
          "patella": patella_landmarks(patella.vertices, up, anterior)}
    frames = {"femur": femur_frame(lm["femur"]), "tibia": tibia_frame(lm["tibia"]),
              "patella": patella_frame(lm["patella"])}
    notes = {n.removeprefix("VH_M_").removesuffix("_R"): np.asarray(m.vertices) for n, m in knee.items()
             if "enthesis" in n}
    notes["fibula"] = np.asarray(fibula.vertices)
    return RealKnee("visible-human-male", femur, tibia, patella, skin, lm, frames, notes)


#: The lenhart2015 files, relative to the data folder.
LENHART = {"geometry": "lenhart2015/geometry", "osim": "lenhart2015/lenhart2015.osim",
           "motion": "lenhart2015/dynamic_mri/passive_body_transformations.sto"}
#: The OpenSim bodies of the bones, and the ligament bundles that stand for the mechanism's fibres
#: (label: the bundle's name without its number).
LENHART_BODIES = {"femur": "femur_distal_r", "tibia": "tibia_proximal_r", "patella": "patella_r"}
LENHART_BUNDLES = {"acl": ("ACLam", "ACLpl"), "pcl": ("PCLal", "PCLpm"), "mcl": ("MCLs",), "tendon": ("PT",)}


def _osim(path: Path):
    """From an OpenSim model: {ligament: [(parent body, location mm)]} of the path points, and every
    PhysicalOffsetFrame's (parent body, translation mm) by name."""
    if not path.is_file():
        raise KneeInputError(f"{path}: not found")
    root = ET.parse(path).getroot()
    ligaments = {}
    for lig in root.iter("Blankevoort1991Ligament"):
        pts = []
        for pp in lig.iter("PathPoint"):
            frame = (pp.findtext("socket_parent_frame") or "").split("/")[-1]
            loc = np.array([float(v) for v in (pp.findtext("location") or "").split()]) * 1000.0
            pts.append((frame, loc))
        ligaments[lig.get("name")] = pts
    offsets = {}
    for fr in root.iter("PhysicalOffsetFrame"):
        parent = (fr.findtext("socket_parent") or "").split("/")[-1]
        offsets[fr.get("name")] = (parent, np.array([float(v) for v in fr.findtext("translation").split()]) * 1000.0)
    return ligaments, offsets


def lenhart_subject(data_folder, out_dir, ct_row: int = 0, mri_row: int = -1) -> Path:
    """Write the lenhart2015 knee as a subject folder in ``out_dir`` (new or empty) and return it.

    - CT: the bone surfaces posed at row ``ct_row`` of the dynamic-MRI table (its scanner frame, mm);
      MRI: bone and cartilage at row ``mri_row`` (another pose, as a separate scan would be).
    - Landmarks found on the surfaces (:mod:`knee.fitting.landmarks`, the bodies' frames giving up and
      anterior); the hip centre and the ankle centre (the malleoli placed 35 mm either side of it along
      the body's lateral axis) from the OpenSim model's joints: these bones stop 90-100 mm from the joint.
    - Attachment areas: the model's ligament path points on each bone (ACL bundles am/pl, PCL al/pm, the
      superficial MCL, the patellar tendon); articular regions computed from the cartilage surfaces
      (:func:`knee.fitting.regions.articular_regions`).
    - The motion: the table itself, named in ``subject.toml``'s ``[motion]`` with ``reference_row =
      ct_row``."""
    folder = Path(data_folder)
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise KneeInputError(f"{out} exists and is not empty; not overwritten")
    table = read_body_transforms(folder / LENHART["motion"])
    n = len(table.time)
    ct_row, mri_row = ct_row % n, mri_row % n
    ligaments, offsets = _osim(folder / LENHART["osim"])
    geo = folder / LENHART["geometry"]
    mesh = {}
    for b in LENHART_BODIES:
        for part in ("bone", "cartilage"):
            f = geo / f"lenhart2015-R-{b}-{part}.stl"
            if not f.is_file():
                raise KneeInputError(f"{f}: not found")
            mesh[b, part] = trimesh.load(f, force="mesh").apply_scale(1000.0)
    up, anterior = np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    lm = {"femur": femur_landmarks(mesh["femur", "bone"].vertices, up, anterior),
          "tibia": tibia_landmarks(mesh["tibia", "bone"].vertices, up, anterior),
          "patella": patella_landmarks(mesh["patella", "bone"].vertices, up, anterior)}
    # the hip centre: femur_r's origin; femur_distal_r sits at femur_r_offset in femur_r (a weld)
    lm["femur"]["HIP"] = -offsets["femur_r_offset"][1]
    # the ankle centre: tibia_r_offset in tibia_r; tibia_r sits at tibia_proximal_r_offset in tibia_proximal_r
    ankle = offsets["tibia_proximal_r_offset"][1] + offsets["tibia_r_offset"][1]
    lm["tibia"]["LM"], lm["tibia"]["MM"] = ankle + [0.0, 0.0, 35.0], ankle - [0.0, 0.0, 35.0]
    F = {"femur": femur_frame(lm["femur"]), "tibia": tibia_frame(lm["tibia"])}
    width = float(np.linalg.norm(lm["femur"]["LE"] - lm["femur"]["ME"]))
    regions = articular_regions(mesh["femur", "cartilage"].vertices, mesh["tibia", "cartilage"].vertices,
                                F["femur"], F["tibia"], width)

    def pose(bone, row):
        return table.poses[LENHART_BODIES[bone]][row]

    def moved(bone, row, pts):
        T = pose(bone, row)
        return np.asarray(pts, float) @ T[:3, :3].T + T[:3, 3]

    with tempfile.TemporaryDirectory(prefix="lenhart-", dir=out.parent if out.parent.exists() else None) as t:
        tmp = Path(t) / "subject"
        for d in ("ct/areas", "mri/areas"):
            (tmp / d).mkdir(parents=True)
        for b in LENHART_BODIES:
            write_surface(tmp / "ct" / f"{b}.stl", mesh[b, "bone"].copy().apply_transform(pose(b, ct_row)))
            both = trimesh.util.concatenate([mesh[b, "bone"], mesh[b, "cartilage"]])
            write_surface(tmp / "mri" / f"{b}.stl", both.apply_transform(pose(b, mri_row)))
        labels, ct_pts, mri_labels, mri_pts = [], [], [], []
        for b, d in lm.items():
            for k, p in d.items():
                labels.append(k)
                ct_pts.append(moved(b, ct_row, p[None])[0])
                if k not in ("HIP", "LM", "MM"):
                    mri_labels.append(k)
                    mri_pts.append(moved(b, mri_row, p[None])[0])
        write_markups(tmp / "ct/landmarks.mrk.json", labels, ct_pts)
        write_markups(tmp / "mri/landmarks.mrk.json", mri_labels, mri_pts)
        for name, pts in regions.items():
            bone = name.split("_")[0]
            space = "ct" if name == "femur_intercondylar" else "mri"
            row = ct_row if space == "ct" else mri_row
            write_markups(tmp / space / "areas" / f"{name}.mrk.json", [name] * len(pts), moved(bone, row, pts))
        for lig, bundles in LENHART_BUNDLES.items():
            ends = {"femur": [], "tibia": [], "patella": []}
            for bundle_name, pts in ligaments.items():
                label = next((bn for bn in bundles if bundle_name.startswith(bn) and bundle_name[len(bn):].isdigit()),
                             None)
                if label is None:
                    continue
                for body, loc in pts:
                    bone = next((k for k, v in LENHART_BODIES.items() if v == body), None)
                    if bone is not None:
                        ends[bone].append((label[len(lig):].lower() or label.lower(), loc))
            sides = ("patella", "tibia") if lig == "tendon" else ("femur", "tibia")
            for bone in sides:
                if not ends[bone]:
                    raise KneeInputError(f"{folder / LENHART['osim']}: no {lig} path points on the {bone}")
                lab = [lb for lb, _ in ends[bone]]
                pts = moved(bone, mri_row, np.array([p for _, p in ends[bone]]))
                write_markups(tmp / "mri/areas" / f"{lig}_{bone}.mrk.json", lab, pts)
        shutil.copyfile(folder / LENHART["motion"], tmp / "passive.sto")
        (tmp / "subject.toml").write_text(
            "# The lenhart2015 knee (Lenhart et al. 2015, Ann Biomed Eng 43:2675; Apache-2.0), written by\n"
            "# knee.fitting.reference_data.lenhart_subject from its public files.\n"
            'format = "knee-subject"\nversion = 1\nname = "lenhart2015"\nside = "right"\n\n'
            f'[motion]\nfile = "passive.sto"\nfemur = "{LENHART_BODIES["femur"]}"\n'
            f'tibia = "{LENHART_BODIES["tibia"]}"\npatella = "{LENHART_BODIES["patella"]}"\n'
            f'length_unit = "m"\nreference_row = {ct_row}\n', encoding="utf-8")
        out.parent.mkdir(parents=True, exist_ok=True)
        if out.exists():
            out.rmdir()
        shutil.move(str(tmp), str(out))
    return out


def visible_human_subject(data_folder, out_dir, band_widths: float = 3.0) -> Path:
    """Write the Visible Human Male's right knee (:func:`visible_human_knee`) as a subject folder for the
    association FEM (no MRI, no motion: a subject's CT alone) in ``out_dir`` (new or empty); returns it.

    ``ct/``: femur, tibia, patella and the skin (the whole body's skin clipped to ``band_widths`` femur
    widths either side of the joint line and closed: the leg around the knee) in the scan's frame, mm; the
    landmarks found on the bones (the hip centre and the malleoli where the bones reach them)."""
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise KneeInputError(f"{out} exists and is not empty; not overwritten")
    vh = visible_human_knee(data_folder)
    lm = vh.landmarks
    width = float(np.linalg.norm(lm["femur"]["LE"] - lm["femur"]["ME"]))
    up = vh.frames["femur"][:3, 1]
    y0 = 0.5 * (0.5 * (lm["femur"]["LE"] + lm["femur"]["ME"]) + 0.5 * (lm["tibia"]["LIT"] + lm["tibia"]["MIT"]))
    skin = clip_to_slab(vh.skin, y0, up, band_widths * width, band_widths * width)
    pieces = skin.split(only_watertight=True)
    if len(pieces) > 1:  # two legs: the piece around this knee
        knee = np.vstack([lm["femur"]["LE"], lm["femur"]["ME"], lm["tibia"]["LIT"], lm["tibia"]["MIT"]])
        skin = max(pieces, key=lambda p: int(SurfaceQuery.of(p).inside(knee).sum()))
    with tempfile.TemporaryDirectory(prefix="vhm-", dir=out.parent if out.parent.exists() else None) as t:
        tmp = Path(t) / "subject"
        (tmp / "ct").mkdir(parents=True)
        for name, m in (("femur", vh.femur), ("tibia", vh.tibia), ("patella", vh.patella), ("skin", skin)):
            # as a reader merges them: the femur, joined from patches, has vertices close enough to merge
            # into non-manifold edges; closed again after the merge
            m = trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.faces), process=True)
            _, inv, cnt = np.unique(np.sort(m.faces, axis=1), axis=0, return_inverse=True, return_counts=True)
            m.update_faces(cnt[inv.ravel()] == 1)  # back-to-back pairs of triangles: both dropped, holes closed
            m = closed_surface(m, name)
            write_surface(tmp / "ct" / f"{name}.ply", m)
        labels, pts = [], []
        for bone in ("femur", "tibia", "patella"):
            for k, p in lm[bone].items():
                if p is not None:
                    labels.append(k)
                    pts.append(p)
        write_markups(tmp / "ct/landmarks.mrk.json", labels, pts)
        (tmp / "subject.toml").write_text(
            "# The Visible Human Male's right knee (U.S. National Library of Medicine; see ../shared/data's\n"
            "# README), written by knee.fitting.reference_data.visible_human_subject from its public files.\n"
            'format = "knee-subject"\nversion = 1\nname = "visible-human-male"\nside = "right"\n', encoding="utf-8")
        out.parent.mkdir(parents=True, exist_ok=True)
        if out.exists():
            out.rmdir()
        shutil.move(str(tmp), str(out))
    return out
