"""The benchmark's case set (issue "an honest benchmark of the FEM methods"): built deterministically from a
seed into a folder, run by ``knee compare CASE_SET``.

What makes the cases honest:

- anatomy: subject folders read as any subject's are, the phantom (the bundled ``volunteer``'s synthetic
  subject) and, where ``../shared/data`` is present, the Visible Human Male's real knee (and, asked for,
  lenhart2015's MRI bones with the Visible Human's skin carried onto them,
  :func:`knee.fitting.reference_data.transplanted_skin`);
- the truth's bone motion is not the prior's: the truth mechanism's motion (the phantom's own parameter
  set; for the Visible Human, a template scaled to the knee) plus a random deviation of the tibia, 1-3 mm
  and 2-5 deg ("mechanism+deviation"), and a measured motion, lenhart2015's dynamic MRI transferred as
  joint coordinates ("measured"; :func:`transferred`: its flexion, and the change of the other five from
  the start of its arc; :func:`measured_poses`: the tibia then slid along its axis to the scan's clearance
  plus the measured knee's own change of clearance); the prior is the truth mechanism with every TF link endpoint moved
  1-2 mm;
- the truth's flexed skin comes from another model of the tissue (:mod:`knee.models.fem.tissue`:
  conforming hyperelastic tetrahedra, not the association model's embedding grid), plus a smooth random
  normal displacement of 0, 1 or 2 mm RMS (correlation length a quarter of the femoral width) standing
  for what no model captures; with ``patella=True`` that tissue also holds the subject's patella, moved by
  the truth mechanism's PF motion (:func:`truth_patella`), which the association model does not model;
- the depth image is rendered in the camera's own frame (RealSense-like noise, 1 mm at 400 mm, 2 %
  dropout; with ``correlation_px`` and ``hole_px``, the error correlated and the lost pixels in blobs, as a
  stereo camera's matching windows make them; with ``flying``, blends of the surfaces at each depth edge, a
  depth camera's flying pixels; read as ``knee fem`` reads a measured image, its flying pixels left out), from the paper's placement (350 mm,
  oblique: 35 deg toward lateral, raised 30 deg) and two others; the methods get the image, the intrinsics and a rough pose of the knee in the camera's frame,
  the truth turned 15-30 deg about the joint centre and moved 25-50 mm.

Folder::

    CASE_SET/case-set.toml     format, seed, the anatomies and the cases (truth poses: CT to camera)
    CASE_SET/subjects/NAME/    the subject folders
    CASE_SET/priors/NAME.toml  each subject's prior
    CASE_SET/cases/ID/depth.npy, initial_pose.txt
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
import time
import tomllib
import zlib
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np
from scipy.optimize import brentq

from knee.app.experiments.cases import CompareRow, reconstruction_row
from knee.app.experiments.subject_cases import camera_stage_errors, camera_target_errors, random_pose
from knee.fitting.optimize import perturb_endpoints
from knee.fitting.pipeline import anatomical_frames
from knee.fitting.reference_data import lenhart_subject, visible_human_knee, visible_human_subject
from knee.fitting.subject import load_subject
from knee.fitting.subject_anatomy import subject_anatomy
from knee.fitting.synthetic import make_subject
from knee.foundations.conventions import invert_poses, joint_to_pose, pose_to_joint, read_pose_file, transform_points
from knee.foundations.errors import KneeError, KneeInputError
from knee.foundations.files import read_text
from knee.foundations.pointclouds import backproject, read_depth_image, voxel_downsample
from knee.foundations.surfaces import SurfaceQuery
from knee.models.fem.anatomy import bone_clearance, bone_queries, in_contact
from knee.models.fem.depth import Camera, DepthNoise, default_camera, render_depth
from knee.models.fem.methods import reconstruct_in_camera
from knee.models.fem.scene import FemSettings, build_knee_model, phantom_anatomy
from knee.models.fem.tissue import EDGE_WIDTHS, TetTissue, smooth_surface_field
from knee.models.mechanism import Mechanism
from knee.models.phantom import build_phantom
from knee.models.mechanism.params import (
    LINK_FEMUR,
    LINK_LENGTH,
    LINK_TIBIA,
    N_LINKS,
    link_entries,
    load_model,
    toml_string,
)
from knee.models.prior import VOXEL_MM

FORMAT = "knee-case-set"
#: Version 2: the intrinsics put pixel centres at whole coordinates (OpenCV's and librealsense's convention);
#: a version 1 set's are the ray caster's, whose principal point lies half a pixel further, and are read so.
VERSION = 2
#: Camera placements: azimuth toward lateral, elevation toward proximal (deg), distance (mm); "paper" is
#: seed 000's (about 35 cm, oblique).
PLACEMENTS = {"paper": (35.0, 30.0, 350.0), "frontal": (0.0, 15.0, 400.0), "lateral": (70.0, 35.0, 300.0)}
MISMATCHES_MM = (0.0, 1.0, 2.0)
#: The anatomies a case set can hold and its families of truth motion (:func:`build_case_set`).
ANATOMIES = ("phantom", "visible-human-male", "lenhart2015")
FAMILIES = ("mechanism+deviation", "measured")
#: The rough pose given to the methods: the truth turned by 15-30 deg and moved by 25-50 mm.
ROUGH_DEG, ROUGH_MM = (15.0, 30.0), (25.0, 50.0)
#: The truth's deviation from its mechanism's motion: 2-5 deg, 1-3 mm.
DEVIATION_DEG, DEVIATION_MM = (2.0, 5.0), (1.0, 3.0)
MECHANISM_FLEXIONS = (30.0, 60.0, 90.0)
MEASURED_FLEXIONS = (20.0, 30.0, 45.0)
#: How far (femur widths) either side of the joint line the Visible Human's skin and bones are kept by
#: default (:func:`knee.fitting.reference_data.visible_human_subject`; the model then keeps 2.5).
VH_SKIN_BAND_WIDTHS = 3.0
#: The skin mismatch field's correlation length, in femoral widths.
FIELD_WIDTHS = 0.25
#: The truth tissue's node spacing, in femur widths (:data:`knee.models.fem.tissue.EDGE_WIDTHS`, the case sets'
#: default). Measured on seed 0's 0 mm paper views (the femur's tissue floor, noise-free points, BENCHMARKS.md "Is
#: the truth's tissue converged?"): refined to 0.07 and 0.05, the Visible Human's and lenhart2015's floors move by
#: 0.15 mm at most, the phantom's by 0.1-2.8 mm a view (most at 90 deg, where its tissue folds behind the knee).
TRUTH_EDGE_WIDTHS = EDGE_WIDTHS


def template_prior(anatomy, template_name: str = "volunteer", with_pf: bool = False):
    """A bundled parameter set scaled to ``anatomy``'s femoral width (link endpoints and lengths), TF only
    (``with_pf``: its PF joint scaled too, points and lengths, the axes' directions kept); returns it and
    the scale."""
    p = load_model(template_name)
    ref, _ = phantom_anatomy(Mechanism(p))
    s = anatomy.width / ref.width
    v = p.to_vector().copy()
    for i in range(N_LINKS):
        for part in (LINK_FEMUR, LINK_TIBIA, LINK_LENGTH):
            v[link_entries(i, part)] *= s
    q = p.with_vector(v)
    init = dataclasses.replace(p.initial, unknowns=p.initial.unknowns * np.r_[1.0, 1.0, s, s, s])
    links = tuple(dataclasses.replace(lk, femur_radius=None if lk.femur_radius is None else lk.femur_radius * s)
                  for lk in q.links)
    pf = None
    if with_pf and p.pf is not None:
        f = p.pf
        pf = dataclasses.replace(f, point_femur=s * f.point_femur, point_patella=s * f.point_patella,
                                 tendon_tibia=s * f.tendon_tibia, tendon_patella=s * f.tendon_patella,
                                 tendon_length=s * f.tendon_length, lambda0=s * f.lambda0, lambda1=s * f.lambda1)
    return dataclasses.replace(q, pf=pf, initial=init, name=f"{template_name}-scaled-{s:.3f}", links=links), s


def measured_motion(data_folder, flexions_deg, subject=None) -> np.ndarray:
    """lenhart2015's measured TF joint coordinates (n, 6; rad, mm) at ``flexions_deg``, from its trial's
    half that covers more flexion (linear interpolation), and the coordinates at that half's start.
    ``subject``: lenhart2015's subject, when already loaded."""
    if subject is None:
        subject = _lenhart(data_folder)
    measured = subject.motion.tf
    k = int(np.argmax(measured[:, 0]))
    up = max((measured[: k + 1], measured[k:]), key=lambda h: np.ptp(h[:, 0]))
    order = np.argsort(up[:, 0])
    a = np.radians(np.asarray(flexions_deg, float))
    q = np.column_stack([np.interp(a, up[order, 0], up[order, j]) for j in range(6)])
    return q, up[order[0]]


def _lenhart(data_folder):
    with tempfile.TemporaryDirectory() as tmp:
        return load_subject(lenhart_subject(data_folder, Path(tmp) / "lenhart2015"))


def measured_clearance_change(subject, q, start) -> np.ndarray:
    """How much farther apart (mm, n; negative: closer) lenhart2015's own femur and tibia are at the joint
    coordinates ``q`` (n, 6) of its measured motion than at ``start`` (6,): the least signed distance between
    its CT bones (:func:`knee.models.fem.anatomy.bone_clearance`) posed by its own frames."""
    frames = anatomical_frames(subject)
    to_femur = invert_poses(frames["femur"])  # CT -> the femur frame
    knee = SimpleNamespace(femur=subject.ct["femur"].copy().apply_transform(to_femur),
                           tibia=subject.ct["tibia"].copy().apply_transform(to_femur),
                           tibia_pose=to_femur @ frames["tibia"])
    queries = bone_queries(knee)
    c = [bone_clearance(knee, T, queries) for T in joint_to_pose(np.vstack([np.asarray(start, float)[None], q]))]
    return np.asarray(c[1:]) - c[0]


def transferred(q, start, scan_tf) -> np.ndarray:
    """Joint coordinates ``q`` (n, 6) of one knee carried to another scanned at ``scan_tf``: flexion as
    measured; the other five (adduction, axial rotation, the three translations) as the other knee's at its
    scan plus their change from ``start``. Two knees' anatomical frames are built from different landmarks,
    so their origins and their neutral adduction and axial rotation differ (the bundled volunteer's frames
    put its tibia 25 deg from the measured knee's at extension); what carries over is how each coordinate
    changes with flexion. Carrying the rotations as measured twisted the phantom's tibia 25-30 deg from its
    own scanned neutral, which no knee does at 20-45 deg of flexion."""
    q = np.array(q, float)
    q[:, 1:] = np.asarray(scan_tf)[1:] + (q[:, 1:] - np.asarray(start)[1:])
    return q


def measured_poses(data, anatomy, flexions_deg) -> np.ndarray:
    """The tibia's poses (n, 4, 4; femur frame) of ``anatomy`` under lenhart2015's measured motion at
    ``flexions_deg``: the joint coordinates carried over (:func:`transferred`), then the tibia slid along its
    own axis until the bones' clearance is the scan's plus the measured knee's own change of clearance from
    the start of its arc (:func:`measured_clearance_change`; :func:`in_contact`). Carried over as they are,
    the measured knee's translations drove the Visible Human's tibia 4, 7 and 11 mm into its femur at 20, 30
    and 45 deg (the two knees' frames put their origins differently about the condyles), a pose no knee
    takes. The measured knee's change of clearance (within about 0.6 mm over its arc) is kept rather than
    the scan's clearance itself: the method (iii) slides overlapping bones back to the scan's clearance
    (:func:`knee.models.fem.methods.keep_bones_apart`), and a truth made by that same rule would favour it."""
    subject = _lenhart(data)
    q, start = measured_motion(data, flexions_deg, subject)
    change = measured_clearance_change(subject, q, start)
    queries = bone_queries(anatomy)
    clearance = bone_clearance(anatomy, anatomy.tibia_pose, queries)
    return np.stack([in_contact(anatomy, T, clearance + dc, queries=queries)
                     for T, dc in zip(joint_to_pose(transferred(q, start, anatomy.scan_tf)), change)])


@dataclass
class Anatomy:
    name: str
    subject: Path
    prior: Path
    truth_mechanism: str
    notes: str = ""


def _write_prior(path: Path, params) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(params.to_toml(), encoding="utf-8")
    return path


#: How many of a set's prior draws :func:`_assembling_prior` tries before it gives up.
PRIOR_DRAWS = 50


def _assembling_prior(params, seed: int):
    """The truth's parameter set with every TF link endpoint moved 1-2 mm, the set's own draw: draws 0, 1, ...
    of :func:`knee.fitting.optimize.perturb_endpoints`, each from the set's stream for the draw's name
    (:func:`case_rng` of ``prior``, the parameter set's name and J, as each part of the set is drawn), until
    one assembles over 0-120 deg (as a fitted prior does, whose fit is refused otherwise). Returns the prior and
    the draw's index. Each seed and each anatomy draws from a stream of its own, so that the sets of different
    seeds hold different priors, and one set's anatomies priors moved in unrelated directions (before, seed s
    tried the draws s + 1, s + 2, ... of one stream shared by the anatomies, and seeds 0-4 all landed on draw
    5: one prior error shared by the five sets, BENCHMARKS.md)."""
    for j in range(PRIOR_DRAWS):
        draw = case_rng(seed, "prior", params.name, str(j))
        p = dataclasses.replace(perturb_endpoints(params, 1.0, 2.0, seed=draw), name=f"{params.name}-perturbed")
        try:
            m = Mechanism(p)
        except KneeError:
            continue
        lo, hi = m.assembly_range
        if lo <= 0.0 and hi >= math.radians(120.0):
            return p, j
    raise KneeError(f"no perturbed prior of {params.name} assembles over 0-120 deg in {PRIOR_DRAWS} draws of "
                    f"seed {seed}")


def _anatomies(out: Path, data, seed: int, names, patella: bool = False,
               skin_band: float = VH_SKIN_BAND_WIDTHS) -> list[tuple[Anatomy, Mechanism, object]]:
    """(entry, truth mechanism, prior params) of each anatomy, their subject folders and priors written
    (``patella``: the Visible Human's truth mechanism with the template's PF joint scaled too; its prior, TF
    only, is the same either way)."""
    res = []
    for name in names:
        if name == "phantom":
            folder = make_subject(out / "subjects" / name, model="volunteer", seed=seed)
            truth = Mechanism.from_name("volunteer")
            prior_of = truth.params
            note = "the bundled volunteer's synthetic subject; truth mechanism volunteer"
        elif name == "lenhart2015":  # a second real knee; its skin the Visible Human's, carried over
            folder = lenhart_subject(data, out / "subjects" / name, ct_row="least-flexion",
                                     skin_from=visible_human_knee(data))
            template, s = template_prior(subject_anatomy(load_subject(folder)), with_pf=patella)
            truth = Mechanism(template)
            prior_of = dataclasses.replace(template, pf=None)
            note = (f"lenhart2015's right knee (MRI bones at its least flexed row of the dynamic MRI), its skin the "
                    f"Visible Human's scaled to its width (it was scanned without one); truth mechanism volunteer "
                    f"scaled by {s:.3f} to its width")
        else:  # "visible-human-male" (the names are checked by build_case_set)
            folder = visible_human_subject(data, out / "subjects" / name, band_widths=skin_band)
            template, s = template_prior(subject_anatomy(load_subject(folder)), with_pf=patella)
            truth = Mechanism(template)
            prior_of = dataclasses.replace(template, pf=None)  # TF only, with the patella or without
            note = f"the Visible Human Male's right knee; truth mechanism volunteer scaled by {s:.3f} to its width"
            if skin_band != VH_SKIN_BAND_WIDTHS:
                note += f"; its skin and bones kept {skin_band:g} femur widths either side of the joint line"
        if patella:
            note += "; the truth's tissue holds the patella, moved by the truth mechanism's PF motion"
        prior, k = _assembling_prior(prior_of, seed)
        note += (f"; prior: every TF link endpoint moved 1-2 mm (draw {k} of seed {seed}, the first that assembles "
                 "over 0-120 deg)")
        path = _write_prior(out / "priors" / f"{name}.toml", prior)
        res.append((Anatomy(name, folder.relative_to(out), path.relative_to(out), truth.params.name, note), truth,
                    prior))
    return res


def case_rng(seed: int, *keys: str) -> np.random.Generator:
    """The random stream of one part of the case set (a pose's deviation, a skin's mismatch field, a view's
    noise and rough pose), seeded by the set's seed and that part's names: building a subset of the cases
    (one anatomy, one family, other flexions or mismatches) draws the same numbers for the cases it shares
    with the full set."""
    return np.random.default_rng([int(seed), zlib.crc32("/".join(keys).encode("utf-8"))])


def check_truth_edge(truth_edge) -> float:
    """The truth tissue's node spacing (femur widths) as a float, or a one-line error: from 0.03 (about 2.5 mm on
    an adult knee; finer takes hours a pose) to 0.2."""
    number = isinstance(truth_edge, (int, float, np.integer, np.floating)) and not isinstance(truth_edge, bool)
    if not (number and 0.03 <= truth_edge <= 0.2):  # also refuses NaN
        shown = f"{float(truth_edge):g}" if number else repr(truth_edge)
        raise KneeInputError(f"the truth tissue's node spacing must lie from 0.03 to 0.2 femur widths, got {shown}")
    return float(truth_edge)


def placement_camera(anatomy, placement: str) -> Camera:
    """The case set's camera at a placement of :data:`PLACEMENTS` (its name), aimed at the knee's centre, in the
    anatomy's femur (model) frame."""
    az, el, dist = PLACEMENTS[placement]
    return default_camera(distance=dist, azimuth_deg=az, elevation_deg=el, target=np.array([0.0, anatomy.joint_y, 0.0]))


def build_case_set(out, seed: int = 0, data=None, anatomies=("phantom", "visible-human-male"),
                   families=("mechanism+deviation", "measured"), progress: Callable[[str], None] | None = None,
                   mechanism_flexions=MECHANISM_FLEXIONS, measured_flexions=MEASURED_FLEXIONS,
                   mismatches=MISMATCHES_MM, patella: bool = False, flying: float = 0.0,
                   correlation_px: float = 0.0, hole_px: float = 0.0, sigma_mm: float = 1.0,
                   skin_band: float = VH_SKIN_BAND_WIDTHS, truth_edge: float = TRUTH_EDGE_WIDTHS) -> Path:
    """Build the case set into ``out`` (a new folder; see the module docstring). ``data``: the folder
    holding ``visible-human-male/`` and ``lenhart2015/``; without it, the phantom's mechanism cases only.
    Each pose is seen from the paper's placement at every skin mismatch, and from the other placements at
    1 mm (or at the middle mismatch given). Each pose, mismatch field and view draws from its own stream
    (:func:`case_rng`), so a case is the same whichever subset of the set is built. ``patella``: the truth's
    tissue holds the subject's patella as a third bone, moved by the truth mechanism's PF motion at each
    case's flexion (:func:`truth_patella`); without, the skin over the knee's front follows the femur and
    the tibia only, as the association model's does. ``flying``: the share of the pixels near each depth
    edge that return a blend of the surfaces on either side (a depth camera's flying pixels; the noise
    model's ``flying``, :class:`knee.models.fem.depth.DepthNoise`); the rest of each image as without.
    ``correlation_px``, ``hole_px``: the noise model's, the width (pixels) over which neighbouring pixels'
    errors are correlated and the size of the blobs the lost pixels come in (0: each pixel on its own);
    ``sigma_mm``: the depth error's standard deviation at 400 mm (growing with the square of the depth).
    ``skin_band``: how far (femur widths) either side of the joint line the Visible Human's skin and bones
    are kept (:data:`VH_SKIN_BAND_WIDTHS`; 1 stands for a short scan, whose field of view ends near the knee).
    ``truth_edge``: the truth tissue's node spacing in femur widths (:data:`TRUTH_EDGE_WIDTHS`, the tissue's
    default; finer is closer to the tissue's converged answer and slower, see :data:`TRUTH_EDGE_WIDTHS`)."""
    out = Path(out)
    say = progress or (lambda text: None)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise KneeInputError(f"the seed must be a non-negative integer, got {seed!r}")
    if not 0.0 <= flying <= 1.0:  # also refuses NaN
        raise KneeInputError(f"the flying pixels' share must lie from 0 to 1, got {flying!r}")
    if not (isinstance(skin_band, (int, float, np.integer, np.floating)) and 0.75 <= skin_band <= 3.0):
        raise KneeInputError(f"the skin band must lie from 0.75 to 3 femur widths, got {skin_band!r}")
    check_truth_edge(truth_edge)
    for name, v, top, unit in (("noise correlation", correlation_px, 100.0, "pixels"),
                               ("hole size", hole_px, 100.0, "pixels"), ("depth noise", sigma_mm, 50.0, "mm")):
        if not (isinstance(v, (int, float, np.integer, np.floating)) and 0.0 <= v <= top):  # also refuses NaN
            raise KneeInputError(f"the {name} must lie from 0 to {top:g} {unit}, got {v!r}")
    noise = DepthNoise(sigma_at_ref=float(sigma_mm), flying=flying, correlation_px=float(correlation_px),
                       hole_px=float(hole_px))
    for kind, given, known in (("anatomy", anatomies, ANATOMIES), ("case family", families, FAMILIES)):
        unknown = [g for g in given if g not in known]
        if unknown or not given:
            raise KneeInputError(f"unknown {kind} {unknown[0]!r}: one or more of {', '.join(known)}" if unknown
                                 else f"no {kind} given: one or more of {', '.join(known)}")
    if data is None or not Path(data).is_dir():
        if "phantom" not in anatomies or "mechanism+deviation" not in families:
            raise KneeInputError("without the data folder (visible-human-male/, lenhart2015/) only the phantom's "
                                 "mechanism+deviation cases can be built")
        anatomies = tuple(a for a in anatomies if a == "phantom")
        families = tuple(f for f in families if f != "measured")
    cases = []
    entries = []
    for entry, truth, prior_params in _anatomies(out, data, seed, anatomies, patella, skin_band):
        entries.append(entry)
        subject = load_subject(out / entry.subject)
        anatomy = subject_anatomy(subject, prior_params)
        Tf = anatomical_frames(subject)["femur"]  # femur frame (the model's) -> CT
        say(f"{entry.name}: the tissue model's mesh")
        pat = truth_patella(subject, anatomy, Tf, truth) if patella else None
        tissue = TetTissue(anatomy, edge=float(truth_edge) * anatomy.width, seed=seed,
                           patella=None if pat is None else pat[0])
        scan = anatomy.scan_tf
        poses = []
        for family in families:
            if family == "mechanism+deviation":
                T = joint_to_pose(truth.motion_at(np.radians(mechanism_flexions))[0])
                T_scan = joint_to_pose(truth.motion_at(np.array([scan[0]]))[0][0])
                for fl, Tm in zip(mechanism_flexions, T):
                    dev = random_pose(case_rng(seed, entry.name, family, f"{fl:g}"), DEVIATION_DEG, DEVIATION_MM,
                                      np.zeros(3))
                    poses.append((family, fl, Tm @ invert_poses(T_scan) @ anatomy.tibia_pose @ dev))
            else:  # "measured" (the families are checked above)
                for fl, Tm in zip(measured_flexions, measured_poses(data, anatomy, measured_flexions)):
                    poses.append((family, fl, Tm))
        centre = np.array([0.0, anatomy.joint_y, 0.0])
        for family, fl, T_tibia in poses:
            t0 = time.perf_counter()
            posed = tissue.pose(T_tibia, None if pat is None else pat[1](fl))
            skin = posed.skin(tissue)
            say(f"{entry.name} {family} {fl:g} deg: truth skin in {time.perf_counter() - t0:.0f} s "
                f"({posed.inverted} inverted tetrahedra)")
            normals = np.asarray(skin.vertex_normals)
            for mm in mismatches:
                pose_id = f"{entry.name}-{family.split('+')[0]}-{fl:g}-{mm:g}mm"
                verts = smooth_surface_field(skin.vertices, normals, mm, FIELD_WIDTHS * anatomy.width,
                                             case_rng(seed, pose_id), faces=skin.faces)
                cams = PLACEMENTS if mm == mismatches[len(mismatches) // 2] else {"paper": PLACEMENTS["paper"]}
                for cname in cams:
                    cid = f"{pose_id}-{cname}"
                    rng = case_rng(seed, cid)
                    cam = placement_camera(anatomy, cname)
                    depth = noise.apply(render_depth(verts, skin.faces, cam), rng)
                    folder = out / "cases" / cid
                    folder.mkdir(parents=True)
                    np.save(folder / "depth.npy", depth.astype(np.float32))
                    T_cam_model = cam.T_cam_world  # the camera was placed in the femur (model) frame
                    rough = T_cam_model @ random_pose(rng, ROUGH_DEG, ROUGH_MM, centre)
                    np.savetxt(folder / "initial_pose.txt", rough @ invert_poses(Tf), fmt="%.9g")
                    rel = T_tibia @ invert_poses(anatomy.tibia_pose)
                    cases.append({
                        "id": cid, "anatomy": entry.name, "family": family,
                        "flexion_deg": round(math.degrees(pose_to_joint(T_tibia)[0]), 3), "mismatch_mm": mm,
                        "camera": cname, "depth": f"cases/{cid}/depth.npy",
                        "initial_pose": f"cases/{cid}/initial_pose.txt",
                        "intrinsics": [cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]],
                        "truth_tf": pose_to_joint(T_tibia).tolist(),
                        "T_camera_femur_ct": (T_cam_model @ invert_poses(Tf)).tolist(),
                        "T_camera_tibia_ct": (T_cam_model @ rel @ invert_poses(Tf)).tolist()})
    _write_index(out, seed, entries, cases, patella, noise, truth_edge)
    return out


#: The patella's vertices its clearance from the femur is measured over (a spread subset; the least distance).
PATELLA_CLEARANCE_POINTS = 600
#: How far (mm) :func:`truth_patella` may slide the patella to keep its clearance from the femur.
PATELLA_REACH_MM = 40.0


def truth_patella(subject, anatomy, T_ct_femur, truth: Mechanism):
    """The subject's patella in the femur frame at the scan (``T_ct_femur`` (4, 4): femur frame to CT;
    ``anatomy``: the subject's :class:`knee.models.fem.anatomy.KneeAnatomy`, whose scan flexion and femur
    it is) and its motion at a flexion: ``motion(flexion_deg) -> (4, 4)``, femur frame.

    The motion is the truth mechanism's PF motion from the scan's flexion to that one (``P(a)
    P(a_scan)^-1``, P the patella's pose in the femur frame), moved so that it carries the mechanism's own
    patella (its phantom's, centred, at the scan) onto the subject's: the subject's patella centroid
    follows the path the mechanism's follows, from where the subject's lies, and turns as it turns. For a
    template scaled to a subject, the helical axis would otherwise swing the subject's patella about an
    axis that is not under it. Then, since the mechanism's path is not the subject's groove, the patella is
    slid along the line from the femur's nearest point to its centroid until its clearance from the femur
    is the scan's (the least distance over :data:`PATELLA_CLEARANCE_POINTS` of its vertices): it rides on
    the subject's own femur, as the tibia of the measured motion is kept at the scan's clearance.

    Raises :class:`KneeInputError` when the subject has no patella surface or the mechanism no PF joint."""
    mesh = subject.ct.get("patella")
    if mesh is None:
        raise KneeInputError(f"subject {subject.name} has no ct/patella surface: the truth's tissue cannot hold one")
    if not truth.has_pf:
        raise KneeInputError(f"the truth mechanism {truth.params.name} has no patello-femoral joint to move the patella")
    patella = mesh.copy().apply_transform(invert_poses(T_ct_femur))
    P_scan = joint_to_pose(truth.motion_at(np.array([anatomy.scan_tf[0]]))[1][0])
    own = transform_points(P_scan, build_phantom(truth.params).patella.centroid[None])[0]
    shift = np.eye(4)
    shift[:3, 3] = patella.centroid - own
    femur = SurfaceQuery.of(anatomy.femur)
    v = np.asarray(patella.vertices, float)
    v = v[np.linspace(0, len(v) - 1, min(len(v), PATELLA_CLEARANCE_POINTS)).astype(int)]
    clearance = float(femur.signed_distance(v).min())
    c = patella.centroid

    def motion(flexion_deg: float) -> np.ndarray:
        M = shift @ joint_to_pose(truth.motion_at(np.radians([flexion_deg]))[1][0]) @ invert_poses(P_scan)
        M = M @ invert_poses(shift)
        moved = transform_points(M, v)
        mc = transform_points(M, c[None])[0]
        u = mc - femur.closest_points(mc[None])[0]
        u /= max(float(np.linalg.norm(u)), 1e-9)

        def f(t):  # the clearance grows with the slide along u
            return float(femur.signed_distance(moved + t * u).min()) - clearance

        reach = PATELLA_REACH_MM
        if f(-reach) > 0.0 or f(reach) < 0.0:
            raise KneeError(f"the patella cannot be brought to {clearance:.2f} mm from the femur within {reach:.0f} mm "
                            f"at {flexion_deg:g} deg")
        M[:3, 3] += brentq(f, -reach, reach, xtol=1e-6) * u
        return M

    return patella, motion


def _write_index(out: Path, seed: int, entries, cases, patella: bool = False, noise: DepthNoise | None = None,
                 truth_edge: float = TRUTH_EDGE_WIDTHS) -> None:
    noise = noise or DepthNoise()
    lines = [f'format = "{FORMAT}"', f"version = {VERSION}", f"seed = {int(seed)}",
             f"truth_patella = {'true' if patella else 'false'}", f"truth_edge_widths = {float(truth_edge)!r}", f"flying_pixels = {float(noise.flying)!r}",
             f"noise_correlation_px = {float(noise.correlation_px)!r}", f"hole_px = {float(noise.hole_px)!r}",
             f"noise_sigma_mm_at_400_mm = {float(noise.sigma_at_ref * (400.0 / noise.ref_depth) ** 2)!r}", ""]
    for e in entries:
        lines += ["[[anatomy]]", f"name = {toml_string(e.name)}", f"subject = {toml_string(str(e.subject))}",
                  f"prior = {toml_string(str(e.prior))}", f"truth_mechanism = {toml_string(e.truth_mechanism)}",
                  f"notes = {toml_string(e.notes)}", ""]
    for c in cases:
        lines.append("[[case]]")
        for k, v in c.items():
            lines.append(f"{k} = {toml_string(v) if isinstance(v, str) else json.dumps(v)}")
        lines.append("")
    (out / "case-set.toml").write_text("\n".join(lines), encoding="utf-8")


def is_case_set(folder) -> bool:
    return (Path(folder) / "case-set.toml").is_file()


def read_case_set(folder) -> dict:
    """The case set's index (``case-set.toml``), checked: a clear error naming what is wrong."""
    folder = Path(folder)
    path = folder / "case-set.toml"
    if not is_case_set(folder):
        raise KneeInputError(f"{folder} is not a case set (scripts/build_case_set.py builds one)")
    try:
        index = tomllib.loads(read_text(path))
    except tomllib.TOMLDecodeError as e:
        raise KneeInputError(f"{path}: not valid TOML ({e})") from None
    if index.get("format") != FORMAT:
        raise KneeInputError(f"{path}: not a case set (format must be {FORMAT!r})")
    names = {a.get("name") for a in index.get("anatomy", [])}
    for c in index.get("case", []):
        missing = [k for k in ("id", "anatomy", "depth", "intrinsics", "initial_pose", "truth_tf",
                               "T_camera_femur_ct", "T_camera_tibia_ct") if k not in c]
        if missing or c["anatomy"] not in names:
            raise KneeInputError(f"{path}: case {c.get('id', '?')}: " + (f"missing {', '.join(missing)}" if missing
                                                                         else f"unknown anatomy {c['anatomy']!r}"))
    if not index.get("case"):
        raise KneeInputError(f"{path}: no cases")
    version = index.get("version", 1)
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= VERSION:
        raise KneeInputError(f"{path}: version must be a whole number from 1 to {VERSION}, got {version!r}")
    if version < 2:  # its depth images were rendered with the principal point half a pixel on: read as such
        for c in index["case"]:
            c["intrinsics"] = [*c["intrinsics"][:2], c["intrinsics"][2] - 0.5, c["intrinsics"][3] - 0.5]
        index["version"] = VERSION
    return index


@dataclass
class CaseRow(CompareRow):
    """A method on one case of a case set (:class:`CompareRow` plus the case's description)."""

    case: str = ""
    anatomy: str = ""
    family: str = ""
    mismatch_mm: float = float("nan")
    registration_inliers: float = float("nan")
    shank_points_true: int = -1
    #: the process's CPU time over the run (s; every thread's): on a shared machine, where other work takes
    #: the cores, the wall time grows and this does not
    cpu_seconds: float = float("nan")
    #: how well the subject's skin, posed at the estimated flexion, fits the depth points (mm; the trimmed RMS
    #: over the nearest 90 %, :attr:`knee.models.prior.FlexionEstimate.rms`): the check on the input that
    #: warns over :data:`knee.models.prior.POOR_FIT_RMS_MM`; NaN where the method made no estimate
    estimate_rms_mm: float = float("nan")


#: The shank, for counting what the camera sees of it: the skin more than this many femur widths below the
#: joint line, in the true tibia's frame (below the prior's blended knee band, a quarter width).
SHANK_BELOW_WIDTHS = 0.25


def seen_shank_points(anatomy, points_cam, T_cam_tibia) -> int:
    """How many depth points (camera frame, after the flexion estimate's voxel thinning) lie on the true
    shank: more than :data:`SHANK_BELOW_WIDTHS` femur widths below the joint line in the true tibia's frame
    (``T_cam_tibia`` takes the tibia's rest model coordinates to the camera). The truth's side of the
    flexion target: the camera sees the shank when this reaches :data:`knee.models.prior.MIN_SEEN_SHANK`."""
    local = transform_points(invert_poses(T_cam_tibia), voxel_downsample(points_cam, VOXEL_MM))
    return int(np.count_nonzero(local[:, 1] < anatomy.joint_y - SHANK_BELOW_WIDTHS * anatomy.width))


def case_intrinsics(case: dict) -> np.ndarray:
    """A case's camera intrinsics ``K`` (3, 3), pixels, from its ``intrinsics`` (fx, fy, cx, cy)."""
    fx, fy, cx, cy = case["intrinsics"]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def case_points_cam(folder: Path, case: dict) -> np.ndarray:
    """A case's depth points (P, 3), mm, in its camera's frame, as a measured image's (mixed pixels left out)."""
    return backproject(read_depth_image(Path(folder) / case["depth"]), case_intrinsics(case), drop_mixed=True)


def run_case(folder: Path, case: dict, method: str, anatomy, prior: Mechanism, T_ct_model, stages: bool = False,
             on_result: Callable | None = None, guess: bool = True, settings: FemSettings | None = None,
             **options) -> tuple[CaseRow, list]:
    """One method on one case: the depth image and the rough pose in, the bones in the camera's frame out,
    measured at the target points (ACL/PCL footprints from the prior's attachments, the epiphyses); the row,
    and with ``stages`` the errors of each stage of the method
    (:func:`knee.app.experiments.subject_cases.camera_stage_errors`; otherwise an empty list). The paper's
    method runs at its best reading (:data:`knee.models.fem.methods.PAPER_AT_BEST`, as
    :func:`knee.models.fem.methods.prior_method` applies it; ``options`` may override it). ``on_result(case, anatomy, method, points_cam, truth, estimate, row)``, when given, gets the
    depth points and the true and estimated bones' poses (``{"femur": (4, 4), "tibia": (4, 4)}``, rest model
    coordinates to the camera; the estimate's are the rigid poses the errors are taken at); for a run that
    failed (:func:`run_case_set`) the points and poses are None. ``guess``: False leaves the case's rough pose
    out (the knee found by the global search). ``settings``: the association model's
    (:class:`knee.models.fem.scene.FemSettings`; None: its defaults), e.g. a finer grid."""
    pts = case_points_cam(folder, case)
    init = read_pose_file(folder / case["initial_pose"], f"case {case['id']}'s initial pose")
    model = build_knee_model(anatomy, settings, prior=prior)
    t0, c0 = time.perf_counter(), time.process_time()
    recon, rough = reconstruct_in_camera(model, prior, pts, invert_poses(init @ T_ct_model) if guess else None, method,
                                         **options)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    T_cam_world = invert_poses(rough.T_model_world)
    T_cam_femur = np.asarray(case["T_camera_femur_ct"]) @ T_ct_model
    T_cam_tibia = np.asarray(case["T_camera_tibia_ct"]) @ T_ct_model
    e = camera_target_errors(anatomy, prior, recon, T_cam_world, T_cam_femur, T_cam_tibia)
    row = reconstruction_row(method, case["camera"], float(case["flexion_deg"]), recon, e, wall, CaseRow,
                             case=case["id"], anatomy=case["anatomy"], family=case["family"],
                             mismatch_mm=float(case["mismatch_mm"]), registration_inliers=rough.inliers,
                             shank_points_true=seen_shank_points(anatomy, pts, T_cam_tibia), cpu_seconds=cpu,
                             estimate_rms_mm=float("nan") if recon.estimate is None else float(recon.estimate.rms))
    staged = camera_stage_errors(anatomy, prior, recon, T_cam_world, T_cam_femur, T_cam_tibia) if stages else []
    if on_result is not None:
        estimate = {b: T_cam_world @ recon.rigid_pose(b) for b in ("femur", "tibia")}
        on_result(case, anatomy, method, pts, {"femur": T_cam_femur, "tibia": T_cam_tibia}, estimate, row)
    return row, staged


def diagnose_case_set(folder, method: str = "links", progress: Callable[[int, int, str], None] | None = None,
                      select: Callable[[dict], bool] | None = None, **options) -> list[tuple[CaseRow, list]]:
    """Method (ii) or (iii) on every case of a case set (``select``: a filter), with the errors of each of
    its stages (:func:`knee.app.experiments.subject_cases.camera_stage_errors`): where the final error
    comes from. A run that fails is a row with its reason and no stages."""
    if method not in ("init", "links"):
        raise KneeInputError(f"only methods (ii) 'init' and (iii) 'links' have stages, got {method!r}")
    return _run_all(folder, [method], progress, select, stages=True, **options)


def _failed_row(method: str, c: dict, e: Exception) -> CaseRow:
    return CaseRow(method, c["camera"], float(c["flexion_deg"]), failed=str(e), case=c["id"], anatomy=c["anatomy"],
                   family=c["family"], mismatch_mm=float(c["mismatch_mm"]))


def iter_cases(folder, select: Callable[[dict], bool] | None = None):
    """The cases of a case set (``select``: a filter), each as (case, (its anatomy, its prior, the CT frame
    to the model frame), its index, the count); each anatomy and prior read once."""
    folder = Path(folder)
    index = read_case_set(folder)
    cases = [c for c in index["case"] if select is None or select(c)]
    setup = {}
    for a in index["anatomy"]:
        if not any(c["anatomy"] == a["name"] for c in cases):
            continue
        prior = Mechanism(load_model(folder / a["prior"]))
        subject = load_subject(folder / a["subject"])
        setup[a["name"]] = (subject_anatomy(subject, prior.params), prior, anatomical_frames(subject)["femur"])
    for i, c in enumerate(cases):
        yield c, setup[c["anatomy"]], i, len(cases)


def run_case_set(folder, methods, progress: Callable[[int, int, str], None] | None = None,
                 select: Callable[[dict], bool] | None = None, on_result: Callable | None = None,
                 guess: bool = True, **options) -> list[CaseRow]:
    """Every method on every case of a case set (``select``: a filter on the cases; ``on_result``: as
    :func:`run_case`'s, called for failed runs too; ``guess``: False leaves the cases' rough poses out;
    ``settings``, among ``options``, the association model's, as :func:`run_case` takes them; the other
    ``options`` go to :func:`knee.models.fem.methods.prior_method`); a run that fails is a row with its
    reason."""
    return [row for row, _ in _run_all(folder, methods, progress, select, on_result=on_result, guess=guess,
                                       **options)]


def _run_all(folder, methods, progress, select, stages: bool = False, on_result: Callable | None = None,
             **options) -> list[tuple[CaseRow, list]]:
    """Every method on every selected case: :func:`run_case`'s (row, stage errors) each, a failed run a row
    with its reason and no stages."""
    folder = Path(folder)
    out = []
    for c, (anatomy, prior, T_ct_model), i, n in iter_cases(folder, select):
        for j, m in enumerate(methods):
            if progress:
                progress(i * len(methods) + j, n * len(methods), f"{m} on {c['id']}")
            try:
                out.append(run_case(folder, c, m, anatomy, prior, T_ct_model, stages=stages, on_result=on_result,
                                    **options))
            except KneeError as e:
                out.append((_failed_row(m, c, e), []))
                if on_result is not None:
                    on_result(c, anatomy, m, None, None, None, out[-1][0])
    if progress:
        progress(len(out), len(out), "done")
    return out
