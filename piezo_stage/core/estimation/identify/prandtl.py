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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TypeVar

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
    around : numpy.ndarray
        The coefficients of the ``Around`` columns it was fitted with (its ``coupled``
        columns, then its ``free`` ones); empty when fitted alone.
    """

    linear_um_per_V: float
    operators: PlayOperators
    offset_um: float
    fit_s: float = 0.0
    smoothness: float = 0.0
    around: np.ndarray = field(default_factory=lambda: np.zeros(0))

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
        L = _cholesky(G)
        out.append((L.T.copy(), np.linalg.solve(L, g)))
    return out


def _cholesky(G: np.ndarray) -> np.ndarray:
    """The Cholesky factor of the Gram matrix ``G`` with the least diagonal load that
    makes it positive definite in floating point: 1e-12 of the mean diagonal, else 100
    and 10,000 times that. Cells that a short record moves together make G singular to
    rounding (a narrow band of a few cycles, found by the property test of the memory
    classes); the penalty rows decide such cells' weights anyway."""
    scale = float(np.trace(G)) / G.shape[0] + 1e-300
    eye = np.eye(G.shape[0])
    for load in (1e-12, 1e-10, 1e-8):
        try:
            return np.linalg.cholesky(G + load * scale * eye)
        except np.linalg.LinAlgError:
            continue
    raise np.linalg.LinAlgError("the record's Gram matrix is singular past a 1e-8 load")


@dataclass(frozen=True)
class Around:
    """What acts around a class's hysteresis while it is fitted (the gap's effects kept
    before it), in the order of the plant (core/model/plant.py): ``op`` the transform
    effects, a linear operator on columns (creep, dynamics, delay) that acts on the
    hysteresis's output and on ``coupled``, columns beside the hysteresis whose weights
    take either sign (a coupling term driven by the other axis's voltage, one column
    per coefficient); ``free`` columns after the transform, either sign (a drift's
    shapes). The class's own weights stay non-negative. The transform acts from rest
    at the record's first sample (op(X - X[0]) + X[0]: the effects of a linear,
    unit-gain operator on a stage resting in its initial state; a band's constant
    part at rest is no step into a creep)."""

    op: Callable[[np.ndarray], np.ndarray] | None = None
    coupled: np.ndarray | None = None
    free: np.ndarray | None = None

    def columns(self, v: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, int]:
        """The fit's columns [op([v, cells]), 1, op(coupled), free] and how many come
        first with a non-negative weight (the linear term and the cells)."""
        blocks = [np.column_stack([v, cells]), np.ones((v.size, 1))]
        if self.coupled is not None:
            blocks.append(self.coupled)
        if self.op is not None:  # from rest at the record's first sample
            blocks = [b if i == 1 else b[0] + self.op(b - b[0]) for i, b in enumerate(blocks)]
        if self.free is not None:
            blocks.append(self.free)
        return np.column_stack(blocks), 1 + cells.shape[1]


def nonneg_weights(R: np.ndarray, q: np.ndarray, P: np.ndarray, n_pos: int) -> np.ndarray:
    """The weights minimising ||R x - q||^2 + ||P x[1:1 + P.shape[1]]||^2 with the
    first ``n_pos`` of them non-negative and the rest of either sign (each such column
    twice, + and -, both non-negative: one non-negative least squares)."""
    from scipy.optimize import nnls
    k = R.shape[1]
    A = np.column_stack([R, -R[:, n_pos:]])
    pen = np.zeros((P.shape[0], A.shape[1]))
    pen[:, 1:1 + P.shape[1]] = P
    coef, _ = nnls(np.vstack([A, pen]), np.concatenate([q, np.zeros(P.shape[0])]),
                   maxiter=50 * A.shape[1])
    th = coef[:k].copy()
    th[n_pos:] -= coef[k:]
    return th


def nonneg_family_rms(X: np.ndarray, F: np.ndarray, w: np.ndarray,
                      n_pos: int) -> Callable[[float], float]:
    """The RMS [um] of the best fit of ``w`` on the columns X - g F, the first
    ``n_pos`` weights non-negative, as a function of g: one pass over the rows for
    the three Gram matrices (X'X, X'F + F'X, F'F), then every g is a small problem
    (an effect linear in its parameter, as creep's fraction gamma is: Creep.apply is
    X - gamma fast_part(X)). For searching g; the fit itself is ``fit_nonneg_class``'s."""
    A, B, C = X.T @ X, X.T @ F, F.T @ F
    B = B + B.T
    xw, fw, ww, n = X.T @ w, F.T @ w, float(w @ w), len(w)
    none = np.zeros((0, n_pos - 1))

    def rms_at(g: float) -> float:
        G = A - g * B + g * g * C
        b = xw - g * fw
        jitter = 1e-12 * float(np.trace(G)) / G.shape[0] + 1e-300
        L = np.linalg.cholesky(G + jitter * np.eye(G.shape[0]))
        q = np.linalg.solve(L, b)
        R = L.T
        th = nonneg_weights(R, q, none, n_pos)
        rr = ww - float(q @ q) + float(np.sum((R @ th - q) ** 2))
        return float(np.sqrt(max(rr, 0.0) / n))
    return rms_at


K = TypeVar("K")


