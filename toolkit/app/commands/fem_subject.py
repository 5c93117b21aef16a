"""``knee fem SUBJECT_DIR --prior FITTED.toml (--depth D --intrinsics fx,fy,cx,cy | --cloud C) --out OUT``:
the association model of a subject's own knee (its CT bones and skin) deformed toward a measured depth
image or point cloud, with the fitted mechanism as its kinematic prior.

The points are in the camera's frame and the knee's pose there is unknown: it is found from a rough
initial pose (``--initial-pose``: the CT frame in the camera's, within about 30 deg and 50 mm) or, without
one, by a global search over rotations as the camera would see the skin, then refined with the flexion
(:func:`knee.models.prior.register_roughly`, :func:`knee.models.fem.methods.prior_method`).

Outputs in OUT (written only when the run succeeds; nothing that looks like a result otherwise):

- ``result.json``: the femur's and the tibia's poses as 4x4 matrices (mm) taking CT coordinates to the
  camera's frame (what an AR overlay needs), the flexion (with methods ii/iii its standard error,
  ``flexion_sd_deg``) and the TF joint coordinates, the fit's quality and the warnings;
- ``femur.stl``, ``tibia.stl``: the CT bones posed in the camera's frame;
- ``fem.rrd``: the points, the reconstructed skin and bones (camera frame);
- ``overlay.png``: the bones' silhouettes over the depth image (or over the points seen from the camera).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from scipy.ndimage import minimum_filter  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from knee.app.console import ProgressBar, numbers, out_dir, say  # noqa: E402
from knee.fitting.pipeline import anatomical_frames  # noqa: E402
from knee.fitting.subject import load_subject, mirror_mesh  # noqa: E402
from knee.fitting.subject_anatomy import subject_anatomy  # noqa: E402
from knee.foundations import recording as R  # noqa: E402
from knee.foundations.conventions import (JOINT_COORDINATES, invert_poses, pose_to_joint, read_pose_file,  # noqa: E402
                                          transform_points)
from knee.foundations.errors import KneeInputError  # noqa: E402
from knee.foundations.files import staged_folder  # noqa: E402
from knee.foundations.imaging import write_surface  # noqa: E402
from knee.foundations.pointclouds import (backproject, load_point_cloud, mixed_pixels, principal_point_note,  # noqa: E402
                                         read_depth_image, sparse_points)
from knee.models.fem.depth import Camera, render_depth  # noqa: E402
from knee.models.fem.methods import reconstruct_in_camera  # noqa: E402
from knee.models.fem.scene import FemSettings, build_knee_model  # noqa: E402
from knee.models.mechanism import Mechanism  # noqa: E402
from knee.models.mechanism.params import load_model  # noqa: E402


#: The bones' silhouettes over the camera's image (the overlay and the recording's 2-D view), RGB.
SILHOUETTE_COLOURS = {"femur": (31, 119, 180), "tibia": (255, 127, 14)}


#: A turn of ``--initial-pose`` from where the points put the femur beyond which it is said (deg): well past
#: the 30 deg it is meant to be within, as a pose given the other way round (the camera in the CT) is.
INITIAL_POSE_WARN_DEG = 45.0


def model_settings(args) -> FemSettings | None:
    """The association model's settings the command line asks for (``--cells-across``: a count or a pair (x,
    z)), or None for its defaults."""
    n = getattr(args, "cells_across", None)
    return None if n is None else FemSettings(n_across=n)


def grid_label(n_across) -> str:
    """A grid's cells across the limb as said to the user: "9 cells across", "14 x 7 cells across" for a pair
    (x, z), or "sized by the knee" for ``"knee"``."""
    if isinstance(n_across, str):
        return "sized by the knee (cells along x about a sixth of the femur's width)"
    return (str(n_across) if np.ndim(n_across) == 0 else " x ".join(str(int(v)) for v in n_across)) + " cells across"


#: The span a camera's view of a knee can have, mm: a smaller one is a cloud or depth image in other units
#: (metres), a larger one in smaller units (micrometres).
VIEW_SPAN_MM = (40.0, 1e5)


def checked_span(points, flag: str, scale: float) -> np.ndarray:
    """``points`` (P, 3) in mm after ``flag``'s ``scale``, or a one-line error when their span cannot be a
    knee's view in millimetres (the unit the scale was meant to give)."""
    span = float(np.ptp(points, axis=0).max()) if len(points) else 0.0
    lo, hi = VIEW_SPAN_MM
    if len(points) and not lo <= span <= hi:
        guess = f"in metres? give {flag} {1000.0 * scale:g}" if span < lo else f"give {flag} to make it mm"
        raise KneeInputError(f"the measured points span {span:.3g} mm with {flag} {scale:g}; a camera's view of a "
                             f"knee spans {lo:g} mm or more: {guess}")
    return points


