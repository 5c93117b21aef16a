"""Example 3: the association FEM with the kinematic prior (method iii) on a virtual depth image.

The subject is the bundled 'volunteer' knee written as a subject folder (CT bones, landmarks, skin) and
read back as any subject's is; the model is built from those surfaces. The prior is 'volunteer' with every
TF link endpoint moved 1-2 mm (realistically wrong). The truth is the knee at 60 deg, its skin made
independently of the association model: a tetrahedral tissue around the subject's bones posed with them
(the honest benchmark's truth), seen by an oblique depth camera with noise. The method sees only the point
cloud; the result is measured against the truth at the ACL/PCL footprints.

    .venv/bin/python tests/examples/fem_with_prior.py
"""

import math
import tempfile
from pathlib import Path

import numpy as np

import knee
from knee.app.experiments.cases import evaluate, tissue_case_points
from knee.fitting.optimize import perturb_endpoints
from knee.fitting.subject_anatomy import subject_anatomy
from knee.models.fem.depth import DepthNoise, default_camera
from knee.models.fem.scene import build_knee_model
from knee.models.fem.tissue import TetTissue


def main(flexion_deg: float = 60.0) -> dict:
    truth = knee.Mechanism(knee.load_model("volunteer"))
    prior = knee.Mechanism(perturb_endpoints(truth.params, 1.0, 2.0, seed=3))
    with tempfile.TemporaryDirectory() as tmp:
        subject = knee.load_subject(knee.make_subject(Path(tmp) / "volunteer", model="volunteer", seed=0))
    anatomy = subject_anatomy(subject, prior.params)            # the subject's bones and skin, femur frame
    model = build_knee_model(anatomy, prior=prior)               # grid, bones, springs, contact at the CT pose
    tissue = TetTissue(anatomy)                                  # the truth's soft tissue, at the CT pose
    truth_tf = truth.solve(math.radians(flexion_deg))[0]         # the true TF joint coordinates
    points = tissue_case_points(tissue, truth_tf, default_camera(), DepthNoise(), seed=3)  # (P, 3) mm
    recon = knee.prior_method("links", model, prior, points)     # (iii): initialise, then the links
    errors = evaluate(model, prior, recon, truth_tf)
    alone = knee.prior_method("kinematics", model, prior, points)  # (iv): the mechanism alone, for comparison
    return {
        "points": int(len(points)),
        "flexion_estimated_deg": round(recon.flexion_deg, 2),
        "flexion_error_deg": round(recon.flexion_deg - math.degrees(truth_tf[0]), 2),
        "flexion_sd_deg": round(recon.flexion_sd_deg, 2),          # its standard error, from the method's fits
        "footprints_mm": round(errors.footprints_mm, 3),
        "epiphysis_mm": round(errors.epiphysis_mm, 3),
        "mechanism_alone_footprints_mm": round(evaluate(model, prior, alone, truth_tf).footprints_mm, 3),
        "steps": recon.steps,
        "tibia_correction_deg": round(float(np.linalg.norm(recon.tibia_correction.rotation_deg)), 2),
    }


if __name__ == "__main__":
    for k, v in main().items():
        print(f"{k:24s} {v}")
