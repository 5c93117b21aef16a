"""The subject-specific 1-DoF spatial parallel mechanism of the knee (seed 002, section 2.3).

- :mod:`.params`   parameters and the versioned TOML format, bundled sets;
- :mod:`.closure`  the closure equations in CasADi;
- :mod:`.compiled` code generation, compilation, on-disk cache and the CasADi fallback;
- :mod:`.solver`   :class:`Mechanism`: solve, sweep, assembly modes, derivatives;
- :mod:`.reference` an independent NumPy/SciPy implementation used as a check and a baseline.
"""

from knee.models.mechanism.params import MechanismParams, bundled_models, load_model
from knee.models.mechanism.solver import Mechanism, Sensitivity, SweepResult

__all__ = ["Mechanism", "MechanismParams", "Sensitivity", "SweepResult", "bundled_models", "load_model"]
