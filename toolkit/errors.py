"""Errors the toolkit raises for bad input.

Every error the user can cause is a :class:`KneeInputError`, a ``ValueError`` subclass whose
message is one line naming what is wrong. The command line prints that line and exits with
code 2; it never shows a traceback for them.
"""

from __future__ import annotations


class KneeInputError(ValueError):
    """Bad input: a missing or malformed field, an unknown name, an unreachable angle."""


class ModelFileError(KneeInputError):
    """A parameter file that cannot be read: missing field, non-finite value, wrong unit."""


class UnknownModelError(KneeInputError):
    """A model name that is neither a bundled parameter set nor an existing TOML file."""


class AssemblyError(KneeInputError):
    """The mechanism does not assemble (no closure) at a requested flexion angle.

    Attributes
    ----------
    last_angle_deg : float or None
        The last flexion angle (degrees) that was solved before the failure, if any.
    """

    def __init__(self, message: str, last_angle_deg: float | None = None):
        super().__init__(message)
        self.last_angle_deg = last_angle_deg
