"""Example 2: write a synthetic subject folder (phantom surfaces, landmarks, attachment areas and a noisy
measured motion, from the bundled 'volunteer'), fit a mechanism to it, and compare with the truth.

    .venv/bin/python tests/examples/fit_synthetic_subject.py
"""

import tempfile
from pathlib import Path

import knee


def main(effort: str = "quick") -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        folder = knee.make_subject(Path(tmp) / "subject", model="volunteer", seed=0, frames=60)
        outcome = knee.fit_subject(folder, seed=0, effort=effort)
    truth = outcome.truth_errors            # the fitted model against the noise-free motion
    return {
        "frames": int(len(outcome.motion.tf)),
        # mean absolute errors: TF adduction, internal rotation (deg); anterior, proximal, lateral (mm)
        "tf_mae_vs_truth": [round(float(v), 3) for v in truth.tf.mae[1:]],
        # PF flexion, tilt, rotation (deg); anterior, proximal, lateral (mm)
        "pf_mae_vs_truth": [round(float(v), 3) for v in truth.pf.mae],
        "fit_seconds": outcome.seconds.fit,
    }


if __name__ == "__main__":
    for k, v in main().items():
        print(f"{k:18s} {v}")
