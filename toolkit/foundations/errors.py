"""The toolkit's two error families.

- :class:`KneeInputError` (a ``ValueError``): bad input, something the user can fix: a missing or
  malformed field, an unknown name, a file that is not what it claims, an angle outside a range given
  up front. The command line prints its one-line message and exits with code 2.
- :class:`KneeNumericalError` (a ``RuntimeError``, not a ``ValueError``): the input was well-formed but
  the numerics failed: the mechanism does not assemble, a simulation diverges, a solve does not
  converge. The command line prints its one-line message and exits with code 3.

Both derive from :class:`KneeError`, so a caller that treats any failure of a case alike (a comparison
over many cases, say) catches that. Messages are one line and name what is wrong.
"""

from __future__ import annotations

#: Exit codes of the ``knee`` command line (README, "Exit codes").
EXIT_BAD_INPUT = 2
EXIT_NUMERICAL = 3
#: An error the toolkit did not expect (a bug): one line, ``KNEE_DEBUG=1`` shows the traceback.
EXIT_INTERNAL = 70
EXIT_INTERRUPTED = 130


class KneeError(Exception):
    """Any error the toolkit raises on purpose; its message is one line."""


class KneeInputError(KneeError, ValueError):
    """Bad input: a missing or malformed field, an unknown name, an unreachable request."""


class ModelFileError(KneeInputError):
    """A parameter file that cannot be read: missing field, non-finite value, wrong unit."""


class UnknownModelError(KneeInputError):
    """A model name that is neither a bundled parameter set nor an existing TOML file."""


class KneeNumericalError(KneeError, RuntimeError):
    """A numerical failure on well-formed input: no closure, divergence, no convergence."""


class AssemblyError(KneeNumericalError):
    """The mechanism does not assemble (no closure) at a requested flexion angle.

    Attributes
    ----------
    last_angle_deg : float or None
        The last flexion angle (degrees) that was solved before the failure, if any.
    """

    def __init__(self, message: str, last_angle_deg: float | None = None):
        super().__init__(message)
        self.last_angle_deg = last_angle_deg


class DivergenceError(KneeNumericalError):
    """A simulation stopped: non-finite values, inverted elements or an energy blow-up at ``step``;
    ``inverted``: whether it stopped for inverted elements (the state is finite, the mesh crushed)."""

    def __init__(self, message: str, step: int, inverted: bool = False):
        super().__init__(message)
        self.step = step
        self.inverted = inverted
