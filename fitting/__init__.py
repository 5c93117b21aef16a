"""From imaging to mechanism parameters (seed 002, sections 2.1-2.4).

Built so far: :mod:`.optimize`, the bounded optimisation of the TF group against a measured motion
(differential evolution, then multi-start Gauss-Newton with exact CasADi sensitivities) and synthetic
motions with fluoroscopy-like noise; :mod:`.isometric`, the isometric-fibre search. The geometric
building blocks (sphere and plane fits, fiducial registration with FRE, principal axes) are in
:mod:`toolkit.geometry`. Still to come: the subject folder, anatomical frames, the pipeline steps
wired together, the PF fit, reports and the ``knee fit`` and ``knee synth-subject`` commands.
"""
