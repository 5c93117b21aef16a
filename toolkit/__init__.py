"""knee: subject-specific knee kinematics and the association FEM model.

A 1-DoF spatial parallel mechanism of the knee (five rigid links for the tibio-femoral joint, a helical
pair and a tendon link for the patella), fitted to a subject from imaging, and the "association"
finite-element model that the mechanism initialises and constrains, deformed toward a depth camera's
point cloud. Units: mm, N, MPa, s; radians inside (degrees at the command line and in CSV files). Bone
frames: x anterior, y proximal, z lateral (a right knee; left knees are mirrored on the way in).

The entry points a researcher uses from Python (``help(knee)`` lists them; each is loaded on first use,
so ``import knee`` is quick):

- the mechanism: :func:`load_model`, :class:`Mechanism` (``solve``, ``sweep``, ``sensitivities``),
  :func:`bundled_models`, :func:`joint_to_pose`, :func:`pose_to_joint`;
- fitting a subject: :func:`load_subject`, :func:`fit_subject`, :func:`make_subject` (a synthetic one);
- the association model: :func:`build_association_model`, :class:`FemSettings`, the methods
  :func:`paper_method` and :func:`prior_method` on a point cloud, and :func:`load_point_cloud`,
  :func:`load_depth_image`;
- the kinematic prior: :func:`estimate_flexion`, :func:`correct_tibia`;
- evaluation: :func:`target_points`, :func:`target_errors`, :func:`pose_errors`;
- clinical questions: :func:`solve_statics`, :func:`hertz`, :func:`analyse_gait`, :func:`osteotomy`;
- recordings: :func:`new_recording`, :func:`save_recording`;
- errors: :class:`KneeInputError` (bad input, a ``ValueError``) and :class:`KneeNumericalError` (a
  numerical failure on good input).

Example::

    import numpy as np
    import knee

    mech = knee.Mechanism(knee.load_model("volunteer"))
    motion = mech.sweep(np.radians(np.arange(0, 121, 10)))   # motion.tf: (13, 6) rad and mm
"""

from __future__ import annotations

import importlib

#: Public name -> the module that defines it (imported on first access).
_API = {
    "Mechanism": "knee.models.mechanism.solver",
    "SweepResult": "knee.models.mechanism.solver",
    "MechanismParams": "knee.models.mechanism.params",
    "load_model": "knee.models.mechanism.params",
    "bundled_models": "knee.models.mechanism.params",
    "joint_to_pose": "knee.foundations.conventions",
    "pose_to_joint": "knee.foundations.conventions",
    "load_subject": "knee.fitting.subject",
    "fit_subject": "knee.fitting.pipeline",
    "make_subject": "knee.fitting.synthetic",
    "build_phantom": "knee.models.phantom",
    "build_association_model": "knee.models.fem.scene",
    "FemSettings": "knee.models.fem.scene",
    "paper_method": "knee.models.fem.methods",
    "prior_method": "knee.models.fem.methods",
    "load_point_cloud": "knee.foundations.pointclouds",
    "load_depth_image": "knee.foundations.pointclouds",
    "estimate_flexion": "knee.models.prior",
    "correct_tibia": "knee.models.prior",
    "target_points": "knee.models.evaluation",
    "target_errors": "knee.models.evaluation",
    "pose_errors": "knee.models.evaluation",
    "solve_statics": "knee.models.statics",
    "hertz": "knee.models.contact",
    "analyse_gait": "knee.models.gait",
    "osteotomy": "knee.models.osteotomy",
    "new_recording": "knee.foundations.recording",
    "save_recording": "knee.foundations.recording",
    "KneeInputError": "knee.foundations.errors",
    "KneeNumericalError": "knee.foundations.errors",
}
_ALIASES = {"save_recording": "save"}

__all__ = sorted(_API)


def __getattr__(name: str):
    if name not in _API:
        raise AttributeError(f"module 'knee' has no attribute {name!r}")
    value = getattr(importlib.import_module(_API[name]), _ALIASES.get(name, name))
    globals()[name] = value  # later accesses skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
