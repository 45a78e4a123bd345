"""A discretized Preisach law, identified like the Prandtl-Ishlinskii class
(``identify --class preisach``).

The Preisach law sums relays (up at v >= c + r, down at v <= c - r) of half-width r
and centre c, weighted by a density mu(r, c) >= 0. A relay of half-width r and centre
c is up exactly when the play operator of threshold r is above c, so the relays of
one half-width with centres in a band [lo, hi] sum to the play's state clipped to the
band (core/model/play.py's ``bands_V``). Discretized so, with the density constant
on each cell (threshold r_i, band j)::

    w[k] = a v[k] + sum_ij mu_ij clip(z_i[k], c_j, c_j+1) + c,   z_i = play_{r_i}(v)

The Prandtl-Ishlinskii class is the special case of a density that does not vary
with the centre. One that does bends the branches differently along the stroke: an
envelope steeper at one end, a loop wider in the middle than at the ends, as
ceramics show and a polynomial or a play sum alone does not follow.

The cells: thresholds from 0 (the relays of width 0: the law's anhysteretic curve)
at the spacing of ``BAND_OPERATORS`` over half the record's span, on to half the
amplifier's range (``reach_V``) as for the Prandtl-Ishlinskii class; the centres in
``BANDS`` bands over the record's voltage span, and one band beyond each end of it,
to the amplifier's range and past (so that a stroke larger than the record's goes
on along a density, not off a cliff). The weights are non-negative least squares, so
that every branch rises with the voltage (the linear term at least ``min_slope``: no
branch is flat anywhere) and the law keeps its class's wiping-out and
congruency; a cell the record never reaches is held (with a small penalty on each
weight, ``LEVEL``) by a penalty on the density's first differences along the centres
(``BAND_SMOOTHNESS``, chosen, as the threshold penalty is, on the record's own later
parts): the branches continue past the record along its end slopes.
"""

from __future__ import annotations

import time
from itertools import product

import numpy as np
from numpy.typing import ArrayLike

from piezo_stage.core.errors import DataError
from piezo_stage.core.estimation.identify.prandtl import (
    SMOOTHNESS,
    Around,
    PrandtlIshlinskii,
    fit_nonneg_class,
)
from piezo_stage.core.model.play import MAX_OPERATORS, PlayOperators, play_columns

BANDS = 4  # centre bands over the record's voltage span (one more beyond each end)
BAND_OPERATORS = 8  # thresholds over half the record's span (the PI class has 12)
# the density's first differences along the centres, penalised this much (relative to
# the cells' mean column norm): a little (the record's own shape) or as much as the
# columns weigh (close to the Prandtl-Ishlinskii class)
BAND_SMOOTHNESS = (0.01, 1.0)
# every cell's weight itself, penalised a little: a cell the record never reaches has a
# constant column, one with the constant's, and without it could take any weight
# the constant takes back (the neighbours' differences alone do not fix their level)
LEVEL = 1e-6


