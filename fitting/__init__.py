"""Fitting: from imaging to mechanism parameters (seed 002, sections 2.1-2.4). Imports models and
foundations, never the application layer.

- :mod:`.subject`: the subject folder (surfaces, Slicer markups, attachment areas, measured motion).
- :mod:`.frames`: anatomical frames from landmarks, with left/right checks.
- :mod:`.pipeline`: the steps (frames, MRI-CT alignment, sphere fits, helical axis and pitch, isometric
  fibres, first estimate, fits, validation) and :func:`.pipeline.fit_subject`, which returns a typed
  :class:`.pipeline.FitOutcome` (``knee fit`` writes its files: :mod:`knee.app.reports.fit`).
- :mod:`.optimize` and :mod:`.pf`: the bounded TF and PF optimisations (differential evolution, then
  Gauss-Newton with exact CasADi sensitivities); :mod:`.isometric`: the isometric-fibre search.
- :mod:`.synthetic`: a synthetic subject folder from a parameter set (``knee synth-subject``).

The geometric building blocks (sphere and plane fits, fiducial registration, principal axes) are in
:mod:`knee.foundations.geometry`; the file formats in :mod:`knee.foundations.imaging`.
"""