def fit_nonneg_class(v: np.ndarray, w: np.ndarray, cells: np.ndarray,
                     pens: Mapping[K, np.ndarray], around: Around | None = None,
                     fallback: K | None = None) -> tuple[np.ndarray, K]:
    """A class's weights [linear, cells..., constant, around...] by non-negative least
    squares on the columns ``around.columns`` gives, the linear term at least
    ``min_slope``, with the penalty rows of one of ``pens`` ({key: rows over the
    cells}): the one that, fitted on the record's first half, two thirds and three
    quarters (``LATER_FROM``), predicts the rest best (summed RMS, offsets removed;
    the only one when ``pens`` has one; ``fallback``, else the first, when the record's
    first parts do not move). One pass over the rows (``gram_factors``): every later
    step is small. -> (weights, the penalty's key)."""
    around = around or Around()
    X, n_pos = around.columns(v, cells)
    floor = min_slope(v, w)  # the linear term's floor: no branch is flat anywhere
    wf = w - floor * X[:, 0]
    cuts = [int(f * v.size) for f in LATER_FROM]
    tried = len(pens) > 1 and v.size >= 30 and all(np.ptp(v[:k]) > 0 for k in cuts)
    factors = gram_factors(X, wf, (cuts if tried else []) + [v.size])
    keys = list(pens)
    choice = keys[0] if fallback is None else fallback
    if tried:
        later = dict.fromkeys(keys, 0.0)
        for k, (R, q) in zip(cuts, factors):
            for key in keys:
                th = nonneg_weights(R, q, pens[key], n_pos)
                later[key] += float(np.std(X[k:] @ th - wf[k:]))
        choice = min(keys, key=later.__getitem__)
    R, q = factors[-1]
    th = nonneg_weights(R, q, pens[choice], n_pos)
    th[0] += floor
    return th, choice


def fit_prandtl_ishlinskii(v: ArrayLike, w: ArrayLike, n: int = OPERATORS
                           ) -> PrandtlIshlinskii:
    """The classical Prandtl-Ishlinskii model of one axis's record, the textbook peer:
    a linear term, ``n`` play operators over half the record's span and a constant,
    by plain least squares (weights of any sign).

    Parameters
    ----------
    v, w : array_like
        Voltage [V] and displacement [um], one sample each.
    n : int
        Play operators besides the linear term, over half the record's span.

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
    X = np.column_stack([v, play_columns(v, r), np.ones_like(v)])
    theta, *_ = np.linalg.lstsq(X, w, rcond=None)
    ops = PlayOperators.at_rest(r, theta[1:-1], float(v[0]))
    return PrandtlIshlinskii(float(theta[0]), ops, float(theta[-1]),
                             time.perf_counter() - t0)


def min_slope(v: ArrayLike, w: ArrayLike) -> float:
    """The least slope [um/V] a class with memory keeps on every branch, its linear
    term's floor: ``MIN_SLOPE`` of the record's mean slope |ptp(w) / ptp(v)|. Right
    after a reversal every play operator of threshold > 0 stands still; with a linear
    term of 0 the branch would be flat there, and a flat branch has no one voltage for
    its displacement (the exact inverse would pick one of many)."""
    span = float(np.ptp(np.asarray(v, float)))
    return MIN_SLOPE * abs(float(np.ptp(np.asarray(w, float)))) / span if span > 0 else 0.0


def fit_pi_class(v: ArrayLike, w: ArrayLike, reach_V: float | None = None,
                 n: int = OPERATORS, around: Around | None = None) -> PrandtlIshlinskii:
    """The Prandtl-Ishlinskii class we identify (``identify --class pi``, the gap's
    memory in its class form): non-negative weights (the linear term at least
    ``min_slope``), operators at the spacing of ``n`` over half the record's span, on
    to ``reach_V`` [V] (half the amplifier's range; None: half the record's span, as the
    peer). Where they reach past the record, the weights past it are free or follow a
    smooth density (``SMOOTHNESS``: first differences penalised as much as the
    operators' columns weigh), whichever, fitted on the record's first half, two thirds
    and three quarters (``LATER_FROM``), predicts the rest better (summed RMS, offsets
    removed); the whole record is then fitted so (``fit_nonneg_class``).

    Parameters
    ----------
    v, w : array_like
        Voltage [V] and displacement [um], one sample each.
    reach_V : float or None
        The largest threshold [V].
    n : int
        Operators over half the record's span.
    around : Around or None
        Effects fitted with it (the gap's kept effects); None: the class alone.

    Returns
    -------
    PrandtlIshlinskii
        The fitted model (its ``smoothness`` the one chosen, its ``around`` the
        coefficients of ``around``'s columns).
    """
    t0 = time.perf_counter()
    v = np.ascontiguousarray(v, dtype=float)
    w = np.asarray(w, dtype=float)
    span = float(np.ptp(v)) if v.size else 0.0
    if v.size < 10 or v.size != w.size or not span > 0 or not np.all(np.isfinite(w)):
        raise DataError("Prandtl-Ishlinskii: a record of >= 10 finite samples whose "
                        "voltage moves")
    step = span / (2 * (n + 1))
    m = n if reach_V is None else int(min(max(n, reach_V // step), MAX_OPERATORS))
    r = np.arange(1, m + 1) * step
    plays = play_columns(v, r)
    pens = {SMOOTHNESS[0]: np.zeros((0, m))}
    if reach_V is not None and reach_V > span / 2 and m > 1:
        scale = float(np.mean(np.linalg.norm(plays, axis=0)))
        D = np.zeros((m - 1, m))
        i = np.arange(m - 1)
        D[i, i], D[i, i + 1] = -1.0, 1.0
        pens.update({s: np.sqrt(s) * scale * D for s in SMOOTHNESS if s > 0})
    th, smooth = fit_nonneg_class(v, w, plays, pens, around)
    ops = PlayOperators.at_rest(r, th[1:m + 1], float(v[0]))
    return PrandtlIshlinskii(float(th[0]), ops, float(th[m + 1]), time.perf_counter() - t0,
                             float(smooth), th[m + 2:])


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
