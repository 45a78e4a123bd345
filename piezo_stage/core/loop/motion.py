"""How long a move takes: a motion-time model fitted to measured settle times.

``t(s) = a + b |s| + r ln(max(1, |s| / tol))`` for a step of ``s`` um to a tolerance
``tol``: a fixed part ``a`` (the filter and the controller's reaction), a part that
grows with the distance ``b |s|`` (the profile's travel at its speed), and the
ring-down ``r`` (a mode decaying as exp(-t / r) from an amplitude that grows with the
step until it is within the tolerance). The three are fitted by non-negative least
squares, so each stays a time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import DataError
from piezo_stage.core.types import Doc


@dataclass(frozen=True)
class MotionTimeModel:
    """``predict(step_um)`` [s] (see the module's docstring)."""

    a_s: float
    b_s_per_um: float
    ring_s: float
    tol_um: float

    def predict(self, step_um: float) -> float:
        """The settle time [s] of a step of ``step_um`` [um]."""
        s = abs(float(step_um))
        return self.a_s + self.b_s_per_um * s + self.ring_s * math.log(
            max(1.0, s / self.tol_um))

    @classmethod
    def fit(cls, steps_um: ArrayLike, settle_s: ArrayLike, tol_um: float) -> MotionTimeModel:
        """The model of measured settle times (at least three steps of two sizes)."""
        from scipy.optimize import nnls
        s = np.abs(np.asarray(steps_um, float))
        t = np.asarray(settle_s, float)
        ok = np.isfinite(s) & np.isfinite(t)
        s, t = s[ok], t[ok]
        if s.size < 3 or np.ptp(s) <= 0 or not tol_um > 0:
            raise DataError("motion time: give settle times of at least three steps of "
                            "two sizes or more, and a tolerance > 0")
        A = np.column_stack([np.ones_like(s), s, np.log(np.maximum(1.0, s / tol_um))])
        x, _ = nnls(A, t)
        return cls(float(x[0]), float(x[1]), float(x[2]), float(tol_um))

    def to_dict(self) -> Doc:
        """The model as data (the client's file, a bench's JSON)."""
        return {"a_s": self.a_s, "b_s_per_um": self.b_s_per_um, "ring_s": self.ring_s,
                "tol_um": self.tol_um}

    @classmethod
    def from_dict(cls, d: Doc) -> MotionTimeModel:
        """The model from ``to_dict``'s data (DataError when a field is missing)."""
        try:
            return cls(float(d["a_s"]), float(d["b_s_per_um"]), float(d["ring_s"]),
                       float(d["tol_um"]))
        except (KeyError, TypeError, ValueError) as e:
            raise DataError(f"motion time model: {e}") from None
