"""A peer to compare identification with: the sparse hysteresis models of Chandra et
al. 2023 ("Discovery of sparse hysteresis models for piezoelectric materials"),
fitted with pysindy.

Their model is an ODE in the displacement w [um], driven by the voltage v [V]::

    dw/dt = Theta(w, v, dv/dt, |dv/dt|, |w|) xi

with Theta every monomial of degree <= 2 of those five signals (a constant included)
and xi sparse: sequentially thresholded least squares (pysindy's STLSQ, threshold
0.01), dw/dt from second-order finite differences of the measured w, as their
published fit of a real actuator does. (On that record they report five terms.)
Their record swings about zero (+-150 V); ours span 0-150 V, and the library is not
shift invariant (|w|, w^2 change meaning), so v is centred on the middle of FIT's
voltage span and w on FIT's mean before the fit, and the prediction shifted back: on
the structure stage's scan that takes the peer from 0.71 to 0.15 um held out.

The fit is pysindy's: ``SINDy`` with w as the state and (v, dv/dt, |dv/dt|, |w|) as
inputs, ``PolynomialLibrary(degree=2)``. Prediction on another record integrates the
ODE (classic Runge-Kutta at the record's rate, the inputs interpolated linearly
between samples) with |w| taken from the state, not from the record; it starts at
the record's first measured output, as their validation does, so a held-out
comparison is one-step-free simulation like ours.

pysindy is a test and bench extra (``pip install -e .[test]``), never a runtime
dependency: ``fit`` raises ConfigError naming the extra when it is missing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from piezo_stage.core.errors import ConfigError
from piezo_stage.core.estimation.record import Record

THRESHOLD = 0.01  # STLSQ's, as published
SIGNALS = ("w", "v", "dv/dt", "|dv/dt|", "|w|")


@dataclass
class SparsePeer:
    """A fitted sparse model: the nonzero terms (coefficients and their monomials'
    powers over SIGNALS), their names, and the fit's wall time [s]."""

    coefficients: np.ndarray
    powers: np.ndarray
    terms: list
    fit_s: float
    v_centre: float = 0.0  # [V], subtracted from v before the library
    w_centre: float = 0.0  # [um], likewise from w

    def rate(self, w: float, v: float, dv: float) -> float:
        """dw/dt [um/s] at (centred) displacement ``w``, voltage ``v`` and its rate
        ``dv``."""
        z = np.array([w, v, dv, abs(dv), abs(w)])
        return float(self.coefficients @ np.prod(z ** self.powers, axis=1))

    def simulate(self, rec: Record, axis: str, w0: float | None = None) -> np.ndarray:
        """The model's displacement [um] over ``rec``'s voltage on ``axis``, from
        ``w0`` (default: the record's first measured output)."""
        v = np.asarray(rec.v[axis], float) - self.v_centre
        t = np.asarray(rec.t, float)
        dv = np.gradient(v, t)
        out = np.empty(v.size)
        x = (float(rec.w[axis][0]) if w0 is None else float(w0)) - self.w_centre
        out[0] = x
        f = self.rate
        for k in range(v.size - 1):
            h = t[k + 1] - t[k]
            vm, dm = 0.5 * (v[k] + v[k + 1]), 0.5 * (dv[k] + dv[k + 1])
            k1 = f(x, v[k], dv[k])
            k2 = f(x + 0.5 * h * k1, vm, dm)
            k3 = f(x + 0.5 * h * k2, vm, dm)
            k4 = f(x + h * k3, v[k + 1], dv[k + 1])
            x += h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            if not np.isfinite(x):  # a sparse ODE may diverge off its fit record
                out[k + 1:] = np.nan
                break
            out[k + 1] = x
        return out + self.w_centre


def fit(rec: Record, axis: str, threshold: float = THRESHOLD) -> SparsePeer:
    """The sparse model of ``rec``'s ``axis`` (see the module docstring)."""
    try:
        import pysindy as ps
    except ImportError:
        raise ConfigError("the sparse peer needs pysindy: pip install -e '.[test]'") \
            from None
    t0 = time.perf_counter()
    v = np.asarray(rec.v[axis], float)
    w = np.asarray(rec.w[axis], float)
    vc, wc = 0.5 * float(v.min() + v.max()), float(w.mean())
    v, w = v - vc, w - wc
    t = np.asarray(rec.t, float)
    dv = np.gradient(v, t)
    model = ps.SINDy(optimizer=ps.STLSQ(threshold=threshold),
                     feature_library=ps.PolynomialLibrary(degree=2),
                     differentiation_method=ps.FiniteDifference(order=2))
    model.fit(w.reshape(-1, 1), t=t, u=np.column_stack([v, dv, np.abs(dv), np.abs(w)]),
              feature_names=list(SIGNALS))
    xi = np.asarray(model.coefficients(), float)[0]
    keep = np.flatnonzero(xi)
    names = model.get_feature_names()
    powers = np.asarray(model.feature_library.powers_)[keep]
    return SparsePeer(xi[keep], powers, [names[i] for i in keep],
                      time.perf_counter() - t0, vc, wc)