def _cells(v: np.ndarray, reach_V: float | None, n: int = BAND_OPERATORS,
           bands: int = BANDS) -> tuple[np.ndarray, np.ndarray]:
    """The cells' thresholds r_i (from 0) and band edges (``bands`` + 2 bands) for a
    record ``v`` and a reach ``reach_V`` [V] (None: half the record's span), at most
    ``MAX_OPERATORS`` cells. -> (thresholds, edges)."""
    lo, hi = float(np.min(v)), float(np.max(v))
    span = hi - lo
    step = span / (2 * (n + 1))
    reach = span / 2 if reach_V is None else max(float(reach_V), span / 2)
    m = max(n, int(reach // step))
    m = min(m, MAX_OPERATORS // (bands + 2) - 1)
    r = np.arange(m + 1) * step
    inner = np.linspace(lo, hi, bands + 1)
    far = reach + span + 1.0  # past any state an operator can reach from the range
    return r, np.concatenate([[lo - far], inner, [hi + far]])


def _columns(v: np.ndarray, r: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(N, cells) outputs of unit-weight banded operators (threshold-major), at rest
    at the record's first voltage."""
    z = play_columns(v, r)  # (N, thresholds)
    return np.clip(z[:, :, None], edges[None, None, :-1], edges[None, None, 1:]).reshape(
        v.size, -1)


def _penalty(m: int, b: int, along_r: float, along_c: float, scale: float) -> np.ndarray:
    """Rows penalising the density's first differences along the thresholds (weight
    ``along_r``) and along the centres (``along_c``), and every weight a little
    (``LEVEL``), for ``m`` thresholds by ``b`` bands, threshold-major."""
    rows = []
    for lam, pairs in ((along_r, [(i * b + j, (i + 1) * b + j) for i in range(m - 1)
                                  for j in range(b)]),
                       (along_c, [(i * b + j, i * b + j + 1) for i in range(m)
                                  for j in range(b - 1)])):
        if lam <= 0 or not pairs:
            continue
        D = np.zeros((len(pairs), m * b))
        k = np.arange(len(pairs))
        a, c = np.array(pairs).T
        D[k, a], D[k, c] = -1.0, 1.0
        rows.append(np.sqrt(lam) * scale * D)
    rows.append(np.sqrt(LEVEL) * scale * np.eye(m * b))
    return np.vstack(rows)


def fit_preisach_class(v: ArrayLike, w: ArrayLike, reach_V: float | None = None,
                       n: int = BAND_OPERATORS, bands: int = BANDS,
                       around: Around | None = None) -> PrandtlIshlinskii:
    """The discretized Preisach class of one axis's record (see the module docstring).

    The penalties along the thresholds (``SMOOTHNESS``, as the Prandtl-Ishlinskii
    class) and along the centres (``BAND_SMOOTHNESS``) are the pair that, fitted on the
    record's first half, two thirds and three quarters (``LATER_FROM``), predicts the
    rest best (summed RMS, offsets removed); the whole record is then fitted so.

    Parameters
    ----------
    v, w : array_like
        Voltage [V] and displacement [um], one sample each.
    reach_V : float or None
        The largest threshold [V] (half the amplifier's range); None: half the
        record's span.
    n : int
        Thresholds over half the record's span.
    bands : int
        Centre bands over the record's voltage span.
    around : Around or None
        Effects fitted with it (the gap's kept effects); None: the law alone.

    Returns
    -------
    PrandtlIshlinskii
        A linear term, banded play operators (``operators.bands_V``) and a constant;
        its ``smoothness`` the threshold penalty chosen, its ``around`` the
        coefficients of ``around``'s columns.
    """
    t0 = time.perf_counter()
    v = np.ascontiguousarray(v, dtype=float)
    w = np.asarray(w, dtype=float)
    span = float(np.ptp(v)) if v.size else 0.0
    if v.size < 30 or v.size != w.size or not span > 0 or not np.all(np.isfinite(w)):
        raise DataError("Preisach: a record of >= 30 finite samples whose voltage moves")
    r, edges = _cells(v, reach_V, n, bands)
    m, b = r.size, edges.size - 1
    C = _columns(v, r, edges)
    scale = float(np.mean(np.linalg.norm(C - C.mean(axis=0), axis=0))) or 1.0
    pens = {(sr, sc): _penalty(m, b, sr, sc, scale)
            for sr, sc in product(SMOOTHNESS, BAND_SMOOTHNESS)}
    th, choice = fit_nonneg_class(v, w, C, pens, around,
                                  fallback=(SMOOTHNESS[0], BAND_SMOOTHNESS[-1]))
    k = m * b
    cells = np.column_stack([np.repeat(edges[:-1][None], m, 0).ravel(),
                             np.repeat(edges[1:][None], m, 0).ravel()])
    ops = PlayOperators.at_rest(np.repeat(r, b), th[1:k + 1], float(v[0]), bands_V=cells)
    return PrandtlIshlinskii(float(th[0]), ops, float(th[k + 1]), time.perf_counter() - t0,
                             float(choice[0]), th[k + 2:])