def measured_cloud(args) -> tuple[np.ndarray, np.ndarray]:
    """``--cloud`` read in mm after ``--cloud-scale``: (the points kept (P, 3), the flying pixels left out
    (F, 3): the points far from the others, none with ``--keep-flying``), or a one-line error for a bad scale
    or a span that cannot be a knee's view in mm."""
    if not (math.isfinite(args.cloud_scale) and args.cloud_scale > 0):
        raise KneeInputError(f"--cloud-scale must be a positive number, got {args.cloud_scale}")
    pts = load_point_cloud(args.cloud) * args.cloud_scale
    flying = np.zeros(len(pts), bool) if args.keep_flying else sparse_points(pts)
    return checked_span(pts[~flying], "--cloud-scale", args.cloud_scale), pts[flying]


def depth_input(args) -> tuple[np.ndarray, np.ndarray]:
    """``--depth``'s image (its own units) and ``--intrinsics``' K (3, 3), pixels, checked: the intrinsics
    given, four numbers with positive focal lengths, a positive ``--depth-scale``, the principal point inside
    the image (intrinsics that put it outside do not belong to it). One path for the subject's and the
    phantom's ``knee fem``."""
    if not args.intrinsics:
        raise KneeInputError("--depth needs --intrinsics fx,fy,cx,cy (pixels)")
    fx, fy, cx, cy = numbers(args.intrinsics, 4, "--intrinsics")
    if not (fx > 0 and fy > 0):
        raise KneeInputError(f"--intrinsics: the focal lengths must be positive, got {fx:g}, {fy:g}")
    if not (math.isfinite(args.depth_scale) and args.depth_scale > 0):
        raise KneeInputError(f"--depth-scale must be a positive number, got {args.depth_scale}")
    depth = read_depth_image(args.depth)
    h, w = depth.shape
    if not (0 <= cx <= w and 0 <= cy <= h):
        raise KneeInputError(f"--depth {args.depth} is {w}x{h} pixels but --intrinsics puts the principal point at "
                             f"({cx:g}, {cy:g}), outside it: the intrinsics do not belong to this image")
    return depth, np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _points(args):
    """(points (P, 3) camera frame, depth image or None, K or None, the flying pixels left out (F, 3): a
    depth image's on depth edges, a cloud's far from the others; none with ``--keep-flying``)."""
    if args.cloud and args.depth:
        raise KneeInputError("give one measured input: --cloud FILE or --depth FILE, not both")
    if not (args.cloud or args.depth):
        raise KneeInputError("give a measured cloud or depth image: --cloud FILE or --depth FILE --intrinsics "
                             "fx,fy,cx,cy")
    if args.cloud:
        if args.intrinsics:
            raise KneeInputError("--intrinsics goes with --depth, not --cloud")
        pts, flying = measured_cloud(args)
        return pts, None, None, flying
    depth, K = depth_input(args)
    depth = depth * args.depth_scale
    mixed = np.zeros(depth.shape, bool) if args.keep_flying else mixed_pixels(depth, K)
    pts = checked_span(backproject(np.where(mixed, 0.0, depth), K), "--depth-scale", args.depth_scale)
    return pts, depth, K, backproject(np.where(mixed, depth, 0.0), K)


