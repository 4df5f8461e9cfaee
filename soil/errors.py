"""The one base class of the errors and warnings regolith-cosim raises on purpose.

Every package of the project (soil, cosim, rover_models) derives its exceptions from
`RegolithError`, in one of two kinds:

- `InputError`: bad input (a scene, an argument, a file, a model, a setting); the message names
  it and what is allowed. The command line exits 2 on these and only these. Each one also
  derives from the matching built-in (ValueError, KeyError), so callers that catch those keep
  working.
- any other RegolithError: a run or a command failed for a reason that is not its input (it
  diverged, a model refused a step, the machine lacks a tool, the project broke one of its own
  rules); these derive from RuntimeError.

So `except RegolithError` catches exactly what the project reports and nothing of Python's own,
and `except InputError` exactly what the user can fix by changing the input.
"""


class RegolithError(Exception):
    """Base class of every regolith-cosim error."""

    def __reduce__(self):
        # Rebuilt from its arguments and attributes, not through __init__, whose signature may differ
        # (SceneError's list of problems, SettlingDiverged's cause and plan): so an error crosses a
        # process (a dask worker, a batch's pipe) as itself, with its type, message and attributes.
        # An OSError keeps OSError's own way (its filename is not among its args).
        if isinstance(self, OSError):
            return OSError.__reduce__(self)
        return (_rebuild_error, (type(self), self.args, self.__dict__))


def _rebuild_error(cls: type[RegolithError], args: tuple, state: dict) -> RegolithError:
    error = cls.__new__(cls, *args)
    error.args = args
    error.__dict__.update(state)
    return error


class RegolithWarning(UserWarning):
    """Base class of every regolith-cosim warning (filter them all with this class)."""


class InputError(RegolithError):
    """Bad input (the message names it and what is allowed): the base of every input error, each
    of which also derives from a built-in (ValueError, KeyError)."""


class SoilInputError(InputError, ValueError):
    """Bad input to the soil API (a builder argument, a step, a setting): the message names it and what is allowed."""


class ArgumentError(InputError, ValueError):
    """A bad argument outside a scene file: a command-line option, an argument of a cosim or
    rover_models function or class, a command a drive controller returns (the message names it and
    what is allowed)."""


class DamagedFileError(InputError, ValueError):
    """A file the project reads is damaged (truncated, bytes changed) or is not the file it should be
    (another format, another scene's): the message names the file, what is wrong and what is left."""


class InternalError(RegolithError, RuntimeError):
    """The project broke one of its own rules (a call out of order, a state that cannot occur): a bug,
    not bad input; the message says what was expected."""


class SetupError(RegolithError, RuntimeError):
    """The machine lacks what a command needs (a C compiler, a POSIX system) or its tool failed on the
    project's own sources: the message names it."""


class OverlapWarning(RegolithWarning):
    """Grains were created deep inside each other: their first contact throws them apart."""


def is_real(value) -> bool:
    """Whether an argument that takes a number got one: a real number, numpy's included, and not a
    boolean (Python counts true as 1) nor a text. The InputError that names the argument is the caller's."""
    import numbers

    return isinstance(value, numbers.Real) and not isinstance(value, bool)
