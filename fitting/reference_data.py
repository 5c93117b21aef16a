"""Readers for the public, real knee data the toolkit is developed and tested on (README, "Real data").

- :func:`visible_human_knee`: the HuBMAP 3D reference objects made from the NLM Visible Human Male
  (``VH_M_Knee_R.glb``, ``VH_M_Skin.glb``; CC BY 4.0): a right leg's femur, tibia, fibula and patella
  and the whole-body skin, in one frame (metres; x the subject's left, y superior, z anterior).

Each returns the surfaces in mm in the source's frame, the bones' anatomical frames from landmarks found
on the surfaces (:mod:`knee.fitting.landmarks`; the source's own annotations, such as entheses, are
returned beside them, not used for them), so that what is computed from them can be checked against the
annotations.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from knee.fitting.frames import femur_frame, patella_frame, tibia_frame
from knee.fitting.landmarks import femur_landmarks, patella_landmarks, tibia_landmarks
from knee.foundations.errors import KneeInputError
from knee.foundations.surfaces import closed_surface

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
