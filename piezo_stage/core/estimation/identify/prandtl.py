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

The class we identify (``identify --class pi``, the gap's ``memory`` in its class
form: ``fit_pi_class``) differs from the peer in three ways: non-negative weights
(monotone branches, the class's wiping-out and congruency properties, an exact
inverse); thresholds that reach on, at the same spacing, to half the amplifier's
range (``reach_V``), where the peer's stop at half the record's span; and, where they
reach past the record, a choice between free weights and a weight density that varies
smoothly with the threshold (a first-difference penalty), made on the record's own
later parts. A play of threshold r larger than the record's loops still moves on the
record's monotone excursions (from rest, one rise of more than r), so these weights are
not free guesses; a smooth density continues the loop's widening with the stroke
(with a constant density it is the Rayleigh law of piezoceramics below their coercive
field), where the peer's loop stops widening at the record's stroke.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import DataError
from piezo_stage.core.model.duhem import DuhemModel, DuhemState
from piezo_stage.core.model.play import MAX_OPERATORS, PlayOperators, play_columns

OPERATORS = 12
# the class's weight-density penalties past the record (fit_pi_class): free weights, or
# first differences penalised as much as the operators' columns weigh
SMOOTHNESS = (0.0, 1.0)
# the record's first parts that predict the rest, to choose between them (rolling
# origin: one split alone chose differently from one split to the next)
LATER_FROM = (1 / 2, 2 / 3, 3 / 4)
MIN_SLOPE = 0.01  # of the record's mean slope: every branch of a class rises at least so
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
    smoothness : float
        The weight-density penalty it was fitted with (0: free weights).
    """

    linear_um_per_V: float
    operators: PlayOperators
    offset_um: float
    fit_s: float = 0.0
    smoothness: float = 0.0

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
        return duhem, ops.moved(np.full(ops.thresholds_V.size, float(v0)))

    @property
    def kind(self) -> str:
        """'preisach' when its operators are banded (fit_preisach_class), else 'pi'."""
        return "preisach" if self.operators.banded else "pi"

    def predict(self, v: ArrayLike) -> np.ndarray:
        """Displacement [um] over the voltages ``v`` [V], the operators at rest at the
        first voltage."""
        v = np.ascontiguousarray(v, dtype=float)
        z = np.full(self.operators.thresholds_V.size, v[0])
        return self.linear_um_per_V * v + self.operators.run(v, z) + self.offset_um


def gram_factors(A: np.ndarray, w: np.ndarray,
                 cuts: list[int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """(R, q) of the first ``cuts`` rows of ``A`` (ascending; the last may be all rows),
    with ||A x - w||^2 = ||R x - q||^2 + a constant: the same minimiser, a small
    problem. R is the Cholesky factor of the Gram matrix, summed block by block (one
    pass over the rows in all); a column the record never moves is a multiple of the
    constant's, so the diagonal gets 1e-12 of its scale (the LEVEL penalty decides
    such a column's weight anyway: the Preisach class's ``LEVEL``, the
    Prandtl-Ishlinskii class's linear term and operators, which always move)."""
    out, k0 = [], 0
    G, g = np.zeros((A.shape[1], A.shape[1])), np.zeros(A.shape[1])
    for k in cuts:
        G += A[k0:k].T @ A[k0:k]
        g += A[k0:k].T @ w[k0:k]
        k0 = k
        jitter = 1e-12 * float(np.trace(G)) / G.shape[0] + 1e-300
        L = np.linalg.cholesky(G + jitter * np.eye(G.shape[0]))
        out.append((L.T.copy(), np.linalg.solve(L, g)))
    return out


