"""A small exception hierarchy on builtins.

Every error the core raises on bad input is one of these, so the CLI can turn it into
one line on stderr and exit code 2, and a node can log it with context and go on.
"""


class PiezoStageError(Exception):
    """Base of all piezo_stage errors."""


class DataError(PiezoStageError, ValueError):
    """A record (CSV, bag, array) is unusable: wrong columns, NaN, bad time base..."""


class ModelError(PiezoStageError, ValueError):
    """A model file or parameter set is malformed or physically meaningless."""


class ConfigError(PiezoStageError, ValueError):
    """A plant or node configuration is malformed."""


class SolverError(PiezoStageError, RuntimeError):
    """An identification solver failed to produce a usable model."""


class RunError(PiezoStageError, RuntimeError):
    """A run of the node set did not complete what it was for (it failed, never armed,
    or ended before its evaluation window): the inputs were fine, a command exits 1."""


class BackendFault(PiezoStageError, RuntimeError):
    """The hardware stopped answering or reported an error (a lost link, a controller
    error): the driver faults, a command exits 1."""


def printable(text: object, limit: int = 200) -> str:
    """``text`` safe to echo in a one-line message: control characters (a terminal's
    escape sequences, NULs, newlines) written as escapes, cut to ``limit`` characters.

    Parameters
    ----------
    text : object
        What to echo (converted with str).
    limit : int
        The most characters kept.

    Returns
    -------
    str
        One line of printable text.
    """
    s = "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii")
                for c in str(text)[:limit + 1])
    return s if len(s) <= limit else s[:limit] + "..."
