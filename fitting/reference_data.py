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
from knee.foundations.conventions import invert_poses, transform_points
from knee.foundations.errors import KneeInputError
from knee.foundations.imaging import read_body_transforms, write_markups, write_surface
from knee.foundations.surfaces import SurfaceQuery, clip_to_slab, closed_surface
from knee.models.fem.anatomy import joint_line

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


def lenhart_subject(data_folder, out_dir, ct_row: int | str = 0, mri_row: int = -1,
                    skin_from: RealKnee | None = None) -> Path:
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
      ct_row``; ``ct_row="least-flexion"``: the row of its least flexion (10 deg; the table starts at 27).
    - ``skin_from``: a knee with a skin (the Visible Human's, :func:`visible_human_knee`) whose skin is
      carried onto these bones (:func:`transplanted_skin`) as ``ct/skin.stl``, cut across the femur's
      axis ``SKIN_INSIDE_BONES_MM`` inside the bones' cut ends (as a scan's field of view cuts the leg and
      its bones alike), so that the association FEM can be built on a second real knee. The knee was scanned
      by MRI without its skin: this one is the other leg's tissue scaled to this knee's width, a
      plausible leg, not its own."""
    folder = Path(data_folder)
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise KneeInputError(f"{out} exists and is not empty; not overwritten")
    table = read_body_transforms(folder / LENHART["motion"])
    n = len(table.time)
    mri_row = mri_row % n
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
    if ct_row == "least-flexion":
        ct_row = _least_flexion_row(table, F)
    elif isinstance(ct_row, (int, np.integer)) and not isinstance(ct_row, bool):
        ct_row = int(ct_row) % n
    else:
        raise KneeInputError(f"ct_row must be a row of the motion table (an integer) or 'least-flexion', got {ct_row!r}")
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
        if skin_from is not None:
            ct = {b: mesh[b, "bone"].copy().apply_transform(pose(b, ct_row)) for b in LENHART_BODIES}
            T = {b: pose(b, ct_row) @ F[b] for b in ("femur", "tibia")}
            to_f = invert_poses(T["femur"])
            y0 = joint_line(transform_points(to_f, ct["femur"].vertices), transform_points(to_f, ct["tibia"].vertices))
            below = y0 - float(transform_points(to_f, ct["tibia"].vertices)[:, 1].min())
            above = float(transform_points(to_f, ct["femur"].vertices)[:, 1].max()) - y0
            # made longer than the bones, then cut a little inside their ends
            skin = transplanted_skin(skin_from, ct["femur"], ct["tibia"], T["femur"], T["tibia"], width,
                                     below + SKIN_MADE_PAST_MM, above + SKIN_MADE_PAST_MM, bones=list(ct.values()))
            # cut where the bones are cut, as a scan's field of view cuts both (across the femur's axis)
            up, o = T["femur"][:3, 1], transform_points(T["femur"], np.array([[0.0, y0, 0.0]]))[0]
            skin = clip_to_slab(skin, o, up, below - SKIN_INSIDE_BONES_MM, above - SKIN_INSIDE_BONES_MM)
            write_surface(tmp / "ct" / "skin.stl", skin)
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


def _least_flexion_row(table, frames) -> int:
    """The row of the dynamic-MRI table where the knee is least flexed: the smallest angle between the femur's
    and the tibia's long axes (``frames``: their anatomical frames in the bodies' own)."""
    yf = (table.poses[LENHART_BODIES["femur"]] @ frames["femur"])[:, :3, 1]
    yt = (table.poses[LENHART_BODIES["tibia"]] @ frames["tibia"])[:, :3, 1]
    return int(np.argmax(np.einsum("ij,ij->i", yf, yt)))


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


#: A transplanted skin (:func:`transplanted_skin`): its rings' spacing along the leg (mm) and points per ring,
#: the least soft tissue (mm) it leaves over a bone, and the half height of the band (femur widths) where
#: it passes from the femur's frame to the tibia's.
SKIN_RING_MM, SKIN_RING_POINTS, SKIN_LEAST_TISSUE_MM, SKIN_BLEND_WIDTHS = 3.0, 120, 3.0, 0.25
#: How far (mm) inside its bones' cut ends lenhart2015's transplanted skin is cut (:func:`lenhart_subject`).
SKIN_INSIDE_BONES_MM = 3.0
#: ... after being made this much (mm) longer than the bones at either end (past the bones' ends the rings
#: would meet no bone, so the cut, not the rings' end, closes the leg).
SKIN_MADE_PAST_MM = 30.0


def _radii(query: SurfaceQuery, heights, angles) -> np.ndarray:
    """How far (heights x angles) a skin lies from the frame's y axis: rays cast from the axis at each height
    out along (cos a, 0, sin a); ``inf`` where a ray meets nothing."""
    H, A = np.meshgrid(heights, angles, indexing="ij")
    zero = np.zeros_like(H)
    origins, directions = np.stack([zero, H, zero], -1), np.stack([np.cos(A), zero, np.sin(A)], -1)
    return query.ray_hits(origins.reshape(-1, 3), directions.reshape(-1, 3)).reshape(H.shape)


def transplanted_skin(source: RealKnee, femur, tibia, T_femur, T_tibia, width: float, below_mm: float,
                      above_mm: float, bones=()) -> trimesh.Trimesh:
    """A skin for a knee scanned without one: ``source``'s skin (a :class:`RealKnee` with its skin) carried
    onto another knee's bones, scaled by the ratio of the two knees' femoral widths.

    ``femur``, ``tibia``: the knee's bone surfaces and ``T_femur``, ``T_tibia`` their anatomical frames (4, 4;
    scan <- bone), all in the scan's frame (mm); ``width``: its femoral width (mm); the skin runs from
    ``below_mm`` below to ``above_mm`` above its joint line (closed flat at both ends); ``bones``: every bone
    surface (scan frame) it must enclose. Returns the skin in the scan's frame.

    The source's skin is read as rings about each bone's long axis: its distance from the axis at each
    height (relative to the joint line, in femur widths) and direction, from the femur's frame above the
    joint line and from the tibia's below; the new skin takes those distances times the width ratio about
    its own bones' axes, the two passing into each other over a band of ``SKIN_BLEND_WIDTHS`` femur widths
    either side of the joint line (so a knee scanned a little more flexed than the source keeps the shank's
    skin around its shank); then it is pushed out wherever it leaves less than ``SKIN_LEAST_TISSUE_MM`` of
    tissue over a bone. What it stands for: a plausible leg of that knee's size, not that subject's own skin
    (the soft tissue's thickness is the source's, scaled)."""
    if source.skin is None:
        raise KneeInputError(f"{source.name} has no skin to carry over")
    Fs, Ts = source.frames["femur"], source.frames["tibia"]
    src_to_f = invert_poses(Fs)
    sy0 = joint_line(transform_points(src_to_f, source.femur.vertices), transform_points(src_to_f, source.tibia.vertices))
    lm = source.landmarks["femur"]
    scale = width / float(np.linalg.norm(lm["LE"] - lm["ME"]))
    to_f = invert_poses(np.asarray(T_femur, float))
    y0 = joint_line(transform_points(to_f, np.asarray(femur.vertices)), transform_points(to_f, np.asarray(tibia.vertices)))
    heights = np.linspace(-below_mm, above_mm, int(np.ceil((below_mm + above_mm) / SKIN_RING_MM)) + 1)
    angles = np.linspace(0.0, 2 * np.pi, SKIN_RING_POINTS, endpoint=False)
    H, A = np.meshgrid(heights, angles, indexing="ij")
    rings = []
    for src_T, T in ((Fs, np.asarray(T_femur, float)), (Ts, np.asarray(T_tibia, float))):
        # the joint line's height in this bone's frame, for the source and for the knee
        s_off = transform_points(invert_poses(src_T) @ Fs, np.array([[0.0, sy0, 0.0]]))[0, 1]
        t_off = transform_points(invert_poses(T) @ np.asarray(T_femur, float), np.array([[0.0, y0, 0.0]]))[0, 1]
        skin_local = source.skin.copy().apply_transform(invert_poses(src_T))
        r = scale * _radii(SurfaceQuery.of(skin_local), s_off + heights / scale, angles)
        if not np.all(np.isfinite(r)):
            raise KneeInputError(f"{source.name}'s skin does not surround its bones' axes from {below_mm:.0f} mm "
                                 f"below to {above_mm:.0f} mm above the joint line (scaled)")
        local = np.stack([r * np.cos(A), t_off + H, r * np.sin(A)], -1)
        rings.append(transform_points(T, local.reshape(-1, 3)).reshape(local.shape))
    t = np.clip((SKIN_BLEND_WIDTHS * width - H) / (2 * SKIN_BLEND_WIDTHS * width), 0.0, 1.0)[..., None]
    w = t * t * (3 - 2 * t)  # the tibia's share: 0 above the band, 1 below it
    ring = (1.0 - w) * rings[0] + w * rings[1]
    n_h, n_a = H.shape
    idx = np.arange(n_h * n_a).reshape(n_h, n_a)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1], nxt[:-1], idx[1:], nxt[1:]
    faces = [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)]
    ends = np.stack([ring[0].mean(axis=0), ring[-1].mean(axis=0)])
    k = n_h * n_a
    faces += [np.stack([np.full(n_a, k), idx[0], nxt[0]], -1), np.stack([np.full(n_a, k + 1), nxt[-1], idx[-1]], -1)]
    skin = trimesh.Trimesh(np.vstack([ring.reshape(-1, 3), ends]), np.concatenate(faces), process=False)
    if skin.volume < 0:
        skin.invert()
    side = [SurfaceQuery.of(m) for m in bones]
    for _ in range(3):  # out along the skin's normals where it lies too close to a bone (or inside one)
        v = np.asarray(skin.vertices, float)
        gap = np.min([q.signed_distance(v) for q in side], axis=0) if side else np.full(len(v), np.inf)
        push = np.clip(SKIN_LEAST_TISSUE_MM - gap, 0.0, None)
        push[k:] = 0.0  # the end caps stay flat
        if not np.any(push > 1e-3):
            break
        skin = trimesh.Trimesh(v + push[:, None] * skin.vertex_normals, skin.faces, process=False)
    return skin
