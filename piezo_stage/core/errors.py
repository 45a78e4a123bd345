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
