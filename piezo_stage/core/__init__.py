"""Pure numerical core: numpy, scipy and (optionally) numba only; never rclpy or messages."""

from piezo_stage.core.errors import (  # noqa: F401
    ConfigError,
    DataError,
    ModelError,
    PiezoStageError,
    SolverError,
)
