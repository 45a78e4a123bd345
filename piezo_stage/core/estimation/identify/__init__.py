"""Duhem identification: segmentation, output-error objective (the paper's eq. 9), solvers.

Solvers: ``fast`` (variable projection: exact least squares in the polynomial
coefficients for fixed alpha, a search over alpha only; the default), ``afsa`` (the
standard artificial fish swarm) and ``afsa-bat`` (the paper's bat-improved swarm).
"""

from piezo_stage.core.estimation.identify.api import (  # noqa: F401
    METHODS,
    AxisResult,
    IdentifyOptions,
    identify_axis,
    validate_axis,
)
