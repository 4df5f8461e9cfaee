"""The one base class of the errors and warnings regolith-cosim raises on purpose.

Every package of the project (soil, cosim, rover_models) derives its exceptions from
`RegolithError` (and, where it helps callers, from the matching built-in: ValueError for
bad input, RuntimeError for a failed run), so `except RegolithError` catches exactly what
the project reports and nothing of Python's own.
"""


class RegolithError(Exception):
    """Base class of every regolith-cosim error."""


class RegolithWarning(UserWarning):
    """Base class of every regolith-cosim warning (filter them all with this class)."""


class SoilInputError(RegolithError, ValueError):
    """Bad input to the soil API (a builder argument, a step, a setting): the message names it and what is allowed."""


class OverlapWarning(RegolithWarning):
    """Grains were created deep inside each other: their first contact throws them apart."""


class DamagedFileError(RegolithError, ValueError):
    """A file the project reads is damaged (truncated, bytes changed) or is not the file it should be
    (another format, another scene's): the message names the file, what is wrong and what is left."""
