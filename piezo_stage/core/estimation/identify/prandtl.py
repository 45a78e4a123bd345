"""The classical Prandtl-Ishlinskii model, fitted by least squares: the textbook peer
our identification is scored beside (``bench identify``, ``bench gap``, the
changed-conditions study).

A linear term plus ``n`` play operators with thresholds evenly spaced over half the
record's voltage span (a play of threshold r moves only in loops wider than 2 r), and
a constant::

    w[k] = a v[k] + sum_j p_j z_j[k] + c,   z_j = play_{r_j}(v), r_j = j span / (2 (n + 1))

The weights (a, p_j, c) are linear least squares on the record's samples, the play
states starting at rest at the record's first voltage. It has return-point memory
(the play operators wipe out their history above each new extremum) and no other
shape than the one its weights give; it is rate independent. Prediction on another
record starts the operators at rest at that record's first voltage: its first
samples carry that unknown state, which is why the scores leave out the first second
and each model's mean offset (``held_out_rms``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import DataError
from piezo_stage.core.model.duhem import DuhemModel, DuhemState
from piezo_stage.core.model.play import PlayOperators

OPERATORS = 12
LINEAR_ALPHA = 1e-3  # [1/V]: the Duhem law standing for the linear term (any > 0 is exact)


@dataclass(frozen=True)
class PrandtlIshlinskii:
    """A fitted classical Prandtl-Ishlinskii model.

    Parameters
    ----------
    linear_um_per_V : float
        The linear term a [um/V].
    operators : PlayOperators
        Thresholds r_j [V] and weights p_j [um/V] (their state starts at rest).
    offset_um : float
        The constant c [um].
    fit_s : float
        The fit's wall time [s].
    """

    linear_um_per_V: float
    operators: PlayOperators
    offset_um: float
    fit_s: float = 0.0

    def to_model(self, v0: float) -> tuple[DuhemModel, PlayOperators]:
        """This model in our model file's terms, at rest at ``v0`` [V]: a whole-curve
        Duhem law that is exactly the linear term and the constant (f = alpha (c + a v),
        g = a: its output stays on w = a v + c), and the play operators beside it, which
        the file's ``play_operators`` hold. Simulate, invert and the feedforward take it
        as they take any model with play operators."""
        a, c = self.linear_um_per_V, self.offset_um
        duhem = DuhemModel.whole(LINEAR_ALPHA, [LINEAR_ALPHA * c, LINEAR_ALPHA * a], [a],
                                 DuhemState(float(v0), a * float(v0) + c))
        ops = self.operators
        return duhem, PlayOperators.at_rest(ops.thresholds_V, ops.weights_um_per_V, v0)

    def predict(self, v: ArrayLike) -> np.ndarray:
        """Displacement [um] over the voltages ``v`` [V], the operators at rest at the
        first voltage."""
        v = np.ascontiguousarray(v, dtype=float)
        z = np.full(self.operators.thresholds_V.size, v[0])
        return self.linear_um_per_V * v + self.operators.run(v, z) + self.offset_um


def _plays(v: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(N, n) outputs of unit-weight play operators of thresholds ``r`` over ``v``."""
    cols = np.empty((v.size, r.size))
    for j, rj in enumerate(r):
        cols[:, j] = PlayOperators.at_rest([rj], [1.0], float(v[0])).run(
            v, np.array([v[0]]))
    return cols


def fit_prandtl_ishlinskii(v: ArrayLike, w: ArrayLike, n: int = OPERATORS,
                           monotone: bool = False) -> PrandtlIshlinskii:
    """The classical Prandtl-Ishlinskii model of one axis's record.

    Parameters
    ----------
    v, w : array_like
        Voltage [V] and displacement [um], one sample each.
    n : int
        Play operators besides the linear term.
    monotone : bool
        The linear term and every weight non-negative (non-negative least squares):
        the model then rises with the voltage on every branch, keeps the wiping-out
        and congruency properties of its class, and has an exact inverse (``identify
        --class pi``); else plain least squares (the peer of the benchmarks).

    Returns
    -------
    PrandtlIshlinskii
        The fitted model.
    """
    t0 = time.perf_counter()
    v = np.ascontiguousarray(v, dtype=float)
    w = np.asarray(w, dtype=float)
    span = float(np.ptp(v)) if v.size else 0.0
    if v.size < 10 or v.size != w.size or not span > 0:
        raise DataError("Prandtl-Ishlinskii: a record of >= 10 samples whose voltage moves")
    r = np.arange(1, n + 1) * span / (2 * (n + 1))
    X = np.column_stack([v, _plays(v, r), np.ones_like(v)])
    if monotone:  # the constant free: +1 and -1 columns, both non-negative
        from scipy.optimize import nnls
        coef, _ = nnls(np.column_stack([X, -np.ones_like(v)]), w)
        theta = np.append(coef[:-2], coef[-2] - coef[-1])
    else:
        theta, *_ = np.linalg.lstsq(X, w, rcond=None)
    ops = PlayOperators.at_rest(r, theta[1:-1], float(v[0]))
    return PrandtlIshlinskii(float(theta[0]), ops, float(theta[-1]),
                             time.perf_counter() - t0)


def held_out_rms(pred: ArrayLike, w: ArrayLike, fs_hz: float, skip_s: float = 1.0) -> float:
    """RMS [um] of ``pred - w`` after the first ``skip_s`` seconds (every model starts
    from an unknown state), its mean removed (every model's offset is its own).

    Parameters
    ----------
    pred, w : array_like
        A model's output and the measurement [um].
    fs_hz : float
        The sample rate [Hz].
    skip_s : float
        Seconds left out at the start.

    Returns
    -------
    float
        The RMS [um]; nan when the prediction is not finite.
    """
    e = np.asarray(pred, float) - np.asarray(w, float)
    e = e[int(round(skip_s * fs_hz)):]
    if e.size == 0 or not np.all(np.isfinite(e)):
        return float("nan")
    return float(np.sqrt(np.mean((e - e.mean()) ** 2)))