def run(args) -> int:
    subject_dir = Path(args.model)
    if not args.prior:
        raise KneeInputError("a subject needs its kinematic prior: --prior FITTED.toml (knee fit's fitted.toml)")
    if not args.out:
        raise KneeInputError("a subject's run writes its results to a folder: --out OUT")
    inputs = (subject_dir,) + tuple(Path(v) for v in (args.prior, args.cloud, args.depth, args.initial_pose) if v)
    out = out_dir(args.out, args.force, inputs=inputs)
    init_pose = read_pose_file(args.initial_pose, "--initial-pose") if args.initial_pose else None
    method = args.method or "links"
    points_cam, depth, K, flying = _points(args)
    subject = load_subject(subject_dir)
    # a left knee is read mirrored into a right one (README, "Subject folders"): the camera's points and the
    # initial pose are mirrored with it (x negated in the camera's frame and in the CT's), and the bones'
    # poses mirrored back, so that the outputs take the subject's own CT coordinates to the camera's frame
    S = np.diag([-1.0, 1.0, 1.0, 1.0]) if subject.side == "left" else np.eye(4)
    points_run = points_cam @ S[:3, :3]
    if init_pose is not None:
        init_pose = S @ init_pose @ S
    try:
        prior = Mechanism(load_model(args.prior))
    except KneeInputError as e:
        raise KneeInputError(f"--prior: {e}") from None
    say(f"knee fem: the association model of subject {subject.name} ...")
    t0 = time.perf_counter()
    anatomy = subject_anatomy(subject, prior.params)
    model = build_knee_model(anatomy, model_settings(args), prior=prior)
    frames = anatomical_frames(subject)
    T_ct_model = frames["femur"]  # model (femur frame) -> CT
    built = time.perf_counter() - t0
    say(f"  grid {len(model.grid.cells)} cells, bones {len(model.femur.el.cells)} + {len(model.tibia.el.cells)} "
        f"tetrahedra; {built:.1f} s")
    # the cloud on the model: a rough placement (initial pose or global search), then the method
    T_init = None if init_pose is None else invert_poses(init_pose @ T_ct_model)  # camera -> model
    t1 = time.perf_counter()
    bar = None if args.quiet else ProgressBar()
    if bar:
        bar(0.1, f"registration and {method}")
    # intrinsics for another resolution or stream read the points at the wrong angles: said beside the result,
    # or beside the refusal when the points then fit no knee
    intrinsics_note = None if K is None else principal_point_note(K, depth.shape)
    try:
        recon, rough = reconstruct_in_camera(model, prior, points_run, T_init, method)
    except KneeInputError as e:
        if intrinsics_note is None:
            raise
        raise KneeInputError(f"{e}; and {intrinsics_note}") from None
    seconds = time.perf_counter() - t1
    lo, hi = (math.degrees(v) for v in prior.assembly_range)
    if recon.estimate is not None and recon.estimate.at_range_end:
        raise KneeInputError(f"the knee's flexion lies at or beyond the end of the prior's assembly range ({lo:.1f} to "
                             f"{hi:.1f} deg): {args.prior} does not cover it; refit with the motion covering it")
    if bar:
        bar(1.0, f"{recon.steps} steps")
    # bones in the camera's frame: rest (model frame) -> reconstruction (rough model frame) -> camera
    T_cam_world = invert_poses(rough.T_model_world)
    poses_run = {b: T_cam_world @ recon.bone_pose(b, getattr(model, b).el.X) @ invert_poses(T_ct_model)
                 for b in ("femur", "tibia")}
    # the joint coordinates in the anatomical frames (a left knee's as its mirrored right knee's, the
    # convention of its coordinates); the poses in the subject's own CT and camera frames
    tf_pose = invert_poses(T_ct_model) @ invert_poses(poses_run["femur"]) @ poses_run["tibia"] @ frames["tibia"]
    tf = pose_to_joint(tf_pose)
    poses = {b: S @ T @ S for b, T in poses_run.items()}
    notes = ([] if intrinsics_note is None else [intrinsics_note + " (used as given)"]) + list(recon.notes)
    initial_off = None
    if init_pose is not None:
        # how far the initial pose was from where the points put the femur (at the knee: the femur frame's
        # origin); the registration recovers from a wrong one, and says so
        off = invert_poses(init_pose) @ poses_run["femur"]
        knee = T_ct_model[:3, 3]
        initial_off = {"deg": math.degrees(Rotation.from_matrix(off[:3, :3]).magnitude()),
                       "mm": float(np.linalg.norm(off[:3, :3] @ knee + off[:3, 3] - knee))}
        if initial_off["deg"] > INITIAL_POSE_WARN_DEG:
            notes.append(f"--initial-pose was {initial_off['deg']:.0f} deg and {initial_off['mm']:.0f} mm (at the "
                         "knee) from where the points put the femur (the registration found the knee without it): "
                         "check it gives the CT frame in the camera's, not the camera in the CT")
    result = {
        "subject": subject.name, "side": subject.side, "method": recon.method, "prior": str(args.prior),
        "flexion_deg": math.degrees(tf[0]),
        # methods ii/iii: the flexion's standard error from the fits that set it (None for the others)
        "flexion_sd_deg": recon.flexion_sd_deg if math.isfinite(recon.flexion_sd_deg) else None,
        "tf_joint_coordinates": {name: (math.degrees(v) if k < 3 else float(v))
                                 for k, (name, v) in enumerate(zip(JOINT_COORDINATES, tf))},
        "units": {"angles": "deg", "translations": "mm", "poses": "4x4, mm: CT coordinates to the camera's frame"},
        "T_camera_femur_ct": poses["femur"].tolist(), "T_camera_tibia_ct": poses["tibia"].tolist(),
        "fit": {"registration_inliers_5mm": rough.inliers, "registration_rms_mm": rough.rms,
                "flexion_estimate_rms_mm": None if recon.estimate is None else recon.estimate.rms,
                "flexion_estimate_inliers": None if recon.estimate is None else recon.estimate.inliers,
                "steps": recon.steps, "converged": recon.converged,
                "flying_pixels_left_out": len(flying)},
        "initial_pose_off": initial_off,
        "model": {"grid_cells": len(model.grid.cells), "cells_across": (
            int(model.settings.n_across) if np.ndim(model.settings.n_across) == 0
            else [int(v) for v in model.settings.n_across])},
        "seconds": {"model": built, "registration_and_method": seconds},
        "warnings": notes,
    }
    # the CT bones as scanned (a left knee's mirrored back), posed in the camera's frame; the FEM's skin too
    meshes = {b: (mirror_mesh(subject.ct[b]) if subject.side == "left" else subject.ct[b].copy()).apply_transform(T)
              for b, T in poses.items()}
    skin = None
    if recon.grid_x is not None:  # the FEM's skin (the mechanism alone has none)
        faces = np.asarray(model.skin_faces)
        skin = (transform_points(S @ T_cam_world, recon.locate("femur", model.skin_vertices)),
                faces[:, ::-1] if subject.side == "left" else faces)
    _write_outputs(out, meshes, skin, points_cam, result, depth, K, flying)
    sd = result["flexion_sd_deg"]
    print(f"{subject.name}: flexion {result['flexion_deg']:.1f} deg"
          + (f" (standard error {sd:.1f} deg)" if sd is not None else "")
          + f" ({recon.method}), {recon.steps} steps in "
          f"{seconds:.1f} s; registration: {100 * rough.inliers:.0f} % of the points within 5 mm of the skin")
    for w in notes:
        print(f"warning: {w}")
    print(f"results: {out / 'result.json'}, {out / 'femur.stl'}, {out / 'tibia.stl'}, {out / 'overlay.png'}\n"
          f"recording: {out / 'fem.rrd'}  (open with: rerun {out / 'fem.rrd'})")
    return 0


