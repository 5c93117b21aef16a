"""From imaging to mechanism parameters (seed 002, sections 2.1-2.4).

Built so far: :mod:`.optimize`, the bounded optimisation of the TF group against a measured motion
(differential evolution, then multi-start Gauss-Newton with exact CasADi sensitivities) and synthetic
motions with fluoroscopy-like noise. Still to come: the subject folder, anatomical frames, MRI-CT
alignment, sphere fits, the isometric-fibre search, the PF fit, reports and the ``knee fit`` and
``knee synth-subject`` commands.
"""
