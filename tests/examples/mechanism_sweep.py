"""Example 1: load a parameter set, sweep the mechanism over flexion, and ask how the motion depends on
the parameters.

    .venv/bin/python tests/examples/mechanism_sweep.py
"""

import numpy as np

import knee
from knee.models.mechanism.params import parameter_names


def main() -> dict:
    mech = knee.Mechanism(knee.load_model("volunteer"))           # seed 002 Table 1, optimised
    lo, hi = np.degrees(mech.assembly_range)
    res = mech.sweep(np.radians(np.arange(0.0, 121.0, 1.0)))     # 121 angles
    tf90 = res.tf[90]                                            # (6,): rad and mm, Grood-Suntay
    sens = mech.sensitivities(np.radians(60.0))                  # d(12 coordinates)/d(parameters)
    i = [lk.name for lk in mech.params.links].index("acl")
    acl = parameter_names().index(f"link{i}.length")              # the ACL's length in the flat vector
    out = {
        "assembly_range_deg": (float(lo), float(hi)),
        "adduction_at_90_deg": float(np.degrees(tf90[1])),
        "internal_rotation_at_90_deg": float(np.degrees(tf90[2])),
        "anterior_at_90_mm": float(tf90[3]),
        "pf_flexion_at_90_deg": float(np.degrees(res.pf[90, 0])),
        "max_residual_mm": float(res.residual.max()),
        # how far the tibia's internal rotation at 60 deg moves per mm of ACL length (deg/mm)
        "d_internal_rotation_d_acl_length": float(np.degrees(sens.d_params[0, 2, acl])),
    }
    return out


if __name__ == "__main__":
    for k, v in main().items():
        print(f"{k:36s} {v}")