def fit_prandtl_ishlinskii(v: ArrayLike, w: ArrayLike, n: int = OPERATORS,
                           monotone: bool = False, reach_V: float | None = None,
                           smoothness: float = 0.0) -> PrandtlIshlinskii:
    """The classical Prandtl-Ishlinskii model of one axis's record.

    Parameters
    ----------
    v, w : array_like
        Voltage [V] and displacement [um], one sample each.
    n : int
        Play operators besides the linear term, over half the record's span.
    monotone : bool
        The linear term at least ``min_slope`` and every weight non-negative
        (non-negative least squares): the model then rises with the voltage on every
        branch, keeps the wiping-out
        and congruency properties of its class, and has an exact inverse (``identify
        --class pi``); else plain least squares (the peer of the benchmarks).
    reach_V : float or None
        More operators at the same spacing, up to this threshold [V] (half the
        amplifier's range); None: the ``n`` alone.
    smoothness : float
        The weights' first differences penalised, this times the operators' mean
        column norm (monotone fits only; 0: none).

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
    step = span / (2 * (n + 1))
    m = n if reach_V is None else int(min(max(n, reach_V // step), MAX_OPERATORS))
    r = np.arange(1, m + 1) * step
    plays = play_columns(v, r)
    X = np.column_stack([v, plays, np.ones_like(v)])
    floor = min_slope(v, w) if monotone else 0.0
    if monotone:  # the constant free: +1 and -1 columns, both non-negative
        from scipy.optimize import nnls
        [(R, q)] = gram_factors(X, w - floor * v, [v.size])  # the same minimiser, small
        A, b = np.column_stack([R, -R[:, -1]]), q
        if smoothness > 0 and m > 1:
            D = np.zeros((m - 1, A.shape[1]))
            i = np.arange(m - 1)
            D[i, 1 + i], D[i, 2 + i] = -1.0, 1.0
            scale = np.sqrt(smoothness) * float(np.mean(np.linalg.norm(plays, axis=0)))
            A, b = np.vstack([A, scale * D]), np.append(b, np.zeros(m - 1))
        coef, _ = nnls(A, b, maxiter=50 * A.shape[1])
        theta = np.append(coef[:-2], coef[-2] - coef[-1])
        theta[0] += floor
    else:
        theta, *_ = np.linalg.lstsq(X, w, rcond=None)
    ops = PlayOperators.at_rest(r, theta[1:-1], float(v[0]))
    return PrandtlIshlinskii(float(theta[0]), ops, float(theta[-1]),
                             time.perf_counter() - t0, float(smoothness) if monotone else 0.0)


def min_slope(v: ArrayLike, w: ArrayLike) -> float:
    """The least slope [um/V] a class with memory keeps on every branch, its linear
    term's floor: ``MIN_SLOPE`` of the record's mean slope |ptp(w) / ptp(v)|. Right
    after a reversal every play operator of threshold > 0 stands still; with a linear
    term of 0 the branch would be flat there, and a flat branch has no one voltage for
    its displacement (the exact inverse would pick one of many)."""
    span = float(np.ptp(np.asarray(v, float)))
    return MIN_SLOPE * abs(float(np.ptp(np.asarray(w, float)))) / span if span > 0 else 0.0


def fit_pi_class(v: ArrayLike, w: ArrayLike, reach_V: float | None = None,
                 n: int = OPERATORS) -> PrandtlIshlinskii:
    """The Prandtl-Ishlinskii class we identify (``identify --class pi``, the gap's
    memory in its class form): non-negative weights, operators up to ``reach_V`` [V]
    (half the amplifier's range; None: half the record's span, as the peer). Where they
    reach past the record, the weights past it are free or follow a smooth density
    (``SMOOTHNESS``), whichever, fitted on the record's first half, two thirds and three
    quarters (``LATER_FROM``), predicts the rest better (summed RMS, offsets removed);
    the whole record is then fitted so.

    Parameters
    ----------
    v, w : array_like
        Voltage [V] and displacement [um], one sample each.
    reach_V : float or None
        The largest threshold [V].
    n : int
        Operators over half the record's span.

    Returns
    -------
    PrandtlIshlinskii
        The fitted model (its ``smoothness`` the one chosen).
    """
    t0 = time.perf_counter()
    v = np.ascontiguousarray(v, dtype=float)
    w = np.asarray(w, dtype=float)
    span = float(np.ptp(v)) if v.size else 0.0
    smooth = 0.0
    cuts = [int(f * v.size) for f in LATER_FROM]
    if reach_V is not None and span > 0 and reach_V > span / 2 and v.size >= 30 and \
            all(np.ptp(v[:k]) > 0 for k in cuts):
        def later(s: float) -> float:
            """The RMS of each first part's prediction of the rest, offset removed."""
            return sum(float(np.std(fit_prandtl_ishlinskii(
                v[:k], w[:k], n, True, reach_V, s).predict(v)[k:] - w[k:])) for k in cuts)
        smooth = min(SMOOTHNESS, key=later)
    pi = fit_prandtl_ishlinskii(v, w, n, True, reach_V, smooth)
    return PrandtlIshlinskii(pi.linear_um_per_V, pi.operators, pi.offset_um,
                             time.perf_counter() - t0, smooth)


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