def _write_outputs(out: Path, meshes, skin, points_cam, result, depth, K, flying=None) -> None:
    """Every output into a temporary folder beside OUT, then renamed into place: a run that fails leaves
    no half-written results."""
    with staged_folder(out) as tmp:
        _write_into(tmp, meshes, skin, points_cam, result, depth, K, flying)


def _write_into(tmp: Path, meshes, skin, points_cam, result, depth, K, flying=None) -> None:
    """``meshes``: the bones posed in the camera's frame; ``skin``: the FEM's skin there (vertices, faces)
    or None; ``flying``: the flying pixels left out (F, 3), shown apart."""
    for b, m in meshes.items():
        write_surface(tmp / f"{b}.stl", m, "LPS")
    (tmp / "result.json").write_text(json.dumps(result, indent=1), encoding="utf-8")
    # the camera's image: the depth image given (or the points splatted into a virtual camera's) and each
    # bone's silhouette rendered with its intrinsics, for the recording's 2-D view and the overlay
    if depth is None:
        depth, K = _points_image(points_cam)
    h, w = depth.shape
    cam = Camera(K=np.asarray(K, float), width=w, height=h, T_world_cam=np.eye(4))
    masks = {b: render_depth(m.vertices, m.faces, cam) > 0 for b, m in meshes.items()}
    rec = R.new_recording()
    R.save(rec, tmp / "fem.rrd", rrb.Blueprint(rrb.Horizontal(rrb.Spatial3DView(origin="camera", name="Camera frame"),
                                                              rrb.Spatial2DView(origin="camera/image",
                                                                                name="Camera image")),
                                                collapse_panels=True))
    rec.log("camera/points", rr.Points3D(points_cam[:: max(1, len(points_cam) // 60000)].astype(np.float32),
                                         colors=[(90, 170, 255)], radii=[0.6]), static=True)
    if flying is not None and len(flying):
        rec.log("camera/flying_pixels", rr.Points3D(flying[:: max(1, len(flying) // 20000)].astype(np.float32),
                                                    colors=[(255, 120, 40)], radii=[0.6]), static=True)
    for b, m in meshes.items():
        R.log_mesh(rec, f"camera/{b}", m, R.BONE_COLOURS[b])
    if skin is not None:
        rec.log("camera/skin", rr.Mesh3D(vertex_positions=skin[0].astype(np.float32),
                                         triangle_indices=np.asarray(skin[1], np.uint32),
                                         albedo_factor=R.BONE_COLOURS["skin"]), static=True)
    rec.log("camera/image", rr.Pinhole(image_from_camera=cam.K, resolution=[w, h]), static=True)
    rec.log("camera/image/depth", rr.DepthImage(np.round(depth).astype(np.uint16), meter=1.0), static=True)
    rec.log("camera/image", rr.AnnotationContext([(k, b, SILHOUETTE_COLOURS[b]) for k, b in enumerate(masks, 1)]),
            static=True)
    for k, (b, mask) in enumerate(masks.items(), 1):  # 0 is transparent: each bone's silhouette over the image
        rec.log(f"camera/image/{b}", rr.SegmentationImage(np.where(mask, k, 0).astype(np.uint8), opacity=0.4),
                static=True)
    R.close(rec)
    _overlay(tmp / "overlay.png", masks, depth)


def _overlay(path, masks, depth) -> None:
    """Each bone's silhouette (``masks``: bone -> (H, W) bool, as the camera sees it whatever covers it)
    filled and outlined over the depth image (H, W), as an AR view would draw it."""
    h, w = depth.shape
    fig, ax = plt.subplots(figsize=(9.0, max(3.0, 9.0 * h / w)))
    ax.imshow(np.where(depth > 0, depth, np.nan), cmap="gray", interpolation="nearest")
    handles = []
    for b, mask in masks.items():
        colour = np.array(SILHOUETTE_COLOURS[b]) / 255.0
        if mask.any():
            ax.imshow(np.ma.masked_where(~mask, np.ones_like(mask, float)), cmap=ListedColormap([colour]),
                      alpha=0.3, interpolation="nearest")
            ax.contour(mask.astype(float), levels=[0.5], colors=[colour], linewidths=1.2)
        handles.append(Patch(facecolor=colour, edgecolor=colour, alpha=0.5,
                             label=b if mask.any() else f"{b} (outside the image)"))
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.legend(handles=handles, loc="upper right")
    ax.set_title("the reconstructed bones over the depth data (camera's view)")
    ax.set_xlabel("u (pixels)")
    ax.set_ylabel("v (pixels)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _points_image(points_cam, size: int = 900, margin: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A depth image (mm, 0 where empty) of points (P, 3) in a camera's frame, and the intrinsics (3, 3) of a
    virtual camera at that frame whose image holds them all (``size`` pixels across their wider extent)."""
    p = np.asarray(points_cam, float)
    p = p[p[:, 2] > 1.0]
    n = p[:, :2] / p[:, 2:3]
    lo, hi = n.min(axis=0), n.max(axis=0)
    f = size / max(float((hi - lo).max()), 1e-6)
    w, h = (np.ceil((hi - lo) * f).astype(int) + 2 * margin)
    cx, cy = margin - lo * f
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    # the pixel whose centre is nearest the projection (pixel centres at whole coordinates)
    u = np.clip(np.round(n[:, 0] * f + cx).astype(int), 0, w - 1)
    v = np.clip(np.round(n[:, 1] * f + cy).astype(int), 0, h - 1)
    depth = np.full((h, w), np.inf)
    np.minimum.at(depth, (v, u), p[:, 2])
    # the gaps between the points of a sparser cloud than the image's pixels, filled from the nearest
    # (a 5-pixel minimum), so that the surface reads as one
    depth = np.where(np.isfinite(depth), depth, minimum_filter(depth, size=5))
    depth[~np.isfinite(depth)] = 0.0
    return depth, K
