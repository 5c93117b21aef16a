"""``knee synth-subject OUT_DIR``: a complete synthetic subject folder from a parameter set, and with
``--depth-frame DEG`` a depth image of its knee as a camera would give it (the input of ``knee fem``)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from knee.app.console import out_dir, say
from knee.app.experiments.cases import tissue_case_depth
from knee.fitting.pipeline import anatomical_frames
from knee.fitting.subject import load_subject
from knee.fitting.subject_anatomy import subject_anatomy
from knee.fitting.synthetic import MAX_FRAMES, MIN_FRAMES, make_subject
from knee.foundations.conventions import JOINT_COORDINATES, invert_poses, joint_to_pose
from knee.foundations.errors import KneeInputError
from knee.foundations.files import staged_folder
from knee.models.fem.depth import DepthNoise, default_camera
from knee.models.fem.tissue import TetTissue
from knee.models.mechanism import Mechanism
from knee.models.mechanism.params import load_model

#: How far the rough CT pose written with a depth frame is from the truth at the knee (the femur frame's
#: origin): a turn about it (deg) and a shift of it (mm), about what a first guess from the set-up gives.
ROUGH_POSE_OFF = (15.0, 25.0)


def run(args) -> int:
    out = out_dir(args.out_dir, force=False, flag="OUT_DIR")
    if not MIN_FRAMES <= args.frames <= MAX_FRAMES:
        raise KneeInputError(f"--frames must be {MIN_FRAMES}-{MAX_FRAMES}, got {args.frames}")
    if args.depth_frame is not None:
        truth = Mechanism.from_name(args.model)
        if not (math.isfinite(args.depth_frame) and truth.in_range(math.radians(args.depth_frame))):
            lo, hi = (math.degrees(v) for v in truth.assembly_range)
            raise KneeInputError(f"--depth-frame must lie within {args.model}'s assembly range ({lo:.1f} to {hi:.1f} "
                                 f"deg), got {args.depth_frame}")
    say(f"knee synth-subject: writing a synthetic subject from '{args.model}' (seed {args.seed}) ...")
    with staged_folder(out) as tmp:
        make_subject(tmp, model=args.model, seed=args.seed, frames=args.frames)
        if args.depth_frame is not None:
            intrinsics = write_depth_frame(tmp, args.depth_frame, args.seed)
    print(f"subject folder: {out}")
    print(f"fit it with:    knee fit {out} --out {out}-fit")
    if args.depth_frame is not None:
        cam = Path(out) / "camera"
        print(f"then the FEM:   knee fem {out} --prior {out}-fit/fitted.toml --depth {cam / 'depth.png'} "
              f"--intrinsics {intrinsics} --initial-pose {cam / 'ct-in-camera-rough.txt'} --out {out}-fem\n"
              f"                (the truth to compare with: {cam / 'truth.json'})")
    return 0


def write_depth_frame(folder: Path, flexion_deg: float, seed: int) -> str:
    """Into ``folder/camera/``: ``depth.png``, the subject's knee posed by its truth (``truth.toml``) at
    ``flexion_deg`` and seen by the oblique camera (350 mm, 35 deg lateral, 30 deg up; RealSense-like noise),
    a 16-bit PNG in mm. The skin it shows is made independently of the association model that ``knee fem``
    builds from the folder: the tetrahedral tissue around the subject's own CT bones inside its CT skin
    (:class:`knee.models.fem.tissue.TetTissue`, the honest benchmark's truth) posed with the truth's tibia; ``intrinsics.txt`` (fx,fy,cx,cy, pixels); ``ct-in-camera-rough.txt``, the CT frame in the
    camera's (4x4) turned about the knee and moved :data:`ROUGH_POSE_OFF` from the truth, for
    ``--initial-pose``; and
    ``truth.json``, the true flexion, TF joint coordinates and bone poses (CT to camera) to check a result
    against. Returns the intrinsics as ``knee fem`` takes them."""
    folder = Path(folder)
    truth = Mechanism(load_model(folder / "truth.toml"))
    cam = default_camera()
    subject = load_subject(folder)
    say(f"knee synth-subject: posing the subject's soft tissue at {flexion_deg:g} deg for the depth frame "
        f"(about 15 s) ...")
    tissue = TetTissue(subject_anatomy(subject, truth.params), seed=seed)
    tf = truth.solve(math.radians(flexion_deg))[0]
    depth = tissue_case_depth(tissue, tf, cam, DepthNoise(), seed)
    frames = anatomical_frames(subject)
    T_cam_model = invert_poses(cam.T_world_cam)  # the model frame is the femur's anatomical frame
    T_cam_femur = T_cam_model @ invert_poses(frames["femur"])
    T_cam_tibia = T_cam_model @ joint_to_pose(tf) @ invert_poses(frames["tibia"])
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    shift = rng.normal(size=3)
    off = np.eye(4)  # in the femur's frame: turned about the knee, then moved
    off[:3, :3] = Rotation.from_rotvec(math.radians(ROUGH_POSE_OFF[0]) * axis / np.linalg.norm(axis)).as_matrix()
    off[:3, 3] = ROUGH_POSE_OFF[1] * shift / np.linalg.norm(shift)
    (folder / "camera").mkdir()
    o3d.io.write_image(str(folder / "camera" / "depth.png"),
                       o3d.geometry.Image(np.clip(np.round(depth), 0, 65535).astype(np.uint16)))
    K = cam.K
    intrinsics = f"{K[0, 0]:.6g},{K[1, 1]:.6g},{K[0, 2]:.6g},{K[1, 2]:.6g}"
    (folder / "camera" / "intrinsics.txt").write_text(intrinsics + "\n", encoding="utf-8")
    np.savetxt(folder / "camera" / "ct-in-camera-rough.txt", T_cam_model @ off @ invert_poses(frames["femur"]),
               header=f"a rough pose of the CT frame in the camera's ({ROUGH_POSE_OFF[0]:g} deg and "
                      f"{ROUGH_POSE_OFF[1]:g} mm off the truth at the knee), for knee fem --initial-pose")
    truth_json = {"flexion_deg": math.degrees(tf[0]),
                  "tf_joint_coordinates": {name: (math.degrees(v) if k < 3 else float(v))
                                           for k, (name, v) in enumerate(zip(JOINT_COORDINATES, tf))},
                  "T_camera_femur_ct": T_cam_femur.tolist(), "T_camera_tibia_ct": T_cam_tibia.tolist(),
                  "camera": "oblique: 350 mm from the knee, 35 deg towards lateral, raised 30 deg; depth noise on",
                  "skin": "the tetrahedral tissue around the subject's CT bones and skin, posed with the truth's "
                          "tibia (not the association model)"}
    (folder / "camera" / "truth.json").write_text(json.dumps(truth_json, indent=1), encoding="utf-8")
    return intrinsics
